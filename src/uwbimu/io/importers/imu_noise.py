"""IMU white-noise densities measured on the stationary start of the sequence an importer reads.

Importers write only what they measured on (or what is documented for) the
sequence they read: the IMU noise densities of ``dataset.yaml`` come from the
first seconds of that sequence when the rig stands still there, else from the
sensor's class preset (and the note says which).  Bias random walks cannot be
measured from a few minutes and always come from the preset.
"""

from __future__ import annotations

from uwbimu.errors import UsageError
import math
from typing import Literal

import numpy as np
import pandas as pd

from uwbimu.models.imu import ImuNoise

__all__ = ["imu_noise_at_rest", "density_welch", "round_up_half_step", "NOISE_BAND_HZ"]

#: Band [Hz] of the at-rest spectrum used for the Welch white-noise density (below a board's low-pass).
NOISE_BAND_HZ = (0.5, 5.0)
#: Largest per-axis sd at rest [rad/s, m/s^2]; above, the start is not taken as "at rest".
REST_GYRO_SD, REST_ACCEL_SD = 0.05, 0.2
GRAVITY = 9.81


def density_welch(x: np.ndarray, fs: float) -> float:
    """Noise density [unit/sqrt(Hz)] from the low-frequency Welch spectrum, mean over axes.

    ``sqrt(mean one-sided PSD over NOISE_BAND_HZ / 2)``: the one-sided PSD of
    white noise of two-sided density ``q`` is ``2 q^2``.  Unlike ``sd *
    sqrt(dt)`` this does not assume the noise is white up to Nyquist, which
    understates the in-band density of a low-pass filtered sensor (~3x on ISAS-Walk).
    """
    from scipy.signal import welch

    nper = int(min(len(x), max(16, round(4.0 * fs))))  # ~4 s segments: 0.25 Hz resolution
    f, pxx = welch(x - x.mean(axis=0), fs=fs, nperseg=nper, axis=0, detrend="linear")
    band = (f >= NOISE_BAND_HZ[0]) & (f <= NOISE_BAND_HZ[1])
    if band.sum() < 2:
        band = f > 0
    return float(np.mean(np.sqrt(pxx[band].mean(axis=0) / 2.0)))


def round_up_half_step(x: float) -> float:
    """``x`` rounded up to a half step of its leading digit (2.93e-4 -> 3.0e-4, 1.39e-3 -> 1.5e-3)."""
    if not x > 0:
        return x
    step = 0.5 * 10.0 ** math.floor(math.log10(x))
    return float(round(math.ceil(x / step - 1e-9) * step, 12))


def imu_noise_at_rest(imu: pd.DataFrame, preset: ImuNoise, rest_s: float, method: Literal["welch", "sd"],
                      preset_name: str, **fixed: float) -> tuple[ImuNoise, str]:
    """White-noise densities measured over the first ``rest_s`` seconds; the rest from ``preset``.

    Parameters
    ----------
    imu : table ``t, ax..az, wx..wz`` (s, m/s^2, rad/s).
    preset : the sensor class's noise (bias random walks, fallback densities).
    rest_s : length of the stationary start [s].
    method : ``"welch"``: mean over axes of the 0.5-5 Hz Welch density (for a
        low-pass filtered board); ``"sd"``: largest per-axis ``sd * sqrt(dt)``,
        rounded up to a half step of its leading digit (white up to Nyquist).
    preset_name : the preset's name, for the note.
    fixed : other :class:`ImuNoise` fields set by the importer (e.g. ``gyro_bias_sigma0``).

    Returns
    -------
    (noise, note): the note says what was measured, over which span, or why the preset was used.
    The initial accelerometer-bias sd is widened to cover the measured ``| |a| - g |`` at rest.
    """
    base = preset.model_copy(update=fixed)
    t = imu["t"].to_numpy(float)
    m = t <= t[0] + rest_s
    if m.sum() < 50:
        return base, f"{preset_name} preset (too few samples in the first {rest_s:g} s to measure noise at rest)"
    w = imu.loc[m, ["wx", "wy", "wz"]].to_numpy(float)
    a = imu.loc[m, ["ax", "ay", "az"]].to_numpy(float)
    sd_w, sd_a = w.std(axis=0), a.std(axis=0)
    if sd_w.max() > REST_GYRO_SD or sd_a.max() > REST_ACCEL_SD:
        return base, f"{preset_name} preset (the first {rest_s:g} s are not at rest)"
    dt = float(np.median(np.diff(t[m])))
    g_err = abs(float(np.linalg.norm(a, axis=1).mean()) - GRAVITY)
    if method == "welch":
        fs = 1.0 / dt
        q_w, q_a = density_welch(w, fs), density_welch(a, fs)
        how = (f"from the Welch spectrum over {NOISE_BAND_HZ[0]:g}-{NOISE_BAND_HZ[1]:g} Hz (sd*sqrt(dt) would "
               f"give {sd_w.mean() * np.sqrt(dt):.2e} and {sd_a.mean() * np.sqrt(dt):.2e}: the board low-pass "
               "filters)")
    elif method == "sd":
        raw_w, raw_a = float(sd_w.max() * np.sqrt(dt)), float(sd_a.max() * np.sqrt(dt))
        q_w, q_a = round_up_half_step(raw_w), round_up_half_step(raw_a)
        how = (f"as the largest per-axis sd*sqrt(dt) ({raw_w:.2e}, {raw_a:.2e}) rounded up to a half step of the "
               "leading digit")
    else:
        raise UsageError(f"method must be 'welch' or 'sd', got {method!r}")
    noise = base.model_copy(update={
        "gyro_noise_density": q_w,
        "accel_noise_density": q_a,
        "accel_bias_sigma0": float(max(base.accel_bias_sigma0, 1.5 * g_err)),
    })
    note = (f"white-noise densities measured at rest over the first {rest_s:g} s {how}: gyro {q_w:.2e} "
            f"rad/s/sqrt(Hz), accel {q_a:.2e} m/s^2/sqrt(Hz); bias random walks of the {preset_name} preset; "
            f"initial accel-bias sd {noise.accel_bias_sigma0:.2f} m/s^2 covers | |a| - g | = {g_err:.3f} m/s^2 "
            "at rest")
    return noise, note
