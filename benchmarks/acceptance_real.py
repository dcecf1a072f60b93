"""Acceptance on real sequences, defaults only: both estimators, lever arm and t_d against the documented.

    python benchmarks/acceptance_real.py DATASET [DATASET ...] [--no-batch]

DATASET: folders imported with the documented verbs (``uwbimu import inrol|isas-walk|cf-usdlog ...``).
Per sequence and estimator (``run_eskf`` with ``smoother="forward_backward"`` = ``uwbimu estimate``,
``calibrate`` = ``uwbimu calibrate``, both otherwise with default options; ``--no-smooth``: the causal filter) it prints: the lever arm ± sigma against the documented antenna offset with
the distance in sigma per axis (or "not identified"), t_d ± sigma with its verdict, the NIS summary
(mean, median of the accepted updates), the noise used (IMU densities and range/TDoA sd, from the log or
the preset), the position RMSE against the ground truth where its frame is the anchors' (ISAS-Walk: not
comparable unaligned, n/a), the ESKF/batch agreement on t_d, and whether a clock event was raised; for the batch
also where it started (``calibration_start``: the ESKF or, when that run fails the health check, a robust
multilateration) and the blocks it held at their priors (``calibration_held``).

The documented antenna offset comes from the dataset (``truth.lever_arm``, else the tag's nominal lever
arm; a Crazyflie microSD import writes the UTIL platform's documented offset there, ``t_uv``: -1.245, 0.127,
9.08 cm); a TDoA dataset without either (an older import) is compared with that same UTIL offset.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from uwbimu.io.importers.cf_usdlog import UTIL_T_UV as UTIL_TAG_OFFSET  # noqa: E402  (one definition)


def documented_lever(ds):
    truth = getattr(ds.meta, "truth", None)
    if truth is not None and getattr(truth, "lever_arm", None) is not None:
        return np.asarray(truth.lever_arm, float), "dataset truth.lever_arm"
    for tag in ds.meta.tags or []:
        if getattr(tag, "lever_arm", None) is not None:
            return np.asarray(tag.lever_arm, float), f"tag {tag.name} nominal"
    if ds.tdoa is not None and len(ds.tdoa):
        return np.asarray(UTIL_TAG_OFFSET), "UTIL t_uv"
    return None, "none"


def position_rmse(ds, t, p):
    gt = ds.groundtruth
    if gt is None or not {"px", "py", "pz"} <= set(gt.columns):
        return None
    from uwbimu.metrics.align import groundtruth_frame

    if not groundtruth_frame(ds.meta.extra).frames_agree:
        return None
    from uwbimu.metrics.filter import truth_at

    ref, _, _, m = truth_at(ds, t)
    return float(np.sqrt(np.mean(np.sum((p[m] - ref[m]) ** 2, axis=1))))


def lever_cells(lever, sd, verdicts, doc):
    out = []
    for i, c in enumerate("xyz"):
        v = (verdicts or {}).get(c, "")
        cell = f"{100 * lever[i]:+.1f} ± {100 * sd[i]:.1f}"
        if doc is not None and sd[i] > 0:
            cell += f" ({abs(lever[i] - doc[i]) / sd[i]:.1f} sd{'' if v == 'identified' else ', ' + (v or 'n/a')})"
        out.append(cell)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--no-batch", action="store_true", help="the ESKF only")
    ap.add_argument("--no-smooth", action="store_true", help="the causal ESKF (uwbimu estimate --no-smooth)")
    a = ap.parse_args()
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.io.loader import load_dataset

    for path in a.datasets:
        ds = load_dataset(path)
        doc, doc_src = documented_lever(ds)
        t0 = time.process_time()
        r = run_eskf(ds, EskfOptions(smoother="off" if a.no_smooth else "forward_backward"))
        cal = r.calibration
        res = r.residuals
        acc = res["accepted"].to_numpy(bool)
        nis = res["nis"].to_numpy(float)[acc]
        noise = r.extra.get("noise", {})
        imu = noise.get("imu", {})
        meas = noise.get("measurements", {}) or {}
        rmse = position_rmse(ds, r.t, r.states[:, :3])
        print(f"\n## {ds.meta.name} ({path}); documented lever arm {None if doc is None else np.round(100 * doc, 2).tolist()} cm "
              f"({doc_src})")
        print(f"ESKF ({time.process_time() - t0:.0f} CPU s): lever arm [cm] "
              + " | ".join(lever_cells(cal["lever_arm"], cal["lever_arm_sd"], cal.get("lever_arm_verdict"), doc))
              + f"; modes {r.config['resolved'].get('modes')}")
        print(f"  t_d {1e3 * cal['time_offset']:+.1f} ± {1e3 * cal['time_offset_sd']:.1f} ms, "
              f"{cal.get('time_offset_verdict')}; NIS mean {nis.mean():.2f} median {np.median(nis):.2f} "
              f"(n {nis.size}); sigma_scale {cal.get('sigma_scale', 1.0):.2f}")
        if "accel" in imu:
            print(f"  noise: accel {imu['accel']['used']:.3g} m/s^2/sqrt(Hz) ({imu['accel']['ratio']:.1f} x preset), "
                  f"gyro {imu['gyro']['used']:.3g} rad/s/sqrt(Hz) ({imu['gyro']['ratio']:.1f} x); "
                  + ", ".join(f"{k} sd {v['sigma_new']:.3f} m" for k, v in meas.items()))
        print(f"  position RMSE {'n/a (ground truth in another frame)' if rmse is None else f'{rmse:.3f} m'}")
        clock = [e for e in r.events if str(e.get("kind", "")).startswith("clock")]
        if a.no_batch:
            continue
        from uwbimu.calibration import calibrate
        from uwbimu.calibration.agreement import estimator_agreement

        t0 = time.process_time()
        b = calibrate(ds, eskf=None)
        bc = b.calibration
        from uwbimu.calibration.agreement import _batch_lever_verdicts

        bl_v = _batch_lever_verdicts(bc)
        td = bc["time_offset"]
        tdv, tds, tdverd = (td.get("value"), td.get("sd"), td.get("verdict")) if isinstance(td, dict) else (
            td, bc.get("time_offset_sd"), bc.get("time_offset_verdict"))
        print(f"batch ({time.process_time() - t0:.0f} CPU s): lever arm [cm] "
              + " | ".join(lever_cells(bc["lever_arm"], bc["lever_arm_sd"], bl_v, doc)))
        tds_txt = "not estimated" if tds is None or not math.isfinite(float(tds)) else f"{1e3 * float(tds):.1f} ms"
        print(f"  t_d {1e3 * float(tdv):+.1f} ± {tds_txt}, {tdverd}; "
              f"IMU noise scale {((bc.get('imu_noise') or {}).get('inflation'))}")
        brmse = position_rmse(ds, b.trajectory["t"].to_numpy(), b.trajectory[["px", "py", "pz"]].to_numpy())
        st = bc.get("start") or {}
        held = (bc.get("held_at_prior") or {}).get("blocks") or []
        print(f"  position RMSE {'n/a (ground truth in another frame)' if brmse is None else f'{brmse:.3f} m'}; "
              f"start {st.get('source')} ({st.get('reason')}); held at prior: {', '.join(held) or 'none'}")
        ag = estimator_agreement(cal, bc, r.config["resolved"].get("modes"))
        print(f"  agreement: {ag['kind']} {ag['disagreeing']}")
        clock += [e for e in (b.events or []) if str(e.get("kind", "")).startswith("clock")]
        print(f"  clock events: {len(clock)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
