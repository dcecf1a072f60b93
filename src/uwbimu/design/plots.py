"""Plots for placement results (matplotlib object API, Agg-safe, written atomically)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from uwbimu.io.atomic import save_figure

__all__ = ["plot_layout_3d", "plot_coverage_map", "plot_pdop_slices", "plot_marginal", "plot_structure_coverage"]


def _box_3d(ax, lo, hi) -> None:
    """A 3-D axes showing the box ``lo..hi`` [m] at its true aspect ratio, axes labelled."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    span = np.maximum(hi - lo, 1e-3)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(span / span.max()))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")


def plot_layout_3d(path, anchors, boresights=None, bars=(), polygon=None, height=None, title="", ids=None,
                   lo=None, hi=None) -> Path:
    """Anchors (with boresight arrows) and the structure's bars or the room outline in 3-D.

    ``lo``/``hi`` [m] set the plotted box (true aspect ratio); default: the anchors' extent.
    """
    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    a = np.asarray(anchors, float)
    for b in bars:
        p0, p1 = np.asarray(b.p0), np.asarray(b.p1)
        ax.plot(*np.column_stack([p0, p1]), color="0.45", lw=1.5)
    if polygon is not None:
        P = np.vstack([polygon, polygon[:1]])
        for z in (0.0, height):
            ax.plot(P[:, 0], P[:, 1], np.full(len(P), z), color="0.5", lw=1)
        for v in polygon:
            ax.plot([v[0], v[0]], [v[1], v[1]], [0, height], color="0.5", lw=1)
    ax.scatter(a[:, 0], a[:, 1], a[:, 2], color="tab:red", s=25, depthshade=False)
    lo = np.min(a, axis=0) if lo is None else np.asarray(lo, float)
    hi = np.max(a, axis=0) if hi is None else np.asarray(hi, float)
    span = np.maximum(hi - lo, 1e-3)
    if boresights is not None:
        b = np.asarray(boresights, float) * 0.06 * float(span.max())
        ax.quiver(a[:, 0], a[:, 1], a[:, 2], b[:, 0], b[:, 1], b[:, 2], color="tab:red", lw=0.8)
    if ids is not None and len(a) <= 16:
        for i, t in enumerate(ids):
            ax.text(a[i, 0], a[i, 1], a[i, 2], t, fontsize=7)
    _box_3d(ax, lo, hi)
    ax.set_title(title or "anchors")
    return save_figure(path, fig)


def plot_coverage_map(path, points, counts, k: int, title="") -> Path:
    """k-coverage seen from above (fraction of heights covered per x–y cell) and from the side."""
    p = np.asarray(points, float)
    cov = np.asarray(counts) >= k
    fig = Figure(figsize=(11, 4.5), layout="constrained")
    for j, (ia, ib, lab) in enumerate(((0, 1, "top view: fraction of z covered"), (1, 2, "side view: fraction of x covered"))):
        ax = fig.add_subplot(1, 2, j + 1)
        ua, ia_ = np.unique(np.round(p[:, ia], 6), return_inverse=True)
        ub, ib_ = np.unique(np.round(p[:, ib], 6), return_inverse=True)
        num = np.zeros((len(ub), len(ua)))
        den = np.zeros_like(num)
        np.add.at(num, (ib_, ia_), cov)
        np.add.at(den, (ib_, ia_), 1)
        with np.errstate(invalid="ignore"):
            frac = num / den
        im = ax.imshow(frac, origin="lower", aspect="auto", vmin=0, vmax=1, cmap="viridis",
                       extent=(ua[0], ua[-1], ub[0], ub[-1]))
        ax.set_xlabel("xyz"[ia] + " [m]")
        ax.set_ylabel("xyz"[ib] + " [m]")
        ax.set_title(lab, fontsize=9)
        fig.colorbar(im, ax=ax)
    fig.suptitle(title or f"{k}-coverage {100 * cov.mean():.1f} %")
    return save_figure(path, fig)


def plot_pdop_slices(path, points, pdop, n_slices: int = 3, axis: int = 2, cap: float = 10.0, title="") -> Path:
    """PDOP maps on ``n_slices`` planes of constant ``axis`` coordinate (capped for colour)."""
    p = np.asarray(points, float)
    v = np.minimum(np.asarray(pdop, float), cap)
    levels = np.unique(np.round(p[:, axis], 6))
    pick = levels[np.linspace(0, len(levels) - 1, min(n_slices, len(levels))).round().astype(int)]
    others = [i for i in range(3) if i != axis]
    fig = Figure(figsize=(4.4 * len(pick), 3.8), layout="constrained")
    fin = v[np.isfinite(v)]
    vmax = float(min(cap, max(np.percentile(fin, 99) if fin.size else cap, 1.5)))
    for j, lev in enumerate(pick):
        ax = fig.add_subplot(1, len(pick), j + 1)
        m = np.isclose(p[:, axis], lev)
        sc = ax.scatter(p[m, others[0]], p[m, others[1]], c=v[m], cmap="magma_r", vmin=1.0, vmax=vmax, s=12, marker="s")
        ax.set_title(f"{'xyz'[axis]} = {lev:.2f} m", fontsize=9)
        ax.set_xlabel("xyz"[others[0]] + " [m]")
        ax.set_ylabel("xyz"[others[1]] + " [m]")
        ax.set_aspect("equal", adjustable="box")
        fig.colorbar(sc, ax=ax, label="PDOP")
    fig.suptitle(title or "PDOP slices")
    return save_figure(path, fig)


def plot_marginal(path, n_anchors, coverage, pdop_p95=None, title="") -> Path:
    """Marginal value of each added anchor: coverage and PDOP p95 versus anchor count."""
    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot()
    ax.plot(n_anchors, 100 * np.asarray(coverage), "o-", color="tab:blue", label="coverage")
    ax.set_xlabel("anchors placed (greedy order)")
    ax.set_ylabel("k-coverage [%]", color="tab:blue")
    if pdop_p95 is not None:
        ax2 = ax.twinx()
        ax2.plot(n_anchors, pdop_p95, "s--", color="tab:orange", label="PDOP p95")
        ax2.set_ylabel("PDOP p95", color="tab:orange")
    ax.set_title(title or "marginal value of each added anchor")
    ax.grid(alpha=0.3)
    return save_figure(path, fig)


def plot_structure_coverage(path, anchors, boresights, bars, points, counts, k: int, lo, hi, title="",
                            max_points: int = 6000, seed: int = 0) -> Path:
    """A structure's anchors with their facing and the k-covered points (the seed paper's Figs 5-6).

    Left: the bars and every anchor as an arrow along its boresight.  Right: the same with a
    random subset (``max_points``, fixed ``seed``) of the covered grid points as blue dots.
    """
    a = np.asarray(anchors, float)
    p = np.asarray(points, float)
    cov = np.asarray(counts) >= k
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    span = np.maximum(hi - lo, 1e-3)
    idx = np.flatnonzero(cov)
    if idx.size > max_points:
        idx = np.random.default_rng(seed).choice(idx, max_points, replace=False)
    fig = Figure(figsize=(12, 6), layout="constrained")
    for j, show_points in enumerate((False, True)):
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        for b in bars:
            ax.plot(*np.column_stack([np.asarray(b.p0), np.asarray(b.p1)]), color="0.35", lw=1.2)
        if show_points:
            ax.scatter(p[idx, 0], p[idx, 1], p[idx, 2], s=1, color="tab:blue", alpha=0.25, depthshade=False)
        b = np.asarray(boresights, float) * 0.06 * float(span.max())
        ax.quiver(a[:, 0], a[:, 1], a[:, 2], b[:, 0], b[:, 1], b[:, 2], color="tab:red", lw=1.0)
        _box_3d(ax, lo, hi)
        ax.set_title("anchors (arrow: facing)" if not show_points
                     else f"covered points ({k} links): {100 * cov.mean():.2f} % (subset drawn)", fontsize=9)
    fig.suptitle(title or "structure layout")
    return save_figure(path, fig)
