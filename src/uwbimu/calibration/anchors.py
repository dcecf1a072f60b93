"""Anchor self-survey of the batch calibrator: which anchors are variables, the gauge, the initial guess.

Conventions (docs/calibrate.md, "Anchor self-survey"):

* An anchor is **estimated** when named in ``CalibrationOptions.estimate_anchors``
  (``--estimate-anchors``) or marked ``surveyed: false`` in ``anchors.csv``.
  A named anchor whose row is surveyed gets a weak isotropic prior (``anchor_prior_sd``)
  around its ``anchors.csv`` position; an unsurveyed one gets no prior: its
  coordinates in the file are ignored and its initial guess is a multilateration
  of its ranges from the ESKF trajectory of the surveyed anchors.
* **Gauge.** The IMU's gravity fixes roll and pitch of the world frame, so the
  remaining gauge is a translation and a rotation about the vertical (4 DoF).
  Two fixed (not estimated) anchors at different horizontal positions fix it.
  With fewer, the *convention* applies: the first fixed anchor in ``anchors.csv``
  order (else the first anchor with coordinates, which is then held at the origin)
  is the origin of translation, and the world x axis points horizontally from it
  to the next anchor with coordinates (that anchor's y is constrained to the
  origin anchor's y).  The file's coordinates are rotated/translated into that
  frame for the initial guess; the result (anchors and trajectory) is in it.
* **Bias / distance confounding** (:func:`bias_confounding`): when the anchor's constant
  range bias is estimated too, its distance along the mean line of sight rests only on
  the spread of viewing directions; the sd inflation against a known bias is reported
  (event ``anchor_bias_confounded`` above ``BIAS_INFLATION``; a warning, never a refusal).
* **Degenerate geometry** (:func:`geometry_checks`): an estimated anchor seen
  from too few directions (its worst-direction sd, from the Fisher information of
  its ranges, is not small against its distance) or lying off a (near-)planar
  trajectory whose mirror image across the trajectory plane fits the ranges as
  well (Delta chi2 below the 3-sigma level) is named in an event; without a prior it is refused
  unless ``degenerate_anchors: warn``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np
import pandas as pd

from uwbimu.errors import InputError

#: sd [m] of the gauge constraint "y of the x-axis anchor = y of the origin anchor" (an exact
#: constraint up to numerics; 1e-5 m keeps the information matrix well conditioned).
GAUGE_SIGMA = 1e-5
#: Delta chi2 between an anchor and its mirror image below which the height is ambiguous
#: (9 = 3 sigma for one parameter, the t_d profile's confidence level).
MIRROR_CHI2 = 9.0
#: An anchor is "located" when this many worst-direction sds stay below its distance to the
#: trajectory (beyond it, the linearised line-of-sight directions themselves are unknown).
DIRECTION_SIGMAS = 3.0
#: sd inflation (bias estimated against bias known) above which an anchor's constant range bias and
#: its distance along the mean line of sight count as confounded (:func:`bias_confounding`): the
#: multiple correlation of the bias with the position is then above sqrt(1 - 1/10^2) = 0.995.
BIAS_INFLATION = 10.0


@dataclass
class AnchorSetup:
    """Anchor variables of one calibration (graph order: sorted ids).

    Attributes
    ----------
    ids : anchor ids, sorted (the graph's index ``j``).
    pos : (J, 3) fixed positions and initial guesses, world (gauge) frame [m].
    estimated : (J,) bool, position is a variable ``P(j)``.
    surveyed : (J,) bool, ``anchors.csv`` gives a surveyed (or guessed) position.
    prior_sd : (J,) prior sd per axis [m]; ``inf``: no prior.
    gauge : dict written to calibration.yaml (kind, description, origin / x-axis anchors).
    yaw_fix : ``(j, y)``: anchor ``j``'s y is held at ``y`` (gauge convention), or None.
    pairs : DataFrame ``a, b`` (indices), ``range``, ``sd`` of ``anchor_ranges.csv``.
    events : structured events (dicts with ``kind``).
    """

    ids: list[str]
    pos: np.ndarray
    estimated: np.ndarray
    surveyed: np.ndarray
    prior_sd: np.ndarray
    gauge: dict
    yaw_fix: Optional[tuple[int, float]] = None
    pairs: Optional[pd.DataFrame] = None
    transform: tuple = (np.eye(3), np.zeros(3))  # world(file) -> gauge frame: x' = R x + t
    events: list = field(default_factory=list)

    @property
    def any_estimated(self) -> bool:
        return bool(self.estimated.any())


def _surveyed_column(anchors: pd.DataFrame) -> np.ndarray:
    if "surveyed" not in anchors.columns:
        return np.ones(len(anchors), bool)
    return anchors["surveyed"].astype(bool).to_numpy()


def plan_anchors(dataset, options) -> AnchorSetup:
    """Decide which anchors are variables, their priors, and the gauge (see module doc).

    Raises
    ------
    InputError
        An id of ``estimate_anchors`` not in anchors.csv, or no gauge possible.
    """
    an = dataset.anchors
    file_ids = [str(a) for a in an["anchor"]]
    xyz = an[["x", "y", "z"]].to_numpy(float)
    surveyed_file = _surveyed_column(an)
    unknown = [a for a in options.estimate_anchors if a not in file_ids]
    if unknown:
        raise InputError(f"--estimate-anchors / estimate_anchors: anchor id(s) {', '.join(map(repr, unknown))} "
                         f"not in anchors.csv, which has: {', '.join(file_ids)}")
    ids = sorted(file_ids)
    row = {a: i for i, a in enumerate(file_ids)}
    pos = np.array([xyz[row[a]] for a in ids]).reshape(-1, 3)
    surveyed = np.array([surveyed_file[row[a]] for a in ids], bool)
    named = np.array([a in options.estimate_anchors for a in ids], bool)
    estimated = named | ~surveyed
    prior_sd = np.where(estimated & surveyed, options.anchor_prior_sd, np.inf)
    events = []
    auto = [a for a, n, s in zip(ids, named, surveyed) if not s and not n]
    if auto:
        events.append({"kind": "anchor_unsurveyed_estimated", "anchors": auto,
                       "message": f"anchors.csv marks {', '.join(auto)} surveyed: false; their positions are "
                                  "estimated (no prior)"})
    setup = AnchorSetup(ids=ids, pos=pos, estimated=estimated, surveyed=surveyed, prior_sd=prior_sd, gauge={},
                        events=events)
    if setup.any_estimated:
        _apply_gauge(setup, [file_ids.index(a) for a in ids])
    else:
        setup.gauge = {"kind": "surveyed", "fixed_anchors": list(ids),
                       "description": "all anchors fixed at their anchors.csv positions"}
    setup.pairs = _pairs(dataset, setup, options)
    return setup


def _apply_gauge(s: AnchorSetup, order_in_file: list[int]) -> None:
    J = len(s.ids)
    by_file = sorted(range(J), key=lambda j: order_in_file[j])  # graph indices in anchors.csv order
    fixed = [j for j in by_file if not s.estimated[j]]
    scale = float(np.ptp(s.pos[s.surveyed], axis=0).max()) if s.surveyed.sum() > 1 else 1.0
    if len(fixed) >= 2:
        P = s.pos[fixed, :2]
        sep = float(np.max(np.linalg.norm(P[:, None] - P[None], axis=-1)))
        if sep > 1e-6 * max(scale, 1e-9):
            s.gauge = {"kind": "surveyed", "fixed_anchors": [s.ids[j] for j in fixed],
                       "description": "the fixed (surveyed, not estimated) anchors define the world frame; "
                                      "gravity (IMU) fixes its vertical"}
            return
    with_xyz = [j for j in by_file if s.surveyed[j]]
    g1 = fixed[0] if fixed else (with_xyz[0] if with_xyz else None)
    g2 = next((j for j in with_xyz if j != g1 and j not in fixed), None)
    if g1 is None or g2 is None or not s.surveyed[g1]:
        raise InputError("anchor self-survey: the frame cannot be fixed: it needs two fixed anchors at different "
                         "horizontal positions, or (gauge convention) two anchors with coordinates in anchors.csv "
                         f"(surveyed or a guess); anchors.csv has {int(s.surveyed.sum())} with coordinates and "
                         f"{len(fixed)} fixed", hint="drop an anchor from --estimate-anchors or give a rough guess "
                         "of its position (surveyed: true) in anchors.csv")
    d = s.pos[g2] - s.pos[g1]
    if np.hypot(d[0], d[1]) <= 1e-9 * max(scale, 1e-9):
        raise InputError(f"anchor self-survey: gauge anchors {s.ids[g1]!r} and {s.ids[g2]!r} are at the same "
                         "horizontal position in anchors.csv; the x axis between them is undefined")
    yaw = np.arctan2(d[1], d[0])
    c, sn = np.cos(-yaw), np.sin(-yaw)
    R = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
    origin_fixed = not s.estimated[g1]
    # Rotate about the origin anchor; translate it to (0, 0, 0) unless it is a surveyed fixed anchor.
    t = s.pos[g1] - R @ s.pos[g1] if origin_fixed else -R @ s.pos[g1]
    s.pos = s.pos @ R.T + t
    s.transform = (R, t)
    s.estimated[g1] = False
    s.prior_sd[g1] = np.inf
    s.yaw_fix = (g2, float(s.pos[g1][1]))
    s.gauge = {"kind": "convention", "origin_anchor": s.ids[g1], "x_axis_anchor": s.ids[g2],
               "origin_fixed_by": "survey" if origin_fixed else "convention (held at 0, 0, 0)",
               "rotation_about_z_deg": float(np.degrees(-yaw)), "translation": [float(v) for v in t],
               "description": f"fewer than two fixed anchors at different horizontal positions: origin at anchor "
                              f"{s.ids[g1]}, x axis horizontal towards anchor {s.ids[g2]} (its y held at the "
                              f"origin anchor's), z up (gravity); anchors.csv coordinates rotated by "
                              f"{np.degrees(-yaw):.3f} deg about z into this frame"}
    s.events.append({"kind": "anchor_gauge_convention", "message": s.gauge["description"]})


def _pairs(dataset, s: AnchorSetup, options) -> Optional[pd.DataFrame]:
    ar = getattr(dataset, "anchor_ranges", None)
    if ar is None or len(ar) == 0:
        return None
    j = {a: i for i, a in enumerate(s.ids)}
    sd = ar["sd"].to_numpy(float) if "sd" in ar.columns else np.full(len(ar), options.anchor_range_sigma)
    return pd.DataFrame({"a": [j[str(a)] for a in ar["anchor_a"]], "b": [j[str(b)] for b in ar["anchor_b"]],
                         "range": ar["range"].to_numpy(float), "sd": sd})


def eskf_dataset(dataset, s: AnchorSetup, with_unsurveyed: bool):
    """The dataset the initialising ESKF runs on: anchors at ``s.pos`` (gauge frame).

    ``with_unsurveyed=False`` leaves out the anchors marked ``surveyed: false`` and their ranges.
    """
    keep = [a for a, sv in zip(s.ids, s.surveyed) if sv or with_unsurveyed]
    an = dataset.anchors[dataset.anchors["anchor"].astype(str).isin(keep)].copy()
    j = {a: i for i, a in enumerate(s.ids)}
    an[["x", "y", "z"]] = np.array([s.pos[j[str(a)]] for a in an["anchor"]])
    uwb = dataset.uwb[dataset.uwb["anchor"].astype(str).isin(keep)].reset_index(drop=True)
    return replace(dataset, anchors=an.reset_index(drop=True), uwb=uwb, groundtruth=None, anchor_ranges=None)


def antenna_positions(eskf, t_uwb: np.ndarray, with_sd: bool = False, lever_arm: Optional[np.ndarray] = None):
    """(M, 3) antenna positions of the ESKF trajectory at UWB stamps ``t_uwb`` (its t_d and lever arm).

    With ``with_sd`` also the (M, 3) position sds of the ESKF (world frame) at those instants.
    ``lever_arm``: (3,) or (M, 3) lever arm(s) p_IU [m, IMU frame] to use instead of the ESKF's
    (several tags: each row its own tag's, :func:`tag_lever_arms`).
    """
    from scipy.spatial.transform import Rotation, Slerp

    td = float(eskf.calibration["time_offset"])
    t_e = eskf.t_imu if eskf.t_imu is not None else eskf.t + td
    s = np.clip(np.asarray(t_uwb, float) + td, t_e[0], t_e[-1])
    st = eskf.states
    p = np.column_stack([np.interp(s, t_e, st[:, c]) for c in range(3)])
    q = st[:, 6:10] / np.linalg.norm(st[:, 6:10], axis=1, keepdims=True)
    _, first = np.unique(t_e, return_index=True)
    rot = Slerp(t_e[first], Rotation.from_quat(q[first][:, [1, 2, 3, 0]]))(s)
    lev = np.asarray(eskf.calibration["lever_arm"] if lever_arm is None else lever_arm, float)
    pu = p + rot.apply(lev)
    if not with_sd:
        return pu
    sd = np.column_stack([np.interp(s, t_e, np.nan_to_num(eskf.sd[:, c])) for c in range(3)])
    return pu, sd


def tag_lever_arms(eskf, names: list[str], tag_i: np.ndarray) -> np.ndarray:
    """(M, 3) lever arm p_IU [m, IMU frame] of each row from the ESKF: its ``calibration["tags"]`` entry of the
    row's tag ``names[tag_i]`` (several tags: one lever arm each), else its (single) ``lever_arm``."""
    cal = eskf.calibration
    etag = cal.get("tags") or {}
    lev = np.array([etag[n]["lever_arm"] if n in etag else cal["lever_arm"] for n in names], float).reshape(-1, 3)
    return lev[np.asarray(tag_i, np.int64)]


def multilaterate(P: np.ndarray, rho: np.ndarray, iterations: int = 20) -> tuple[np.ndarray, float]:
    """Anchor position from ranges ``rho`` measured at antenna positions ``P`` (M, 3).

    Linear least squares on the differences of squared ranges, then Gauss-Newton on
    ``|P - a| - rho``.  Returns the position and the RMS residual [m].  Near-planar
    ``P`` leave the side of the plane weakly determined: see :func:`geometry_checks`.
    """
    A = np.column_stack([2.0 * P, -np.ones(len(P))])
    b = np.sum(P**2, axis=1) - rho**2
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    a = x[:3]
    for _ in range(iterations):
        u = a - P
        r = np.linalg.norm(u, axis=1)
        e = r - rho
        J = u / r[:, None]
        step, *_ = np.linalg.lstsq(J, -e, rcond=None)
        a = a + step
        if np.linalg.norm(step) < 1e-9:
            break
    e = np.linalg.norm(a - P, axis=1) - rho
    return a, float(np.sqrt(np.mean(e**2)))


def geometry_checks(anchor_id: str, a: np.ndarray, P: np.ndarray, rho: np.ndarray, sigma: float,
                    bias_sd: Optional[float], position_sd: Optional[np.ndarray] = None) -> list[dict]:
    """Degenerate-geometry events for one estimated anchor (empty list: well located).

    Parameters
    ----------
    a : (3,) anchor position estimate [m]; P : (M, 3) antenna positions; rho : (M,) ranges [m].
    sigma : range sd of the measurement model [m] (information and chi2 units).
    bias_sd : prior sd of the anchor's range bias [m], or None when no bias is estimated.
    position_sd : (M, 3) sd of the antenna positions [m] (the estimated trajectory's), or None.  Their
        noise is not motion: the out-of-plane spread is shrunk by it before the mirror test (an
        estimated trajectory of a planar motion is never exactly planar).

    Events
    ------
    ``anchor_few_directions``: ``DIRECTION_SIGMAS`` worst-direction sds (Fisher information of the
    ranges' unit line-of-sight vectors, with the range bias as a nuisance) exceed the anchor's
    distance to the nearest antenna position.
    ``anchor_mirror_ambiguity``: the anchor mirrored across the trajectory's best-fit plane lies
    more than ``DIRECTION_SIGMAS`` sds (along the plane normal) away and fits the ranges within
    ``MIRROR_CHI2`` (coplanar motion: the anchor's side/height is ambiguous).
    """
    events = []
    u = P - a
    r = np.linalg.norm(u, axis=1)
    n = u / r[:, None]
    # Information of [a, b] from e = |P - a| + b - rho: rows [-n, 1] / sigma.
    Jr = np.column_stack([-n, np.ones(len(n))]) / sigma
    H = Jr.T @ Jr
    if bias_sd is None:
        Ha = H[:3, :3]
    else:
        hbb = H[3, 3] + 1.0 / bias_sd**2
        Ha = H[:3, :3] - np.outer(H[:3, 3], H[3, :3]) / hbb
    lam, vec = np.linalg.eigh(Ha)
    sd_worst = float(1.0 / np.sqrt(max(lam[0], 1e-300)))
    s_min = float(np.sqrt(max(np.linalg.eigvalsh(n.T @ n / len(n))[0], 0.0)))
    d_min = float(r.min())
    if DIRECTION_SIGMAS * sd_worst > d_min:
        events.append({"kind": "anchor_few_directions", "anchor": anchor_id, "sd_worst_m": sd_worst,
                       "worst_direction": [float(v) for v in vec[:, 0]], "los_span_min": s_min,
                       "distance_min_m": d_min,
                       "message": f"anchor {anchor_id} is seen from too few directions: worst-direction sd "
                                  f"{sd_worst:.3g} m ({DIRECTION_SIGMAS:g} sd > its {d_min:.2f} m distance to the "
                                  f"trajectory; line-of-sight span {s_min:.3f}); walk or fly past it on more sides"})
    c = P.mean(axis=0)
    _, sv, Vt = np.linalg.svd(P - c, full_matrices=False)
    normal = Vt[-1]
    off = (P - c) @ normal
    spread2 = float(np.mean(off**2))
    noise2 = float(np.mean(position_sd**2 @ normal**2)) if position_sd is not None else 0.0
    shrink = np.sqrt(max(spread2 - noise2, 0.0) / spread2) if spread2 > 0 else 0.0
    Pm = P - (1.0 - shrink) * np.outer(off, normal)  # out-of-plane motion without the trajectory's noise
    planarity = float(np.sqrt(max(spread2 - noise2, 0.0) * len(P)) / sv[0]) if sv[0] > 0 else 0.0
    h = float((a - c) @ normal)
    mirror = a - 2.0 * h * normal
    # Expected (noise-free) chi2 increase of the mirror image: sum of its range changes over sigma.  The
    # realised increase adds a zero-mean cross term with the trajectory's own errors, which would make the
    # verdict depend on the initialising ESKF's accuracy rather than on the geometry.
    dchi2 = float(np.sum((np.linalg.norm(Pm - mirror, axis=1) - np.linalg.norm(Pm - a, axis=1)) ** 2) / sigma**2)
    # A mirror image within a few sds of the anchor is local uncertainty (the marginal sd reports it), not a
    # second solution: only a distinct mirror that fits as well is an ambiguity.
    sd_normal = float(np.sqrt(np.sum((vec.T @ normal) ** 2 / np.maximum(lam, 1e-300))))
    if dchi2 < MIRROR_CHI2 and 2.0 * abs(h) > DIRECTION_SIGMAS * sd_normal:
        events.append({"kind": "anchor_mirror_ambiguity", "anchor": anchor_id, "delta_chi2": dchi2,
                       "planarity": planarity, "height_above_plane_m": h,
                       "mirror_position": [float(v) for v in mirror],
                       "message": f"anchor {anchor_id}: the trajectory is nearly planar (smallest/largest extent "
                                  f"{planarity:.3f}) and the anchor mirrored across its plane ({h:+.2f} m from it) "
                                  f"fits the ranges as well (delta chi2 {dchi2:.2g} < {MIRROR_CHI2:g}): its side "
                                  "(height) is ambiguous; vary the height of the motion"})
    return events


def bias_confounding(anchor_id: str, a: np.ndarray, P: np.ndarray, threshold: float = BIAS_INFLATION) -> dict:
    """How far an anchor's constant range bias and its position are confounded (scale-free).

    With ranges ``|P_i - a| + b`` the information of ``(a, b)`` has rows ``[-n_i, 1]`` (unit lines of
    sight ``n_i`` from the antenna positions to the anchor).  The multiple correlation ``R`` of the bias
    with the position is ``R^2 = q / (1 + q)``, ``q = m' C^-1 m``, ``m`` and ``C`` the mean and covariance
    of the ``n_i``; estimating the bias inflates the sd of the position's most correlated combination
    (about the distance along the mean line of sight) by ``1 / sqrt(1 - R^2)`` against a known bias.  A
    trajectory seen from the anchor in a narrow cone (a small flight volume far away, or an anchor in a
    corner) gives a large inflation: the white-noise sd grows by that factor, and any range error that is
    not white (direction dependent, slowly varying) is no longer averaged down along that direction.

    Parameters
    ----------
    anchor_id : the anchor's id (for the event).
    a : (3,) anchor position [m]; P : (M, 3) antenna positions [m] (same frame).
    threshold : inflation above which the event ``anchor_bias_confounded`` is returned.

    Returns
    -------
    dict with ``inflation`` (>= 1), ``correlation`` (R), ``mean_los_length`` (|m|, 1 for a single direction),
    ``mean_los`` (unit mean line of sight, tag -> anchor) and, above ``threshold``, ``event`` (a dict with
    ``kind: anchor_bias_confounded`` and a message naming the anchor and what helps); else ``event: None``.
    """
    u = np.asarray(a, float) - np.asarray(P, float)
    n = u / np.linalg.norm(u, axis=1)[:, None]
    m = n.mean(axis=0)
    C = np.cov(n.T, bias=True)
    lam, V = np.linalg.eigh(C)
    q = float(np.sum((V.T @ m) ** 2 / np.maximum(lam, 1e-300)))
    r2 = q / (1.0 + q)
    infl = float(np.sqrt(1.0 + q))  # 1 / sqrt(1 - R^2)
    ml = float(np.linalg.norm(m))
    out = {"anchor": anchor_id, "inflation": infl, "correlation": float(np.sqrt(r2)), "mean_los_length": ml,
           "mean_los": [float(v) for v in m / max(ml, 1e-300)], "event": None}
    if infl > threshold:
        out["event"] = {
            "kind": "anchor_bias_confounded", "anchor": anchor_id, "inflation": infl,
            "correlation": float(np.sqrt(r2)), "mean_los_length": ml,
            "message": f"anchor {anchor_id}: its constant range bias and its distance along the mean line of sight "
                       f"are confounded (bias-position correlation {np.sqrt(r2):.4f}; the trajectory is seen from "
                       f"the anchor in a narrow cone, mean line-of-sight length {ml:.2f}): that distance's sd is "
                       f"{infl:.0f}x the one with a known bias, and range errors that are not white (direction-"
                       "dependent antenna delay, multipath) are not averaged down along it; move on more sides "
                       "of the anchor, or fix its bias (estimate_anchor_bias: false: a constant bias then shifts it "
                       "along the line of sight by about that bias)"}
    return out
