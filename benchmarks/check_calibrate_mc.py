"""Batch calibrator on simulation against the Cramer-Rao bound (issue 12 item 4).

For each built-in scenario and noise seed: simulate, run ``uwbimu.calibration.calibrate`` (free
t_d, no profile, defaults otherwise) and compare the lever arm and t_d with the truth and with
the posterior Cramer-Rao bound of the same flight (``uwbimu.studies.crlb.posterior_bound``: the
bound at the end of the log, which for constant parameters is the full-log bound).  Prints per
scenario and quantity: RMS error, RMS reported sigma, sqrt(mean CRLB^2), RMS error / CRLB and
RMS(error / sigma).

    PYTHONPATH=src python benchmarks/check_calibrate_mc.py [--seeds 20] [--first-seed 0] [--workers 2]
        [--scenarios calibration-flight,excited-90s,lissajous] [--duration 60] [--config C.yaml] [--json OUT]

``crlb_bias`` (TWR, when the calibrator estimates every anchor's bias): the second baseline, the bound with an
unknown constant bias per anchor (prior ``anchor_bias_prior_sd``; ``posterior_bound(..., anchor_bias_sd=)``), the
bound of the calibrator's own parameterisation; the control-variate table quotes the ratio to it as well.
``--max-seeds N`` with ``--from-json``: the tables of the first N seeds of each scenario only.

``--config``: calibrator options (``CalibrationOptions`` YAML) on top of the profile-off default, e.g.
``huber_k: 100`` to measure what the robust loss costs on Gaussian ranges (same seeds, paired).
``--from-json OUT [OUT2 ...]``: the tables again from saved runs, pooled (no calibration).

``--control-variate``: the range noise's part of each error is, to first order, a fixed linear map of the
simulated draws whose sd is known exactly (``check_calibrate_linear_split.truth_step``: the plain least-squares
graph linearised at the truth).  Its sample RMS over the seeds is pure sampling of the draws;
``sqrt(mean e^2 - mean g^2 + E g^2)`` removes it (an unbiased control-variate estimate of the mean square error,
with its bootstrap sd), so that the estimator's efficiency is measured with far fewer seeds.

Sampling: for an efficient estimator ``sum (e_i / CRLB_i)^2`` over ``n`` seeds is chi-square with ``n``
degrees of freedom, so RMS(error / CRLB) has the two-sided 95 % band ``sqrt(chi2_{0.025, n} / n) ..
sqrt(chi2_{0.975, n} / n)`` (20 seeds: 0.69-1.30; 100 seeds: 0.86-1.13).  The second table gives, per
cell and pooled over the scenarios, that statistic, the band and whether it lies inside: a per-cell
threshold such as "<= 1.05 on 20 seeds" cannot be met reliably even by an efficient estimator.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

NAMES = ("lever x", "lever y", "lever z", "t_d")


def one(args) -> dict:
    name, seed, duration, config = args[:4]
    control_variate = len(args) > 4 and args[4]
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.sim import builtin_scenario, simulate_full
    from uwbimu.studies.crlb import posterior_bound

    sc = builtin_scenario(name)
    upd = {"seeds": sc.seeds.model_copy(update={"noise": 1000 + seed})}
    if duration:
        upd["duration"] = float(duration)
    sc = sc.model_copy(update=upd)
    sim = simulate_full(sc)  # the dataset and the truth the bound needs, simulated once
    ds = sim.dataset
    t0 = time.process_time()
    o = CalibrationOptions.model_validate({"td_profile": {"enabled": False}} | dict(config))
    res = calibrate(ds, o)
    cpu = time.process_time() - t0
    cal, truth = res.calibration, ds.meta.truth
    err = np.append(np.subtract(cal["lever_arm"], truth.lever_arm), cal["time_offset"]["value"] - truth.time_offset)
    sd = np.append(cal["lever_arm_sd"], cal["time_offset"]["sd"])
    # the white-model marginal (equal to sd with covariance: model)
    sd_model = np.append(cal.get("lever_arm_sd_model", cal["lever_arm_sd"]),
                         cal["time_offset"].get("sd_model", cal["time_offset"]["sd"]))
    b = posterior_bound(sim, sc)
    crlb = np.append(b["lever_arm_sd"], b["time_offset_sd"])
    row = {"scenario": name, "seed": seed, "err": err.tolist(), "sd": sd.tolist(), "sd_model": sd_model.tolist(),
           "crlb": crlb.tolist(), "cpu_s": cpu, "huber_k": cal["ranges"]["huber_k"]}
    if o.estimate_anchor_bias is True and sc.uwb.mode == "twr":
        # the second baseline: the bound of the calibrator's own parameterisation (an unknown bias per anchor)
        bb = posterior_bound(sim, sc, anchor_bias_sd=o.anchor_bias_prior_sd)
        row["crlb_bias"] = np.append(bb["lever_arm_sd"], bb["time_offset_sd"]).tolist()
    if control_variate:
        # the range noise's part of the error to first order: a fixed linear map of the draws, exact sd known
        import sys
        from pathlib import Path

        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from check_calibrate_linear_split import PLAIN, truth_step

        st = truth_step(sim, sc, res.eskf, CalibrationOptions.model_validate(PLAIN))
        row |= {"cv": st["gn_range"], "cv_sd": st["pred_range"]}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0, help="noise seeds 1000 + first-seed ... (an independent "
                                                                "replication: e.g. --first-seed 100)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scenarios", default="calibration-flight,excited-90s,lissajous")
    ap.add_argument("--duration", type=float, default=0.0, help="override the scenarios' duration [s] (0: keep)")
    ap.add_argument("--config", default=None, help="CalibrationOptions YAML merged over the profile-off default")
    ap.add_argument("--json", default=None)
    ap.add_argument("--control-variate", action="store_true",
                    help="also RMS error / CRLB with the range noise's sampling removed (control variate, see above)")
    ap.add_argument("--from-json", default=None, nargs="+",
                    help="print the tables of saved --json runs (several: pooled, e.g. two seed ranges)")
    ap.add_argument("--max-seeds", type=int, default=0,
                    help="with --from-json: only the first N seeds of each scenario (e.g. 20: the issue's count)")
    a = ap.parse_args()
    if a.from_json:
        rows = []
        for path in a.from_json:
            with open(path) as fh:
                rows += json.load(fh)["rows"]
        if a.max_seeds:
            first = {}
            for r in sorted(rows, key=lambda r: r["seed"]):
                first.setdefault(r["scenario"], []).append(r)
            rows = [r for R in first.values() for r in R[:a.max_seeds]]
        tables(rows)
        return
    config = {}
    if a.config:
        import yaml

        with open(a.config) as fh:
            config = yaml.safe_load(fh) or {}
    jobs = [(n.strip(), s, a.duration, config, a.control_variate) for n in a.scenarios.split(",") for s in range(a.first_seed, a.first_seed + a.seeds)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.workers) as ex:
        rows = list(ex.map(one, jobs))
    wall = time.perf_counter() - t0
    print(f"{len(rows)} calibrations, {wall:.0f} s wall, {a.workers} workers, "
          f"median {np.median([r['cpu_s'] for r in rows]):.1f} s CPU each")
    tables(rows)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"rows": rows, "wall_s": wall}, fh)


def efficiency_band(n: int) -> tuple[float, float]:
    """Two-sided 95 % band of RMS(error / CRLB) over ``n`` seeds for an efficient estimator."""
    from scipy.stats import chi2

    return float(np.sqrt(chi2.ppf(0.025, n) / n)), float(np.sqrt(chi2.ppf(0.975, n) / n))


def tables(rows: list) -> None:
    print("| scenario | quantity | RMS error | RMS sigma | CRLB | RMS error / CRLB | RMS(error / sigma) | "
          "RMS sigma / CRLB | RMS(error / sigma_model) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in dict.fromkeys(r["scenario"] for r in rows):
        R = [r for r in rows if r["scenario"] == name]
        E, S, C, M = (np.array([r[k] for r in R]) for k in ("err", "sd", "crlb", "sd_model"))
        for j, q in enumerate(NAMES):
            unit, f = ("ms", 1e3) if q == "t_d" else ("mm", 1e3)
            rms_e = np.sqrt(np.mean(E[:, j] ** 2))
            rms_s = np.sqrt(np.mean(S[:, j] ** 2))
            cr = np.sqrt(np.mean(C[:, j] ** 2))
            z = np.sqrt(np.mean((E[:, j] / S[:, j]) ** 2))
            zm = np.sqrt(np.mean((E[:, j] / M[:, j]) ** 2))
            print(f"| {name} | {q} | {f * rms_e:.2f} {unit} | {f * rms_s:.2f} {unit} | {f * cr:.2f} {unit} | "
                  f"{rms_e / cr:.2f} | {z:.2f} | {rms_s / cr:.2f} | {zm:.2f} |")
    print()
    print("| cells | quantity | seeds | RMS(error / CRLB) | 95 % band if efficient | inside |")
    print("|---|---|---|---|---|---|")
    groups = [(name, [r for r in rows if r["scenario"] == name]) for name in dict.fromkeys(r["scenario"] for r in rows)]
    groups.append(("pooled", rows))
    outside = 0
    for name, R in groups:
        E, C = np.array([r["err"] for r in R]), np.array([r["crlb"] for r in R])
        lo, hi = efficiency_band(len(R))
        for j, q in enumerate(NAMES):
            t = float(np.sqrt(np.mean((E[:, j] / C[:, j]) ** 2)))
            ok = lo <= t <= hi
            outside += (not ok) and name != "pooled"
            print(f"| {name} | {q} | {len(R)} | {t:.2f} | {lo:.2f}-{hi:.2f} | {'yes' if ok else 'NO'} |")
    print(f"cells outside their band: {outside} of {len(NAMES) * (len(groups) - 1)} (about 5 % expected by chance)")
    if all("cv" in r for r in rows):
        print()
        with_bias = all("crlb_bias" in r for r in rows)
        print("| cells | quantity | seeds | RMS(error / CRLB) | with the control variate | its bootstrap sd | "
              "range part / its exact sd |" + (" with the control variate, against the CRLB with anchor biases |"
                                               if with_bias else ""))
        print("|---|---|---|---|---|---|---|" + ("---|" if with_bias else ""))
        for name, R in groups:
            C = np.array([r["crlb"] for r in R])
            E = np.array([r["err"] for r in R]) / C
            G_, P_ = np.array([r["cv"] for r in R]) / C, np.array([r["cv_sd"] for r in R]) / C
            est, sd = control_variate_rms(E, G_, P_)
            part = np.sqrt(np.mean(G_**2, axis=0) / np.mean(P_**2, axis=0))
            est_b = None
            if with_bias:
                f = C / np.array([r["crlb_bias"] for r in R])
                est_b = control_variate_rms(E * f, G_ * f, P_ * f)[0]
            for j, q in enumerate(NAMES):
                print(f"| {name} | {q} | {len(R)} | {np.sqrt(np.mean(E[:, j] ** 2)):.3f} | {est[j]:.3f} | {sd[j]:.3f} | "
                      f"{part[j]:.3f} |" + (f" {est_b[j]:.3f} |" if est_b is not None else ""))


def control_variate_rms(E: np.ndarray, G_: np.ndarray, P_: np.ndarray, n_boot: int = 2000) -> tuple:
    """RMS of the normalised errors ``E`` (n, p) with the control variate ``G_`` (the range noise's part of each
    error, normalised alike) whose exact RMS ``P_`` is known: ``sqrt(mean E^2 - mean G^2 + mean P^2)``, and its
    bootstrap sd over the seeds (fixed seed)."""
    def f(i):
        return np.sqrt(np.maximum(np.mean(E[i] ** 2, 0) - np.mean(G_[i] ** 2, 0) + np.mean(P_[i] ** 2, 0), 0.0))

    n = len(E)
    rng = np.random.default_rng(0)
    boot = np.array([f(rng.integers(0, n, n)) for _ in range(n_boot)])
    return f(np.arange(n)), boot.std(axis=0)


if __name__ == "__main__":
    main()
