"""Time-base, rate and physical plausibility checks of a loaded dataset.

Called by :func:`uwbimu.io.loader.load_dataset` after each table is read and
validated on its own.  A check either refuses (``src.error(...)``, which builds
a :class:`uwbimu.io.loader.DatasetError` naming file, line and column) or records
a structured warning ``{"code": ..., "file": ..., "message": ...}`` in the load
report.  The warning codes are public (documented in docs/dataset_format.md):

``imu_rate_low``, ``span_overlap_partial``, ``anchors_coincident``,
``anchors_coplanar``, ``accel_high``, ``lenient_accepted``.

Thresholds are relative where a scale exists (anchor geometry against the
anchors' own extent, spans against each other) and physical otherwise (MEMS
full scales).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Optional

import numpy as np
import pandas as pd

#: IMU rates [Hz]: below the first the load is refused (unless lenient), below the second it warns.
IMU_RATE_REFUSE_HZ = 10.0
IMU_RATE_WARN_HZ = 50.0
#: Largest plausible |specific force| of one sample [m/s^2] (high-g MEMS full scale ~ 200 g).
ACCEL_MAX = 200 * 9.81
#: Above this |a| a sample is unusual for a consumer IMU (16 g full scale): warning.
ACCEL_WARN = 16 * 9.81
#: Largest plausible |angular rate| of one sample [rad/s] (4000 deg/s full scale).
GYRO_SAMPLE_MAX = math.radians(4000.0)
#: Anchor and ground-truth coordinates beyond this are refused [m] (UWB covers < 1 km).
COORD_MAX = 1000.0
#: A recording longer than this is refused as a unit mistake [s] (30 days).
MAX_SPAN_S = 30 * 86400.0
#: A uniform grid over the IMU span may hold at most this many times the rows read.
MAX_GRID_FACTOR = 50.0
#: Relative singular value below which the anchors' extent in a direction counts as zero.
DEGENERATE_REL = 1e-3
#: Relative singular value below which anchors count as (nearly) coplanar (warning).
COPLANAR_REL = 0.02
#: Two anchors closer than this fraction of the anchors' extent are "coincident".
COINCIDENT_REL = 1e-3

_UNIT_GUESSES = (("ms", 1e-3), ("us", 1e-6), ("ns", 1e-9))


def _median_dt(t: np.ndarray) -> float:
    d = np.diff(t)
    d = d[d > 0]
    return float(np.median(d)) if len(d) else float("nan")


def _unit_guess(dt: float, lo_hz: float = 10.0, hi_hz: float = 10000.0) -> Optional[str]:
    """The time unit ('ms', 'us', 'ns') under which a sample interval ``dt`` gives a plausible rate."""
    for name, scale in _UNIT_GUESSES:
        rate = 1.0 / (dt * scale)
        if lo_hz <= rate <= hi_hz:
            return name
    return None


def check_time_base(tables: dict[str, tuple[Any, pd.DataFrame]], lenient: bool,
                    warn: Callable[..., None]) -> None:
    """Units of the time columns, rate bands, span overlap and grid size.

    ``tables`` maps a table name (``imu``, ``uwb``, ``tdoa``, ``groundtruth``) to
    ``(source, frame)``; ``warn(code, file, message, **fields)`` records a warning.
    """
    src, imu = tables["imu"]
    t = imu["t"].to_numpy()
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    if len(t) < 2 or span <= 0:
        raise src.error(f"the IMU needs at least two distinct timestamps, got {len(t)} row(s) spanning "
                        f"{span:g} s", None, "t")
    dt = _median_dt(t)
    rate = 1.0 / dt
    guess = _unit_guess(dt)
    # Another table whose span matches the IMU's says the IMU stamps are in seconds after all.
    for name, (_s, df) in tables.items():
        tt = df["t"].to_numpy()
        if name != "imu" and len(tt) > 1 and 1 / 3 < (tt[-1] - tt[0]) / span < 3:
            guess = None
    for name, (s, df) in tables.items():
        tt = df["t"].to_numpy()
        if len(tt) > 1 and tt[-1] - tt[0] > MAX_SPAN_S:
            g = _unit_guess(_median_dt(tt), 0.1, 1e5)
            raise s.error(f"the stamps span {tt[-1] - tt[0]:.4g} s (more than 30 days): the time unit is not "
                          f"seconds{f' (it looks like {g})' if g else ''}; convert column 't' to seconds",
                          None, "t")
    if rate < IMU_RATE_REFUSE_HZ:
        if guess is not None:
            raise src.error(f"median IMU sample interval {dt:.4g} gives {rate:.3g} Hz: the stamps look like "
                            f"they are in {guess}, not seconds; convert column 't' to seconds", None, "t")
        if not lenient:
            raise src.error(f"IMU rate {rate:.3g} Hz is below {IMU_RATE_REFUSE_HZ:g} Hz: too slow to integrate "
                            f"motion between ranges", None, "t",
                            hint="--lenient accepts it with a warning (expect poor results)")
        warn("lenient_accepted", src.name, f"IMU rate {rate:.3g} Hz accepted by lenient loading", rate_hz=rate)
    elif rate < IMU_RATE_WARN_HZ:
        warn("imu_rate_low", src.name, f"IMU rate {rate:.3g} Hz is below {IMU_RATE_WARN_HZ:g} Hz: expect larger "
             f"errors between ranges", rate_hz=rate)
    grid = span * rate
    if grid > MAX_GRID_FACTOR * len(t) and grid > 1e7:
        raise src.error(f"the IMU span {span:.4g} s at its median rate {rate:.4g} Hz makes {grid:.3g} samples, "
                        f"{grid / len(t):.0f} times the {len(t)} rows: mixed time units or a huge gap",
                        None, "t")
    t0, t1 = float(t[0]), float(t[-1])
    for name in ("uwb", "tdoa", "groundtruth"):
        if name not in tables:
            continue
        s, df = tables[name]
        tt = df["t"].to_numpy()
        if len(tt) == 0:
            continue
        a0, a1 = float(tt[0]), float(tt[-1])
        ratio = (a1 - a0) / span if a1 > a0 else float("nan")
        overlap = min(a1, t1) - max(a0, t0)
        for unit, factor in (("ms", 1e3), ("us", 1e6), ("ns", 1e9)):
            if ratio == ratio and factor / 3 < ratio < factor * 3:
                raise s.error(f"its stamps span {a1 - a0:.4g} units against {span:.4g} s of IMU data "
                              f"({ratio:.3g} times longer): column 't' looks like it is in {unit}; convert it "
                              f"to seconds", None, "t")
            if ratio == ratio and 1 / (factor * 3) < ratio < 3 / factor:
                raise s.error(f"its stamps span {a1 - a0:.4g} s against {span:.4g} units of IMU data: the IMU "
                              f"stamps look like they are in {unit}; convert them to seconds", None, "t")
        if overlap <= 0:
            off = a0 - t0
            why = (" (an offset of about 1e9 s: one file has Unix epoch stamps, the other relative ones)"
                   if abs(off) > 1e8 else "")
            raise s.error(f"its time span [{a0:.6g}, {a1:.6g}] s does not overlap the IMU span "
                          f"[{t0:.6g}, {t1:.6g}] s{why}; all tables must share one time base", None, "t")
        shorter = min(a1 - a0, span)
        if shorter > 0 and overlap < 0.5 * shorter:
            warn("span_overlap_partial", s.name, f"only {overlap:.3g} s of its {a1 - a0:.3g} s span overlaps the "
                 f"IMU span [{t0:.6g}, {t1:.6g}] s", overlap_s=overlap)


def check_imu_physics(src: Any, imu: pd.DataFrame, warn: Callable[..., None]) -> None:
    """Per-sample accelerometer and gyro magnitudes within sensor full scales."""
    a = np.linalg.norm(imu[["ax", "ay", "az"]].to_numpy(), axis=1)
    w = np.linalg.norm(imu[["wx", "wy", "wz"]].to_numpy(), axis=1)
    for vals, limit, col, what in ((a, ACCEL_MAX, "ax", "specific force"), (w, GYRO_SAMPLE_MAX, "wx", "rate")):
        bad = np.flatnonzero(vals > limit)
        if len(bad):
            k = int(bad[0])
            raise src.error(f"|{what}| = {vals[k]:.4g} is beyond any IMU's full scale ({limit:.4g}; "
                            f"{len(bad)} such row(s)): a corrupt sample", imu.index[k], col)
    high = np.flatnonzero(a > ACCEL_WARN)
    if len(high):
        warn("accel_high", src.name, f"{len(high)} sample(s) with |a| above 16 g (first at "
             f"{src.at(imu.index[int(high[0])])})", rows=int(len(high)))


def check_coordinates(src: Any, df: pd.DataFrame, columns: list[str], what: str) -> None:
    """Coordinates within :data:`COORD_MAX` of the origin."""
    v = np.abs(df[columns].to_numpy())
    bad = np.argwhere(v > COORD_MAX)
    if len(bad):
        r, c = int(bad[0][0]), int(bad[0][1])
        raise src.error(f"{what} coordinate {v[r, c]:.4g} m is beyond {COORD_MAX:g} m from the origin "
                        f"(UWB covers less than 1 km): a unit mistake (mm?) or a corrupt value", df.index[r],
                        columns[c])


def check_anchor_geometry(src: Any, anchors: pd.DataFrame, lenient: bool, warn: Callable[..., None]) -> None:
    """Name coincident, collinear and coplanar anchors with the consequence for estimation."""
    ids = [str(a) for a in anchors["anchor"]]
    p = anchors[["x", "y", "z"]].to_numpy()
    if len(p) < 2:
        if not lenient:
            raise src.error(f"only {len(p)} anchor: ranges to one anchor cannot fix a position", None, "anchor",
                            hint="--lenient accepts it with a warning")
        warn("lenient_accepted", src.name, "a single anchor accepted by lenient loading")
        return
    centred = p - p.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    extent = float(s[0]) / math.sqrt(len(p))  # rms distance from the centroid [m]
    rel = s / s[0] if s[0] > 0 else np.zeros(3)
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    iu = np.triu_indices(len(p), 1)
    close = [(ids[i], ids[j]) for i, j in zip(*iu) if d[i, j] <= COINCIDENT_REL * max(extent, 1e-9) or d[i, j] < 1e-6]
    if s[0] <= 1e-9 or rel[1] < DEGENERATE_REL:
        kind = "all at one point" if s[0] <= 1e-9 else "collinear (on one line)"
        msg = (f"anchors {', '.join(ids)} are {kind}: the position about that "
               f"{'point' if s[0] <= 1e-9 else 'line'} is unobservable from ranges, so position, lever arm and "
               f"time offset would be estimated from the IMU alone")
        if not lenient:
            raise src.error(msg, None, "x", hint="fix the anchor survey (or --lenient to accept it with a warning)")
        warn("lenient_accepted", src.name, msg, geometry=kind)
        return
    if close:
        warn("anchors_coincident", src.name, f"anchors at the same position: {', '.join('/'.join(c) for c in close)}"
             f"; they add no geometry (check the survey for a copy-paste error)", pairs=[list(c) for c in close])
    if len(p) >= 3 and rel[2] < COPLANAR_REL:
        warn("anchors_coplanar", src.name, f"the anchors are {'coplanar' if rel[2] < DEGENERATE_REL else 'nearly coplanar'}"
             f" (out-of-plane spread {float(s[2]) / math.sqrt(len(p)):.3g} m against {extent:.3g} m in plane): the "
             f"mirror position across their plane fits the ranges too; the height is weakly observable and "
             f"the IMU and initialisation must pick the side", relative_thickness=float(rel[2]))
