"""The range / TDoA noise level by the filter's own predictive likelihood (rule 2 of :mod:`.noise_from_data`).

Covariance matching (:func:`~uwbimu.estimation.noise_passes.match_measurement_noise`) fits the core of a
pass's innovations.  On real logs the errors are heavy-tailed and correlated (multipath, NLOS bursts): a
level fitted to the core makes the gate reject a fifth of the Crazyflie TDoA3 log and the filter follow
the rest too closely, while a level fitted to the tails (the mean-square statistic) also inflates it where
the gate should reject (the ``nlos`` simulation).  Here the level is the one under which the filter
*predicts* its measurements best: the mean one-step predictive log-likelihood of every processed
innovation under an outlier mixture (:func:`~uwbimu.estimation.noise_from_data.predictive_loglik`), each
level scored by a filter pass that used it.  The search walks in steps of :data:`STEP` (a factor on the sd)
from the matched level uphill, at most :data:`MAX_STEPS` steps, then refines once by a parabola in
log(sd) through the best level and its two neighbours.  It runs only where matching had to correct the
configured level (so a log whose noise the preset describes, e.g. a simulation with matched noise, costs
nothing), and each kind (range, TDoA) is searched in turn.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from uwbimu.estimation import kernels as K
from uwbimu.estimation.filterpass import REC_INNOV, REC_S, REC_STATUS, PassResult, Problem
from uwbimu.estimation.noise_from_data import outlier_width, predictive_loglik
from uwbimu.estimation.noise_passes import accepted_records

#: factor between two levels of the search (on the sd): coarse enough that the likelihood difference
#: is well above its sampling noise on a few thousand measurements, fine enough that the parabola refines
STEP = math.sqrt(2.0)
#: steps from the matched level at most (a factor 16 either way; the walk stops at the first step down, so
#: a level near the matched one costs two or three passes; ``at_limit`` in the report when it ran out)
MAX_STEPS = 8
#: a refined level closer than this (relative) to an evaluated one is not evaluated
REFINE_MIN = 0.05


def kind_loglik(prob: Problem, passes: list[PassResult], kind: str) -> dict[str, Any]:
    """Predictive log-likelihood (:func:`predictive_loglik`) of the processed measurements of one kind
    (``"range"`` or ``"tdoa"``) of a finished filter run (``prob``, ``passes``)."""
    rec, _ = accepted_records(prob, passes)
    processed = np.isfinite(rec[:, REC_INNOV]) & np.isfinite(rec[:, REC_S]) & (rec[:, REC_STATUS] == K.UPD_OK)
    is_td = (prob.uwb_b >= 0) if prob.uwb_b is not None else np.zeros(len(prob.uwb_t), bool)
    sel = processed & (is_td if kind == "tdoa" else ~is_td)
    return predictive_loglik(rec[sel, REC_INNOV], rec[sel, REC_S], outlier_width(prob.anchors))


def search_level(sigma0: float, score0: dict[str, Any], evaluate: Callable[[float], tuple[dict[str, Any], Any]],
                 payload0: Any = None) -> tuple[float, Any, dict[str, Any]]:
    """Maximise a pass's predictive log-likelihood over the noise sd, from ``sigma0`` [m].

    Parameters
    ----------
    sigma0 : the level of the pass already run (the matched one) [m].
    score0 : its :func:`kind_loglik`.
    evaluate : ``sigma -> (score, payload)``: runs a filter pass with that sd and scores it; the payload
        (the finished pass) is returned for the level chosen, so the caller need not rerun it.
    payload0 : the payload of the pass at ``sigma0``.

    Returns
    -------
    ``(sigma, payload, report)``: the chosen sd, its pass, and ``{levels: [[sd, score, eps], ...] in the order
    evaluated, sigma, ll (the chosen level's score), outlier_fraction, step, refined, at_limit}``.
    """
    key = "score" if "score" in score0 else "ll"
    tried: dict[float, tuple[float, float, Any]] = {sigma0: (score0[key], score0["eps"], payload0)}
    order = [sigma0]

    def run(sig: float) -> float:
        sc, pl = evaluate(sig)
        ll = sc[key] if np.isfinite(sc[key]) else -np.inf
        tried[sig] = (ll, sc["eps"], pl)
        order.append(sig)
        return ll

    best = sigma0
    ll_best = tried[sigma0][0] if np.isfinite(tried[sigma0][0]) else -np.inf
    at_limit = False
    for direction in (STEP, 1.0 / STEP):
        sig = best
        moved = False
        for i in range(MAX_STEPS):
            sig = sig * direction
            ll = run(sig)
            if ll > ll_best:
                best, ll_best, moved = sig, ll, True
                at_limit = i == MAX_STEPS - 1
            else:
                break
        if moved:
            break  # uphill found in this direction: the other side of sigma0 is below it

    def near(target: float):
        """The level evaluated at ``target`` (a product of steps: equal up to rounding), or None."""
        for s in tried:
            if abs(s / target - 1.0) < 1e-9:
                return s
        return None

    refined = False
    lo, hi = near(best / STEP), near(best * STEP)
    if lo is not None and hi is not None and all(np.isfinite(tried[s][0]) for s in (lo, hi)):
        # parabola through (log sd, ll) at lo, best, hi; its vertex within half a step of best
        y0, y1, y2 = tried[lo][0], ll_best, tried[hi][0]
        curv = y0 - 2.0 * y1 + y2
        if curv < 0:
            off = 0.5 * (y0 - y2) / curv  # in steps
            off = float(np.clip(off, -0.5, 0.5))
            cand = best * STEP ** off
            if abs(cand / best - 1.0) > REFINE_MIN:
                refined = True
                if run(cand) > ll_best:
                    best, ll_best = cand, tried[cand][0]
    report = {"levels": [[float(s), float(tried[s][0]), float(tried[s][1])] for s in order],
              "sigma": float(best), "ll": float(ll_best), "outlier_fraction": float(tried[best][1]),
              "step": STEP, "refined": refined, "at_limit": at_limit, "statistic": "predictive_likelihood"}
    return best, tried[best][2], report
