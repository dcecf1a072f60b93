"""Dataset conventions the factor graph does not model itself: a z-down anchors' frame and documented
range biases.

The graph's world has z up (gravity ``[0, 0, -g]``, ``PreintegrationCombinedParams.MakeSharedU``).
A dataset whose anchors' frame is z-down (``dataset.yaml`` ``anchor_frame_up: -z``, e.g. ISAS-Walk) is
calibrated in that frame turned 180 deg about x (``y -> -y, z -> -z``, a proper rotation, its own
inverse; the ESKF does the same, :data:`uwbimu.estimation.eskf.FLIP_X`) and every world-frame output
is turned back.  Documented constant range biases (``known_anchor_bias``, measured = true + bias)
are subtracted from the ranges (TDoA ``b_b - b_a``) before the graph, as the ESKF does; the graph's
per-anchor bias is then what remains on top of them.  Body-frame quantities (lever arm, IMU biases,
attitude sd) and times do not change.
"""

from __future__ import annotations

import dataclasses
import numpy as np

#: diagonal of the rotation of 180 deg about x and its quaternion [w, x, y, z]
FLIP = np.array([1.0, -1.0, -1.0])
Q_FLIP = np.array([0.0, 1.0, 0.0, 0.0])


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (N, 4) [w, x, y, z] quaternions."""
    w1, x1, y1, z1 = a.T
    w2, x2, y2, z2 = b.T
    return np.column_stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def flip_quat(q: np.ndarray) -> np.ndarray:
    """``q_FLIP ⊗ q`` for (N, 4) [w, x, y, z] quaternions (body -> flipped world)."""
    q = np.asarray(q, float)
    return _qmul(np.broadcast_to(Q_FLIP, q.shape), q)


def anchor_frame_up(dataset, eskf_options=None) -> str:
    """The anchors' up direction: the ESKF options' when set, else the dataset's, else ``"+z"``."""
    opt = getattr(eskf_options, "anchor_frame_up", None) if eskf_options is not None else None
    if opt is not None:
        return str(opt)
    meta = dataset.meta
    return str(getattr(meta, "anchor_frame_up", None) or (meta.extra or {}).get("anchor_frame_up") or "+z")


@dataclasses.dataclass
class FrameSetup:
    """What :func:`to_graph_frame` did: ``flipped`` (z-down anchors' frame) and the biases removed."""

    flipped: bool
    known_bias: dict


def to_graph_frame(dataset, eskf_options=None, eskf=None):
    """The dataset (and optionally an ESKF result in the anchors' frame) in the graph's convention.

    Returns ``(dataset, eskf_options, eskf, FrameSetup)``; the inputs are not modified.  With
    nothing to do the inputs are returned as they are.
    """
    up = anchor_frame_up(dataset, eskf_options)
    kb = {str(k): float(v) for k, v in (dataset.meta.known_anchor_bias or {}).items()}
    setup = FrameSetup(flipped=(up == "-z"), known_bias=kb)
    if not setup.flipped and not kb:
        return dataset, eskf_options, eskf, setup
    uwb = dataset.uwb.copy()
    if kb:
        uwb["range"] = uwb["range"].to_numpy(float) - uwb["anchor"].astype(str).map(kb).fillna(0.0).to_numpy(float)
    tdoa = getattr(dataset, "tdoa", None)
    if tdoa is not None and len(tdoa) and kb:
        tdoa = tdoa.copy()
        ba = tdoa["anchor_a"].astype(str).map(kb).fillna(0.0).to_numpy(float)
        bb = tdoa["anchor_b"].astype(str).map(kb).fillna(0.0).to_numpy(float)
        tdoa["tdoa"] = tdoa["tdoa"].to_numpy(float) - (bb - ba)
    anchors = dataset.anchors.copy()
    meta_update: dict = {"known_anchor_bias": None}
    if setup.flipped:
        anchors[["x", "y", "z"]] = anchors[["x", "y", "z"]].to_numpy(float) * FLIP
        quat = ["qw", "qx", "qy", "qz"]
        if set(quat) <= set(anchors.columns):
            anchors[quat] = flip_quat(anchors[quat].to_numpy(float))
        meta_update["anchor_frame_up"] = "+z"
        extra = dict(dataset.meta.extra or {})
        extra.pop("anchor_frame_up", None)
        meta_update["extra"] = extra
    changes = {"uwb": uwb, "anchors": anchors, "meta": dataset.meta.model_copy(update=meta_update)}
    if tdoa is not None and hasattr(dataset, "tdoa"):
        changes["tdoa"] = tdoa
    ds = dataclasses.replace(dataset, **changes)
    if eskf_options is not None and setup.flipped:
        eskf_options = eskf_options.model_copy(update={"anchor_frame_up": "+z"})
    if eskf is not None and setup.flipped:
        eskf = flip_result(eskf)
    return ds, eskf_options, eskf, setup


def flip_result(eskf):
    """An ESKF result turned about x (positions, velocities, attitude; covariances' p and v blocks)."""
    st = eskf.states.copy()
    st[:, 0:3] *= FLIP
    st[:, 3:6] *= FLIP
    st[:, 6:10] = flip_quat(st[:, 6:10])
    upd = {"states": st}
    cov = getattr(eskf, "covariances", None)
    if cov is not None:
        d = np.ones(cov.shape[1])
        d[0:6] = np.concatenate([FLIP, FLIP])
        upd["covariances"] = cov * d[None, :, None] * d[None, None, :]
    return dataclasses.replace(eskf, **upd)


def from_graph_frame(result, setup: FrameSetup):
    """Turn a :class:`~uwbimu.calibration.batch.CalibrationResult` back into the anchors' frame (in place)."""
    cal = result.calibration
    cal["anchor_frame_up"] = "-z" if setup.flipped else "+z"
    if setup.known_bias:
        cal["known_anchor_bias_removed"] = dict(setup.known_bias)
    if not setup.flipped:
        return result
    tr = result.trajectory
    for c in ("px", "py", "pz"), ("vx", "vy", "vz"):
        tr[list(c)] = tr[list(c)].to_numpy(float) * FLIP
    tr[["qw", "qx", "qy", "qz"]] = flip_quat(tr[["qw", "qx", "qy", "qz"]].to_numpy(float))
    # sd of p and v: the diagonal of R C R^T with R = diag(1, -1, -1) is the diagonal of C
    if result.anchors is not None:
        a = result.anchors
        a[["x", "y", "z"]] = a[["x", "y", "z"]].to_numpy(float) * FLIP
        quat = ["qw", "qx", "qy", "qz"]
        if set(quat) <= set(a.columns):
            a[quat] = flip_quat(a[quat].to_numpy(float))
    anc = cal.get("anchors")
    if anc:
        for e in anc.get("positions", {}).values():
            e["position"] = [float(v) for v in np.asarray(e["position"]) * FLIP]
            if "moved_from_anchors_csv" in e:
                e["moved_from_anchors_csv"] = [float(v) for v in np.asarray(e["moved_from_anchors_csv"]) * FLIP]
        anc["frame_note"] = "positions turned back into the z-down anchors' frame (180 deg about x)"
    corr = cal.get("correlations")
    if corr:
        d = np.array([-1.0 if n.startswith(("anchor_y_", "anchor_z_")) else 1.0 for n in corr["names"]])
        m = np.asarray(corr["matrix"], float) * np.outer(d, d)
        corr["matrix"] = [[round(float(c), 4) for c in row] for row in m]
    if result.eskf is not None:
        result.eskf = flip_result(result.eskf)  # the initialising ESKF, back in the anchors' frame too
    return result

