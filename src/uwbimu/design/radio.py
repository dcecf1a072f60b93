"""Radio model for coverage: range presets, Friis link budget, antenna patterns, LOS.

Link budget
-----------
A link between an anchor at ``a`` (antenna boresight ``b``) and a tag at ``p`` closes when::

    margin = B + G_anchor(dir) + G_tag - FSPL(d) - L_nlos >= 0   [dB]
    FSPL(d) = 20 log10(4 pi d f / c)                             (Friis, free space)

The budget ``B`` (transmit power minus receiver sensitivity minus fade margin) is
set from a preset's *maximum line-of-sight range with 0 dBi antennas*
``R0``: ``B = FSPL(R0)``.  Hence an antenna gain ``G`` [dB] scales the reach as
``R = R0 * 10^(G/20)``, and an NLOS loss of ``L`` dB shrinks it by ``10^(-L/20)``.

Presets (``R0``, LOS, 0 dBi): ``dw1000-indoor`` 15 m (DW1000 standard 6.8 Mbps
indoors with a fade margin), ``dw1000-long-range`` 30 m (110 kbps, long preamble),
``outdoor-high-power`` 50 m (boosted Tx, outdoor).  These are round numbers in the
range vendors quote; replace them by ``max_range`` measured for your hardware.

Antenna patterns
----------------
Gains are given in dBi as a function of the direction to the tag expressed in the
antenna frame (x = boresight, z = "up" of the antenna, y = z x x):

* :class:`Omni` — constant gain;
* :class:`CosN` — ``G(theta) = G0 cos^n(theta)`` in front (theta from boresight) with
  ``n`` chosen from the half-power beamwidth ``cos^n(bw/2) = 1/2``, peak gain ``G0``
  defaulting to the directivity of a cos^n hemisphere ``2(n+1)``, and a floor
  ``front_to_back_db`` below the peak (behind the antenna and at grazing angles);
* :class:`TablePattern` — measured azimuth/elevation grid read from a CSV with columns
  ``azimuth_deg, elevation_deg, gain_dbi`` (bilinear interpolation, azimuth wraps).

Line of sight is checked by casting the anchor–tag segment against axis-aligned
:class:`Box` obstacles and :class:`Bar` capsules (segment + radius); every obstacle
crossed adds its NLOS loss.  An obstacle that contains the anchor itself (an anchor
mounted on a bar or inside a wall box) is ignored for that anchor — the antenna's
front-to-back ratio models the shadow of its own mount.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from numba import njit

from uwbimu.errors import ConfigError, InputError, UsageError

__all__ = [
    "SPEED_OF_LIGHT",
    "RANGE_PRESETS",
    "fspl_db",
    "Omni",
    "CosN",
    "TablePattern",
    "PatternError",
    "load_pattern_csv",
    "Box",
    "Bar",
    "LinkModel",
    "antenna_frames",
    "blocked_loss_db",
    "k_coverage",
    "count_links_fast",
    "count_links_grid",
    "geometry_grid",
    "lobe_sphere",
    "to_soa",
    "coverage_fraction_fast",
]

SPEED_OF_LIGHT = 299_792_458.0
DEFAULT_FREQUENCY_HZ = 6.4896e9  # UWB channel 5 centre frequency

RANGE_PRESETS: dict[str, float] = {
    "dw1000-indoor": 15.0,
    "dw1000-long-range": 30.0,
    "outdoor-high-power": 50.0,
}


def fspl_db(d, frequency_hz: float = DEFAULT_FREQUENCY_HZ) -> np.ndarray:
    """Free-space path loss (Friis) [dB] at distance ``d`` [m]; clamped at 1 cm."""
    d = np.maximum(np.asarray(d, dtype=float), 0.01)
    return 20.0 * np.log10(4.0 * np.pi * d * frequency_hz / SPEED_OF_LIGHT)


# --------------------------------------------------------------------------- patterns
class PatternError(InputError):
    """A gain pattern file or definition is invalid (message names file, line and column; exit 1)."""


@dataclass(frozen=True)
class Omni:
    """Omnidirectional antenna with constant gain [dBi]."""

    gain_dbi: float = 0.0
    axisymmetric = True

    def gain_cos(self, cos_theta) -> np.ndarray:
        return np.full(np.shape(cos_theta), float(self.gain_dbi))

    def gain_local(self, dirs) -> np.ndarray:
        return np.full(np.shape(dirs)[:-1], float(self.gain_dbi))

    @property
    def peak_dbi(self) -> float:
        return float(self.gain_dbi)


@dataclass(frozen=True)
class CosN:
    """Directional ``cos^n`` pattern set by its half-power beamwidth [deg].

    ``peak_gain_dbi=None`` uses the directivity of a cos^n hemisphere, ``2(n+1)``.
    """

    beamwidth_deg: float = 90.0
    peak_gain_dbi: float | None = None
    front_to_back_db: float = 20.0
    axisymmetric = True

    def __post_init__(self):
        if not 0.0 < self.beamwidth_deg < 180.0:
            raise PatternError(f"CosN beamwidth_deg must be in (0, 180), got {self.beamwidth_deg}")

    @property
    def n(self) -> float:
        return math.log(0.5) / math.log(math.cos(math.radians(self.beamwidth_deg) / 2.0))

    @property
    def peak_dbi(self) -> float:
        if self.peak_gain_dbi is not None:
            return float(self.peak_gain_dbi)
        return 10.0 * math.log10(2.0 * (self.n + 1.0))

    def gain_cos(self, cos_theta) -> np.ndarray:
        c = np.clip(np.asarray(cos_theta, dtype=float), -1.0, 1.0)
        floor = 10.0 ** (-self.front_to_back_db / 10.0)
        lin = np.where(c > 0, np.maximum(np.abs(c) ** self.n, floor), floor)
        return self.peak_dbi + 10.0 * np.log10(lin)

    def gain_local(self, dirs) -> np.ndarray:
        return self.gain_cos(np.asarray(dirs)[..., 0])


@dataclass(frozen=True)
class TablePattern:
    """Measured pattern on a regular azimuth × elevation grid [deg] with gains [dBi].

    Azimuth is measured in the antenna x–y plane from boresight (x) towards y and
    wraps around; elevation from the x–y plane towards z.
    """

    az_deg: np.ndarray
    el_deg: np.ndarray
    gain_dbi: np.ndarray  # (n_el, n_az)
    source: str = "<table>"
    axisymmetric = False

    @property
    def peak_dbi(self) -> float:
        return float(np.max(self.gain_dbi))

    def gain_local(self, dirs) -> np.ndarray:
        d = np.asarray(dirs, dtype=float)
        az = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
        el = np.degrees(np.arcsin(np.clip(d[..., 2], -1.0, 1.0)))
        # Azimuth: append the first column at +360 so interpolation wraps.
        azg = np.concatenate([self.az_deg, [self.az_deg[0] + 360.0]])
        gg = np.concatenate([self.gain_dbi, self.gain_dbi[:, :1]], axis=1)
        az = (az - azg[0]) % 360.0 + azg[0]
        ia = np.clip(np.searchsorted(azg, az, side="right") - 1, 0, len(azg) - 2)
        ie = np.clip(np.searchsorted(self.el_deg, el, side="right") - 1, 0, len(self.el_deg) - 2)
        ta = (az - azg[ia]) / (azg[ia + 1] - azg[ia])
        te = np.clip((el - self.el_deg[ie]) / (self.el_deg[ie + 1] - self.el_deg[ie]), 0.0, 1.0)
        g00 = gg[ie, ia]
        g01 = gg[ie, ia + 1]
        g10 = gg[ie + 1, ia]
        g11 = gg[ie + 1, ia + 1]
        return (1 - te) * ((1 - ta) * g00 + ta * g01) + te * ((1 - ta) * g10 + ta * g11)


def load_pattern_csv(path: str | Path) -> TablePattern:
    """Read a gain pattern CSV (``azimuth_deg, elevation_deg, gain_dbi``).

    The rows must form a full regular grid (every azimuth at every elevation, once);
    azimuths in [-180, 360), elevations in [-90, 90].  Errors name file, row, column.
    """
    path = Path(path)
    if not path.is_file():
        raise PatternError(f"{path}: pattern file not found")
    need = ["azimuth_deg", "elevation_deg", "gain_dbi"]
    rows: list[tuple[float, float, float]] = []
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        header = [h.strip() for h in (reader.fieldnames or [])]
        missing = [c for c in need if c not in header]
        if missing:
            raise PatternError(f"{path}: missing column(s) {', '.join(missing)}; header is {header}, expected {need}")
        for lineno, row in enumerate(reader, start=2):
            row = {k.strip(): v for k, v in row.items() if k is not None}
            vals = []
            for c in need:
                try:
                    v = float(row[c])
                except (TypeError, ValueError):
                    raise PatternError(f"{path}: line {lineno}, column '{c}': not a number: {row.get(c)!r}") from None
                if not math.isfinite(v):
                    raise PatternError(f"{path}: line {lineno}, column '{c}': not finite: {v}")
                vals.append(v)
            az, el, g = vals
            if not -180.0 <= az < 360.0:
                raise PatternError(f"{path}: line {lineno}, column 'azimuth_deg': {az} outside [-180, 360)")
            if not -90.0 <= el <= 90.0:
                raise PatternError(f"{path}: line {lineno}, column 'elevation_deg': {el} outside [-90, 90]")
            rows.append((az, el, g))
    if not rows:
        raise PatternError(f"{path}: no data rows")
    arr = np.array(rows)
    az_u = np.unique(arr[:, 0])
    el_u = np.unique(arr[:, 1])
    if len(az_u) < 2 or len(el_u) < 2:
        raise PatternError(f"{path}: need at least 2 distinct azimuths and 2 elevations")
    if az_u[-1] - az_u[0] >= 360.0:
        raise PatternError(f"{path}: azimuths span {az_u[-1] - az_u[0]} deg >= 360 (duplicate of the wrap point?)")
    grid = np.full((len(el_u), len(az_u)), np.nan)
    ia = np.searchsorted(az_u, arr[:, 0])
    ie = np.searchsorted(el_u, arr[:, 1])
    for r, (i, j) in enumerate(zip(ie, ia)):
        if not np.isnan(grid[i, j]):
            raise PatternError(
                f"{path}: line {r + 2}: duplicate grid point azimuth={arr[r, 0]}, elevation={arr[r, 1]}"
            )
        grid[i, j] = arr[r, 2]
    if np.isnan(grid).any():
        i, j = np.argwhere(np.isnan(grid))[0]
        raise PatternError(
            f"{path}: grid incomplete: no row for azimuth={az_u[j]}, elevation={el_u[i]} "
            f"({int(np.isnan(grid).sum())} missing of {grid.size})"
        )
    return TablePattern(az_u, el_u, grid, source=str(path))


# --------------------------------------------------------------------------- obstacles
@dataclass(frozen=True)
class Box:
    """Axis-aligned box obstacle [m]; ``loss_db=None`` uses the model's NLOS loss."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    loss_db: float | None = None

    def contains(self, x, tol: float = 1e-9) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return np.all((x >= np.asarray(self.lo) - tol) & (x <= np.asarray(self.hi) + tol), axis=-1)

    def hits(self, origin, targets) -> np.ndarray:
        """Does segment ``origin -> targets[k]`` cross the box? (slab test), ``(P,)`` bool."""
        o = np.asarray(origin, dtype=float)
        d = np.asarray(targets, dtype=float) - o
        d = np.where(np.abs(d) < 1e-12, 1e-12, d)
        t1 = (np.asarray(self.lo) - o) / d
        t2 = (np.asarray(self.hi) - o) / d
        tn = np.max(np.minimum(t1, t2), axis=1)
        tf = np.min(np.maximum(t1, t2), axis=1)
        return (tn <= tf) & (tf >= 0.0) & (tn <= 1.0)


@dataclass(frozen=True)
class Bar:
    """Structural bar: segment ``p0 -> p1`` with ``radius`` [m] (a capsule)."""

    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float = 0.1
    loss_db: float | None = None

    def distance(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        a = np.asarray(self.p0, float)
        ab = np.asarray(self.p1, float) - a
        t = np.clip(((x - a) @ ab) / max(ab @ ab, 1e-300), 0.0, 1.0)
        return np.linalg.norm(x - (a + t[..., None] * ab), axis=-1)

    def contains(self, x, tol: float = 1e-9) -> np.ndarray:
        return self.distance(x) <= self.radius + tol

    def hits(self, origin, targets) -> np.ndarray:
        """Does segment ``origin -> targets[k]`` pass within ``radius`` of the bar?"""
        return _segment_segment_distance(np.asarray(origin, float), np.asarray(targets, float),
                                         np.asarray(self.p0, float), np.asarray(self.p1, float)) <= self.radius


def _segment_segment_distance(p0, p1s, q0, q1) -> np.ndarray:
    """Closest distance between segments ``p0->p1s[k]`` and ``q0->q1`` (clamped), ``(P,)``."""
    d1 = p1s - p0  # (P,3)
    d2 = q1 - q0  # (3,)
    r = p0 - q0  # (3,)
    a = np.einsum("ij,ij->i", d1, d1)
    e = float(d2 @ d2)
    f = float(d2 @ r)
    c = d1 @ r
    b = d1 @ d2
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12 * np.maximum(a * e, 1e-300), np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
        if e > 1e-300:
            t = (b * s + f) / e
        else:
            t = np.zeros_like(s)
        # Clamp t and recompute s for the clamped t (standard clamped closest-point scheme).
        t_cl = np.clip(t, 0.0, 1.0)
        s = np.where(t < 0.0, np.clip(-c / np.maximum(a, 1e-300), 0.0, 1.0), s)
        s = np.where(t > 1.0, np.clip((b - c) / np.maximum(a, 1e-300), 0.0, 1.0), s)
    c1 = p0 + s[:, None] * d1
    c2 = q0 + t_cl[:, None] * d2
    return np.linalg.norm(c1 - c2, axis=1)


def blocked_loss_db(anchor, points, obstacles: Sequence, default_loss_db: float) -> np.ndarray:
    """Total NLOS loss [dB] of the segments ``anchor -> points`` through ``obstacles``."""
    loss = np.zeros(len(points))
    for ob in obstacles:
        if bool(ob.contains(anchor)):
            continue  # the anchor's own mount: shadowing is in the antenna pattern
        l_db = default_loss_db if ob.loss_db is None else ob.loss_db
        loss += np.where(ob.hits(anchor, points), l_db, 0.0)
    return loss


# --------------------------------------------------------------------------- link model
def antenna_frames(boresights, ups=None) -> np.ndarray:
    """Rotation matrices (N, 3, 3) whose rows are the antenna x (boresight), y, z axes in world."""
    b = np.asarray(boresights, dtype=float).reshape(-1, 3)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    if ups is None:
        ups = np.tile([0.0, 0.0, 1.0], (len(b), 1))
    u = np.asarray(ups, dtype=float).reshape(-1, 3)
    z = u - np.einsum("ij,ij->i", u, b)[:, None] * b
    bad = np.linalg.norm(z, axis=1) < 1e-9
    if bad.any():  # boresight parallel to "up": use world x as the reference instead
        alt = np.tile([1.0, 0.0, 0.0], (int(bad.sum()), 1))
        z[bad] = alt - np.einsum("ij,ij->i", alt, b[bad])[:, None] * b[bad]
        still = np.linalg.norm(z, axis=1) < 1e-9
        z[still] = np.array([0.0, 1.0, 0.0])
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    y = np.cross(z, b)
    return np.stack([b, y, z], axis=1)


@dataclass
class LinkModel:
    """Everything that decides whether an anchor–tag link closes.

    Parameters
    ----------
    max_range : 0 dBi line-of-sight range ``R0`` [m] defining the budget
    anchor_pattern : anchor antenna gain pattern (see module docstring)
    tag_gain_dbi : tag antenna gain (omni) [dBi]
    nlos_loss_db : default extra loss per obstacle crossed [dB]
    obstacles : boxes / bars for ray casting
    frequency_hz : carrier frequency for the Friis loss
    """

    max_range: float = 15.0
    anchor_pattern: object = field(default_factory=Omni)
    tag_gain_dbi: float = 0.0
    nlos_loss_db: float = 10.0
    obstacles: list = field(default_factory=list)
    frequency_hz: float = DEFAULT_FREQUENCY_HZ

    @classmethod
    def from_preset(cls, preset: str, **kw) -> "LinkModel":
        if preset not in RANGE_PRESETS:
            raise ConfigError(f"unknown radio preset {preset!r}; choose one of {', '.join(map(str, sorted(RANGE_PRESETS)))}")
        return cls(max_range=RANGE_PRESETS[preset], **kw)

    @property
    def budget_db(self) -> float:
        return float(fspl_db(self.max_range, self.frequency_hz))

    @property
    def peak_range(self) -> float:
        """Longest possible LOS link [m] (peak antenna gain)."""
        return self.max_range * 10.0 ** ((self.anchor_pattern.peak_dbi + self.tag_gain_dbi) / 20.0)

    def margin_db(self, points, anchors, boresights=None, ups=None, ray_cast: bool = True) -> np.ndarray:
        """Link margin [dB] (P, N): the reference (NumPy, float64) implementation."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        a = np.asarray(anchors, dtype=float).reshape(-1, 3)
        d = p[:, None, :] - a[None, :, :]
        r = np.linalg.norm(d, axis=2)
        u = d / np.maximum(r, 1e-9)[..., None]
        if boresights is None:
            boresights = np.tile([0.0, 0.0, -1.0], (len(a), 1))
        R = antenna_frames(boresights, ups)
        local = np.einsum("nij,pnj->pni", R, u)
        g = self.anchor_pattern.gain_local(local)
        m = self.budget_db + g + self.tag_gain_dbi - fspl_db(r, self.frequency_hz)
        if ray_cast and self.obstacles:
            for j in range(len(a)):
                m[:, j] -= blocked_loss_db(a[j], p, self.obstacles, self.nlos_loss_db)
        return m

    def links(self, points, anchors, boresights=None, ups=None, ray_cast: bool = True) -> np.ndarray:
        """Which links close, (P, N) bool."""
        return self.margin_db(points, anchors, boresights, ups, ray_cast) >= 0.0

    def reach_lut(self, size: int = 4097) -> np.ndarray:
        """Squared reach [m^2] versus ``cos(theta)`` on ``linspace(-1, 1, size)``.

        Only for axisymmetric patterns: the link closes iff ``d^2 <= lut(cos theta)``
        (LOS).  Used by the fast kernel.
        """
        if not getattr(self.anchor_pattern, "axisymmetric", False):
            raise UsageError("the fast coverage kernel needs an axisymmetric pattern (Omni or CosN)")
        c = np.linspace(-1.0, 1.0, size)
        g = self.anchor_pattern.gain_cos(c) + self.tag_gain_dbi
        return (self.max_range**2 * 10.0 ** (g / 10.0)).astype(np.float32)


def k_coverage(links, k: int = 3) -> np.ndarray:
    """Points where at least ``k`` links close, (P,) bool."""
    return np.asarray(links).sum(axis=1) >= k


@njit(cache=True, fastmath=True)
def _count_links_kernel(x, y, z, anchors, bores, lut, counts):  # pragma: no cover - numba
    n_lut = lut.shape[0]
    half = np.float32(0.5 * (n_lut - 1))
    rmax2 = np.float32(0.0)
    for i in range(n_lut):
        if lut[i] > rmax2:
            rmax2 = lut[i]
    P = x.shape[0]
    for j in range(anchors.shape[0]):
        ax = np.float32(anchors[j, 0])
        ay = np.float32(anchors[j, 1])
        az = np.float32(anchors[j, 2])
        bx = np.float32(bores[j, 0])
        by = np.float32(bores[j, 1])
        bz = np.float32(bores[j, 2])
        for i in range(P):
            dx = x[i] - ax
            dy = y[i] - ay
            dz = z[i] - az
            d2 = dx * dx + dy * dy + dz * dz
            if d2 <= rmax2:
                if d2 > np.float32(1e-12):
                    c = (dx * bx + dy * by + dz * bz) / np.sqrt(d2)
                else:
                    c = np.float32(1.0)
                f = (c + np.float32(1.0)) * half
                k = int(f)
                if k >= n_lut - 1:
                    k = n_lut - 2
                if k < 0:
                    k = 0
                t = f - np.float32(k)
                r2 = lut[k] + t * (lut[k + 1] - lut[k])
                if d2 <= r2:
                    counts[i] += 1
    return counts


@njit(cache=True, fastmath=True)
def _lut_hits(d2, cd, lut, half, n_lut):  # pragma: no cover - numba
    # 1 if the squared distance d2 is within the interpolated squared reach at cos = cd/d.
    c = cd / np.sqrt(max(d2, np.float32(1e-12)))
    f = min(max((c + np.float32(1.0)) * half, np.float32(0.0)), np.float32(n_lut - 1) - np.float32(1e-3))
    k = int(f)
    t = f - np.float32(k)
    return 1 if d2 <= lut[k] + t * (lut[k + 1] - lut[k]) else 0


@njit(cache=True, fastmath=True)
def _grid_kernel(xs, ys, zs, hx, hy, hz, anchors, bores, lut, dlut, m_off, rho, counts, g6, want_g6):  # pragma: no cover
    # Regular grid (float32 axes xs, ys, zs with spacings hx, hy, hz).  Every direction's
    # reach lies inside the "lobe sphere" of radius rho centred m_off metres along the
    # boresight (see lobe_sphere); only cells inside it are visited: x and y ranges from
    # the sphere, the z range per (x, y) column analytically.  For a cos^2 patch this
    # visits ~1/6 of the cells of the peak-reach sphere.  The x/y parts of d^2 and of the
    # boresight projection are hoisted out of the z loop.  With want_g6 every closing link
    # also adds its unit line-of-sight outer product u u^T (packed xx, yy, zz, xy, xz, yz)
    # to g6 (float32); without it the z loop is branch-free (the flag is loop-invariant).
    nx, ny, nz = xs.shape[0], ys.shape[0], zs.shape[0]
    x0, y0, z0 = xs[0], ys[0], zs[0]
    n_lut = lut.shape[0]
    half = np.float32(0.5 * (n_lut - 1))
    fmax = np.float32(n_lut - 1) - np.float32(1e-3)
    rho2 = np.float32(rho * rho)
    for j in range(anchors.shape[0]):
        ax = np.float32(anchors[j, 0])
        ay = np.float32(anchors[j, 1])
        az = np.float32(anchors[j, 2])
        bx = np.float32(bores[j, 0])
        by = np.float32(bores[j, 1])
        bz = np.float32(bores[j, 2])
        cx = ax + np.float32(m_off) * bx
        cy = ay + np.float32(m_off) * by
        cz = az + np.float32(m_off) * bz
        ix0 = max(0, int(np.ceil((cx - rho - x0) / hx)))
        ix1 = min(nx - 1, int(np.floor((cx + rho - x0) / hx)))
        iy0 = max(0, int(np.ceil((cy - rho - y0) / hy)))
        iy1 = min(ny - 1, int(np.floor((cy + rho - y0) / hy)))
        for ix in range(ix0, ix1 + 1):
            dx = xs[ix] - ax
            ex = xs[ix] - cx
            for iy in range(iy0, iy1 + 1):
                ey = ys[iy] - cy
                exy2 = ex * ex + ey * ey
                if exy2 > rho2:
                    continue
                dy = ys[iy] - ay
                dxy2 = dx * dx + dy * dy
                cxy = dx * bx + dy * by
                ezm = np.sqrt(rho2 - exy2)
                iz0 = max(0, int(np.ceil((cz - ezm - z0) / hz)))
                iz1 = min(nz - 1, int(np.floor((cz + ezm - z0) / hz)))
                base = (ix * ny + iy) * nz
                for iz in range(iz0, iz1 + 1):
                    dz = zs[iz] - az
                    d2 = dxy2 + dz * dz
                    if want_g6:
                        inv = np.float32(1.0) / np.sqrt(max(d2, np.float32(1e-12)))
                        c = (cxy + dz * bz) * inv
                    else:
                        inv = np.float32(0.0)
                        c = (cxy + dz * bz) / np.sqrt(max(d2, np.float32(1e-12)))
                    f = min(max((c + np.float32(1.0)) * half, np.float32(0.0)), fmax)
                    k = int(f)
                    t = f - np.float32(k)
                    hit = d2 <= lut[k] + t * dlut[k]
                    i = base + iz
                    counts[i] += np.int16(hit)
                    if want_g6 and hit:
                        ux = dx * inv
                        uy = dy * inv
                        uz = dz * inv
                        g6[i, 0] += ux * ux
                        g6[i, 1] += uy * uy
                        g6[i, 2] += uz * uz
                        g6[i, 3] += ux * uy
                        g6[i, 4] += ux * uz
                        g6[i, 5] += uy * uz
    return counts


def _grid_inputs(axes, boresights, lut, sphere, check_uniform):
    # Shared argument preparation of count_links_grid and geometry_grid.
    xyz, hs = [], []
    for ax in axes:
        ax = np.asarray(ax, dtype=float)
        h = float(ax[1] - ax[0]) if len(ax) > 1 else 1.0
        if check_uniform and len(ax) > 2 and not np.allclose(np.diff(ax), h, rtol=1e-6, atol=1e-9):
            raise UsageError("count_links_grid needs uniformly spaced axes")
        xyz.append(np.ascontiguousarray(ax, dtype=np.float32))
        hs.append(h)
    b = np.asarray(boresights, dtype=np.float64)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    lut = np.asarray(lut, np.float32)
    dlut = np.append(np.diff(lut), np.float32(0.0)).astype(np.float32)
    m, rho = lobe_sphere(lut) if sphere is None else sphere
    n = len(xyz[0]) * len(xyz[1]) * len(xyz[2])
    return xyz, hs, b, lut, dlut, m, rho, n


def geometry_grid(axes, anchors, boresights, lut, sphere=None) -> tuple[np.ndarray, np.ndarray]:
    """Closing LOS links per grid cell and the summed unit-LOS outer products.

    Returns ``counts`` (P,) int16 and ``g6`` (P, 6) float32 packed ``H^T H`` (``xx, yy,
    zz, xy, xz, yz``) over the closing links — PDOP per cell follows from
    :func:`uwbimu.design.placement.pdop_from_g6`.  Same ordering and link test as
    :func:`count_links_grid`.
    """
    xyz, hs, b, lut, dlut, m, rho, n = _grid_inputs(axes, boresights, lut, sphere, check_uniform=False)
    counts = np.zeros(n, dtype=np.int16)
    g6 = np.zeros((n, 6), dtype=np.float32)
    _grid_kernel(*xyz, *hs, np.asarray(anchors, np.float64), b, lut, dlut, m, rho, counts, g6, True)
    return counts, g6


def lobe_sphere(lut) -> tuple[float, float]:
    """Smallest sphere centred on the boresight axis that holds the whole reach lobe.

    Returns ``(m, rho)``: centre ``m`` metres along the boresight from the anchor and
    radius ``rho`` [m], padded by 1 % + 1 cm for the LUT's linear interpolation.
    """
    lut = np.asarray(lut, dtype=float)
    c = np.linspace(-1.0, 1.0, len(lut))
    r = np.sqrt(lut)
    along, perp = r * c, r * np.sqrt(np.clip(1.0 - c * c, 0.0, None))
    rmax = float(r.max())

    def radius(m: float) -> float:
        return float(np.sqrt(np.max((along - m) ** 2 + perp**2)))

    # radius(m) is a max of convex functions of m, hence convex: ternary search.
    lo, hi = -rmax, rmax
    for _ in range(80):
        a, b = lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0
        if radius(a) <= radius(b):
            hi = b
        else:
            lo = a
    m = 0.5 * (lo + hi)
    return m, radius(m) * 1.01 + 0.01


def count_links_grid(axes, anchors, boresights, lut, sphere=None) -> np.ndarray:
    """Closing LOS links per cell of a regular grid (fast numba kernel, one core).

    Parameters
    ----------
    axes : three 1-D uniformly spaced coordinate arrays ``(xs, ys, zs)`` [m]; the
        result is ordered like ``np.meshgrid(xs, ys, zs, indexing="ij")`` raveled
    anchors, boresights : (N, 3)
    lut : squared-reach table from :meth:`LinkModel.reach_lut`
    sphere : ``(m, rho)`` from :func:`lobe_sphere` (computed when None; pass it to
        skip the ~1 ms it costs in a loop)
    """
    xyz, hs, b, lut, dlut, m, rho, n = _grid_inputs(axes, boresights, lut, sphere, check_uniform=True)
    counts = np.zeros(n, dtype=np.int16)
    g6 = np.zeros((1, 6), dtype=np.float32)  # unused without want_g6
    return _grid_kernel(*xyz, *hs, np.asarray(anchors, np.float64), b, lut, dlut, m, rho, counts, g6, False)


def count_links_fast(points_soa, anchors, boresights, lut) -> np.ndarray:
    """Number of closing LOS links per point (fast float32 numba kernel, one core).

    Parameters
    ----------
    points_soa : tuple of three float32 (P,) arrays ``(x, y, z)`` [m]
    anchors, boresights : (N, 3) positions [m] and unit boresights
    lut : float32 squared-reach table from :meth:`LinkModel.reach_lut`
    """
    x, y, z = points_soa
    b = np.asarray(boresights, dtype=np.float64)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    counts = np.zeros(x.shape[0], dtype=np.int16)
    return _count_links_kernel(x, y, z, np.asarray(anchors, np.float64), b, lut, counts)


def coverage_fraction_fast(points_soa, anchors, boresights, lut, k: int = 3) -> float:
    """Fraction of points that are k-covered (fast kernel)."""
    c = count_links_fast(points_soa, anchors, boresights, lut)
    return float(np.count_nonzero(c >= k)) / c.shape[0]


def to_soa(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P, 3) float -> contiguous float32 ``(x, y, z)`` arrays for the fast kernel."""
    p = np.asarray(points, dtype=np.float32)
    return (np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]), np.ascontiguousarray(p[:, 2]))
