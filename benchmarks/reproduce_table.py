"""Render the table of docs/reproducibility.md from measured results.

    python benchmarks/reproduce_blas_spread.py seed-ocp delay calib pcrb room crane demo --out spread.json
    python benchmarks/reproduce_blas_spread.py boundary --variants threads1,threads2,SandyBridge,Prescott --out spread_boundary.json
    python benchmarks/reproduce_blas_spread.py seed-ocp-sweep pointmass predictor place-extra --variants threads2 --out extra.json
    python benchmarks/reproduce_table.py spread.json spread_boundary.json extra.json > table.md

Each catalogue entry names where a figure is quoted, the figure as quoted (the number's
printed digits set the rounding tolerance), the command that produces it and the key
under which ``reproduce_figures.py`` reports it.  "match" is yes when every variant's value
rounds to the quoted one (half a unit of the last quoted digit), "spread" when the quoted
value lies inside the measured min..max widened by that half unit, else no.
"""

from __future__ import annotations

import json
import sys
from decimal import Decimal
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reproduce_blas_spread import spread as spread_of

RF = "python benchmarks/reproduce_figures.py"
CMD = {
    "seed-ocp": "uwbimu plan seed-ocp --out OUT (plan.json)",
    "delay": f"{RF} delay",
    "calib": "uwbimu plan calibration examples/plan/calibration_handheld.yaml --out OUT (design.json)",
    "pcrb": f"{RF} pcrb",
    "room": "uwbimu place --example room --out OUT (placement.json)",
    "crane": "uwbimu place --example crane --out OUT (placement.json)",
    "demo": "uwbimu demo --out OUT (estimate/observability.csv, calibration.yaml)",
    "boundary": "python -m uwbimu.observability.boundary --points 20",
    "seed-ocp-sweep": f"{RF} seed-ocp-sweep",
    "pointmass": f"{RF} pointmass",
    "predictor": f"{RF} predictor",
    "place-extra": f"{RF} place-extra",
    "crane-readings": "python benchmarks/crane_readings.py",
}
R, O, P, T = (
    "README.md",
    "docs/observability.md",
    "docs/placement.md",
    "docs/trajectory_design.md",
)
B19, BPM, BTD, BTDOA = (
    "boundary.19-state_uwb-imu_model",
    "boundary.point_mass",
    "boundary.time_offset",
    "boundary.tdoa",
)

# (file, section, figure, quoted, group, key)
# fmt: off
CATALOGUE = [
    (R, "Observability", "TDoA, 2 anchors, excited motion: rank", "18", "boundary", f"{BTDOA}.0.rank / 18 (min)"),
    (R, "Observability", "PCRB = matched ESKF sigma within 5 %: lever x ratio", "0.95..1.05", "pcrb", "pcrb.ratio_eskf_over_bound.lx"),
    (R, "Observability", "same: lever y ratio", "0.95..1.05", "pcrb", "pcrb.ratio_eskf_over_bound.ly"),
    (R, "Observability", "same: lever z ratio", "0.95..1.05", "pcrb", "pcrb.ratio_eskf_over_bound.lz"),
    (R, "Observability", "same: t_d ratio", "0.95..1.05", "pcrb", "pcrb.ratio_eskf_over_bound.td"),
    (R, "Observability", "point mass in the beacons' plane: rank at order 1", "5", "boundary", f"{BPM}.3.rank / 6 (min)"),
    (R, "Observability", "point mass in the beacons' plane: rank at order 2", "6", "boundary", f"{BPM}.4.rank / 6 (min)"),
    (R, "Observability", "no excitation: rank", "12", "boundary", f"{B19}.15.rank / 18 (min over points)"),
    (R, "Anchor placement", "crane, seed set-up with fitted R0 = 26.7 m: coverage [%] (the seed paper's 91.3 %)", "91.58", "crane", "crane.seed_setup_coverage_pct"),
    (O, "Quick start", "3 anchors: rank", "18", "delay", "obs.quick.rank"),
    (O, "Quick start", "3 anchors: Lie order", "2", "delay", "obs.quick.lie_order"),
    (O, "Quick start", "1 anchor: rank", "17", "delay", "obs.quick.single_anchor_rank"),
    (O, "Quick start", "gyro only: T2 (0 = False)", "0", "delay", "obs.quick.delay_T2"),
    (O, "Time offset", "zero lever arm, gyro x,y,z, t_d = 0.5 ms: identifiable (1 = yes)", "1", "delay", "obs.delay.zero_lever_gyro_0p5ms.identifiable"),
    (O, "Time offset", "same: power of t_d", "3", "delay", "obs.delay.zero_lever_gyro_0p5ms.td_power"),
    (O, "Per-window PCRB, checks", "60 s flight, ESKF sd / bound, lever x (was 0.986, corrected)", "0.987", "pcrb", "pcrb.ratio_eskf_over_bound.lx"),
    (O, "Per-window PCRB, checks", "same, lever y", "1.003", "pcrb", "pcrb.ratio_eskf_over_bound.ly"),
    (O, "Per-window PCRB, checks", "same, lever z", "0.997", "pcrb", "pcrb.ratio_eskf_over_bound.lz"),
    (O, "Per-window PCRB, checks", "same, t_d", "0.993", "pcrb", "pcrb.ratio_eskf_over_bound.td"),
    (O, "Per-window PCRB, checks", "demo: chained bound at the end, lever x [cm]", "1.32", "demo", "demo.bound_cm.lx"),
    (O, "Per-window PCRB, checks", "demo: bound lever y [cm]", "1.19", "demo", "demo.bound_cm.ly"),
    (O, "Per-window PCRB, checks", "demo: bound lever z [cm]", "0.41", "demo", "demo.bound_cm.lz"),
    (O, "Per-window PCRB, checks", "demo: bound t_d [ms]", "2.33", "demo", "demo.bound_ms.td"),
    (O, "Per-window PCRB, checks", "demo: ESKF sd lever x [cm]", "1.32", "demo", "demo.eskf_sd_cm.lx"),
    (O, "Per-window PCRB, checks", "demo: ESKF sd lever y [cm]", "1.20", "demo", "demo.eskf_sd_cm.ly"),
    (O, "Per-window PCRB, checks", "demo: ESKF sd lever z [cm]", "0.41", "demo", "demo.eskf_sd_cm.lz"),
    (O, "Per-window PCRB, checks", "demo: ESKF sd t_d [ms]", "2.38", "demo", "demo.eskf_sd_ms.td"),
    (O, "Per-window PCRB, checks", "demo: every 5 s window excites both (1 = yes)", "1", "demo", "demo.all_windows_excited"),
    (P, "Room example", "optimised: PDOP p50", "1.692", "room", "room.optimised.pdop_p50"),
    (P, "Room example", "optimised: PDOP p95", "1.959", "room", "room.optimised.pdop_p95"),
    (P, "Room example", "optimised: N-1 worst PDOP p95", "3.198", "room", "room.optimised.n1_pdop_p95"),
    (P, "Room example", "optimised: outside hull [%]", "25.4", "room", "room.optimised.outside_hull_pct"),
    (P, "Room example", "optimised: coverage [%]", "100", "room", "room.coverage_pct"),
    (P, "Room example", "all on the ceiling: PDOP p50", "1.601", "room", "room.all-on-ceiling.pdop_p50"),
    (P, "Room example", "all on the ceiling: PDOP p95", "2.981", "room", "room.all-on-ceiling.pdop_p95"),
    (P, "Room example", "all on the ceiling: N-1 PDOP p95", "4.318", "room", "room.all-on-ceiling.n1_pdop_p95"),
    (P, "Room example", "Bitcraze 3 high / 3 low: PDOP p50", "1.739", "room", "room.bitcraze-3-high-3-low.pdop_p50"),
    (P, "Room example", "Bitcraze: PDOP p95", "2.013", "room", "room.bitcraze-3-high-3-low.pdop_p95"),
    (P, "Room example", "Bitcraze: N-1 PDOP p95", "3.404", "room", "room.bitcraze-3-high-3-low.n1_pdop_p95"),
    (P, "Room example", "Bitcraze: outside hull [%]", "24.2", "room", "room.bitcraze-3-high-3-low.outside_hull_pct"),
    (P, "Room example", "PDOP only: PDOP p50", "1.465", "place-extra", "place.room_pdop_only.pdop_p50"),
    (P, "Room example", "PDOP only: PDOP p95", "1.677", "place-extra", "place.room_pdop_only.pdop_p95"),
    (P, "Room example", "PDOP only: N-1 PDOP p95", "2.446", "place-extra", "place.room_pdop_only.n1_pdop_p95"),
    (P, "Room example", "PDOP only: outside hull [%]", "61.4", "place-extra", "place.room_pdop_only.outside_hull_pct"),
    (P, "Crane", "seed set-up, our PSO, R0 26.7: coverage [%]", "91.58", "crane", "crane.seed_setup_coverage_pct"),
    (P, "Crane", "ours, 40 anchors: coverage [%]", "99.01", "crane", "crane.coverage_pct"),
    (P, "Crane", "ours: geometric coverage (PDOP <= 5) [%]", "34.30", "crane", "crane.geometric_coverage_pct"),
    (P, "Crane", "seed set-up: geometric coverage [%]", "18.23", "crane", "crane.seed_setup_geometric_pct"),
    (P, "Crane", "ours: PDOP p50", "7.22", "crane", "crane.pdop_p50"),
    (P, "Crane", "8 stations (crane_fewer.yaml): coverage [%]", "96.05", "place-extra", "place.crane_fewer.coverage_pct"),
    (P, "Geometric objective", "crane_geometric.yaml: k-coverage [%]", "88.20", "place-extra", "place.crane_geometric.coverage_pct"),
    (P, "Geometric objective", "crane_geometric.yaml: geometric coverage [%]", "57.79", "place-extra", "place.crane_geometric.geometric_coverage_pct"),
    (P, "Geometric objective", "crane_geometric.yaml: PDOP p50", "3.85", "place-extra", "place.crane_geometric.pdop_p50"),
    (P, "Geometric objective", "bridge, seed-style (our PSO): coverage [%]", "99.52", "place-extra", "place.bridge.seed_style_coverage_pct"),
    (P, "Geometric objective", "bridge, seed-style: geometric coverage [%]", "63.15", "place-extra", "place.bridge.seed_style_geometric_pct"),
    (P, "Geometric objective", "bridge, ours: coverage [%]", "99.98", "place-extra", "place.bridge.coverage_pct"),
    (P, "Geometric objective", "bridge, ours: geometric coverage [%]", "62.99", "place-extra", "place.bridge.geometric_coverage_pct"),
    (P, "Geometric objective", "bridge, ours: PDOP p50", "4.12", "place-extra", "place.bridge.pdop_p50"),
    (P, "Geometric objective", "bridge_geometric.yaml: coverage [%]", "99.70", "place-extra", "place.bridge_geometric.coverage_pct"),
    (P, "Geometric objective", "bridge_geometric.yaml: geometric coverage [%]", "80.60", "place-extra", "place.bridge_geometric.geometric_coverage_pct"),
    (P, "Geometric objective", "bridge_geometric.yaml: PDOP p50", "2.74", "place-extra", "place.bridge_geometric.pdop_p50"),
    (T, "1. seed OCP, table", "PD: J", "256.7185", "seed-ocp", "ocp.cost_pd"),
    (T, "1. seed OCP, table", "PD: det mean", "0.5593", "seed-ocp", "ocp.det_mean_pd"),
    (T, "1. seed OCP, table", "indirect (PMP): J", "76.257854", "seed-ocp", "ocp.cost_indirect"),
    (T, "1. seed OCP, table", "direct (IPOPT): J", "76.257854", "seed-ocp", "ocp.cost_direct"),
    (T, "1. seed OCP, table", "optimum: det mean", "0.6680", "seed-ocp", "ocp.det_mean_opt"),
    (T, "1. seed OCP, table", "fixed final state: J", "104.3588", "seed-ocp", "ocp.cost_fixed_final"),
    (T, "1. seed OCP, table", "fixed final state: det mean", "0.6253", "seed-ocp", "ocp.det_mean_fixed_final"),
    (T, "1. seed OCP, agreement", "abs(J_ind - J_dir) / J", "1.3e-15", "seed-ocp", "ocp.rel_dJ_ind_dir"),
    (T, "1. seed OCP, grid convergence", "J* at N = 58", "76.263430", "seed-ocp-sweep", "ocp.n58.cost_direct"),
    (T, "1. seed OCP, grid convergence", "J* at N = 116", "76.258970", "seed-ocp-sweep", "ocp.n116.cost_direct"),
    (T, "1. seed OCP, grid convergence", "J* at N = 464", "76.257575", "seed-ocp-sweep", "ocp.n464.cost_direct"),
    (T, "1. seed OCP, weights", "w_det = 0: det mean", "0.659", "seed-ocp-sweep", "ocp.w_det0.det_mean_opt"),
    (T, "1. seed OCP, weights", "w_det = 10: det mean", "0.728", "seed-ocp-sweep", "ocp.w_det10.det_mean_opt"),
    (T, "1. seed OCP, weights", "w_det = 100: det mean", "0.903", "seed-ocp-sweep", "ocp.w_det100.det_mean_opt"),
    (T, "1. seed OCP, weights", "LQR gains (Kp 1, Kd sqrt 2): PD J", "79.10", "seed-ocp-sweep", "ocp.lqr_gains.cost_pd"),
    (T, "1. seed OCP, weights", "LQR gains: PD det mean", "0.681", "seed-ocp-sweep", "ocp.lqr_gains.det_mean_pd"),
]
for obj, vals in {"none": ("61.819", "715.7", "1.884e-3", "0.990"), "logdet": ("62.465", "1138.8", "1.384e-3", "1.109"),
                  "min_eig": ("62.615", "1404.0", "1.234e-3", "1.398"), "trace_inv": ("62.330", "1042.9", "1.460e-3", "1.006")}.items():  # fmt: skip
    for k, q in zip(("logdet", "min_eig", "trace_inv", "control_effort"), vals):
        CATALOGUE.append((T, "2. point-mass planner, table", f"objective {obj}: {k}", q, "pointmass", f"pm.{obj}.{k}"))
for ax, qp, qe in zip("xyz", ("13.33", "11.99", "4.05"), ("13.24", "12.04", "4.06")):
    CATALOGUE.append((T, "3. predictor check (60 s calibration-flight)", f"predicted lever sd {ax} [mm]", qp, "predictor", f"pred.predicted_lever_mm.{ax}"))
    CATALOGUE.append((T, "3. predictor check (60 s calibration-flight)", f"ESKF lever sd {ax} [mm]", qe, "predictor", f"pred.eskf_lever_mm.{ax}"))
CATALOGUE += [
    (T, "3. predictor check (60 s calibration-flight)", "predicted t_d sd [ms]", "2.331", "predictor", "pred.predicted_td_ms"),
    (T, "3. predictor check (60 s calibration-flight)", "ESKF t_d sd [ms]", "2.380", "predictor", "pred.eskf_td_ms"),
]
for t, name, vals in (("designed", "designed", ("0.90", "0.96", "0.99", "0.99", "0.99")),
                      ("figure8", "figure-8 (naive)", ("0.95", "0.99", "0.81", "0.40", "0.27")),
                      ("figure8_excited", "figure-8, attitude at bounds", ("0.95", "0.99", "0.81", "0.99", "0.99"))):  # fmt: skip
    for k, q in zip(("box", "speed", "accel", "tilt", "rate"), vals):
        CATALOGUE.append((T, "3. bound usage table", f"{name}: {k}", q, "calib", f"calib.{t}.bound_usage.{k}"))
for t, name, vals in (("designed", "designed", ("7.72", "4.99", "7.20", "1.842")),
                      ("figure8", "figure-8 (naive)", ("37.36", "35.60", "11.47", "5.815")),
                      ("figure8_excited", "figure-8, attitude at bounds", ("3.98", "5.38", "5.22", "9.131"))):  # fmt: skip
    for k, q in zip(("sigma_lever_mm.x", "sigma_lever_mm.y", "sigma_lever_mm.z", "sigma_td_ms"), vals):
        CATALOGUE.append((T, "3. predicted sigma table", f"{name}: {k}", q, "calib", f"calib.{t}.{k}"))
CATALOGUE += [
    (T, "3. predicted ratios", "figure-8 / designed, lever arm", "4.53", "calib", "calib.ratio_figure8_over_designed.lever"),
    (T, "3. predicted ratios", "figure-8 / designed, t_d", "3.16", "calib", "calib.ratio_figure8_over_designed.td"),
    (T, "3. predicted ratios", "figure-8 excited / designed, lever arm", "0.73", "calib", "calib.ratio_figure8_excited_over_designed.lever"),
    (T, "3. predicted ratios", "figure-8 excited / designed, t_d", "4.96", "calib", "calib.ratio_figure8_excited_over_designed.td"),
]
# issue 16 item 3: the crane's two station readings (added after the table above was measured)
CR = "4. crane readings"
for _rd, _vals in (("diagonal", ("26.58", "91.32", "97.00", "91.26", "98.83", "99.23")),
                   ("axis-aligned", ("22.43", "91.32", "91.32", "91.09", "94.92", "94.92"))):
    for _k, _lab, _q in zip(("r0_m", "seed_setup_pct", "reoriented_pct", "ours_same_variables_pct", "ours_per_station_pct",
                             "ours_per_station_from_best_angle_pct"),
                            ("fitted R0 [m]", "seed set-up [%]", "best common rotation [%]", "ours, 10 variables [%]",
                             "ours, 30 variables [%]", "ours from the best rotation [%]"), _vals):
        CATALOGUE.append((P, CR, f"{_rd}: {_lab}", _q, "crane-readings", f"crane_readings.{_rd}.{_k}"))
    for _a, _q in zip(("0", "15", "22.5", "30", "45"),
                      (("91.32", "91.99", "94.18", "95.97", "97.00") if _rd == "diagonal"
                       else ("91.32", "88.83", "86.02", "83.26", "81.12"))):
        CATALOGUE.append((P, CR, f"{_rd}: common rotation {_a} deg [%]", _q, "crane-readings", f"crane_readings.{_rd}.rot{_a}_pct"))
CATALOGUE += [
    (P, CR, "crane_axis_aligned.yaml: ours [%]", "94.92", "place-extra", "place.crane_axis_aligned.coverage_pct"),
    (P, CR, "crane_axis_aligned.yaml: seed set-up [%]", "91.32", "place-extra", "place.crane_axis_aligned.seed_style_coverage_pct"),
    (P, CR, "crane_axis_aligned.yaml: geometric coverage [%]", "17.18", "place-extra", "place.crane_axis_aligned.geometric_coverage_pct"),
    (P, "Bridge", "ray casting: coverage [%]", "98.14", "place-extra", "place.bridge.ray_cast_coverage_pct"),
]

# fmt: on


def half_unit(q: str) -> float:
    """Half a unit in the last printed digit of a quoted number ('76.257854' -> 5e-7)."""
    d = Decimal(q)
    return 0.5 * float(Decimal(1).scaleb(d.as_tuple().exponent))


def fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}" if 0 < abs(v) < 1e-3 else f"{v:.10g}"
    return str(v)


def verdict(quoted: str, lo, hi) -> str:
    if ".." in quoted:  # a quoted interval ("within 5 %")
        a, b = (float(x) for x in quoted.split(".."))
        return (
            "yes"
            if a <= lo and hi <= b
            else ("spread" if lo <= b and hi >= a else "no")
        )
    try:
        q, h = float(quoted), half_unit(quoted)
        lo, hi = float(lo), float(hi)
    except (ValueError, ArithmeticError):  # text figures (verdicts) compare as text
        return "yes" if str(lo) == quoted and str(hi) == quoted else "no"
    if abs(lo - q) <= h * (1 + 1e-9) and abs(hi - q) <= h * (1 + 1e-9):
        return "yes"
    if lo - h <= q <= hi + h:
        return "spread"
    return "no"


def _boundary_section(results: dict) -> None:
    """Every cell of the generated boundary tables against docs/observability.md, per variant."""
    from reproduce_figures import ROOT, parse_md_tables

    doc = {}
    for title, rows in parse_md_tables(
        (ROOT / "docs" / "observability.md").read_text()
    ).items():
        tkey = title.split("(")[0].strip().lower().replace(" ", "_")
        for i, r in enumerate(rows):
            for col, val in list(r.items())[1:]:
                doc[f"boundary.{tkey}.{i}.{col}"] = val
    print()
    print(
        "| boundary table (docs/observability.md) | cells | equal to the doc in every variant | cells that differ between variants | cells that differ from the doc |"
    )
    print("|---|---|---|---|---|")
    tables = sorted({k.split(".")[1] for k in doc})
    for t in tables:
        keys = [k for k in doc if k.split(".")[1] == t]
        vals = {k: {str(r.get(k)) for r in results.values()} for k in keys}
        equal = sum(1 for k in keys if vals[k] == {doc[k]})
        varying = [k for k in keys if len(vals[k]) > 1]
        off = [
            f"{k.split('.', 2)[2]}: doc {doc[k]}, measured {' / '.join(sorted(vals[k]))}"
            for k in keys
            if vals[k] != {doc[k]}
        ]
        print(
            f"| {t} | {len(keys)} | {equal} | {len(varying)} | {'; '.join(off) or '-'} |"
        )


def main(argv=None) -> int:
    files = argv if argv is not None else sys.argv[1:]
    spread: dict = {}
    corenames: dict = {}
    merged: dict = {}
    for f in files:
        raw = json.loads(Path(f).read_text())
        corenames.update(raw.get("corename", {}))
        for g, d in raw["groups"].items():
            merged[g] = {
                **merged.get(g, {}),
                **d["results"],
            }  # files with the same group add variants
    for g, res in merged.items():
        spread[g] = {"spread": spread_of(res), "variants": list(res)}
    boundary_raw = merged.get("boundary")
    print(
        "| # | where | figure | quoted | command | key | measured min | measured max | rel. spread | variants | match |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for i, (f, sec, fig, q, g, key) in enumerate(CATALOGUE, 1):
        s = spread.get(g, {}).get("spread", {}).get(key)
        if s is None:
            print(
                f"| {i} | {f}, {sec} | {fig} | {q} | `{CMD[g]}` | `{key}` | not measured | - | - | - | - |"
            )
            continue
        n = s["n"]
        if "min" in s:
            lo, hi = s["min"], s["max"]
            rel = "0" if lo == hi else f"{abs(hi - lo) / max(abs(hi), 1e-300):.1e}"
            mlo, mhi = fmt(lo), fmt(hi)
        else:
            lo = hi = s["values"][0] if len(s["values"]) == 1 else None
            mlo, mhi = s["values"][0], s["values"][-1]
            rel = "0" if lo is not None else "differs"
        m = verdict(q, lo, hi) if lo is not None else "no"
        print(
            f"| {i} | {f}, {sec} | {fig} | {q} | `{CMD[g]}` | `{key}` | {mlo} | {mhi} | {rel} | {n} | {m} |"
        )
    if boundary_raw is not None:
        _boundary_section(boundary_raw)
    print()
    print(
        "Core types selected: " + ", ".join(f"{v} -> {c}" for v, c in corenames.items())
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
