"""One pass of the ESKF over (part of) a dataset, with the data in plain arrays.

:class:`Problem` holds the dataset as contiguous arrays plus the resolved
numeric settings; :func:`run_pass` runs the filter from a given initial
state, range index and IMU sample until the data (or a window) ends or the
supervisor declares divergence.  The initialiser's hypothesis bank and the
main run both use it.

Time-offset handling
--------------------
A range stamped ``t`` (UWB clock) observes the state at IMU time
``tau = t + t_d_hat``.  The filter is propagated with the IMU samples until
its time ``t_k`` (an IMU stamp) passes ``tau`` — so ranges are processed with
a delay of at most one IMU period when ``t_d > 0`` and as soon as possible when
``t_d < 0`` — then the state at ``tau`` is obtained by integrating the actual
IMU samples *backward* from the current estimate (:func:`kernels.state_at`).
The update itself is applied at ``t_k`` with the measurement Jacobian mapped
through ``dx(tau) = (I - F (t_k - tau)) dx(t_k)`` (first order); since
``t_k - tau`` is below one IMU period except right after a large correction of
``t_d_hat`` (bounded by ``max_lookback_s``), this approximation of the
correlation between the two instants is of order ``dt_imu`` and negligible.
The Jacobian with respect to ``t_d`` is the time derivative of the predicted
antenna position, ``-u^T (v + R [w]x p_IU)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np

from uwbimu.estimation import kernels as K

# columns of the per-range output record
REC_PRED, REC_INNOV, REC_NIS, REC_ACC, REC_W, REC_STATUS, REC_S = range(7)
STATUS_NOT_PROCESSED = -1
STATUS_STALE = 2  # tau older than max_lookback behind the filter
STATUS_IN_GAP = 3  # tau inside an IMU gap: the motion there is unknown, the range is not used


@dataclass
class Problem:
    """A dataset as arrays, with the numeric settings resolved from the options."""

    imu_t: np.ndarray  # (n,) IMU clock [s]
    imu_u: np.ndarray  # (n, 6)
    imu_um: np.ndarray  # (n-1, 6) cubic mid-interval inputs (reference.midpoint_inputs)
    uwb_t: np.ndarray  # (m,) UWB clock [s]
    uwb_a: np.ndarray  # (m,) anchor index
    uwb_r: np.ndarray  # (m,) range [m] (documented biases already removed)
    anchor_ids: list[str]
    anchors: np.ndarray  # (M, 3)
    noise: np.ndarray  # (6,) squared densities for kernels.cov_step (+ (2,) Gauss-Markov bias variance, 1/tau)
    r_var: float  # range variance [m^2]
    bias_idx: np.ndarray  # (M,) error index of each anchor's bias or -1
    gain_mask: np.ndarray  # (N,)
    dt_nom: float
    dt_max: float
    gate: float  # NIS threshold (<= 0: none)
    robust_kind: int
    robust_c: float
    reopen_after: int
    cov_every: int
    max_lookback: float
    out_period: float
    store_cov: bool
    hull_lo: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    hull_hi: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    max_pos_var: float = np.inf
    all_reject_run: int = 10**9
    supervise: bool = False

    @property
    def n_err(self) -> int:
        return self.gain_mask.shape[0]


@dataclass
class PassResult:
    """Outputs of :func:`run_pass`."""

    t_imu: np.ndarray  # (K,) filter times (IMU clock)
    states: np.ndarray  # (K, 20 + nb)
    cov_diag: np.ndarray  # (K, N)
    covs: Optional[np.ndarray]  # (K, N, N) or None
    rec: np.ndarray  # (m, 7) per-range record for ranges [j0, j_end)
    j0: int
    j_end: int
    x: np.ndarray
    P: np.ndarray
    k: int
    diverged: Optional[str] = None
    events: list[dict[str, Any]] = field(default_factory=list)


def _diverged(prob: Problem, x: np.ndarray, P: np.ndarray, all_rej: int) -> Optional[str]:
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(np.diag(P)))):
        return "NaN in state or covariance"
    if np.any(np.diag(P) < -1e-9):
        return "negative covariance diagonal"
    pv = P[0, 0] + P[1, 1] + P[2, 2]
    if pv > prob.max_pos_var:
        return f"position sd {np.sqrt(pv):.1f} m above limit"
    if np.any(x[:3] < prob.hull_lo) or np.any(x[:3] > prob.hull_hi):
        return f"position {np.round(x[:3], 2).tolist()} far outside the anchors' hull"
    if all_rej >= prob.all_reject_run:
        return f"{all_rej} consecutive ranges rejected"
    return None


def run_pass(
    prob: Problem,
    x0: np.ndarray,
    P0: np.ndarray,
    k0: int,
    j0: int,
    t_uwb_end: float = np.inf,
    record: bool = True,
    to_end: bool = True,
    progress: Optional[Callable[[int], None]] = None,
) -> PassResult:
    """Run the filter from IMU sample ``k0`` (state ``x0``, ``P0``) and range ``j0``.

    Ranges with stamps beyond ``t_uwb_end`` are left alone.  ``record``
    stores the state and covariance every ``out_period`` seconds; ``to_end``
    propagates (and records) to the end of the IMU stream after the last range.
    """
    imu_t, imu_u = prob.imu_t, prob.imu_u
    n_imu = imu_t.shape[0]
    x = np.array(x0, dtype=float)
    P = np.array(P0, dtype=float)
    N = P.shape[0]
    k = int(k0)
    ws = np.zeros(1)
    m = prob.uwb_t.shape[0]
    rec = np.full((max(m - j0, 0), 7), np.nan)
    rec[:, REC_STATUS] = STATUS_NOT_PROCESSED
    rec[:, REC_ACC] = 0.0
    consec = np.zeros(len(prob.anchor_ids), dtype=np.int64)
    all_rej = 0
    out_t: list[float] = []
    out_x: list[np.ndarray] = []
    out_d: list[np.ndarray] = []
    out_P: list[np.ndarray] = []
    events: list[dict[str, Any]] = []
    o = np.empty(7)
    diverged = None

    def _record():
        out_t.append(imu_t[k])
        out_x.append(x.copy())
        out_d.append(np.diag(P).copy())
        if prob.store_cov:
            out_P.append(P.copy())

    next_out = imu_t[k]
    j = j0
    t_last = imu_t[-1]
    while j < m:
        tj = prob.uwb_t[j]
        if tj > t_uwb_end:
            break
        tau = tj + x[19]
        if tau > t_last:
            break
        if record:
            while next_out <= tau:
                k = K.propagate_until(x, P, imu_t, imu_u, prob.imu_um, k, next_out, prob.noise, prob.dt_max,
                                      prob.cov_every, ws)
                _record()
                next_out += prob.out_period
                if prob.supervise:
                    diverged = _diverged(prob, x, P, all_rej)
                    if diverged:
                        break
                if progress is not None:
                    progress(k)
            if diverged:
                break
        k = K.propagate_until(x, P, imu_t, imu_u, prob.imu_um, k, tau, prob.noise, prob.dt_max, prob.cov_every,
                              ws)
        i = j - j0
        if imu_t[k] - tau > prob.max_lookback:
            rec[i, REC_STATUS] = STATUS_STALE
            j += 1
            continue
        if k > 0 and imu_t[k] - imu_t[k - 1] > prob.dt_max and imu_t[k - 1] < tau < imu_t[k]:
            rec[i, REC_STATUS] = STATUS_IN_GAP
            j += 1
            continue
        a = prob.uwb_a[j]
        force = consec[a] >= prob.reopen_after
        K.range_update(
            x, P, imu_t, imu_u, prob.imu_um, k, tau, prob.anchors[a], prob.bias_idx[a], prob.uwb_r[j], prob.r_var,
            prob.gate, force, prob.robust_kind, prob.robust_c, prob.gain_mask, prob.dt_max, o,
        )
        rec[i] = o
        if o[REC_ACC] > 0:
            if force:
                # a reopened gate does not prove the filter healthy: keep counting towards divergence
                events.append({"t": float(tj), "kind": "gate_reopened", "anchor": prob.anchor_ids[a],
                               "after_rejections": int(consec[a])})
                all_rej += 1
            else:
                all_rej = 0
            consec[a] = 0
        elif o[REC_STATUS] == K.UPD_OK:
            consec[a] += 1
            all_rej += 1
        j += 1
        if prob.supervise and all_rej >= prob.all_reject_run:
            diverged = _diverged(prob, x, P, all_rej)
            if diverged:
                break
    if not diverged and record and to_end:
        while next_out <= t_last + 1e-12:
            k = K.propagate_until(x, P, imu_t, imu_u, prob.imu_um, k, next_out, prob.noise, prob.dt_max,
                                      prob.cov_every, ws)
            _record()
            next_out += prob.out_period
            if k >= n_imu - 1:
                break
    if progress is not None:
        progress(k)
    nb = x.shape[0]
    return PassResult(
        t_imu=np.array(out_t),
        states=np.array(out_x).reshape(-1, nb),
        cov_diag=np.array(out_d).reshape(-1, N),
        covs=np.array(out_P).reshape(-1, N, N) if prob.store_cov else None,
        rec=rec[: j - j0],
        j0=j0,
        j_end=j,
        x=x,
        P=P,
        k=k,
        diverged=diverged,
        events=events,
    )
