"""Re-measure the figures quoted in the README and the design / analysis docs.

One command per group of figures; each runs the very command the docs list (in a
temporary folder) and prints the figures it produced, keyed by the names used in
docs/reproducibility.md::

    python benchmarks/reproduce_figures.py seed-ocp     # uwbimu plan seed-ocp
    python benchmarks/reproduce_figures.py room         # uwbimu place --example room
    python benchmarks/reproduce_figures.py crane        # uwbimu place --example crane
    python benchmarks/reproduce_figures.py calib        # uwbimu plan calibration examples/plan/calibration_handheld.yaml
    python benchmarks/reproduce_figures.py boundary     # python -m uwbimu.observability.boundary --points 20
    python benchmarks/reproduce_figures.py delay        # the README/doc delay and rank cases (cheap)
    python benchmarks/reproduce_figures.py pcrb         # PCRB vs matched ESKF sigma, 60 s flight
    python benchmarks/reproduce_figures.py demo         # uwbimu demo: chained bound vs ESKF sigma
    python benchmarks/reproduce_figures.py seed-ocp-sweep   # seed OCP: grid, weights, LQR gains
    python benchmarks/reproduce_figures.py pointmass    # uwbimu plan point-mass, 4 objectives
    python benchmarks/reproduce_figures.py predictor    # predicted vs ESKF sd, calibration-flight
    python benchmarks/reproduce_figures.py place-extra  # room_pdop_only, crane_fewer, *_geometric, bridge, crane_axis_aligned
    python benchmarks/reproduce_figures.py crane-readings  # benchmarks/crane_readings.py (R0 fits, attribution; ~4 min)

``--json`` prints one JSON object instead of a table.  The BLAS/CPU spread of the
same figures is measured by ``benchmarks/reproduce_blas_spread.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str], cwd: Path = ROOT) -> str:
    env = dict(os.environ)
    env.setdefault("PYTHONPATH", str(ROOT / "src"))
    env.setdefault("MPLBACKEND", "Agg")
    p = subprocess.run(
        args, check=False, cwd=cwd, env=env, capture_output=True, text=True
    )
    if p.returncode != 0:
        raise SystemExit(
            f"command failed ({p.returncode}): {' '.join(args)}\n{p.stderr[-2000:]}"
        )
    return p.stdout


def _uwbimu(*args: str) -> str:
    # the `uwbimu` console script, run with this interpreter and PYTHONPATH
    return _run(
        [
            sys.executable,
            "-c",
            "import sys; sys.argv[0] = 'uwbimu'; from uwbimu.cli.main import app; app()",
            *args,
        ]
    )


def seed_ocp() -> dict:
    with tempfile.TemporaryDirectory() as d:
        _uwbimu("plan", "seed-ocp", "--out", f"{d}/o")
        j = json.loads(Path(f"{d}/o/plan.json").read_text())
    return {
        "ocp.cost_pd": j["cost_pd"],
        "ocp.cost_indirect": j["cost_indirect"],
        "ocp.cost_direct": j["cost_direct"],
        "ocp.cost_fixed_final": j["cost_direct_fixed_final"],
        "ocp.det_mean_pd": j["det_mean_pd"],
        "ocp.det_mean_opt": j["det_mean_opt"],
        "ocp.det_mean_fixed_final": j["det_mean_fixed_final"],
        "ocp.rel_dJ_ind_dir": abs(j["cost_indirect"] - j["cost_direct"])
        / j["cost_direct"],
    }


def _table_rows(j: dict) -> dict:
    return {str(r.get("layout")): r for r in j.get("table", [])}


def room() -> dict:
    with tempfile.TemporaryDirectory() as d:
        _uwbimu("place", "--example", "room", "--out", f"{d}/o")
        j = json.loads(Path(f"{d}/o/placement.json").read_text())
    out = {
        "room.coverage_pct": 100 * j["coverage"],
        "room.outside_hull_pct": 100 * j["hull_outside"],
    }
    for r in j["table"]:
        key = r["layout"]
        out[f"room.{key}.pdop_p50"] = r["pdop_p50"]
        out[f"room.{key}.pdop_p95"] = r["pdop_p95"]
        out[f"room.{key}.n1_pdop_p95"] = r["n1_pdop_p95"]
        out[f"room.{key}.outside_hull_pct"] = 100 * r["hull_outside"]
    return out


def crane() -> dict:
    with tempfile.TemporaryDirectory() as d:
        _uwbimu("place", "--example", "crane", "--out", f"{d}/o")
        j = json.loads(Path(f"{d}/o/placement.json").read_text())
    rows = list(_table_rows(j).values())
    seed = next(r for r in rows if "seed set-up" in r["layout"])
    return {
        "crane.coverage_pct": 100 * j["coverage"],
        "crane.geometric_coverage_pct": 100 * j["geometric_coverage"],
        "crane.pdop_p50": j["pdop_p50"],
        "crane.seed_setup_coverage_pct": 100 * seed["coverage"],
        "crane.seed_setup_geometric_pct": 100 * seed["geometric_coverage"],
    }


def calib() -> dict:
    with tempfile.TemporaryDirectory() as d:
        _uwbimu(
            "plan", "calibration", "examples/plan/calibration_handheld.yaml", "--out", f"{d}/o"
        )
        j = json.loads(Path(f"{d}/o/design.json").read_text())
    out = {}
    for t in ("designed", "figure8", "figure8_excited"):
        for i, ax in enumerate("xyz"):
            out[f"calib.{t}.sigma_lever_mm.{ax}"] = 1e3 * j[t]["sigma_lever_arm_m"][i]
        out[f"calib.{t}.sigma_td_ms"] = 1e3 * j[t]["sigma_time_offset_s"]
        for k, u in j[t]["bound_usage"].items():
            out[f"calib.{t}.bound_usage.{k}"] = u
    for t in ("figure8", "figure8_excited"):
        r = j[f"predicted_ratio_{t}_over_designed"]
        out[f"calib.ratio_{t}_over_designed.lever"] = r["lever_arm_sigma_norm"]
        out[f"calib.ratio_{t}_over_designed.td"] = r["time_offset_sigma"]
    return out


# ---------------------------------------------------------------- boundary tables
def parse_md_tables(text: str) -> dict[str, list[dict]]:
    """Markdown tables under '### title' headings -> {title: [row dicts]}."""
    tables: dict[str, list[dict]] = {}
    title, header = None, None
    for line in text.splitlines():
        if line.startswith("### "):
            title, header = line[4:].strip(), None
            continue
        if not line.startswith("|") or title is None:
            header = None if not line.startswith("|") else header
            continue
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
        if header is None:
            header = cells
            tables.setdefault(title, [])
        elif set("".join(cells)) <= set("-: "):
            continue
        else:
            tables[title].append(dict(zip(header, cells)))
    return tables


def boundary() -> dict:
    t0 = time.perf_counter()
    text = _run(
        [sys.executable, "-m", "uwbimu.observability.boundary", "--points", "20"]
    )
    out: dict = {"boundary.seconds": time.perf_counter() - t0}
    for title, rows in parse_md_tables(text).items():
        tkey = title.split("(")[0].strip().lower().replace(" ", "_")
        for i, r in enumerate(rows):
            for col, val in list(r.items())[1:]:
                out[f"boundary.{tkey}.{i}.{col}"] = val
    return out


def delay() -> dict:
    """Cheap verdicts quoted in the README / docs (seconds, no subprocess)."""
    from uwbimu.observability import delay_verdict, structural_verdict

    a3 = [[0, 0, 0], [5, 0, 0.5], [0, 5, 1.0]]
    v = structural_verdict({"anchors": a3, "lever_arm": [0.12, -0.08, 0.14]})
    out = {"obs.quick.rank": v["rank"], "obs.quick.lie_order": v["lie_order"]}
    v = structural_verdict(
        {"anchors": a3[:1], "lever_arm": [0.12, -0.08, 0.14], "random_points": 3}
    )
    out["obs.quick.single_anchor_rank"] = v["rank"]
    d = delay_verdict(
        {"anchors": a3, "excitation": {"accel": [], "gyro": ["x", "y", "z"]}}
    )
    out["obs.quick.delay_T2"] = int(d["conditions"]["T2"])
    d = delay_verdict({"anchors": a3, "lever_arm": [0, 0, 0], "time_offset": 0.0005,
                       "excitation": {"accel": [], "gyro": ["x", "y", "z"]}})  # fmt: skip
    out["obs.delay.zero_lever_gyro_0p5ms.identifiable"] = int(d["identifiable"])
    out["obs.delay.zero_lever_gyro_0p5ms.td_power"] = d["numeric"]["td_power"]
    return out


def pcrb() -> dict:
    """docs/observability.md: whole-log PCRB vs the matched plain ESKF's final sigma on a 60 s
    simulated calibration flight (the set-up of tests/test_obs_window.py, 60 s instead of 30 s)."""
    import numpy as np

    from uwbimu import sim
    from uwbimu.estimation import run_eskf
    from uwbimu.estimation.options import EskfOptions
    from uwbimu.models import state as S
    from uwbimu.observability.window import posterior_crb

    ds = sim.simulate(
        sim.builtin_scenario("calibration-flight").model_copy(update={"duration": 60.0})
    )
    opts = EskfOptions.model_validate({"lever_arm": {"min_rotation_rate": 0.0}, "gating": {"probability": 1.0, "robust": "none"},
                                       "supervisor": {"enabled": False},
                                       # matched by construction: the simulator's own noise, one pass
                                       "noise": "preset", "sigma_from_residuals": False,
                                       "hold_unidentified": False})  # fmt: skip
    res = run_eskf(ds, opts)
    P_end, _ = posterior_crb(
        ds, t_start=float(res.t_imu[0]), prior_cov=res.covariances[0]
    )
    sd_b, sd_e = np.sqrt(np.diag(P_end)), res.sd[-1]
    return {
        f"pcrb.ratio_eskf_over_bound.{n}": float(sd_e[i] / sd_b[i])
        for n, i in (("lx", S.E_L), ("ly", S.E_L + 1), ("lz", S.E_L + 2), ("td", S.E_TD))
    }


def demo() -> dict:
    """docs/observability.md: `uwbimu demo`, chained 5 s-window bound at the end vs the ESKF's sigma."""
    import pandas as pd

    with tempfile.TemporaryDirectory() as d:
        _uwbimu("demo", "--out", f"{d}/demo")
        obs = pd.read_csv(f"{d}/demo/estimate/observability.csv")
        import yaml

        from uwbimu.io.calibration_file import read_calibration

        cal = read_calibration(Path(f"{d}/demo/estimate/calibration.yaml"))
    last = obs.iloc[-1]
    out = {
        f"demo.bound_cm.{n}": 100 * float(last[f"sd_{n}"]) for n in ("lx", "ly", "lz")
    }
    out["demo.bound_ms.td"] = 1e3 * float(last["sd_time_offset"])  # (key kept: docs/reproducibility.md rows)
    for i, n in enumerate(("lx", "ly", "lz")):
        out[f"demo.eskf_sd_cm.{n}"] = 100 * float(cal["lever_arm_sd"][i])
    out["demo.eskf_sd_ms.td"] = 1e3 * float(cal["time_offset"]["sd"])
    out["demo.all_windows_excited"] = int(
        bool(obs["lever_arm_excited"].all() and obs["time_offset_excited"].all())
    )
    return out


def seed_ocp_sweep() -> dict:
    """docs/trajectory_design.md sec. 1: grid convergence, weight sensitivity, LQR gains
    (`uwbimu plan seed-ocp --config` with one field changed from examples/plan/seed_ocp.yaml)."""
    import math

    import yaml

    base = yaml.safe_load((ROOT / "examples/plan/seed_ocp.yaml").read_text())
    cases = {"n58": {"n_steps": 58}, "n116": {"n_steps": 116}, "n464": {"n_steps": 464},
             "w_det0": {"w_det": 0.0}, "w_det10": {"w_det": 10.0}, "w_det100": {"w_det": 100.0},
             "lqr_gains": {"kp": 1.0, "kd": math.sqrt(2.0)}}  # fmt: skip
    out = {}
    with tempfile.TemporaryDirectory() as d:
        for name, over in cases.items():
            Path(f"{d}/{name}.yaml").write_text(yaml.safe_dump({**base, **over}))
            _uwbimu(
                "plan",
                "seed-ocp",
                "--config",
                f"{d}/{name}.yaml",
                "--out",
                f"{d}/{name}",
            )
            j = json.loads(Path(f"{d}/{name}/plan.json").read_text())
            out[f"ocp.{name}.cost_direct"] = j["cost_direct"]
            out[f"ocp.{name}.det_mean_opt"] = j["det_mean_opt"]
            out[f"ocp.{name}.cost_pd"] = j["cost_pd"]
            out[f"ocp.{name}.det_mean_pd"] = j["det_mean_pd"]
    return out


def pointmass() -> dict:
    """docs/trajectory_design.md sec. 2 table: `uwbimu plan point-mass examples/plan/pointmass.yaml`
    with `objective` set to each of none / logdet / min_eig / trace_inv."""
    import yaml

    base = yaml.safe_load((ROOT / "examples/plan/pointmass.yaml").read_text())
    out = {}
    with tempfile.TemporaryDirectory() as d:
        for obj in ("none", "logdet", "min_eig", "trace_inv"):
            Path(f"{d}/{obj}.yaml").write_text(
                yaml.safe_dump({**base, "objective": obj})
            )
            _uwbimu("plan", "point-mass", f"{d}/{obj}.yaml", "--out", f"{d}/{obj}")
            m = json.loads(Path(f"{d}/{obj}/plan.json").read_text())["plan"]["metrics"]
            for k in ("logdet", "min_eig", "trace_inv", "control_effort"):
                out[f"pm.{obj}.{k}"] = m[k]
    return out


def predictor() -> dict:
    """docs/trajectory_design.md sec. 3: predicted sd vs the ESKF's reported sd on the builtin
    60 s `calibration-flight` (the check of `python benchmarks/bench_plan.py`)."""
    from uwbimu.design.trajectory.calibration import (
        CalibrationDesignConfig,
        evaluate_sim_trajectory,
    )
    from uwbimu.estimation import run_eskf
    from uwbimu.sim import builtin_scenario, simulate

    sc = builtin_scenario("calibration-flight")
    cfg = CalibrationDesignConfig(
        duration=sc.duration,
        truth={"lever_arm": list(sc.lever_arm), "time_offset": sc.time_offset},
    )
    pred = evaluate_sim_trajectory(sc.trajectory.build(), cfg)
    cal = run_eskf(simulate(sc)).calibration
    out = {}
    for i, ax in enumerate("xyz"):
        out[f"pred.predicted_lever_mm.{ax}"] = 1e3 * pred["sigma_lever_arm_m"][i]
        out[f"pred.eskf_lever_mm.{ax}"] = 1e3 * cal["lever_arm_sd"][i]
    out["pred.predicted_td_ms"] = 1e3 * pred["sigma_time_offset_s"]
    out["pred.eskf_td_ms"] = 1e3 * cal["time_offset_sd"]
    return out


def place_extra() -> dict:
    """docs/placement.md: the other example configs (`uwbimu place CONFIG --out OUT`)."""
    out = {}
    with tempfile.TemporaryDirectory() as d:
        for name in (
            "room_pdop_only",
            "crane_fewer",
            "crane_geometric",
            "bridge",
            "bridge_geometric",
            "crane_axis_aligned",
        ):
            _uwbimu("place", f"examples/placement/{name}.yaml", "--out", f"{d}/{name}")
            j = json.loads(Path(f"{d}/{name}/placement.json").read_text())
            out[f"place.{name}.coverage_pct"] = 100 * j["coverage"]
            out[f"place.{name}.geometric_coverage_pct"] = 100 * j["geometric_coverage"]
            out[f"place.{name}.pdop_p50"] = j["pdop_p50"]
            out[f"place.{name}.pdop_p95"] = j["pdop_p95"]
            if "hull_outside" in j:
                out[f"place.{name}.outside_hull_pct"] = 100 * j["hull_outside"]
            out[f"place.{name}.n1_pdop_p95"] = j["worst_single_failure"]["pdop_p95"]
            if "coverage_with_ray_casting" in j:
                out[f"place.{name}.ray_cast_coverage_pct"] = 100 * j["coverage_with_ray_casting"]
            for r in j.get("table", []):
                if "coverage" in r and "our PSO" in str(r.get("layout")):
                    out[f"place.{name}.seed_style_coverage_pct"] = 100 * r["coverage"]
                    if "geometric_coverage" in r:
                        out[f"place.{name}.seed_style_geometric_pct"] = (
                            100 * r["geometric_coverage"]
                        )
    return out


def crane_readings() -> dict:
    """docs/placement.md, crane readings: ``python benchmarks/crane_readings.py`` (same functions)."""
    from uwbimu.design.crane import attribute_gain, fit_seed_range

    out = {}
    for rd in ("diagonal", "axis-aligned"):
        f = fit_seed_range(rd)
        g = attribute_gain(f.range_m, rd)
        out[f"crane_readings.{rd}.r0_m"] = f.range_m
        keys = ("seed_setup", "reoriented", "ours_same_variables", "ours_per_station", "ours_per_station_from_best_angle")
        for k in keys:
            out[f"crane_readings.{rd}.{k}_pct"] = 100 * getattr(g, k)
        out[f"crane_readings.{rd}.best_angle_deg"] = g.best_angle_deg
        for a, v in g.orientation.items():
            out[f"crane_readings.{rd}.rot{a:g}_pct"] = 100 * v
    return out


GROUPS = {"seed-ocp": seed_ocp, "crane-readings": crane_readings, "room": room, "crane": crane, "calib": calib, "boundary": boundary, "delay": delay,
          "pcrb": pcrb, "demo": demo, "seed-ocp-sweep": seed_ocp_sweep, "pointmass": pointmass,
          "predictor": predictor, "place-extra": place_extra}  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("group", choices=sorted(GROUPS))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    res = GROUPS[a.group]()
    if a.json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:60s} {v}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
