"""Uncertainty of the batch calibration: the graph's marginals and the honest sigma of the calibration parameters.

Split from :mod:`uwbimu.calibration.batch` (which orchestrates): :func:`_marginals` (GTSAM's, or a SciPy
factorisation of the same linearisation where GTSAM's Cholesky gives up), :func:`_calibration_covariance`
(the white model, the HAC sandwich and its block check, :mod:`uwbimu.calibration.covariance`), the block
check's event (:func:`_block_event`) and the t_d profile's honesty scale (:func:`_profile_chi2_scale`).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from uwbimu.calibration import keys
from uwbimu.calibration.robust_loss import whitened_residuals


def _calibration_covariance(pb, graph, values, assoc, param_keys, td: float, td_free: bool, marg=None):
    """Covariance of the variables ``param_keys`` by ``options.covariance``: (cov, cov_model, yaml section).

    ``sandwich``: :func:`uwbimu.calibration.covariance.sandwich_covariance` over the range/TDoA rows
    (Huber inliers ``|z| <= huber_k`` in the bread; bandwidth from the lever arm's and t_d's score series).
    ``marg``: the graph's marginals when the caller already has them (:func:`_marginals`).
    """
    import gtsam

    from uwbimu.calibration.covariance import sandwich_covariance

    marg = marg if marg is not None else _marginals(pb, graph, values)
    cov_model = marg.jointMarginalCovariance(gtsam.KeyVector(param_keys)).fullMatrix()
    if pb.options.covariance == "model":
        return cov_model, cov_model, {"method": "model", "description": "GTSAM marginals of the white range-noise model"}
    inlier = np.abs(whitened_residuals(pb, graph, assoc, values, td)) <= pb.options.huber_k
    cov, cov_model, info = sandwich_covariance(graph, values, param_keys, assoc.slots, pb.t_range[assoc.used],
                                               1.0 / pb.options.keyframe_hz, inlier=inlier,
                                               interest=np.arange(4 if td_free else 3), cov_model=cov_model,
                                               blocks=pb.options.block_check.blocks,
                                               block_level=pb.options.block_check.level)
    if info.block is not None:
        # where the blocks' variance is the larger, that parameter's sigma is the blocks' (the HAC's correlations kept)
        w = info.block.widened
        sd_h = np.sqrt(np.maximum(np.diag(cov), 0.0))
        sd_b = np.where(w, np.sqrt(np.maximum(np.diag(info.block.cov), 0.0)), sd_h)
        with np.errstate(invalid="ignore", divide="ignore"):
            f = np.where(sd_h > 0, sd_b / sd_h, 1.0)
        cov = cov * np.outer(f, f)
    # The sandwich may only widen the model's sigma: below it, the difference is sampling noise of the meat (a
    # 20 s white simulated flight gave 0.8x the model sigma, whose errors then reach 2.9 sigma) or an overstated
    # range_sigma, neither a reason to claim more than the model.  Its correlations are kept.
    sd_s, sd_m = np.sqrt(np.maximum(np.diag(cov), 0.0)), np.sqrt(np.maximum(np.diag(cov_model), 0.0))
    sd = np.maximum(sd_s, sd_m)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.where(np.outer(sd_s, sd_s) > 0, cov / np.outer(sd_s, sd_s), 0.0)
    np.fill_diagonal(corr, 1.0)
    cov = corr * np.outer(sd, sd)
    sec = {"method": "sandwich", "description": "HAC (Newey-West, Bartlett kernel) sandwich over the range "
                                                "factors' scores; IMU factors and priors keep their model information; "
                                                "each sigma at least the model's",
           "floored_at_model": int(np.sum(sd_m > sd_s)),
           "bandwidth_rule": info.method, "bandwidth_s": info.bandwidth_s, "bin_s": info.bin_s,
           "n_bins": info.n_bins, "andrews_bandwidth_s": float(info.andrews_bins * info.bin_s),
           "plateau_bandwidth_s": float(info.plateau_bins * info.bin_s),
           "score_ar1": [round(x, 4) for x in info.rho], "mean_leverage": info.mean_leverage}
    if info.block is not None:
        bc = info.block
        sec["block_check"] = {"blocks": bc.blocks, "block_s": bc.block_s, "level": bc.level,
                              "variance_ratio": [float(x) for x in bc.ratio], "dof": [float(x) for x in bc.dof],
                              "p_value": [float(x) for x in bc.p_value], "significant": [bool(x) for x in bc.significant],
                              "widened": [bool(x) for x in bc.widened]}
    return cov, cov_model, sec


def _block_event(bc: Optional[dict], drift_on: bool = False) -> Optional[dict]:
    """``range_errors_correlated_over_blocks`` when the block check rejects the HAC sandwich for a parameter.

    Its advice: a slowly varying anchor bias (``range_bias_drift``) when it is off.  Measured (docs/calibrate.md
    "The block check"): on both shared real logs it removes what the blocks see (INRoL lever ratios 2.7-3.1 ->
    0.7-1.4, ISAS-Walk's 4 flagged anchor biases -> none, every p > 0.02)."""
    if not bc:
        return None
    sig = {n: p for n, p in bc["parameters"].items() if p["significant"]}
    if not sig:
        return None
    advice = ("the range model already has a slowly varying bias: look for direction-dependent range errors "
              "(range_model.direction) or a changing IMU error" if drift_on else
              "model a slowly varying anchor bias (range_bias_drift: {sd: 0.1, correlation_time: 2.0}, "
              "docs/calibrate.md)")
    return {"kind": "range_errors_correlated_over_blocks", "severity": "warning", "blocks": bc["blocks"],
            "level": bc["level"], "parameters": sorted(sig),
            "variance_ratio": {n: p["variance_ratio"] for n, p in sig.items()}, "advice": advice,
            "message": f"the range scores of {len(sig)} parameter(s) vary between the {bc['blocks']} parts of the log "
                       "more than the HAC sandwich allows (the range model misses an error that follows the motion "
                       f"for tens of seconds); their sigma is the blocks'; {advice}"}


def _profile_chi2_scale(pb, graph, values, assoc) -> float:
    """Model / sandwich variance of t_d at a free solve (1 with ``covariance: model``)."""
    if pb.options.covariance == "model":
        return 1.0
    td = float(values.atVector(keys.time_offset())[0])
    cov, cov_model, _ = _calibration_covariance(pb, graph, values, assoc, [keys.lever_arm(0), keys.time_offset()],
                                                td, True)
    return float(min(1.0, cov_model[3, 3] / cov[3, 3])) if cov[3, 3] > 0 else 1.0


class SparseMarginals:
    """Marginal covariances from the sparse Gauss-Newton Hessian ``J^T J`` (SciPy ``splu``).

    Used when ``gtsam.Marginals`` refuses a system: GTSAM's Cholesky calls IMU-chain graphs
    "indeterminate" whose conditioning spans ~12 decades (bias random walk against the first
    keyframe's prior, e.g. a hover) although the Hessian is positive definite.  Same linearisation
    (robust weights and noise models baked in by ``graph.linearize``), same covariances: pinned to
    ``gtsam.Marginals`` by ``tests/test_calibrate_sim.py``.
    """

    def __init__(self, graph, values):
        from scipy.sparse.linalg import splu

        from uwbimu.calibration.covariance import linear_system

        J, _b, _row0, self._cols = linear_system(graph, values)  # columns ordered by key
        self._lu = splu((J.T @ J).tocsc())
        self._n = J.shape[1]

    def _block(self, keys):
        cols = np.concatenate([self._cols[int(k)] for k in keys])
        E = np.zeros((self._n, len(cols)))
        E[cols, np.arange(len(cols))] = 1.0
        return self._lu.solve(E)[cols]

    def marginalCovariance(self, key):  # noqa: N802 - gtsam.Marginals' name
        return self._block([key])

    def jointMarginalCovariance(self, keys):  # noqa: N802
        cov = self._block(list(keys))
        return type("Joint", (), {"fullMatrix": lambda _self: cov})()


class _Marginals:
    """``gtsam.Marginals`` that falls back to :class:`SparseMarginals` when GTSAM's Cholesky refuses the
    system, at construction or at any later query (GTSAM eliminates lazily per query)."""

    def __init__(self, graph, values):
        import gtsam

        self._graph, self._values = graph, values
        try:
            self._m = gtsam.Marginals(graph, values)
        except RuntimeError:
            self._m = SparseMarginals(graph, values)

    def _call(self, name, arg):
        try:
            return getattr(self._m, name)(arg)
        except RuntimeError:
            if isinstance(self._m, SparseMarginals):
                raise
            self._m = SparseMarginals(self._graph, self._values)
            return getattr(self._m, name)(arg)

    def marginalCovariance(self, key):  # noqa: N802 - gtsam.Marginals' name
        return self._call("marginalCovariance", key)

    def jointMarginalCovariance(self, keys):  # noqa: N802
        return self._call("jointMarginalCovariance", keys)


def _marginals(pb, graph, values):
    """``gtsam.Marginals``, or :class:`SparseMarginals` when GTSAM's Cholesky refuses the system."""
    return _Marginals(graph, values)
