"""Crazyflie logs: ours (ESKF, batch) against TDoA multilateration and the dataset authors' ESKF.

    python benchmarks/compare_crazyflie.py DATASET [DATASET ...] [--raw RAWLOG ...] [--anchors-npz NPZ]
        [--util-repo PATH] [--util-python PYTHON] [--no-batch] [--markdown]

DATASET: a folder imported with ``uwbimu import cf-usdlog RAWLOG DATASET --anchors anchors.csv``;
``--raw`` gives the raw microSD logs in the same order (needed by the authors' ESKF only).

Per log, the position RMSE [m] against the logged Vicon pose (``groundtruth.csv`` px, py, pz, linearly
interpolated to each method's stamps; the frames agree) over the whole log and over the flight segment,
for:

(a) ``run_eskf(load_dataset(path), EskfOptions(smoother="forward_backward"))``, otherwise default options
    (= ``uwbimu estimate``: the filter and its forward-backward smoothing), its ``states[:, :3]``; and the
    causal filter alone (``uwbimu estimate --no-smooth``: ``extra["filtered"]`` of the same run, what a
    robot gets online);
(b) ``calibrate(ds)`` with default options (= ``uwbimu calibrate``), the px, py, pz of its
    ``trajectory`` (the table ``uwbimu calibrate`` writes as trajectory.csv), at ``t_imu``;
(c) TDoA-only multilateration in 0.5 s windows: robust (soft-L1, 0.1 m scale) nonlinear least squares
    of ``|p - b| - |p - a| = tdoa`` over the window's rows (``anchor_a`` = a, ``anchor_b`` = b, the
    dataset's convention), started from the previous window's fix (the anchors' centroid first); the
    tag position, not the body's (the antenna is about 9 cm above the body origin; not removed);
(d) the dataset authors' ESKF (``scripts/estimation/main.py`` of utiasDSL/util-uwb-dataset), run
    unmodified as a subprocess from ``--util-repo`` (a checkout, e.g. ``git archive HEAD | tar -x``):
    the raw log is first converted by their ``scripts/flight-dataset/sdcard_scripts/log_to_csv.py``
    (which imports their ROS-bag writer: ``rosbag``, ``rospy`` and ``sensor_msgs`` are given as empty
    stub modules on PYTHONPATH, nothing of theirs is changed), then ``main.py -i anchor_0425.npz
    LOG.csv`` runs under ``runpy`` with ``MPLBACKEND=Agg`` and its module globals (``t``, ``eskf.Xpo``,
    ``min_t``) are saved so that its trajectory is scored here the same way as the others.  Its own
    printed RMS (against its spline-smoothed Vicon, whole log) is quoted in the notes.  It needs
    numpy < 2 (``numpy.lib.function_base``), pandas, scipy, matplotlib, pyquaternion and scikit-learn:
    ``--util-python`` names an interpreter that has them.  Without ``--util-repo`` or when a step
    fails the row says "not run" and why.

Flight segment: from the first to the last Vicon sample more than 0.3 m above the floor (the median
height of the first second), ground truth only, so that no method's own take-off detection defines it.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

#: window length [s] and soft-L1 scale [m] of the multilateration reference
ML_WINDOW_S = 0.5
ML_LOSS_SCALE = 0.1
#: height above the floor [m] that counts as flying (ground truth)
FLIGHT_HEIGHT = 0.3


def flight_segment(gt) -> tuple[float, float]:
    """First and last ground-truth stamp [s] more than ``FLIGHT_HEIGHT`` above the first second's height."""
    t = gt["t"].to_numpy(float)
    z = gt["pz"].to_numpy(float)
    floor = float(np.median(z[t <= t[0] + 1.0]))
    up = np.flatnonzero(z > floor + FLIGHT_HEIGHT)
    if up.size == 0:
        raise SystemExit(f"groundtruth.csv: the vehicle never rises {FLIGHT_HEIGHT} m above the floor")
    return float(t[up[0]]), float(t[up[-1]])


def _errors(ds, t, p, span=None) -> tuple[np.ndarray, np.ndarray]:
    """Position error norms [m] at the stamps inside the ground truth (and ``span``), and those stamps' indices;
    the ground truth interpolated by :func:`uwbimu.metrics.filter.truth_at`."""
    from uwbimu.metrics.filter import truth_at

    t = np.asarray(t, float)
    ref, _, _, m = truth_at(ds, t)
    if span is not None:
        m &= (t >= span[0]) & (t <= span[1])
    idx = np.flatnonzero(m)
    return np.linalg.norm(np.asarray(p, float)[idx] - ref[idx], axis=1), idx


def rmse(ds, t, p, span=None) -> tuple[float | None, int]:
    """Position RMSE [m] of ``p`` (n, 3) at stamps ``t`` [s] against the interpolated ground truth,
    over the stamps inside the ground truth (and ``span``); ``(None, 0)`` when none or non-finite."""
    e, idx = _errors(ds, t, p, span)
    if idx.size == 0:
        return None, 0
    if not np.all(np.isfinite(e)):
        return None, int(idx.size)
    return float(np.sqrt(np.mean(e**2))), int(idx.size)


def max_error(ds, t, p) -> str:
    """``"max error X m at T s"`` over the stamps inside the ground truth ("" when none is finite)."""
    e, idx = _errors(ds, t, p)
    if idx.size == 0 or not np.isfinite(e).any():
        return ""
    k = int(np.nanargmax(e))
    return f"max error {e[k]:.3g} m at {np.asarray(t, float)[idx[k]]:.1f} s"


def multilaterate_tdoa(ds, window_s: float = ML_WINDOW_S, loss_scale: float = ML_LOSS_SCALE):
    """TDoA-only fixes in consecutive windows.

    Returns ``(t, p, n_skipped)``: window centres [s], tag positions (n, 3) [m] and the number of windows
    with fewer than 6 TDoA rows or 4 distinct anchors (no fix).
    """
    from scipy.optimize import least_squares

    pos = ds.anchor_positions()
    td = ds.tdoa
    ok = (td["anchor_a"].astype(str).isin(pos.keys()) & td["anchor_b"].astype(str).isin(pos.keys())).to_numpy()
    td = td[ok & np.isfinite(td["tdoa"].to_numpy(float))].sort_values("t", kind="stable")
    tt = td["t"].to_numpy(float)
    A = np.array([pos[a] for a in td["anchor_a"].astype(str)], float).reshape(-1, 3)
    B = np.array([pos[b] for b in td["anchor_b"].astype(str)], float).reshape(-1, 3)
    z = td["tdoa"].to_numpy(float)
    ids = np.array([f"{a}" for a in td["anchor_a"].astype(str)]), np.array([f"{b}" for b in td["anchor_b"].astype(str)])
    x = np.mean(np.array(list(pos.values()), float), axis=0)
    out_t, out_p, skipped = [], [], 0
    edges = np.arange(tt[0], tt[-1] + window_s, window_s)
    for w0, w1 in zip(edges[:-1], edges[1:]):
        sel = (tt >= w0) & (tt < w1)
        if sel.sum() < 6 or len(set(ids[0][sel]) | set(ids[1][sel])) < 4:
            skipped += 1
            continue
        a, b, zz = A[sel], B[sel], z[sel]

        def resid(p, a=a, b=b, zz=zz):
            return np.linalg.norm(p - b, axis=1) - np.linalg.norm(p - a, axis=1) - zz

        sol = least_squares(resid, x, loss="soft_l1", f_scale=loss_scale)
        if not np.all(np.isfinite(sol.x)):
            skipped += 1
            continue
        x = sol.x
        out_t.append(0.5 * (w0 + w1))
        out_p.append(sol.x)
    return np.array(out_t), np.array(out_p).reshape(-1, 3), skipped


_STUB = "# empty stub (the ROS bag writer is not used by log_to_csv.py)\nclass Imu:\n    pass\n"

_RUN_MAIN = textwrap.dedent("""
    import runpy, sys, os, numpy as np
    main, npz, csv, out = sys.argv[1:5]
    sys.path.insert(0, os.path.dirname(main))
    sys.argv = [main, "-i", npz, csv]
    g = runpy.run_path(main, run_name="__main__")
    np.savez(out, t=np.asarray(g["t"], float).ravel(), p=np.asarray(g["eskf"].Xpo[:, :3], float),
             min_t=float(g["min_t"]), t_vicon0=float(np.asarray(g["t_vicon"]).ravel()[0]) + float(g["min_t"]))
""")


def run_authors_eskf(repo: Path, python: str, raw: Path, npz: Path, work: Path, timeout: float = 1200):
    """Convert ``raw`` with the authors' log_to_csv.py and run their ESKF main.py on it.

    Returns ``(t, p, note, t_vicon0)`` (stamps on their csv clock: ms since the log's first record / 1000,
    as in our importer; ``t_vicon0`` their first Vicon stamp, to check that) or ``(None, None, reason, None)``.
    """
    repo, raw, npz, work = (Path(x).resolve() for x in (repo, raw, npz, work))
    conv = repo / "scripts/flight-dataset/sdcard_scripts/log_to_csv.py"
    main = repo / "scripts/estimation/main.py"
    for f in (conv, main):
        if not f.is_file():
            return None, None, f"not run: {f} missing (is --util-repo a checkout of utiasDSL/util-uwb-dataset?)", None
    if not raw.is_file():
        return None, None, f"not run: raw log {raw} missing", None
    if not npz.is_file():
        return None, None, f"not run: anchor survey {npz} missing", None
    stub = work / "stubs"
    (stub / "sensor_msgs").mkdir(parents=True, exist_ok=True)
    for name in ("rosbag.py", "rospy.py", "sensor_msgs/__init__.py"):
        (stub / name).write_text(_STUB if name != "sensor_msgs/__init__.py" else "")
    (stub / "sensor_msgs/msg.py").write_text(_STUB)
    log = work / raw.name
    shutil.copyfile(raw, log)
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=str(stub))
    env.pop("PYTHONHOME", None)

    def step(cmd, cwd, what):
        try:
            cp = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return None, f"not run: {what} exceeded {timeout:.0f} s"
        except OSError as e:
            return None, f"not run: {what}: {e}"
        if cp.returncode != 0:
            last = (cp.stderr.strip().splitlines() or ["(no stderr)"])[-1]
            return None, f"not run: {what} exit {cp.returncode}: {last}"
        return cp, ""

    cp, why = step([python, conv.name, str(log)], conv.parent, "log_to_csv.py")
    if cp is None:
        return None, None, why, None
    csv = Path(str(log) + ".csv")
    if not csv.is_file():
        return None, None, f"not run: log_to_csv.py wrote no {csv.name}", None
    out = work / "authors_eskf.npz"
    cp, why = step([python, "-c", _RUN_MAIN, str(main), str(npz), str(csv), str(out)], main.parent, "main.py")
    if cp is None:
        return None, None, why, None
    m = re.search(r"overall RMS error of position estimation is ([-+0-9.eEnaif]+)", cp.stdout)
    own = f"their own printed RMS {float(m.group(1)):.2f} m" if m else "no RMS printed"
    d = np.load(out)
    return d["t"] + float(d["min_t"]), d["p"], own, float(d["t_vicon0"])


def fmt(x) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+", help="folders imported with `uwbimu import cf-usdlog`")
    ap.add_argument("--raw", nargs="*", default=[], help="the raw microSD logs, one per DATASET, same order")
    ap.add_argument("--anchors-npz", default="../shared/datasets/util_0425/survey/anchor_0425.npz",
                    help="the survey npz the authors' ESKF reads (an_pos)")
    ap.add_argument("--util-repo", default=None, help="checkout of utiasDSL/util-uwb-dataset (method d)")
    ap.add_argument("--util-python", default=sys.executable,
                    help="interpreter for the authors' scripts (numpy<2, pandas, scipy, matplotlib, pyquaternion, "
                         "scikit-learn)")
    ap.add_argument("--no-batch", action="store_true", help="skip (b), the batch calibration")
    ap.add_argument("--markdown", action="store_true", help="print markdown tables")
    a = ap.parse_args()
    if a.raw and len(a.raw) != len(a.datasets):
        ap.error(f"--raw: {len(a.raw)} logs for {len(a.datasets)} datasets")

    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.io.loader import load_dataset

    for i, path in enumerate(a.datasets):
        ds = load_dataset(path)
        gt = ds.groundtruth
        span = flight_segment(gt)
        t_log = (float(ds.imu["t"].iloc[0]), float(ds.imu["t"].iloc[-1]))
        rows = []

        def add(name, t, p, note, secs=None):
            if t is None:
                rows.append((name, None, None, note))
                return
            whole, n = rmse(ds, t, p)
            fl, _ = rmse(ds, t, p, span)
            if whole is None and n:
                note = "; ".join(x for x in (note, "non-finite positions") if x)
            cover = f"covers {float(np.min(t)):.1f}-{float(np.max(t)):.1f} s"
            extra = "; ".join(x for x in (note, cover, max_error(ds, t, p), None if secs is None else f"{secs:.0f} s") if x)
            rows.append((name, whole, fl, extra))

        t0 = time.perf_counter()
        try:
            r = run_eskf(ds, EskfOptions(smoother="forward_backward"))
            secs = time.perf_counter() - t0
            add("ours: ESKF, defaults (uwbimu estimate: filter + forward-backward smoothing)", r.t, r.states[:, :3],
                "", secs)
            add("ours: ESKF filter alone (--no-smooth, causal)", r.t, r.extra["filtered"]["states"][:, :3],
                "the forward pass of the same run")
        except Exception as e:  # noqa: BLE001 - a benchmark row, not a library path
            add("ours: ESKF, defaults", None, None, f"failed: {type(e).__name__}: {e}")
        if not a.no_batch:
            from uwbimu.calibration import calibrate

            t0 = time.perf_counter()
            try:
                b = calibrate(ds)
                tr = b.trajectory
                add("ours: batch (calibrate), defaults", tr["t_imu"].to_numpy(float),
                    tr[["px", "py", "pz"]].to_numpy(float), "", time.perf_counter() - t0)
            except Exception as e:  # noqa: BLE001
                add("ours: batch (calibrate), defaults", None, None, f"failed: {type(e).__name__}: {e}")
        t0 = time.perf_counter()
        mt, mp, skipped = multilaterate_tdoa(ds)
        add(f"TDoA multilateration, {ML_WINDOW_S:g} s windows", mt, mp,
            f"tag position; {len(mt)} fixes, {skipped} windows without", time.perf_counter() - t0)
        name = "dataset authors' ESKF (util-uwb-dataset)"
        if a.util_repo is None:
            add(name, None, None, "not run: no --util-repo given")
        elif not a.raw:
            add(name, None, None, "not run: no --raw log given")
        else:
            t0 = time.perf_counter()
            with tempfile.TemporaryDirectory(prefix="utilrun") as tmp:
                ut, up, note, tv0 = run_authors_eskf(Path(a.util_repo), a.util_python, Path(a.raw[i]),
                                                     Path(a.anchors_npz), Path(tmp))
            if tv0 is not None and abs(tv0 - float(gt["t"].iloc[0])) > 1e-3:
                note += (f"; their first Vicon stamp {tv0:.3f} s, ours {float(gt['t'].iloc[0]):.3f} s: "
                         "clocks differ, not corrected")
            if ut is not None and "TDOA3" in str(a.raw[i]).upper():
                note += "; their script hard-codes TDOA2 = True (only pairs 7-0, 0-1, ..., 6-7 are used)"
            add(name, ut, up, note, time.perf_counter() - t0 if ut is not None else None)

        title = (f"{ds.meta.name} ({path}): log {t_log[0]:.1f}-{t_log[1]:.1f} s, flight segment "
                 f"{span[0]:.1f}-{span[1]:.1f} s (Vicon > {FLIGHT_HEIGHT} m above the floor)")
        if a.markdown:
            print(f"\n**{title}**\n")
            print("| method | RMSE whole log [m] | RMSE flight segment [m] | notes |")
            print("| --- | --- | --- | --- |")
            for n, w, f, note in rows:
                print(f"| {n} | {fmt(w)} | {fmt(f)} | {note} |")
        else:
            print(f"\n## {title}")
            wn = max(len(r[0]) for r in rows)
            print(f"{'method':<{wn}}  {'whole':>7}  {'flight':>7}  notes")
            for n, w, f, note in rows:
                print(f"{n:<{wn}}  {fmt(w):>7}  {fmt(f):>7}  {note}")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
