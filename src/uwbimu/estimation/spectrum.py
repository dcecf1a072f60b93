"""Welch's power spectral density without importing :mod:`scipy.signal`.

``scipy.signal`` imports ``scipy.stats`` on its way in (about 0.6 s of CPU, more than half the filter pass of a
10-minute 1 kHz log), and the IMU noise rule of :mod:`uwbimu.estimation.noise_from_data` is its only user on
the ``uwbimu estimate`` path.  :func:`welch_psd` is the one call that rule makes, ``scipy.signal.welch(x,
fs=fs, nperseg=nperseg, axis=axis)`` with the defaults (periodic Hann window, half overlap, constant
detrend, one-sided density, mean of the segments), written with the same NumPy operations in the same order
on arrays of the same layout as SciPy 1.17's ``csd`` / ``ShortTimeFFT.spectrogram``, so the result is
bit-identical (``tests/test_spectrum.py`` compares it, bit for bit, with ``scipy.signal.welch`` of the
installed SciPy on several shapes; a SciPy whose welch computes differently fails that test).
"""

from __future__ import annotations

import warnings

import numpy as np

from uwbimu.errors import InputError

__all__ = ["welch_psd", "hann_periodic"]


def hann_periodic(m: int) -> np.ndarray:
    """The periodic (DFT-even) Hann window of ``m`` points, as ``scipy.signal.get_window("hann", m)``."""
    if m <= 1:
        return np.ones(m, dtype=np.float64)
    # general cosine window a = (0.5, 0.5) on m + 1 points, the last dropped (SciPy's construction)
    fac = np.linspace(-np.pi, np.pi, m + 1, dtype=np.float64)
    w = np.zeros(m + 1, dtype=np.float64)
    a = np.asarray([0.5, 1.0 - 0.5], dtype=np.float64)
    for k in range(a.shape[0]):
        w += a[k] * np.cos(k * fac)
    return w[:-1]


def welch_psd(x: np.ndarray, fs: float, nperseg: int, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density by Welch's method, ``scipy.signal.welch(x, fs=fs, nperseg=nperseg,
    axis=axis)`` bit for bit.

    Parameters
    ----------
    x : real samples (any shape), the time axis ``axis``.
    fs : sample rate [Hz] (> 0).
    nperseg : segment length [samples] (>= 1; the signal's length when longer, with SciPy's warning).
    axis : the time axis of ``x``.

    Returns
    -------
    (f, psd): frequencies [Hz], ``(nperseg // 2 + 1,)``; the density [unit^2 / Hz] along ``axis`` at those
    frequencies (the other axes of ``x`` kept).

    Raises
    ------
    InputError
        For complex or empty ``x``, ``fs <= 0`` or ``nperseg < 1`` (SciPy's other branches, not used here).
    """
    from scipy import fft as fft_lib  # scipy.fft: already imported with scipy.linalg, no scipy.stats

    x = np.asarray(x)
    axis = int(axis)
    if np.iscomplexobj(x) or x.size == 0:
        raise InputError("welch_psd: x must be real and non-empty")
    if not fs > 0:
        raise InputError(f"welch_psd: the sample rate must be positive, got {fs}")
    out_dtype = np.result_type(x, np.complex64)
    n = x.shape[axis]
    nperseg = int(nperseg)
    if nperseg < 1:
        raise InputError(f"welch_psd: nperseg must be a positive integer, got {nperseg}")
    if n < nperseg:
        warnings.warn(f"{nperseg=} is greater than signal length max(len(x), len(y)) = {n}, using "
                      f"nperseg = {n}", stacklevel=2)
        nperseg = n
    win = hann_periodic(nperseg)
    nfft = nperseg
    noverlap = nperseg // 2
    hop = nperseg - noverlap
    # ShortTimeFFT(win, hop, fs, fft_mode="onesided", mfft=nfft, scale_to="psd", phase_shift=None)
    T = 1 / fs
    s_fac = 1 / np.sqrt(sum(win.real ** 2 + win.imag ** 2) / T)
    win = win * s_fac
    m_num, m_num_mid = len(win), len(win) // 2
    f_pts = nfft // 2 + 1
    # spectrogram(x, x, detr="constant", p0=0, p1=(n - noverlap) // hop, k_offset=nperseg // 2, axis=axis)
    p0, p1 = 0, (n - noverlap) // hop
    k_offset = nperseg // 2
    if x.ndim > 1:
        x = np.moveaxis(x, axis, -1)
    S_shape_1d = (f_pts, p1 - p0)
    S = np.zeros(x.shape[:-1] + S_shape_1d if x.ndim > 1 else S_shape_1d, dtype=complex)
    n1 = (p1 - p0) * hop
    k0 = p0 * hop - m_num_mid + k_offset
    k1 = k0 + n1 + m_num
    i0, i1 = max(k0, 0), min(k1, n)
    pad_width = [(0, 0)] * (x.ndim - 1) + [(-min(k0, 0), max(k1 - n, 0))]
    x1 = np.pad(x[..., i0:i1], pad_width, mode="constant", constant_values=(0, 0))
    win_c = win.conj()
    for p_, k_ in enumerate(range(0, n1, hop)):
        x_ = x1[..., k_:k_ + m_num]
        x_ = x_ - np.mean(x_, -1, keepdims=True)  # detrend(type="constant")
        S[..., :, p_] = fft_lib.rfft(x_ * win_c, n=nfft, axis=-1)
    if x.ndim > 1:
        S = np.moveaxis(S, -2, axis if axis >= 0 else axis - 1)
    Pxy = S.real ** 2 + S.imag ** 2
    # one-sided: the bins other than DC (and Nyquist for an even length) doubled
    f_axis = Pxy.ndim - 1 + axis if axis < 0 else axis
    Pxy = np.moveaxis(Pxy, f_axis, -1)
    Pxy[..., 1:-1 if nfft % 2 == 0 else None] *= 2
    Pxy = np.moveaxis(Pxy, -1, f_axis)
    if Pxy.shape[-1] > 1:
        Pxy = Pxy.mean(axis=-1)
    else:
        Pxy = np.reshape(Pxy, Pxy.shape[:-1])
    Pxy = Pxy.astype(out_dtype).real
    return fft_lib.rfftfreq(nfft, T), Pxy
