"""The range model chosen on the log: held-out likelihood over time blocks (cross-validation).

Which range model serves a log (white noise plus a constant bias per anchor; plus a direction-dependent
bias in the tag's body frame; plus a slowly varying bias per anchor; both) and which Huber threshold
is decided on that log, from the range residuals about a trajectory already fitted: nothing is re-solved,
so the choice costs a fraction of a second to a few seconds.  ``uwbimu calibrate`` uses the batch's own first
free solve (:mod:`uwbimu.calibration.range_model_stage`, :func:`select_on_residuals`); :func:`select_range_model`
takes any trajectory (e.g. an ESKF run).

Rule (stated, tested in ``tests/test_range_model_select.py``):

1. **Residuals.** ``r = range - ||p(t) + R(t) p_IU - a_j||`` with the trajectory interpolated at the
   range stamps (UWB clock) and its lever arm, and the line of sight ``w_b = R^T (a_j - p - R p_IU)``
   in the body frame for the direction features
   (:func:`uwbimu.calibration.range_factor.direction_features`).
2. **Folds.** The span of the ranges is cut into ``K`` contiguous time blocks of equal duration
   (contiguous: errors correlated in time would otherwise leak from the training rows into the
   held-out ones and favour the richer models).
3. **Fit on K-1 blocks.** The mean model (a constant bias per anchor, plus the shared direction
   coefficients for the direction families; ridge priors of ``anchor_bias_prior_sd`` and the direction's
   ``prior_sd``) by Huber IRLS; then the noise parameters by maximum likelihood: white sd ``sigma``
   and, for the drift families, the stationary sd and correlation time of a first-order Gauss-Markov
   bias per anchor (the ``range_bias_drift`` model, in continuous time).
4. **Score the held-out block.** Its log-likelihood per range under the fitted model: the residuals
   run through a per-anchor scalar Kalman filter of the Gauss-Markov bias (restarted from its
   stationary prior at every block edge: the held-out block is predicted from itself only), each
   standardised one-step prediction error ``z`` scored by the normalised Huber density
   ``exp(-rho_k(z)) / C_k`` (``C_k = sqrt(2 pi) (2 Phi(k) - 1) + 2 exp(-k^2 / 2) / k``) and
   ``-ln sqrt(v)``; the filter update uses the clipped error (Huber-robust).  A white model is the
   same with no bias state.  The Huber threshold ``k`` is thereby a parameter of a proper density,
   chosen on the same scores.
5. **Choose.** Family first: each family at its best ``k`` (mean score); the simplest family (order
   white, direction, drift, direction+drift) whose per-fold score difference from the best family has
   mean within one standard error (of the paired differences) is chosen.  Then ``k`` within that
   family the same way, the largest ``k`` (closest to least squares) counting as the simplest.

The importers write no model choice: only this record, computed on the log, chooses
(:func:`select_range_model`; :func:`apply_selection` turns it into calibration options).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Optional, Sequence

import numpy as np
from numba import njit
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation, Slerp
from scipy.stats import norm

from uwbimu.errors import InputError

#: Families in order of simplicity (the one-standard-error rule favours the earlier).
FAMILIES = ("white", "direction", "drift", "direction+drift")
#: Huber thresholds tried (in sigmas); the largest counts as the simplest (closest to least squares).
HUBER_GRID = (1.0, 1.345, 2.0, 3.0, 5.0)
#: Time blocks of the cross-validation.
N_FOLDS = 5
#: Fewest ranges a block must hold.
MIN_BLOCK_ROWS = 50
#: Ranges where the trajectory's position sd exceeds this multiple of its median are left out (settling).
SETTLED_SD_RATIO = 2.0
#: Window [s] of the trajectory correction fitted with every model (the fitted trajectory's own error).
TRAJECTORY_WINDOW_S = 0.5
#: Prior sd [m] of that correction per axis (keeps a window with poor geometry near the trajectory).
TRAJECTORY_PRIOR_SD = 0.2
#: A summed held-out log-likelihood gain below this [nats] is a tie (2 x 3 = 6: a chi-square(2) at 95 %).
TIE_NATS = 3.0
#: Most training rows the noise parameters are fitted on (every m-th range beyond it: the parameters are
#: continuous-time, so a thinned series has the same ones)
MAX_FIT_ROWS = 8000
#: Bounds of the fitted correlation time [s] of the slowly varying bias.
TAU_BOUNDS = (0.05, 200.0)


@dataclass
class RangeModelSelection:
    """What :func:`select_range_model` found.

    Attributes
    ----------
    candidates : family names tried (:data:`FAMILIES`).
    huber_grid : Huber thresholds tried [sigmas].
    folds : number of time blocks; ``block_edges`` their edges [s, UWB clock].
    scores : ``{family: {k: [held-out log-likelihood per range, one per fold]}}`` (k as a string).
    family_scores : per family, the per-fold scores at its best ``k``; ``family_k`` that ``k``.
    chosen : the family chosen; ``huber_k`` the threshold chosen.
    reason : the rule's outcome in words, with the numbers that decided it.
    params : the chosen model refitted on the whole log: ``sigma`` [m], ``drift_sd`` [m],
        ``correlation_time`` [s] (drift families), ``direction`` coefficients [m] (direction families),
        ``anchor_bias`` [m] per anchor.
    n_ranges : ranges used.
    basis : what the residuals are about: ``trajectory`` (a given trajectory, e.g. the initialising ESKF's) or
        ``free_solve`` (the batch's own first free solve, :mod:`uwbimu.calibration.range_model_stage`).
    """

    candidates: list[str]
    huber_grid: list[float]
    folds: int
    block_edges: list[float]
    scores: dict[str, dict[str, list[float]]]
    family_scores: dict[str, list[float]]
    family_k: dict[str, float]
    chosen: str
    huber_k: float
    reason: str
    params: dict[str, Any] = field(default_factory=dict)
    n_ranges: int = 0
    basis: str = "trajectory"

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (floats, lists, dicts) for calibration.yaml and events."""
        return asdict(self)


# ---------------------------------------------------------------------------------------------- residuals
def range_residuals(dataset, trajectory) -> dict[str, np.ndarray]:
    """Range residuals about a fitted trajectory and the body-frame lines of sight.

    Parameters
    ----------
    dataset : :class:`uwbimu.io.dataset.Dataset` with ``uwb`` (``t`` [s, UWB clock], ``anchor``,
        ``range`` [m]) and ``anchors`` (``anchor, x, y, z`` [m], world frame).
    trajectory : an :class:`~uwbimu.estimation.EstimationResult` (``t`` UWB clock, states with ``p``
        [m, world] and ``q`` [qw, qx, qy, qz], body -> world; ``calibration["lever_arm"]`` [m, IMU frame]).

    Returns
    -------
    dict of arrays: ``t`` [s], ``anchor`` (int index into ``anchors``), ``anchors`` (names), ``r``
    residual [m] (range - predicted), ``wb`` (n, 3) line of sight tag antenna -> anchor, body frame [m].
    Ranges outside the trajectory's span or with a non-finite state are left out.
    """
    from uwbimu.models.state import EP, P, Q

    u = getattr(dataset, "uwb", None)
    if u is None or len(u) == 0:
        raise InputError("range model selection needs two-way ranges (uwb.csv): the log has none")
    anchors = dataset.anchors
    pos = {str(a): np.array([x, y, z], float) for a, x, y, z in anchors[["anchor", "x", "y", "z"]].itertuples(index=False)}
    tt = np.asarray(trajectory.t, float)
    X = np.asarray(trajectory.states, float)
    ok = np.isfinite(tt) & np.all(np.isfinite(X[:, P]), axis=1) & np.all(np.isfinite(X[:, Q]), axis=1)
    tt, X = tt[ok], X[ok]
    # a filter writes several states at one stamp (updates at an IMU sample's time): the last one is the
    # state after every update of that instant; the interpolation needs strictly increasing times
    rev = np.unique(tt[::-1], return_index=True)[1]
    last = len(tt) - 1 - rev
    tt, X = tt[last], X[last]
    if len(tt) < 2:
        raise InputError("range model selection: the trajectory has fewer than two finite states")
    lever = np.asarray(trajectory.calibration["lever_arm"], float)
    t = u["t"].to_numpy(float)
    names = u["anchor"].astype(str).to_numpy()
    keep = (t >= tt[0]) & (t <= tt[-1]) & np.isin(names, list(pos)) & np.isfinite(u["range"].to_numpy(float))
    t, names, rng = t[keep], names[keep], u["range"].to_numpy(float)[keep]
    p = np.column_stack([np.interp(t, tt, X[:, P][:, i]) for i in range(3)])
    qw = X[:, Q]
    rot = Slerp(tt, Rotation.from_quat(np.column_stack([qw[:, 1:], qw[:, :1]])))(t)
    ant = p + rot.apply(lever)
    names_sorted = sorted(set(names))
    idx = np.searchsorted(names_sorted, names)
    a_xyz = np.array([pos[n] for n in names_sorted])[idx]
    los_w = a_xyz - ant
    dist = np.linalg.norm(los_w, axis=1)
    r = rng - dist
    out = {"t": t, "anchor": idx.astype(np.int64), "anchors": np.array(names_sorted), "r": r,
           "wb": rot.inv().apply(los_w), "u": los_w / np.maximum(dist, 1e-9)[:, None]}
    sd = getattr(trajectory, "sd", None)
    if sd is not None and np.asarray(sd).ndim == 2 and np.asarray(sd).shape[1] >= EP.stop:
        psd = np.linalg.norm(np.asarray(sd, float)[ok][last][:, EP], axis=1)
        good = np.isfinite(psd)
        if good.sum() >= 2:
            # the filter's settling (position sd well above its typical value) is left out: there the
            # residuals are the start-up's, not the range model's
            settled = np.interp(t, tt[good], psd[good]) <= SETTLED_SD_RATIO * float(np.median(psd[good]))
            out = {k: (v[settled] if k != "anchors" else v) for k, v in out.items()}
    return out


# ---------------------------------------------------------------------------------------------- likelihood
def huber_log_norm(k: float) -> float:
    """``ln C_k`` of the normalised Huber density ``exp(-rho_k(z)) / C_k`` (unit scale)."""
    return math.log(math.sqrt(2 * math.pi) * (2 * norm.cdf(k) - 1) + 2 * math.exp(-0.5 * k * k) / k)


@njit(cache=True)
def _gm_loglik(t, e, anchor, block, n_anchor, sigma, sd_d, tau, k, log_ck, out):
    """Per-row log-likelihood of residuals ``e`` under white noise ``sigma`` plus a per-anchor
    Gauss-Markov bias (stationary sd ``sd_d``, correlation time ``tau``), Huber-``k`` scored and
    Huber-robust updated; the bias state restarts at its stationary prior when the block changes."""
    m = np.zeros(n_anchor)
    P = np.zeros(n_anchor)
    tl = np.zeros(n_anchor)
    bl = np.full(n_anchor, -1)
    s2, d2 = sigma * sigma, sd_d * sd_d
    for i in range(len(e)):
        a = anchor[i]
        if bl[a] != block[i]:
            m[a] = 0.0
            P[a] = d2
        else:
            phi = math.exp(-(t[i] - tl[a]) / tau) if tau > 0 else 0.0
            m[a] = phi * m[a]
            P[a] = phi * phi * P[a] + d2 * (1.0 - phi * phi)
        v = P[a] + s2
        sv = math.sqrt(v)
        z = (e[i] - m[a]) / sv
        az = abs(z)
        rho = 0.5 * z * z if az <= k else k * az - 0.5 * k * k
        out[i] = -rho - math.log(sv) - log_ck
        psi = z if az <= k else k * (1.0 if z > 0 else -1.0)
        g = P[a] / v
        m[a] = m[a] + g * psi * sv
        P[a] = (1.0 - g) * P[a]
        tl[a] = t[i]
        bl[a] = block[i]


def _loglik(d: dict, e: np.ndarray, rows: np.ndarray, noise: tuple[float, float, float], k: float) -> np.ndarray:
    out = np.empty(int(rows.sum()))
    _gm_loglik(d["t"][rows], e[rows], d["anchor"][rows], d["block"][rows], len(d["anchors"]), noise[0], noise[1],
               noise[2], float(k), huber_log_norm(k), out)
    return out


def _fit_noise(d: dict, e: np.ndarray, rows: np.ndarray, drift: bool, k: float,
               start: Optional[tuple[float, float, float]] = None) -> tuple[float, float, float]:
    """Maximum-likelihood ``(sigma, drift_sd, tau)`` on ``rows`` (``drift_sd = 0`` without drift);
    ``start``: a previous optimum to start from (one start), else two starts in ``tau``."""
    x = e[rows]
    s0 = max(1.4826 * float(np.median(np.abs(x - np.median(x)))), 1e-4)
    # 1 % on the (log) parameters, 0.1 nat on the training log-likelihood: far below what the held-out scores resolve
    opts = {"xatol": 1e-2, "fatol": 0.1, "maxiter": 300}
    if not drift:
        def nll1(ls):
            return -float(np.sum(_loglik(d, e, rows, (math.exp(ls[0]), 0.0, 1.0), k)))
        x0 = math.log(start[0]) if start is not None else math.log(s0)
        r = minimize(nll1, [x0], method="Nelder-Mead", options=opts)
        return math.exp(r.x[0]), 0.0, 1.0

    def nll(th):
        tau = float(np.clip(math.exp(th[2]), *TAU_BOUNDS))
        return -float(np.sum(_loglik(d, e, rows, (math.exp(th[0]), math.exp(th[1]), tau), k)))
    if start is None:
        # moments: the lag-one covariance of each anchor's consecutive residuals is about the bias variance
        a = d["anchor"][rows]
        order = np.argsort(a, kind="stable")
        xs, same = x[order], a[order][1:] == a[order][:-1]
        c1 = float(np.clip(np.mean((xs[1:] * xs[:-1])[same]), 0.05 * s0 * s0, 0.95 * s0 * s0)) if same.any() else 0.5 * s0 * s0
        start = (math.sqrt(s0 * s0 - c1), math.sqrt(c1), 2.0)
    starts = [np.log(np.maximum(start, 1e-6))]
    best = min((minimize(nll, x0, method="Nelder-Mead", options=opts) for x0 in starts), key=lambda r: r.fun)
    return (math.exp(best.x[0]), math.exp(best.x[1]), float(np.clip(math.exp(best.x[2]), *TAU_BOUNDS)))


# ---------------------------------------------------------------------------------------------- mean model
def _design(d: dict, direction: bool, dir_opts) -> np.ndarray:
    from uwbimu.calibration.range_factor import direction_features

    A = np.zeros((len(d["r"]), len(d["anchors"])))
    A[np.arange(len(d["r"])), d["anchor"]] = 1.0
    if not direction:
        return A
    orders = tuple(range(dir_opts.lowest_order, dir_opts.harmonics + 1))
    F, _ = direction_features(d["wb"], orders, bool(dir_opts.elevation))
    return np.hstack([A, F])


def _fit_mean(A: np.ndarray, r: np.ndarray, rows: np.ndarray, prior_sd: np.ndarray, iters: int = 10) -> np.ndarray:
    """Huber (k = 1.345) IRLS with ridge priors ``N(0, prior_sd^2)`` per coefficient, on ``rows``."""
    Ar, rr = A[rows], r[rows]
    w = np.ones(len(rr))
    beta = np.zeros(A.shape[1])
    for _ in range(iters):
        res = rr - Ar @ beta
        s = max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 1e-4)
        z = np.abs(res) / s
        w = np.where(z <= 1.345, 1.0, 1.345 / np.maximum(z, 1e-12))
        N = (Ar * w[:, None]).T @ Ar + np.diag((s / prior_sd) ** 2)
        beta = np.linalg.solve(N, (Ar * w[:, None]).T @ rr)
    return beta


def _trajectory_correction(d: dict, e: np.ndarray) -> np.ndarray:
    """``e`` less the projection of a position correction constant over each window (per time block):
    ``r ~ -u . dp`` (``u`` the unit line of sight antenna -> anchor, world frame), Huber IRLS with a prior
    of :data:`TRAJECTORY_PRIOR_SD` per axis.  The fitted trajectory (a filter's, not smoothed) carries a
    position error correlated over seconds; left in the residuals it would look like a slowly varying
    range bias to every model.  It is common to all anchors, the range-model terms are not."""
    win = d["window"]
    nw = int(win.max()) + 1
    U = -d["u"]
    out = e.copy()
    wt = np.ones(len(e))
    dp = np.zeros((nw, 3))
    for _ in range(3):
        s = max(1.4826 * float(np.median(np.abs(out - np.median(out)))), 1e-4)
        N = np.zeros((nw, 3, 3))
        b = np.zeros((nw, 3))
        np.add.at(N, win, wt[:, None, None] * U[:, :, None] * U[:, None, :])
        np.add.at(b, win, (wt * e)[:, None] * U)
        dp = np.linalg.solve(N + np.eye(3) * (s / TRAJECTORY_PRIOR_SD) ** 2, b[:, :, None])[:, :, 0]
        out = e - np.einsum("ij,ij->i", U, dp[win])
        z = np.abs(out) / s
        wt = np.where(z <= 1.345, 1.0, 1.345 / np.maximum(z, 1e-12))
    return out


def _family_residuals(d: dict, A: np.ndarray, prior: np.ndarray, train: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of every row after the family's mean model (fitted on ``train``) and the trajectory
    correction (fitted on every row, each block on its own), alternated; and the mean coefficients."""
    beta = np.zeros(A.shape[1])
    for _ in range(3):
        corr = d["r"] - _trajectory_correction(d, d["r"] - A @ beta) - A @ beta  # the trajectory's share
        beta = _fit_mean(A, d["r"] - corr, train, prior)
    return _trajectory_correction(d, d["r"] - A @ beta), beta


# ---------------------------------------------------------------------------------------------- selection
def _one_se(order: Sequence[str], per_fold: dict[str, np.ndarray], n_fold: np.ndarray) -> tuple[str, str]:
    """The first of ``order`` whose paired per-fold deficit to the best is within one standard error,
    or whose summed held-out deficit is below :data:`TIE_NATS`."""
    means = {c: float(np.mean(per_fold[c])) for c in order}
    best = max(order, key=lambda c: means[c])
    for c in order:
        diff = per_fold[best] - per_fold[c]
        se = float(np.std(diff, ddof=1) / math.sqrt(len(diff))) if len(diff) > 1 else 0.0
        # a nested model near its boundary (drift sd -> 0) gains consistently but negligibly: the paired
        # SE is then ~0, and TIE_NATS keeps such a gain a tie
        if float(np.mean(diff)) <= se or float(np.sum(diff * n_fold)) <= TIE_NATS:
            return c, (f"{c}: mean held-out score {means[c]:.4f} per range, {float(np.mean(diff)):.4f} below the best "
                       f"({best}, {means[best]:.4f}) within one standard error {se:.4f} of the paired differences")
    return best, f"{best}: best mean held-out score {means[best]:.4f} per range"  # pragma: no cover (best is within)


def _thinned(rows: np.ndarray) -> np.ndarray:
    """``rows`` thinned to every m-th selected row so that at most :data:`MAX_FIT_ROWS` remain."""
    idx = np.flatnonzero(rows)
    m = max(1, math.ceil(len(idx) / MAX_FIT_ROWS))
    out = np.zeros_like(rows)
    out[idx[::m]] = True
    return out


def select_range_model(dataset, trajectory, options=None, folds: Optional[int] = None,
                       huber_grid: Sequence[float] = HUBER_GRID,
                       families: Sequence[str] = FAMILIES) -> RangeModelSelection:
    """Choose the range model and Huber threshold of a log by blocked cross-validation (module docstring).

    Parameters
    ----------
    dataset : the log (two-way ranges, anchors), in the trajectory's frame.
    trajectory : a fitted trajectory (:func:`range_residuals`), e.g. the initialising ESKF's run.
    options : :class:`~uwbimu.calibration.options.CalibrationOptions` whose priors and direction model
        (``range_model.direction``; when none, :class:`~uwbimu.calibration.options.DirectionBias` with
        ``lowest_order: 2``, order 1 being the lever arm's) the candidates use; defaults when None.
    folds : time blocks (at least 3, each with :data:`MIN_BLOCK_ROWS` ranges); default the options'
        ``range_model.select_folds`` (:data:`N_FOLDS`).
    huber_grid : Huber thresholds tried [sigmas].
    families : subset of :data:`FAMILIES` to try (kept in that order).

    Returns
    -------
    :class:`RangeModelSelection`.

    Raises
    ------
    InputError : no ranges, too few per block, or an unknown family / fewer than 3 folds.
    """
    return select_on_residuals(range_residuals(dataset, trajectory), options, folds, huber_grid, families,
                               basis="trajectory")


def select_on_residuals(d: dict, options=None, folds: Optional[int] = None,
                        huber_grid: Sequence[float] = HUBER_GRID, families: Sequence[str] = FAMILIES,
                        basis: str = "trajectory") -> RangeModelSelection:
    """:func:`select_range_model` on residuals already computed.

    Parameters
    ----------
    d : dict of arrays as :func:`range_residuals` returns (``t`` [s, UWB clock], ``anchor`` index into
        ``anchors``, ``r`` residual range - predicted distance [m], ``wb`` (n, 3) line of sight antenna ->
        anchor in the body frame [m], ``u`` (n, 3) unit line of sight, world frame); not modified.
    options, folds, huber_grid, families : as :func:`select_range_model`.
    basis : what the residuals are about, recorded in :attr:`RangeModelSelection.basis` (``trajectory``: a
        given trajectory, e.g. the ESKF's; ``free_solve``: the batch's own first solve).
    """
    from uwbimu.calibration.options import CalibrationOptions, DirectionBias

    o = options or CalibrationOptions()
    folds = int(folds if folds is not None else getattr(o.range_model, "select_folds", N_FOLDS))
    fam = [f for f in FAMILIES if f in families]
    if len(fam) != len(set(families)) or not fam:
        raise InputError(f"range model selection: families must be among {FAMILIES}, got {list(families)}")
    if folds < 3:
        raise InputError(f"range model selection: at least 3 folds, got {folds}")
    # order 1 of a shared body-frame term is, to first order, the lever arm (DirectionBias); the trajectory's
    # lever arm is held here, so order-1 terms would score its error as a direction bias: by default the
    # candidate starts at order 2
    dir_opts = o.range_model.direction or DirectionBias(lowest_order=2)
    d = dict(d)
    edges = np.linspace(d["t"].min(), d["t"].max(), folds + 1)
    d["block"] = np.clip(np.searchsorted(edges, d["t"], side="right") - 1, 0, folds - 1).astype(np.int64)
    wi = np.floor((d["t"] - d["t"].min()) / TRAJECTORY_WINDOW_S).astype(np.int64)
    d["window"] = np.unique(wi * folds + d["block"], return_inverse=True)[1].ravel()  # never across a block edge
    counts = np.bincount(d["block"], minlength=folds)
    if counts.min() < MIN_BLOCK_ROWS:
        raise InputError(f"range model selection: a time block holds {int(counts.min())} ranges, fewer than "
                         f"{MIN_BLOCK_ROWS}; use fewer folds or a longer log")
    n_anchor = len(d["anchors"])
    designs, priors = {}, {}
    for with_dir in (False, True):
        designs[with_dir] = _design(d, with_dir, dir_opts)
        pr = [o.anchor_bias_prior_sd] * n_anchor + ([dir_opts.prior_sd] * dir_opts.n_coef if with_dir else [])
        priors[with_dir] = np.asarray(pr, float)
    scores: dict[str, dict[str, list[float]]] = {f: {str(k): [] for k in huber_grid} for f in fam}
    for b in range(folds):
        train, test = d["block"] != b, d["block"] == b
        fit_rows = _thinned(train)
        for f in fam:
            with_dir, drift = "direction" in f, "drift" in f
            e, _ = _family_residuals(d, designs[with_dir], priors[with_dir], train)
            noise = None
            for k in sorted(huber_grid, reverse=True):  # each k starts from the previous k's optimum
                noise = _fit_noise(d, e, fit_rows, drift, k, noise)
                scores[f][str(k)].append(float(np.mean(_loglik(d, e, test, noise, k))))
    best_k = {f: max(huber_grid, key=lambda k: np.mean(scores[f][str(k)])) for f in fam}
    fam_scores = {f: np.asarray(scores[f][str(best_k[f])]) for f in fam}
    chosen, why_f = _one_se(fam, fam_scores, counts)
    k_order = sorted(huber_grid, reverse=True)
    k_chosen, why_k = _one_se([str(k) for k in k_order], {str(k): np.asarray(scores[chosen][str(k)]) for k in k_order},
                              counts)
    # the chosen model refitted on the whole log
    all_rows = np.ones(len(d["r"]), bool)
    with_dir = "direction" in chosen
    e, beta = _family_residuals(d, designs[with_dir], priors[with_dir], all_rows)
    sigma, sd_d, tau = _fit_noise(d, e, _thinned(all_rows), "drift" in chosen, float(k_chosen))
    params: dict[str, Any] = {"sigma": sigma,
                              "anchor_bias": {str(a): float(v) for a, v in zip(d["anchors"], beta[:n_anchor])}}
    if "drift" in chosen:
        params.update({"drift_sd": sd_d, "correlation_time": tau})
    if with_dir:
        params["direction"] = dict(zip(dir_opts.names(), map(float, beta[n_anchor:])))
        params["direction_model"] = dir_opts.model_dump()
    return RangeModelSelection(
        candidates=fam, huber_grid=[float(k) for k in huber_grid], folds=folds, block_edges=edges.tolist(),
        scores=scores, family_scores={f: v.tolist() for f, v in fam_scores.items()},
        family_k={f: float(k) for f, k in best_k.items()}, chosen=chosen, huber_k=float(k_chosen),
        reason=f"family {why_f}; Huber k {why_k}", params=params, n_ranges=int(len(d["r"])), basis=basis)


def apply_selection(options, selection: RangeModelSelection, huber: bool = True):
    """A copy of ``options`` (:class:`~uwbimu.calibration.options.CalibrationOptions`) with the chosen range
    model: ``range_model.direction`` (the candidate's model) or none, ``range_bias_drift`` (the fitted sd and
    correlation time, knots at most a quarter of it and at most 0.5 s apart) or none, ``huber_k`` the chosen
    threshold (``huber=False``: ``huber_k`` as in ``options``)."""
    from uwbimu.calibration.options import DirectionBias, RangeBiasDrift

    p = selection.params
    rm = options.range_model.model_copy(update={
        "direction": DirectionBias(**p["direction_model"]) if "direction" in selection.chosen else None})
    drift = None
    if "drift" in selection.chosen:
        tau = float(p["correlation_time"])
        drift = RangeBiasDrift(sd=float(p["drift_sd"]), correlation_time=tau, knot_spacing=max(0.01, min(0.5, tau / 4)))
    upd = {"range_model": rm, "range_bias_drift": drift} | ({"huber_k": selection.huber_k} if huber else {})
    return options.model_copy(update=upd)
