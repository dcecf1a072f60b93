""":func:`uwbimu.estimation.spectrum.welch_psd` is ``scipy.signal.welch`` (default window, overlap, detrend,
scaling, averaging) bit for bit, without importing ``scipy.signal`` (and with it ``scipy.stats``)."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest
from scipy.signal import get_window, welch

from uwbimu.errors import InputError
from uwbimu.estimation.spectrum import hann_periodic, welch_psd


@pytest.mark.parametrize("shape, axis, fs, nperseg", [
    ((60000, 6), 0, 1000.0, 2000),      # the IMU noise rule's call: 1 kHz, 0.5 Hz bins, six axes
    ((60001, 6), 0, 999.7, 1999),       # odd segment: no Nyquist bin, a partial last hop
    ((5000,), -1, 200.0, 400),
    ((6, 7001), 1, 100.0, 201),
    ((3, 4, 3001), -1, 50.0, 100),
    ((100, 2), 0, 10.0, 300),           # segment longer than the signal: shortened, with SciPy's warning
    ((2000, 3), 0, 100.0, 1),
    ((2000, 3), 0, 100.0, 2),
])
def test_welch_psd_is_scipy_welch_bit_for_bit(shape, axis, fs, nperseg):
    x = np.random.default_rng(len(shape) * nperseg).standard_normal(shape) * 3.0 + 1.5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f_ref, p_ref = welch(x, fs=fs, nperseg=nperseg, axis=axis)
        f, p = welch_psd(x, fs=fs, nperseg=nperseg, axis=axis)
    assert p.dtype == p_ref.dtype and p.shape == p_ref.shape
    assert np.array_equal(f, f_ref)
    assert np.array_equal(p, p_ref)  # bit for bit, not close


@pytest.mark.parametrize("m", [1, 2, 7, 2000])
def test_hann_periodic_is_scipy_window(m):
    assert np.array_equal(hann_periodic(m), get_window("hann", m))


def test_welch_psd_refuses_bad_input():
    with pytest.raises(InputError):
        welch_psd(np.zeros(0), fs=1.0, nperseg=4)
    with pytest.raises(InputError):
        welch_psd(np.ones(10) + 1j, fs=1.0, nperseg=4)
    with pytest.raises(InputError):
        welch_psd(np.ones(10), fs=0.0, nperseg=4)
    with pytest.raises(InputError):
        welch_psd(np.ones(10), fs=1.0, nperseg=0)


def test_welch_psd_does_not_import_scipy_signal():
    code = ("import sys, numpy as np\n"
            "from uwbimu.estimation.spectrum import welch_psd\n"
            "welch_psd(np.random.default_rng(0).standard_normal((4000, 6)), fs=1000.0, nperseg=2000, axis=0)\n"
            "print(sorted(m for m in ('scipy.signal', 'scipy.stats') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]"
