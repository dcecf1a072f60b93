"""Explore the boundary of the seeds' conditions and write the tables of docs/observability.md.

Run ``python -m uwbimu.observability.boundary [--points 20] [--out FILE]``: every
number in the printed Markdown comes from the rank test (20 random points per
case by default, seeded), nothing is typed in by hand.
"""

from __future__ import annotations

import argparse
import re
import time

import numpy as np

from uwbimu.observability.delay import delay_verdict
from uwbimu.observability.engine import numerical_rank
from uwbimu.observability.models import sample_uwb_imu_state
from uwbimu.observability.seed001 import seed001_blocks
from uwbimu.observability.structural import structural_verdict

A3 = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.5], [0.0, 5.0, 1.0]]
A3_FLAT = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0]]
LEVER = [0.10, 0.05, 0.20]
ALL = ["x", "y", "z"]

#: (case, seed statement, config overrides) for the 19-state model
UWB_CASES = [
    ("3 anchors, C1-C4 hold", "Thm 2: full rank", {}),
    ("tag coplanar with the 3 anchors (C2 fails)", "Thm 2 silent (Lemma 1 block singular)",
     {"anchors": A3_FLAT, "points": [{"antenna": [1.5, 1.0, 0.0]}, {"antenna": [0.5, 3.0, 0.0]}, {"antenna": [2.0, 2.0, 0.0]}]}),
    ("4 non-coplanar anchors", "Thm 2: full rank", {"anchors": A3 + [[2.0, 2.0, 3.0]]}),
    ("2 anchors, horizontal baseline", "C1 fails", {"anchors": [[0, 0, 0], [5, 0, 0]]}),
    ("2 anchors, vertical baseline", "C1 fails", {"anchors": [[0, 0, 0], [0, 0, 3]]}),
    ("1 anchor", "C1 fails", {"anchors": [[1.0, 2.0, 3.0]]}),
    ("3 collinear anchors (horizontal)", "C1 fails", {"anchors": [[0, 0, 0], [5, 0, 0], [10, 0, 0]]}),
    ("3 collinear anchors (vertical)", "C1 fails", {"anchors": [[0, 0, 0], [0, 0, 2], [0, 0, 4]]}),
    ("zero lever arm, all axes excited", "Thm 2: full rank (T3 fails)", {"lever_arm": [0, 0, 0]}),
    ("zero lever arm, accel only", "C4 fails", {"lever_arm": [0, 0, 0], "excitation": {"accel": ALL, "gyro": []}}),
    ("accel only (gyro constant)", "C4 fails", {"excitation": {"accel": ALL, "gyro": []}}),
    ("gyro only (accel constant)", "C3 fails", {"excitation": {"accel": [], "gyro": ALL}}),
    ("single axis: a_x + w_z", "C3, C4 fail", {"excitation": {"accel": ["x"], "gyro": ["z"]}}),
    ("single axis: a_x only", "C3, C4 fail", {"excitation": {"accel": ["x"], "gyro": []}}),
    ("single axis: w_z only", "C3, C4 fail", {"excitation": {"accel": [], "gyro": ["z"]}}),
    ("no excitation (generic constant IMU reading)", "C3, C4 fail", {"excitation": {"accel": [], "gyro": []}}),
    ("no excitation, seed drift f0 (u = 0)", "C3, C4 fail",
     {"excitation": {"accel": [], "gyro": []}, "nominal_input": [0, 0, 0, 0, 0, 0]}),
    ("3 anchors, C1-C4, Lie order 2", "(order 3 in the seed)", {"lie_order": 2}),
    ("3 anchors, C1-C4, Lie order 1", "(order 3 in the seed)", {"lie_order": 1}),
    ("2 anchors, horizontal baseline, zero lever arm, gyro x,y only", "C1, C3, C4 fail",
     {"anchors": [[0, 0, 0], [5, 0, 0]], "lever_arm": [0, 0, 0], "excitation": {"accel": [], "gyro": ["x", "y"]}}),
    ("same, Lie order 3", "C1, C3, C4 fail",
     {"anchors": [[0, 0, 0], [5, 0, 0]], "lever_arm": [0, 0, 0], "excitation": {"accel": [], "gyro": ["x", "y"]}, "lie_order": 3}),
    ("zero lever arm, gyro only", "C3 fails", {"lever_arm": [0, 0, 0], "excitation": {"accel": [], "gyro": ALL}}),
    ("1 anchor, zero lever arm, all axes excited", "C1 fails", {"anchors": [[1.0, 2.0, 3.0]], "lever_arm": [0, 0, 0]}),
    ("2 anchors 1e-8 rad off vertical", "C1 fails", {"anchors": [[0, 0, 0], [3e-8, 0, 3]]}),
]  # fmt: skip

PM_B3 = [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0]]
PM_CASES = [
    ("3 beacons, off plane", 0, "rank 3 (of p)", {"anchors": PM_B3, "points": [{"p": [1, 1, 1.5]}, {"p": [2, -1, -2]}]}),
    ("3 beacons, in plane", 0, "rank 2 (of p)", {"anchors": PM_B3, "points": [{"p": [1, 1, 0]}, {"p": [3, -2, 0]}]}),
    ("3 beacons, off plane", 1, "rank 6", {"anchors": PM_B3, "points": [{"p": [1, 1, 1.5]}, {"p": [2, -1, -2]}]}),
    ("3 beacons, in plane, v leaves plane", 1, "rank 6", {"anchors": PM_B3, "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.7]}]}),
    ("3 beacons, in plane, v leaves plane", 2, "(rank 6)", {"anchors": PM_B3, "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.7]}]}),
    ("3 beacons, in plane, v in plane", 3, "rank < 6", {"anchors": PM_B3, "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.0]}]}),
    ("4 non-coplanar beacons (random points)", 0, "rank 3 (of p)", {"anchors": PM_B3 + [[0, 0, 3]], "random_points": 20}),
    ("4 non-coplanar beacons (random points)", 1, "rank 6", {"anchors": PM_B3 + [[0, 0, 3]], "random_points": 20}),
    ("4 coplanar beacons, in plane, v in plane", 3, "rank < 6", {"anchors": PM_B3 + [[4, 4, 0]], "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.0]}]}),
    ("2 beacons + altimeter, off vertical plane", 0, "rank 3 (of p)", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "altimeter": True, "points": [{"p": [1, 2, 1.5]}]}),
    ("2 beacons + altimeter, on vertical plane", 0, "rank 2 (of p)", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "altimeter": True, "points": [{"p": [1, 0, 1.5]}]}),
    ("2 beacons + altimeter, off vertical plane", 1, "rank 6", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "altimeter": True, "points": [{"p": [1, 2, 1.5], "v": [0.3, 0.1, 0.2]}]}),
    ("2 beacons + altimeter, on vertical plane, v not along line", 1, "rank 6", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "altimeter": True, "points": [{"p": [1, 0, 1.5], "v": [0.3, 0.6, 0.2]}]}),
    ("2 beacons + altimeter, on vertical plane, v not along line", 2, "(rank 6)", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "altimeter": True, "points": [{"p": [1, 0, 1.5], "v": [0.3, 0.6, 0.2]}]}),
    ("2 beacons + altimeter, on vertical plane, v in that plane, not along line", 3, "rank 6 (v not along line)", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "altimeter": True, "points": [{"p": [1, 0, 1.5], "v": [0.3, 0.0, 0.5]}]}),
    ("2 beacons, no altimeter (random points)", 3, "-", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "random_points": 20}),
    ("2 beacons, no altimeter, accel excited", 3, "-", {"anchors": [[0, 0, 0], [4, 0, 0.5]], "random_points": 20, "excitation": {"accel": ALL}}),
    ("3 beacons, in plane, v in plane", "auto", "rank < 6", {"anchors": PM_B3, "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.0]}]}),
    ("3 beacons, 1e-6 m off plane, v in plane", "auto", "rank 6", {"anchors": PM_B3, "points": [{"p": [1, 1, 1e-6], "v": [0.5, 0.2, 0.0]}]}),
    ("3 beacons, in plane, v leaves plane", "auto", "rank 6", {"anchors": PM_B3, "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.7]}]}),
]  # fmt: skip

DELAY_CASES = [
    ("all axes excited", {}),
    ("gyro x,y,z only, zero lever arm, t_d = 0.5 ms", {"excitation": {"accel": [], "gyro": ALL}, "lever_arm": [0, 0, 0], "time_offset": 5e-4}),
    ("accel x only, x perpendicular to the line of sight (1 anchor)",
     {"anchors": [[1.0, 6.0, 2.0]], "excitation": {"accel": ["x"], "gyro": []}, "random_points": 1,
      "points": [{"antenna": [1.0, 1.0, 1.0], "q": [1, 0, 0, 0], "v": [0.5, 0.2, 0.1]}]}),
    ("gyro x,y,z only, anchor on the IMU-antenna line (1 anchor)",
     {"anchors": [[2.0, 1.5, 3.0]], "excitation": {"accel": [], "gyro": ALL}, "random_points": 1,
      "points": [{"p": [1.0, 1.0, 1.0], "q": [1, 0, 0, 0], "v": [0.5, 0.2, 0.1]}]}),
    ("accel x only (T2)", {"excitation": {"accel": ["x"], "gyro": []}}),
    ("gyro x,y,z only, lever arm != 0 (T3)", {"excitation": {"accel": [], "gyro": ALL}}),
    ("gyro x,y only, lever arm != 0", {"excitation": {"accel": [], "gyro": ["x", "y"]}}),
    ("gyro x,y,z only, zero lever arm", {"excitation": {"accel": [], "gyro": ALL}, "lever_arm": [0, 0, 0]}),
    ("nothing excited", {"excitation": {"accel": [], "gyro": []}}),
]


_AXIS_PART = re.compile(r" along (?:(?:body|world) )?(?:\[[^\]]*\](?: \((?:body|world)\))?|[xyz])|: .*$")


def direction_family(name: str) -> str:
    """The generator family of a named direction, without its basis-dependent axis.

    Inside a multi-dimensional null space the individual vectors (and so the
    axes in their names) depend on an arbitrary basis choice of the SVD; the
    families (which candidate subspace a direction was found in) and their
    dimensions do not.
    """
    return _AXIS_PART.sub("", name).strip()


A4 = A3 + [[2.0, 2.0, 3.0]]
SQUARE = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0], [5.0, 5.0, 0.0]]

#: (case, config overrides) for TDoA (differences to anchor 0) with the 19-state model
TDOA_CASES = [
    ("2 anchors (1 difference), all axes excited", {"anchors": A4[:2]}),
    ("3 anchors", {"anchors": A3}),
    ("4 non-coplanar anchors", {"anchors": A4}),
    ("4 coplanar anchors, tag off their plane", {"anchors": SQUARE}),
    ("4 coplanar anchors, tag in their plane", {"anchors": SQUARE, "points": [{"antenna": [1, 2, 0]}, {"antenna": [3, 1, 0]}]}),
    ("2 anchors, tag on the pair's hyperboloid axis", {"anchors": A4[:2], "points": [{"antenna": [-2, 0, -0.2]}, {"antenna": [7.5, 0, 0.75]}]}),
    ("2 anchors, vertical baseline", {"anchors": [[0, 0, 0], [0, 0, 3]]}),
    ("4 anchors, zero lever arm", {"anchors": A4, "lever_arm": [0, 0, 0]}),
]  # fmt: skip

TDOA_DELAY_CASES = [
    ("all axes excited", {}),
    ("accel x only (T2)", {"excitation": {"accel": ["x"], "gyro": []}}),
    ("gyro x,y,z only, lever arm != 0 (T3)", {"excitation": {"accel": [], "gyro": ALL}}),
    ("gyro x,y,z only, zero lever arm", {"excitation": {"accel": [], "gyro": ALL}, "lever_arm": [0, 0, 0]}),
    ("2 anchors, tag on the pair's axis (T1' fails)", {"anchors": A4[:2], "points": [{"antenna": [-2, 0, -0.2]}], "random_points": 1}),
    ("nothing excited", {"excitation": {"accel": [], "gyro": []}}),
]  # fmt: skip


def _names(v: dict) -> str:
    """Basis-independent summary: generator families and the dimension each spans."""
    fams: dict[str, int] = {}
    for d in v["unobservable_directions"]:
        f = direction_family(d["name"])
        fams[f] = fams.get(f, 0) + 1
    return "; ".join(f"{f} (x{k})" if k > 1 else f for f, k in fams.items()) or "-"


def _order(v: dict) -> str:
    """Lie order of the reported rank, the setting and why the search stopped."""
    if v["lie_order_setting"] == "auto":
        return f"auto: {v['lie_order']} ({v['stop_reason']})"
    return f"{v['lie_order']} (explicit)"


def _cross(v: dict) -> str:
    cc = v["cross_check"]
    return "-" if cc is None else str(cc["rank"])


def _margin(v: dict) -> str:
    return "-" if v["margin_decades"] is None else f"{v['margin_decades']:.1f}"


def uwb_table(points: int) -> str:
    lines = [
        "| case | seed statement | rank / 18 (min over points) | verdict | Lie order | trajectory test rank | margin [decades] (min) | unobservable families (weakest point; xk = k dimensions) |",
        "|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for case, seed, over in UWB_CASES:
        cfg = {"name": case, "anchors": A3, "lever_arm": LEVER, "random_points": points, "seed": 1}
        cfg.update(over)
        v = structural_verdict(cfg)
        lines.append(f"| {case} | {seed} | {v['rank']} | {v['verdict']} | {_order(v)} | {_cross(v)} | {_margin(v)} | {_names(v)} |")
    return "\n".join(lines)


def lemma_table(points: int) -> str:
    rng = np.random.default_rng(7)
    subsets = [(), ("x",), ("x", "y"), ("x", "y", "z")]
    lines = [
        "| excited axes | Lemma 2 `F5F0-F6` rank / 4 (seed: >= 2 accel axes) | Lemma 4 `F5F3+F18` rank / 3 (seed: 3 accel axes) | Lemma 3 `F13R-F15` rank / 3 (seed: 3 gyro axes) |",
        "|---|---|---|---|",
    ]
    samples = [(sample_uwb_imu_state(rng), rng.uniform(-5, 5, (3, 3))) for _ in range(points)]
    for sub in subsets:
        r2 = min(_rank(seed001_blocks(x, A, sub, sub)["lemma2"]) for x, A in samples)
        r4 = min(_rank(seed001_blocks(x, A, sub, sub)["lemma4"]) for x, A in samples)
        r3 = min(_rank(seed001_blocks(x, A, sub, sub)["lemma3"]) for x, A in samples)
        lines.append(f"| {', '.join(sub) or 'none'} | {r2} | {r4} | {r3} |")
    return "\n".join(lines)


def _rank(M) -> int:
    return numerical_rank(M)[0] if M.size else 0


def point_mass_table(points: int) -> str:
    lines = ["| case | Lie order | seed 002 statement | rank / 6 (min) | verdict | margin [decades] | unobservable families |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for case, order, seed, over in PM_CASES:
        cfg = {"name": case, "model": "point_mass", "lie_order": order, "nominal_input": [0, 0, 0], "seed": 1}
        cfg.update(over)
        if "random_points" in cfg:
            cfg["random_points"] = points
        v = structural_verdict(cfg)
        lines.append(f"| {case} | {_order(v)} | {seed} | {v['rank']} | {v['verdict']} | {_margin(v)} | {_names(v)} |")
    return "\n".join(lines)


def tdoa_table(points: int) -> str:
    lines = ["| case | rank / 18 (min) | verdict | Lie order | trajectory test rank | margin [decades] | pairs on an axis (weakest point) | unobservable families |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for case, over in TDOA_CASES:
        cfg = {"name": case, "measurement": "tdoa", "anchors": A4, "lever_arm": LEVER, "random_points": points, "seed": 1}
        cfg.update(over)
        v = structural_verdict(cfg)
        axis = v["conditions"].get("tdoa_pairs_on_axis") or "-"
        lines.append(f"| {case} | {v['rank']} | {v['verdict']} | {_order(v)} | {_cross(v)} | {_margin(v)} | {axis} | {_names(v)} |")
    return "\n".join(lines)


def delay_table(points: int, cases=None, measurement: str = "range") -> str:
    lines = ["| case | T1 | T2 | T3 | Theorem 1 | first-order criterion (accel / gyro) | max \\|dh/du\\| at t_d (weakest point) | power of t_d | identifiable |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for case, over in cases or DELAY_CASES:
        cfg = {"anchors": A3 if measurement == "range" else A4, "lever_arm": LEVER, "random_points": points,
               "time_offset": 0.02, "seed": 1, "measurement": measurement}  # fmt: skip
        cfg.update(over)
        v = delay_verdict(cfg)
        c, f, num = v["conditions"], v["first_order"], v["numeric"]
        s = max(num["sensitivity"].values(), default=0.0)
        yn = lambda b: "yes" if b else "no"  # noqa: E731
        pw = "-" if num["td_power"] is None else f"{num['td_power']:.0f}"
        lines.append(f"| {case} | {yn(c['T1'])} | {yn(c['T2'])} | {yn(c['T3'])} | {yn(v['theorem1'])} | "
                     f"{f['accel']:.2f} / {f['gyro']:.2f} | {s:.2e} | {pw} | {yn(v['identifiable'])} |")  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=20)
    ap.add_argument("--out", default=None, help="write the Markdown here (atomically) instead of stdout")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    parts = [
        "### 19-state UWB-IMU model (lie_order: auto unless stated)\n", uwb_table(a.points),
        "\n\n### Lemma 2-4 blocks vs excited axes (same axes for accelerometer and gyro)\n", lemma_table(a.points),
        "\n\n### Point mass (seed 002), drift only with zero nominal acceleration unless stated\n", point_mass_table(a.points),
        "\n\n### Time offset (Theorem 1), t_d = 0.02 s unless stated\n", delay_table(a.points),
        "\n\n### TDoA (differences to anchor 0), lie_order: auto, anchors A3 + [2, 2, 3] unless stated\n", tdoa_table(a.points),
        "\n\n### TDoA time offset (T1' = some pair's difference has a gradient), t_d = 0.02 s\n",
        delay_table(a.points, TDOA_DELAY_CASES, "tdoa"),
        f"\n\n_Generated by `python -m uwbimu.observability.boundary --points {a.points}` in {time.perf_counter() - t0:.1f} s._\n",
    ]  # fmt: skip
    text = "".join(parts)
    if a.out:
        from uwbimu.io.atomic import write_text

        write_text(a.out, text)
    else:
        print(text)


if __name__ == "__main__":
    main()
