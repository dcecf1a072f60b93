"""Figures of the trajectory-design tools (object API, no global pyplot state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from uwbimu.design.trajectory.seed_ocp import SeedOcpResult, det_observability
from uwbimu.io.atomic import save_figure


def seed_trajectory_figure(res: SeedOcpResult) -> Figure:
    """Seed fig. 7: PD vs optimal trajectories (3-D view and per axis)."""
    fig = Figure(figsize=(11, 4.5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    styles = {
        "pd": ("tab:blue", "-", "PD"),
        "indirect": ("tab:red", "-", "optimal (indirect, PMP)"),
        "direct": ("k", "--", "optimal (direct, IPOPT)"),
        "direct_fixed_final": ("tab:green", ":", "optimal, final state fixed at rest"),
    }
    methods = [m for m in (res.pd, res.indirect, res.direct, res.fixed_final) if m is not None]
    for m in methods:
        c, ls, lab = styles[m.name]
        ax3.plot(m.x[:, 0], m.x[:, 1], m.x[:, 2], color=c, ls=ls, label=lab)
    bea = np.asarray(res.cfg.beacons)
    ax3.scatter(bea[:, 0], bea[:, 1], bea[:, 2], marker="^", color="g", label="beacons")
    ax3.scatter(*res.cfg.x0[:3], color="k", marker="o", label="start")
    ax3.scatter(*res.cfg.goal, color="m", marker="*", s=80, label="goal")
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m]")
    ax3.legend(fontsize=7, loc="upper left")
    ax3.set_title("Trajectories (seed fig. 7)")
    ax = fig.add_subplot(1, 2, 2)
    for m in methods:
        c, ls, lab = styles[m.name]
        for i, comp in enumerate("xyz"):
            ax.plot(m.t, m.x[:, i], color=c, ls=ls, alpha=1.0 - 0.25 * i, label=f"{lab} {comp}" if m.name != "direct" else None)
    for g in res.cfg.goal:
        ax.axhline(g, color="m", lw=0.6, ls=":")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("position [m]")
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3)
    return fig


def seed_det_figure(res: SeedOcpResult) -> Figure:
    """Seed fig. 8: ``det(O)`` along time for PD and the optimal control."""
    fig = Figure(figsize=(6.5, 4))
    ax = fig.add_subplot(1, 1, 1)
    bea = np.asarray(res.cfg.beacons)
    rows = [(res.pd, "tab:blue", "-", "PD"), (res.indirect, "tab:red", "-", "optimal (indirect)"), (res.direct, "k", "--", "optimal (direct)")]
    if res.fixed_final is not None:
        rows.append((res.fixed_final, "tab:green", ":", "optimal, final state fixed"))
    for m, c, ls, lab in rows:
        ax.plot(m.t, det_observability(m.x[:, :3], bea), color=c, ls=ls, label=f"{lab}, mean {m.cost['det_mean']:.3f}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("det(O)  (unit line-of-sight vectors)")
    ax.set_title("Observability along the trajectory (seed fig. 8)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return fig


def seed_convergence_figure(res: SeedOcpResult) -> Figure:
    """Indirect method: ``max |H_u|`` and cost per gradient iteration."""
    fig = Figure(figsize=(9, 3.5))
    h = res.indirect.history
    ax = fig.add_subplot(1, 2, 1)
    ax.semilogy(h["hu_max"])
    ax.axhline(res.cfg.hu_tol, color="r", ls=":", label="threshold")
    ax.set_xlabel("iteration")
    ax.set_ylabel("max_k |H_u,k| [m/s^2]")
    ax.grid(alpha=0.3)
    ax.legend()
    ax2 = fig.add_subplot(1, 2, 2)
    c = np.asarray(h["cost"])
    ax2.semilogy(c - res.direct.cost["total"] + 1e-12)
    ax2.set_xlabel("iteration")
    ax2.set_ylabel("J - J*(direct)")
    ax2.grid(alpha=0.3)
    return fig


def seed_controls_figure(res: SeedOcpResult) -> Figure:
    """Control histories ``u(t)`` of PD and the optimal control."""
    fig = Figure(figsize=(6.5, 4))
    ax = fig.add_subplot(1, 1, 1)
    t = res.cfg.t[:-1]
    for m, c, lab in ((res.pd, "tab:blue", "PD"), (res.direct, "tab:red", "optimal")):
        for i, comp in enumerate("xyz"):
            ax.step(t, m.u[:, i], where="post", color=c, alpha=1.0 - 0.25 * i, label=f"{lab} u_{comp}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("u [m/s^2]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return fig


def save_seed_figures(res: SeedOcpResult, out: str | Path) -> list[Path]:
    """Write the four seed-OCP figures into ``out``; returns their paths."""
    out = Path(out)
    paths = []
    for name, fn in (
        ("fig7_trajectories.png", seed_trajectory_figure),
        ("fig8_det_observability.png", seed_det_figure),
        ("indirect_convergence.png", seed_convergence_figure),
        ("controls.png", seed_controls_figure),
    ):
        fig = fn(res)
        paths.append(save_figure(out / name, fig))
    return paths


# --------------------------------------------------------------------------
# Calibration manoeuvre
# --------------------------------------------------------------------------
def calibration_figure(res: dict, cfg) -> Figure:
    """Designed manoeuvre vs figure-8: path (3-D), attitude, speed/rate, predicted sigmas."""
    fig = Figure(figsize=(14, 8.5))
    fig.subplots_adjust(left=0.05, right=0.98, wspace=0.38, hspace=0.3)
    t = np.arange(0.0, cfg.duration, 0.02)
    kd = res["designed"].kinematics(t)
    kf = res["figure8"].kinematics(t)
    A = cfg.anchor_array()
    ax = fig.add_subplot(2, 3, 1, projection="3d")
    ax.plot(*kd["p"].T, color="tab:red", lw=0.8, label="designed")
    ax.plot(*kf["p"].T, color="tab:blue", lw=0.8, label="figure-8")
    ax.scatter(*A.T, marker="^", color="g", label="anchors")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(2, 3, 2)
    for i, n in enumerate(("roll", "pitch", "yaw")):
        ax.plot(t, np.rad2deg(kd["euler"][:, i]), label=f"designed {n}")
    for i, n in enumerate(("roll", "pitch", "yaw")):
        ax.plot(t, np.rad2deg(kf["euler"][:, i]), ls="--", label=f"figure-8 {n}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("attitude [deg]")
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(2, 3, 3)
    for k, c, lab in ((kd, "tab:red", "designed"), (kf, "tab:blue", "figure-8")):
        ax.plot(t, np.linalg.norm(k["v"], axis=1), color=c, label=f"{lab} speed [m/s]")
        ax.plot(t, np.linalg.norm(k["a"], axis=1), color=c, ls="--", label=f"{lab} accel [m/s^2]")
        ax.plot(t, np.linalg.norm(k["w"], axis=1), color=c, ls=":", label=f"{lab} rate [rad/s]")
    b = cfg.motion_bounds()  # the platform's tilt / rate limits
    for v in (b.speed, b.accel, b.rate):
        ax.axhline(v, color="k", lw=0.5)
    ax.set_xlabel("t [s]")
    ax.legend(fontsize=6)
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(2, 3, 4)
    for k, c, lab in ((kd, "tab:red", "designed"), (kf, "tab:blue", "figure-8")):
        ax.plot(*k["p"][:, :2].T, color=c, lw=0.8, label=lab)
    ax.scatter(*A[:, :2].T, marker="^", color="g")
    ax.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle(cfg.box_min[:2], cfg.box_max[0] - cfg.box_min[0], cfg.box_max[1] - cfg.box_min[1], fill=False, ls=":"))
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("top view (box dotted)")
    ax = fig.add_subplot(2, 3, 5)
    labels = ["lever x", "lever y", "lever z", "t_d"]
    xx = np.arange(4)
    bars = [("figure8", "tab:blue", "figure-8"), ("figure8_excited", "tab:gray", "figure-8, attitude at bounds"), ("designed", "tab:red", "designed")]
    bars = [b for b in bars if f"metrics_{b[0]}" in res]
    wd = 0.8 / len(bars)
    for j, (key, c, lab) in enumerate(bars):
        m = res[f"metrics_{key}"]
        v = [1e3 * x for x in m["sigma_lever_arm_m"]] + [1e3 * m["sigma_time_offset_s"]]
        ax.bar(xx + (j - (len(bars) - 1) / 2) * wd, v, wd, color=c, label=lab)
    ax.set_xticks(xx, labels)
    ax.set_ylabel("predicted 1-sigma [mm | ms]")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("linearised ESKF covariance at the end")
    ax = fig.add_subplot(2, 3, 6)
    ax.plot(t, np.rad2deg(kd["tilt"]), color="tab:red", label="designed tilt")
    ax.plot(t, np.rad2deg(kf["tilt"]), color="tab:blue", label="figure-8 tilt")
    ax.axhline(np.rad2deg(b.tilt), color="k", lw=0.5)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("tilt [deg]")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return fig


def save_calibration_figures(res: dict, cfg, out: str | Path) -> list[Path]:
    out = Path(out)
    return [save_figure(out / "calibration_design.png", calibration_figure(res, cfg))]


def save_pointmass_figure(base, res, cfg, path) -> Path:
    """Minimum-effort vs information-optimal point-mass paths (3-D and top view)."""
    fig = Figure(figsize=(11, 4.5))
    bea = np.asarray(cfg.beacons)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    for r, c, lab in ((base, "tab:blue", "min effort"), (res, "tab:red", cfg.objective)):
        ax.plot(*r.x[:, :3].T, color=c, label=lab)
    ax.scatter(*bea.T, marker="^", color="g", label="beacons")
    for ob in cfg.obstacles:
        ax.scatter(*ob.center, color="k", marker="s" if ob.kind == "box" else "o", s=40)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 2, 2)
    for r, c, lab in ((base, "tab:blue", "min effort"), (res, "tab:red", cfg.objective)):
        ax.plot(r.x[:, 0], r.x[:, 1], color=c, label=lab)
    ax.scatter(bea[:, 0], bea[:, 1], marker="^", color="g")
    th = np.linspace(0, 2 * np.pi, 100)
    for ob in cfg.obstacles:
        if ob.kind == "sphere":
            rr = ob.radius + ob.margin
            ax.plot(ob.center[0] + rr * np.cos(th), ob.center[1] + rr * np.sin(th), "k-", lw=0.8)
        else:
            hx, hy = ob.half_size[0] + ob.margin, ob.half_size[1] + ob.margin
            ax.plot(ob.center[0] + np.array([-hx, hx, hx, -hx, -hx]), ob.center[1] + np.array([-hy, -hy, hy, hy, -hy]), "k-", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("top view (obstacles: horizontal sections)")
    ax.legend(fontsize=7)
    return save_figure(path, fig)
