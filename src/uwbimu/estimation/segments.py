"""Flight segments of a log: take-off and landing from the IMU.

A multirotor sits on the floor before take-off and after landing, with its motors already (or still)
running.  There the UWB radio is shadowed by the floor and, on the Crazyflie logs of the UTIL dataset,
the TDoA of a vehicle on the floor agree with a position several metres away (a mirror solution of
the anchors' geometry) as well as in-flight TDoA agree with the true one: no residual test on the
ranges can tell the floor from the air.  The IMU can: a vehicle resting on the floor does not move
vertically, and a take-off is a sustained climb.

:func:`detect_flight` finds, from the IMU only:

* an initial rest (the first ``rest_s`` seconds quiet: low gyro rate) giving gravity's direction and
  magnitude in the body frame (the accelerometer's scale error and the bias along gravity cancel);
* the vertical velocity by strapdown integration of the specific force along gravity (the gyro keeps
  the attitude; over the few seconds of a take-off its drift is negligible);
* take-off: the first time the vertical velocity exceeds ``climb_speed`` [m/s] *and* the climb
  reaches ``airborne_height`` [m] within ``climb_window_s``; the vertical bias of a vibrating IMU on the
  floor is removed first (the vehicle is static there, so its mean vertical acceleration is zero; the
  last floor second's bias and the crossing are found together by a fixed-point iteration, see
  ``_first_climb``);
* landing: the same test run backwards in time from a final rest.

A log that does not start at rest, or in which no climb is found, gives ``None`` (the whole log is
used): a ground robot, a hand-held sensor or a log cut in flight is never cropped.  The estimators use
the segment from the moment the vehicle is ``airborne_height`` above the floor (the radio is shadowed
close to it) to touch-down.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np



@dataclass(frozen=True)
class FlightSegment:
    """Take-off and landing of one flight, IMU clock [s].

    ``takeoff`` / ``landing``: the vertical velocity crosses ``climb_speed`` (leaving / reaching the
    floor); ``start`` / ``end``: the vehicle is ``airborne_height`` above the floor (after take-off, before
    landing); the estimators use ``[start, end]``.  ``landing`` is None when the log ends in flight.
    """

    takeoff: float
    start: float
    landing: Optional[float]
    end: float
    rest_s: float
    climb_speed: float
    airborne_height: float

    def to_dict(self) -> dict:
        return {"takeoff": self.takeoff, "start": self.start, "landing": self.landing, "end": self.end,
                "rest_s": self.rest_s, "climb_speed": self.climb_speed, "airborne_height": self.airborne_height}


def _quiet_prefix(t: np.ndarray, u: np.ndarray, gyro_thr: float, block_s: float = 0.05,
                  acc_thr: float = 0.5) -> int:
    """Number of samples of the initial rest: blocks of ``block_s`` seconds whose mean body rate stays
    below ``gyro_thr`` [rad/s] on every axis and whose sd stays below twice that (idling motors shake a
    vehicle that does not move), and whose mean specific force stays within ``acc_thr`` [m/s^2] of the
    first block's (a vehicle that accelerates is not at rest), from the first sample on."""
    n = 0
    k = 0
    f_ref = None
    while k < len(t):
        k1 = int(np.searchsorted(t, t[k] + block_s))
        if k1 <= k + 1:
            break
        w = u[k:k1, 3:6]
        f = u[k:k1, :3].mean(axis=0)
        f_ref = f if f_ref is None else f_ref
        if np.any(np.abs(w.mean(axis=0)) >= gyro_thr) or np.any(w.std(axis=0) >= 2 * gyro_thr) or \
                np.linalg.norm(f - f_ref) > acc_thr:
            break
        n = k = k1
    return n


def _vertical_acceleration(t: np.ndarray, u: np.ndarray, n_rest: int) -> np.ndarray:
    """World-vertical acceleration [m/s^2]: the specific force along the up direction minus its rest
    value.  The up direction in the body frame, ``e``, follows ``de/dt = -(w - b_g) x e`` (gyro bias: its
    rest mean), integrated per sample and renormalised."""
    f0 = u[:n_rest, :3].mean(axis=0)
    g_mag = float(np.linalg.norm(f0))
    e = f0 / g_mag
    w = u[:, 3:6] - u[:n_rest, 3:6].mean(axis=0)
    dt = np.diff(t, prepend=t[0])
    ex, ey, ez = (float(c) for c in e)
    up = np.empty((len(t), 3))
    for k, (wx, wy, wz) in enumerate(w.tolist()):
        h = dt[k]
        # e <- e - h (w x e), then renormalise (first order; the climb lasts seconds)
        cx, cy, cz = wy * ez - wz * ey, wz * ex - wx * ez, wx * ey - wy * ex
        ex, ey, ez = ex - h * cx, ey - h * cy, ez - h * cz
        n = math.sqrt(ex * ex + ey * ey + ez * ez)
        ex, ey, ez = ex / n, ey / n, ez / n
        up[k] = (ex, ey, ez)
    return np.einsum("ij,ij->i", up, u[:, :3]) - g_mag


def _first_climb(t: np.ndarray, a_up: np.ndarray, k_from: int, climb_speed: float, airborne_height: float,
                 window_s: float) -> Optional[tuple[int, int]]:
    """First (take-off index, airborne index) after ``k_from``: the vertical velocity rises by
    ``climb_speed`` above its lowest value so far and the height then reaches ``airborne_height``
    within ``window_s``.

    The vehicle is static on the floor until it lifts off, so the mean vertical acceleration there is
    the bias of the vibrating IMU; while the motors spin up that bias moves by tenths of m/s^2, so it is
    taken from the last floor second only, ``[crossing - 1.5 s, crossing - 0.5 s]`` (the half second
    before the crossing may hold the lift-off), removed, the velocity integrated again from that window
    and the crossing found again, until it stays put."""
    if k_from >= len(t) - 2:
        return None
    dt = np.diff(t, prepend=t[0])
    k_w, bias, k_up = k_from, 0.0, None
    for _ in range(8):
        v = np.cumsum((a_up[k_w:] - bias) * dt[k_w:])
        rise = v - np.minimum.accumulate(np.minimum(v, 0.0))
        idx = np.flatnonzero(rise > climb_speed)
        if not len(idx):
            return None
        if k_up is not None and k_w + int(idx[0]) == k_up:
            break
        k_up = k_w + int(idx[0])
        k_w = max(k_from, int(np.searchsorted(t, t[k_up] - 1.5)))
        k_s = int(np.searchsorted(t, t[k_up] - 0.5))
        if k_s - k_w <= 10:
            k_w = k_from
            break
        bias = float(a_up[k_w:k_s].mean())
    v = np.cumsum((a_up[k_w:] - bias) * dt[k_w:])
    # integrate the height from the lowest velocity before the crossing (the last moment not climbing)
    k0 = k_w + int(np.argmin(v[: k_up - k_w + 1]))
    k_end = int(np.searchsorted(t, t[k0] + window_s))
    h = np.cumsum((v[k0 - k_w:k_end - k_w] - v[k0 - k_w]) * dt[k0:k_end])
    air = np.flatnonzero(h > airborne_height)
    if not len(air):
        return None
    return k_up, k0 + int(air[0])


def detect_flight(imu_t: np.ndarray, imu_u: np.ndarray, *, min_rest_s: float = 0.05, gyro_thr: float = 0.05,
                  climb_speed: float = 0.3, airborne_height: float = 0.3, climb_window_s: float = 3.0,
                  max_ground_s: float = 60.0) -> Optional[FlightSegment]:
    """Take-off and landing of a log that starts on the floor (see the module docstring).

    Parameters
    ----------
    imu_t : (N,) IMU stamps [s], increasing.
    imu_u : (N, 6) specific force [m/s^2] and body rate [rad/s] in the IMU frame.
    min_rest_s : shortest initial (and final) rest accepted as the reference [s]; the rest is the
        longest quiet prefix (50 ms blocks whose mean body rate is below ``gyro_thr``, sd below twice that).
    gyro_thr : body-rate level [rad/s] below which the IMU is at rest (3 deg/s: far above a MEMS gyro's
        noise at rest, far below any deliberate motion).
    climb_speed : vertical speed [m/s] that marks the take-off (and, backwards, the landing).
    airborne_height : height above the floor [m] from which the ranges are used.
    climb_window_s : the climb must reach ``airborne_height`` within this time after take-off [s].
    max_ground_s : take-off searched within this time from the start [s].

    Returns
    -------
    FlightSegment, or None when the log does not start at rest or no take-off is found.
    """
    t = np.asarray(imu_t, dtype=float)
    u = np.asarray(imu_u, dtype=float)
    if len(t) < 50:
        return None
    n_rest = _quiet_prefix(t, u, gyro_thr)
    if n_rest < 20 or n_rest > len(t) - 20 or t[n_rest - 1] - t[0] < min_rest_s:
        return None
    k_max = int(np.searchsorted(t, t[0] + max_ground_s))
    a_up = _vertical_acceleration(t[:k_max], u[:k_max], n_rest)
    found = _first_climb(t[:k_max], a_up, n_rest, climb_speed, airborne_height, climb_window_s)
    if found is None:
        return None
    k_takeoff, k_start = found
    landing, end = None, float(t[-1])
    # landing: the same test backwards in time from a final rest (time reversed: a descent is a climb)
    t_rev = -t[::-1]
    u_rev = u[::-1] * np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])
    n_end = _quiet_prefix(t_rev, u_rev, gyro_thr)
    if 20 <= n_end < len(t) - 20 and t_rev[n_end - 1] - t_rev[0] >= min_rest_s:
        k_min = max(k_start, int(np.searchsorted(t, t[-1] - max_ground_s)))
        # time reversed: stamps negated, body rates negated (the attitude runs backwards)
        m = len(t) - k_min
        tr, a_rev = t_rev[:m], _vertical_acceleration(t_rev[:m], u_rev[:m], n_end)
        back = _first_climb(tr, a_rev, n_end, climb_speed, airborne_height, climb_window_s)
        if back is not None:
            k_land_r, k_end_r = back
            landing = float(-tr[k_land_r])
            end = float(-tr[k_end_r])
    if end - float(t[k_start]) < 2 * climb_window_s:
        return None
    return FlightSegment(takeoff=float(t[k_takeoff]), start=float(t[k_start]), landing=landing, end=end,
                         rest_s=float(t[n_rest - 1] - t[0]), climb_speed=climb_speed, airborne_height=airborne_height)


def measurement_rows(ds, t0: float = -np.inf, t1: float = np.inf, tag: Optional[str] = None):
    """The range and TDoA rows over ``[t0, t1]`` (UWB clock) whose anchors are surveyed, of ``tag`` when given
    and the table names its tags: ``(t, p_b, p_a, z, ids)`` with ``p_b`` the (second) anchor's position,
    ``p_a`` the first anchor's for a TDoA row (``z = |x - p_b| - |x - p_a|``) and NaN for a range
    (``z = |x - p_b|``), ``ids`` the anchor or ``"a-b"`` pair; ranges first, then TDoA, in table order.
    None without rows.  The one reader of rows for the model-free fixes (this module, the batch's start check)."""
    pos = ds.anchor_positions()

    def rows_of(tab):
        sel = (tab["t"] >= t0) & (tab["t"] <= t1)
        if tag is not None and "tag" in tab.columns:
            sel &= tab["tag"].astype(str) == str(tag)
        return tab[sel.to_numpy()]

    ts, rows_p, rows_a, rows_z, ids = [], [], [], [], []
    if ds.uwb is not None and len(ds.uwb):
        u = rows_of(ds.uwb)
        u = u[u["anchor"].astype(str).isin(pos.keys()).to_numpy()]
        ts.append(u["t"].to_numpy(float))
        rows_p.append(np.array([pos[a] for a in u["anchor"].astype(str)], float).reshape(-1, 3))
        rows_a.append(np.full((len(u), 3), np.nan))
        rows_z.append(u["range"].to_numpy(float))
        ids.append(u["anchor"].astype(str).to_numpy())
    td = getattr(ds, "tdoa", None)
    if td is not None and len(td):
        d = rows_of(td)
        d = d[(d["anchor_a"].astype(str).isin(pos.keys()) & d["anchor_b"].astype(str).isin(pos.keys())).to_numpy()]
        ts.append(d["t"].to_numpy(float))
        rows_p.append(np.array([pos[b] for b in d["anchor_b"].astype(str)], float).reshape(-1, 3))
        rows_a.append(np.array([pos[a] for a in d["anchor_a"].astype(str)], float).reshape(-1, 3))
        rows_z.append(d["tdoa"].to_numpy(float))
        ids.append((d["anchor_a"].astype(str) + "-" + d["anchor_b"].astype(str)).to_numpy())
    if not rows_z:
        return None
    return tuple(np.concatenate(x) for x in (ts, rows_p, rows_a, rows_z, ids))


def _fix(ds, t0: float, t1: float) -> Optional[tuple[np.ndarray, float]]:
    """Robust (soft-L1) multilateration of the tag over ``[t0, t1]`` (UWB clock) from the ranges and
    TDoA; returns ``(position, sd)`` with ``sd`` the fix's position sd (robust residual scale times the
    geometry), or None with fewer than 6 rows."""
    from scipy.optimize import least_squares

    pos = ds.anchor_positions()
    rows = measurement_rows(ds, t0, t1)
    if rows is None:
        return None
    _, pb, pa, z, _ = rows
    fin = np.isfinite(z)
    pb, pa, z = pb[fin], pa[fin], z[fin]
    if len(z) < 6:
        return None
    is_td = np.isfinite(pa[:, 0])
    pa0 = np.where(is_td[:, None], pa, 0.0)

    def resid(x):
        r = np.linalg.norm(x - pb, axis=1)
        return r - np.where(is_td, np.linalg.norm(x - pa0, axis=1), 0.0) - z

    x0 = np.mean(np.array(list(pos.values())), axis=0)
    scale = max(float(np.median(np.abs(resid(x0)))), 0.1)
    sol = least_squares(resid, x0, loss="soft_l1", f_scale=scale)
    sol = least_squares(resid, sol.x, loss="soft_l1", f_scale=max(1.4826 * float(np.median(np.abs(sol.fun))), 0.02))
    s = 1.4826 * float(np.median(np.abs(sol.fun)))
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s * s
        sd = float(np.sqrt(np.trace(cov)))
    except np.linalg.LinAlgError:
        sd = float("inf")
    return sol.x, sd


def ground_ranges_shadowed(ds, seg: FlightSegment, t_d: float = 0.0) -> dict:
    """Whether the ranges on the floor contradict the airborne ones (the radio is shadowed there).

    The fix from the last second on the floor before take-off (and the first second after landing) is
    compared with the fix from the first half second airborne (the last before landing).  Between the
    two the vehicle climbed about ``airborne_height`` (the IMU's estimate, which may be off by as much
    again) and moved at the airborne speed (from the next half second's fix) for the time between the
    windows, so they agree within ``2 airborne_height + 0.5 m + speed x gap`` plus three combined fix sds
    unless the floor ranges are wrong (or the vehicle was not on the floor); the shadowed floor of the
    Crazyflie logs is 5-7 m off.  Returns ``{"before": bool|None, "after":
    bool|None, "offset_before": m, "offset_after": m}`` (None: not enough data to tell).
    """
    out: dict = {"before": None, "after": None, "offset_before": None, "offset_after": None,
                 "tolerance_before": None, "tolerance_after": None}
    sides = [("before", (seg.takeoff - 1.2, seg.takeoff - 0.2), (seg.start, seg.start + 0.5), +1.0)]
    if seg.landing is not None:
        sides.append(("after", (seg.landing + 0.2, seg.landing + 1.2), (seg.end - 0.5, seg.end), -1.0))
    for name, (g0, g1), (a0, a1), way in sides:
        fg = _fix(ds, g0 - t_d, g1 - t_d)
        fa = _fix(ds, a0 - t_d, a1 - t_d)
        fa2 = _fix(ds, a0 + way * 0.5 - t_d, a1 + way * 0.5 - t_d)  # the next half second in the air
        if fg is None or fa is None:
            continue
        off = float(np.linalg.norm(fg[0] - fa[0]))
        # how far the vehicle may have moved between the two windows' centres at the airborne speed
        speed = float(np.linalg.norm(fa2[0] - fa[0])) / 0.5 if fa2 is not None else 0.0
        gap = abs(0.5 * (a0 + a1) - 0.5 * (g0 + g1))
        tol = 2.0 * seg.airborne_height + 0.5 + speed * gap + 3.0 * math.hypot(fg[1], fa[1])
        out[name] = bool(off > tol)
        out["offset_" + name] = off
        out["tolerance_" + name] = tol
    return out


def crop_streams(ds, t0: float, t1: float):
    """A copy of ``ds`` whose IMU, UWB and TDoA rows lie in ``[t0, t1]`` (ground truth kept whole, for
    the comparison)."""
    import dataclasses

    changes = {}
    for name in ("imu", "uwb", "tdoa"):
        df = getattr(ds, name, None)
        if df is not None and len(df):
            changes[name] = df[(df["t"] >= t0) & (df["t"] <= t1)].reset_index(drop=True)
    return dataclasses.replace(ds, **changes)


def select_segment(ds, mode: str = "auto", start: Optional[float] = None, end: Optional[float] = None):
    """The part of the log the estimators use, and the event that says why.

    ``start`` / ``end`` [s, the dataset's stamps] given: that span.  Else ``mode="auto"``: the flight
    from :func:`detect_flight`, cropped on each side where :func:`ground_ranges_shadowed` finds the floor
    ranges contradicting the airborne ones (elsewhere the time on the floor is kept: its ranges are
    good and its rest helps the start); ``"whole"``: the whole log.

    Returns ``(dataset, event)`` with ``event = {"kind": "flight_segment", "t", "used": [t0, t1], "cropped",
    ...}`` (``message``: the warning line, when cropped).  The IMU and UWB stamps are compared as if on one
    clock: an unknown time offset shifts the floor and air windows by as much (fractions of a second against
    windows of 0.5-1 s).
    """
    t_first, t_last = float(ds.imu["t"].iloc[0]), float(ds.imu["t"].iloc[-1])
    ev: dict = {"kind": "flight_segment", "t": t_first, "mode": mode}
    t0 = t_first if start is None else float(start)
    t1 = t_last if end is None else float(end)
    if start is not None or end is not None:
        ev.update(source="options", used=[t0, t1])
    elif mode == "auto":
        seg = detect_flight(ds.imu["t"].to_numpy(float), ds.imu[["ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float))
        if seg is None:
            ev.update(source="auto", detected=False, used=[t0, t1])
        else:
            sh = ground_ranges_shadowed(ds, seg)
            if sh["before"]:
                t0 = seg.start
            if sh["after"]:
                t1 = seg.end
            ev.update(source="auto", detected=True, **seg.to_dict(), shadowed_before=sh["before"],
                      shadowed_after=sh["after"], ground_fix_offset_before=sh["offset_before"],
                      ground_fix_offset_after=sh["offset_after"], used=[t0, t1])
    else:
        ev.update(source="whole", used=[t0, t1])
    if t1 - t0 <= 0:
        from uwbimu.errors import UsageError

        raise UsageError(f"segment: start {t0:g} s is not before end {t1:g} s (log {t_first:g}-{t_last:g} s)")
    ev["cropped"] = (t0, t1) != (t_first, t_last)
    if ev["cropped"]:
        ds = crop_streams(ds, t0, t1)
        ev["message"] = segment_warning(ev)
    return ds, ev


def segment_warning(ev: dict) -> str:
    """One line for the console and the report from a ``flight_segment`` event."""
    t0, t1 = ev["used"]
    if ev.get("source") == "options":
        return f"segment: the log is used from {t0:.2f} s to {t1:.2f} s (start/end options)"
    parts = []
    if ev.get("shadowed_before"):
        parts.append(f"before take-off ({ev['takeoff']:.2f} s; the floor fix is {ev['ground_fix_offset_before']:.1f} m "
                     f"from the airborne one)")
    if ev.get("shadowed_after"):
        parts.append(f"after landing ({ev['landing']:.2f} s; {ev['ground_fix_offset_after']:.1f} m)")
    return (f"segment: the ranges on the floor contradict the airborne ones {' and '.join(parts)}: the radio is "
            f"shadowed there; the log is used from {t0:.2f} s to {t1:.2f} s (segment: whole keeps it all)")
