"""Sensor noise levels measured on the log itself, and the variance factor the residuals ask for.

A preset (a datasheet's densities, or what an importer measured at rest) describes the sensor on the
bench. On a vehicle the accelerometer also carries vibration (a multirotor's is 100 times its
datasheet density), and the ranges carry multipath and non-line-of-sight errors no preset knows.
Three rules, each stated and tested (``tests/test_noise_from_data.py``):

1. **IMU densities from the spectrum** (:func:`imu_noise_from_log`). The white-noise density of each
   sensor is read off the Welch power spectral density of the IMU samples in the band
   :data:`IMU_BAND_HZ` (5-25 Hz, capped at 0.4 x the sample rate): the motion of the vehicles that carry a
   UWB tag (people, robots, multirotors) lies below 5 Hz, so the band holds the sensor noise plus the
   vibration, which for the filter is noise. A white sequence of density ``q`` has the one-sided PSD
   ``2 q^2``, hence ``q = sqrt(mean PSD over the band / 2)`` (the power of the three axes averaged).
   The density used is the larger of the preset and this estimate: a spectrum below the preset can
   only come from the sensor's own low-pass filter. The bias random walks are scaled by the same ratio
   (vibration rectifies into a wandering bias).
2. **Measurement noise by covariance matching** (:func:`measurement_noise_from_innovations`). After
   a first filter pass, the robust variance of the normalised innovations ``nu / sqrt(S)`` of each
   measurement kind (range, TDoA) is compared with 1; when it lies outside its 99 % sampling band the
   noise variance is corrected by ``R' = R + (k - 1) median(S)`` (``E[nu^2] = H P H^T + R``) and the
   pass is repeated once.
   A second statistic, ``statistic="mean_square"``, is the mean square of the normalised innovations of
   every processed measurement (accepted by the gate or not), each square capped at
   :data:`WINSOR_SIGMAS` squared: the level of the whole error distribution, tails included, for a
   pass whose sigma already fits the core (the robust step first). On real logs the errors are
   heavy-tailed and correlated in time (multipath, NLOS); a sigma fitted to the core alone makes the
   gate reject a fifth of the Crazyflie TDoA3 log and the filter follow the rest too closely.  From a
   pass with a badly wrong sigma it would overshoot (the filter off track inflates every innovation),
   hence robust first, then this.  It is not the default: robust, then mean square (one more pass) took
   the position RMSE of the Crazyflie TDoA2 / TDoA3 and INRoL logs from 0.307 / 0.431 / 0.191 m to
   0.272 / 0.401 / 0.181 m, but on the built-in ``nlos`` simulation (bursts of NLOS ranges, which the
   gate should reject) it raised the range sd from 0.05 to 0.093 m and the RMSE from 0.040 to 0.084 m.
   **Then the predictive likelihood** (:func:`predictive_loglik`, :mod:`.noise_search`). Covariance
   matching fits the core of the innovations; when it had to correct the configured sd (the log's noise
   is not the preset's), the sd is then chosen by the filter's own one-step predictive likelihood (the
   prediction-error decomposition of the likelihood, maximised over the noise level: the classical
   maximum-likelihood tuning of a Kalman filter), with each processed innovation's density a mixture of
   ``N(0, S)`` and a uniform outlier density over :func:`outlier_width` (outlier fraction fitted by EM at
   each level). It scores every processed measurement, accepted by the gate or not, under the pass that
   used that level, so a level whose filter follows the outliers, or rejects too much, or diverges,
   scores low; the score is the median over time blocks of the block means, so that a transient fault
   (a clock jump, a burst) does not set the level of the whole log. Measured (``python benchmarks/check_noise_search.py``): it takes the Crazyflie TDoA3 log
   from the matched 0.194 m to 0.349 m (position RMSE 0.420 -> 0.345 m), the mean NIS of the four real
   logs to 0.86-0.93; on a simulation with 10 % NLOS ranges and a configured sd 2.5 x too small, the
   RMSE from 0.202 to 0.176 m and the RMS t_d error / sd from 3.4 to 2.1 (3 seeds).  On the built-in
   ``nlos`` simulation matching keeps the configured (true) 0.05 m and no search runs, where the
   mean-square statistic above raised it to 0.093 m.
3. **The variance factor of the residuals** (:func:`residual_variance_factor`). The long-run
   variance of the normalised innovations, per measurement channel (anchor or TDoA pair), by batch
   means over blocks of ``ceil(sqrt(n))`` samples, pooled over the channels: for residuals that agree
   with the filter's model it is 1. When it is significantly above 1 (one-sided 99 %), the
   calibration sigmas are multiplied by its square root, as a least-squares a-posteriori variance
   factor: the sigma then agrees with the residuals' scatter and their correlation over time.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np

from uwbimu.errors import UsageError
from uwbimu.models.imu import ImuNoise

#: band [Hz] of the spectrum the IMU white-noise density is read from (capped at 0.4 x the sample rate)
IMU_BAND_HZ = (5.0, 25.0)
#: shortest stretch of IMU data the spectrum is computed on [s]
MIN_IMU_SECONDS = 8.0
#: one-sided normal quantile of the significance tests (99 %)
Z_99 = 2.326
#: relative efficiency of the MAD-based variance against the sample variance (normal data)
_MAD_VAR_EFFICIENCY = 0.37
#: ``statistic="mean_square"``: each squared normalised innovation counts at most this many sigmas squared
#: (a gross spike, e.g. a +100 m range, must not set the noise level alone)
WINSOR_SIGMAS = 10.0


def imu_noise_from_log(t: np.ndarray, u: np.ndarray, preset: ImuNoise) -> tuple[ImuNoise, dict[str, Any]]:
    """IMU densities measured on the log (rule 1 of the module docstring).

    Parameters
    ----------
    t : (n,) IMU stamps [s].
    u : (n, 6) specific force [m/s^2] and body rate [rad/s], IMU frame.
    preset : the densities known before the data (dataset.yaml's, or a datasheet preset).

    Returns
    -------
    (noise, report): the densities to use, and ``{accel: {preset, log, used, ratio}, gyro: {...},
    band_hz: [lo, hi], seconds, status}`` with densities in m/s^2/sqrt(Hz) and rad/s/sqrt(Hz);
    ``status`` is ``measured`` or ``too short`` (then the preset is used unchanged).
    """
    from uwbimu.estimation.spectrum import welch_psd as welch

    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    report: dict[str, Any] = {"seconds": float(t[-1] - t[0]) if len(t) else 0.0}
    if len(t) < 16 or report["seconds"] < MIN_IMU_SECONDS:
        report["status"] = "too short"
        return preset, report
    dt = float(np.median(np.diff(t)))
    fs = 1.0 / dt
    lo, hi = IMU_BAND_HZ[0], min(IMU_BAND_HZ[1], 0.4 * fs)
    if hi <= lo * 1.5:
        report["status"] = "sample rate too low"
        return preset, report
    nper = int(round(2.0 * fs))  # 0.5 Hz bins
    f, psd = welch(u - u.mean(axis=0), fs=fs, nperseg=nper, axis=0)
    band = (f >= lo) & (f <= hi)
    dens = np.sqrt(psd[band].mean(axis=0) / 2.0)  # per axis
    acc = float(np.sqrt(np.mean(dens[:3] ** 2)))
    gyr = float(np.sqrt(np.mean(dens[3:] ** 2)))
    used_acc = max(preset.accel_noise_density, acc)
    used_gyr = max(preset.gyro_noise_density, gyr)
    ra = used_acc / preset.accel_noise_density if preset.accel_noise_density > 0 else 1.0
    rg = used_gyr / preset.gyro_noise_density if preset.gyro_noise_density > 0 else 1.0
    noise = ImuNoise(gyro_noise_density=used_gyr, accel_noise_density=used_acc,
                     gyro_bias_rw=preset.gyro_bias_rw * rg, accel_bias_rw=preset.accel_bias_rw * ra,
                     gyro_bias_sigma0=preset.gyro_bias_sigma0, accel_bias_sigma0=preset.accel_bias_sigma0)
    report.update({
        "status": "measured", "band_hz": [lo, hi],
        "accel": {"preset": preset.accel_noise_density, "log": acc, "used": used_acc, "ratio": ra},
        "gyro": {"preset": preset.gyro_noise_density, "log": gyr, "used": used_gyr, "ratio": rg},
    })
    return noise, report


def _robust_var(e: np.ndarray) -> float:
    med = np.median(e)
    return float((1.4826 * np.median(np.abs(e - med))) ** 2)


def measurement_noise_from_innovations(innov: np.ndarray, S: np.ndarray, sigma: float,
                                       statistic: str = "robust") -> dict[str, Any]:
    """Covariance matching of one measurement kind (rule 2 of the module docstring).

    Parameters
    ----------
    innov, S : innovations [m] and their predicted variances [m^2]: of the accepted measurements for
        ``statistic="robust"``, of every processed one for ``"mean_square"``.
    sigma : the noise sd [m] the pass used.
    statistic : ``"robust"``: the MAD-based variance of the normalised innovations (the core of the
        distribution); ``"mean_square"``: their mean square, each capped at :data:`WINSOR_SIGMAS`
        squared (the whole distribution, tails included).

    Returns
    -------
    ``{n, k, band: [lo, hi], sigma, sigma_new, changed, statistic}``: ``k`` the chosen variance of the
    normalised innovations, ``sigma_new`` the corrected sd (``sigma`` when ``k`` lies in its 99 % band).
    """
    if statistic not in ("robust", "mean_square"):
        raise UsageError(f"statistic must be 'robust' or 'mean_square', got {statistic!r}")
    ok = np.isfinite(innov) & np.isfinite(S) & (S > 0)
    e = innov[ok] / np.sqrt(S[ok])
    n = int(e.size)
    out: dict[str, Any] = {"n": n, "sigma": float(sigma), "sigma_new": float(sigma), "changed": False,
                           "statistic": statistic}
    if n < 30:
        out.update({"k": float("nan"), "band": [float("nan")] * 2})
        return out
    if statistic == "robust":
        k = _robust_var(e)
        half = 2.576 * math.sqrt(2.0 / (_MAD_VAR_EFFICIENCY * n))
    else:
        k = float(np.mean(np.minimum(e * e, WINSOR_SIGMAS**2)))
        half = 2.576 * math.sqrt(2.0 / n)  # sd of the mean of n chi2(1) / n
    out.update({"k": k, "band": [1.0 - half, 1.0 + half]})
    if abs(k - 1.0) > half:
        r2 = sigma**2 + (k - 1.0) * float(np.median(S[ok]))
        # never below a quarter of the variance used: S is dominated by R in steady state, and a
        # collapse to 0 would make every later residual an outlier
        out["sigma_new"] = float(math.sqrt(max(r2, 0.25 * sigma**2)))
        out["changed"] = True
    return out


def residual_variance_factor(innov: np.ndarray, S: np.ndarray, channel: np.ndarray) -> dict[str, Any]:
    """Long-run variance of the normalised innovations, pooled over channels (rule 3).

    Parameters
    ----------
    innov, S : innovations and their predicted variances of the accepted measurements, in time order.
    channel : (n,) integer channel of each (anchor, or TDoA pair).

    Returns
    -------
    ``{factor, variance, long_run_variance, n, threshold, applied}``: ``variance`` the mean normalised
    innovation squared (the NIS per dof), ``long_run_variance`` the pooled batch-means estimate,
    ``threshold`` its one-sided 99 % bound under a model that fits, ``factor`` the sigma multiplier
    (``sqrt(long_run_variance)`` when above the bound, else 1).
    """
    ok = np.isfinite(innov) & np.isfinite(S) & (S > 0)
    e = innov[ok] / np.sqrt(S[ok])
    ch = np.asarray(channel)[ok]
    num, den, n_blocks = 0.0, 0, 0
    for c in np.unique(ch):
        x = e[ch == c]
        n = x.size
        b = int(math.ceil(math.sqrt(n)))
        nb = n // b
        if nb < 4:
            continue
        m = x[: nb * b].reshape(nb, b).mean(axis=1)
        num += b * float(np.sum(m**2))  # b * block-mean^2 estimates the long-run variance (zero mean)
        den += nb
        n_blocks += nb
    out: dict[str, Any] = {"n": int(e.size), "variance": float(np.mean(e**2)) if e.size else float("nan")}
    if den == 0:
        out.update({"long_run_variance": float("nan"), "threshold": float("nan"), "factor": 1.0,
                    "applied": False})
        return out
    lrv = num / den
    # under a fitting model each b*mean^2 is chi2(1): the pooled mean has sd sqrt(2 / blocks)
    thr = 1.0 + Z_99 * math.sqrt(2.0 / n_blocks)
    applied = bool(lrv > thr)
    out.update({"long_run_variance": lrv, "blocks": n_blocks, "threshold": thr, "applied": applied,
                "factor": math.sqrt(lrv) if applied else 1.0})
    return out


def outlier_width(anchors: np.ndarray) -> float:
    """Width [m] of the uniform outlier density of :func:`predictive_loglik`: twice the largest anchor
    separation (a range or a range difference lies within it; a gross error beyond it is still scored,
    at that density).  Scale-aware: a 4 m room and a 40 m hall get their own."""
    a = np.asarray(anchors, dtype=float).reshape(-1, 3)
    if len(a) < 2:
        return 20.0
    d = np.sqrt(((a[:, None, :] - a[None, :, :]) ** 2).sum(axis=-1))
    return float(max(2.0 * d.max(), 1.0))


def predictive_loglik(innov: np.ndarray, S: np.ndarray, width: float, iters: int = 200) -> dict[str, Any]:
    """Mean one-step predictive log-likelihood of a pass's innovations under an outlier mixture.

    Each innovation ``nu_i`` with predicted variance ``S_i`` has the density
    ``(1 - eps) N(nu_i; 0, S_i) + eps / width``; the outlier fraction ``eps`` is fitted by EM (the mean
    posterior probability of the outlier component, a concave problem in ``eps``).

    Parameters
    ----------
    innov, S : innovations [m] and their predicted variances [m^2] of every processed measurement (accepted
        by the gate or not), in any order.
    width : the outlier density's width [m] (:func:`outlier_width`).
    iters : EM iterations at most (stops when ``eps`` changes by < 1e-9).

    Returns
    -------
    ``{ll, score, eps, n}``: ``ll`` the mean log-likelihood per measurement [nats], ``score`` the median over
    consecutive blocks of ``ceil(sqrt(n))`` innovations of their mean (what the search maximises: a transient
    fault in a few blocks does not move it), ``eps`` the outlier fraction, ``n`` the number of innovations.
    """
    ok = np.isfinite(innov) & np.isfinite(S) & (S > 0)
    nu, s = np.asarray(innov, float)[ok], np.asarray(S, float)[ok]
    n = int(nu.size)
    if n == 0:
        return {"ll": float("nan"), "score": float("nan"), "eps": float("nan"), "n": 0}
    # log N(nu; 0, S) and log(1/width); mixture via logaddexp (an innovation of 100 sigma must not underflow)
    lg = -0.5 * (nu * nu / s + np.log(2.0 * math.pi * s))
    lu = -math.log(width)
    eps = 0.05
    for _ in range(iters):
        la = np.log1p(-eps) + lg
        lb = math.log(eps) + lu
        post = np.exp(lb - np.logaddexp(la, lb))
        new = float(np.clip(post.mean(), 1e-6, 0.5))
        if abs(new - eps) < 1e-9:
            eps = new
            break
        eps = new
    li = np.logaddexp(np.log1p(-eps) + lg, math.log(eps) + lu)
    # the score of the level: the median over consecutive blocks of ceil(sqrt(n)) innovations (in the order
    # given: time) of their mean log-likelihood, so that a transient fault confined to a few blocks (a clock
    # jump, a burst while the filter re-converges) does not set the noise level of the whole log
    b = int(math.ceil(math.sqrt(n)))
    nb = n // b
    score = float(np.median(li[: nb * b].reshape(nb, b).mean(axis=1))) if nb >= 3 else float(np.mean(li))
    return {"ll": float(np.mean(li)), "score": score, "eps": eps, "n": n}
