"""Structure mode: anchors slide along the bars of a large structure (jib crane, bridge).

Reconstruction of the seed's jib crane (assumptions, the seed gives no drawing data)
---------------------------------------------------------------------------------
* Inspection space: the cuboid ``x in [0, 30], y in [0, 80], z in [0, 80]`` m sampled at
  1 m cell centres -> 30 x 80 x 80 = 192,000 points (seed: "30m x 80m x 80m ... 1m").
* Mast (vertical bar): a lattice of square cross-section ``2 m`` (the seed: "the inward
  side is of small order and symmetrical") with axis ``x = 15, y = 8``, ``z in [0, 72]``.
* Jib (horizontal bar): same cross-section, axis ``x = 15, z = 70``, ``y in [2, 78]``.
* Decision variables ``[x_1..x_5, y_1..y_5]``, ``0 < x_i, y_i < 60`` (seed eq. for S*):
  a 60 m usable rail on each bar, mast stations at ``z = 5 + x_i``, jib stations at
  ``y = 15 + y_i``.
* Each variable is a "double-sided arrow" station of **4 anchors on a square**.  The seed
  does not say which way the four face, so two readings are offered (``reading``):
  ``"diagonal"`` (default): the four corners of the bar cross-section, boresights along
  the corner diagonals, perpendicular to the bar; ``"axis-aligned"``: the centres of
  the four faces, boresights along the face normals (the diagonal station turned by
  45 deg about the bar) -> 5 + 5 stations x 4 = 40 modules, as in the seed.  Each
  reading needs its own fitted range R0 (docs/placement.md).
* Radio ("measured range / directional antenna model", not given in the seed):
  ``dw1000-long-range`` budget (R0 = 30 m LOS with 0 dBi) and a 90 deg half-power
  beamwidth cos^n patch (n = 2, 7.8 dBi peak, 20 dB front-to-back), omni tag.  A point
  is covered when k = 3 links close.  No ray casting in the coverage objective (the
  bars are thin lattices).

"More freedom" adds, per station, a rotation about the bar axis and a tilt of the
boresights along the bar (see :class:`StructureProblem`).
"""

from __future__ import annotations

from uwbimu.errors import ConfigError
from dataclasses import dataclass, field

import numpy as np

from uwbimu.design.radio import Bar, CosN, LinkModel, count_links_grid, geometry_grid, lobe_sphere

__all__ = ["READINGS", "Rail", "Structure", "StructureProblem", "jib_crane", "girder_bridge", "grid_axes"]


def grid_axes(lo, hi, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell-centre coordinates of a box ``lo..hi`` at resolution ``step`` [m]."""
    return tuple(np.arange(float(a) + step / 2.0, float(b), step) for a, b in zip(lo, hi))


def _perp_basis(axis, ref) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.asarray(axis, float) / np.linalg.norm(axis)
    v = np.asarray(ref, float) - np.dot(ref, t) * t
    v /= np.linalg.norm(v)
    w = np.cross(t, v)
    return t, v, w


@dataclass
class Rail:
    """A segment along which a station of anchors slides.

    ``offsets`` and ``boresights`` of the station's anchors are given in the rail frame
    ``(t, v, w)``: ``t`` along the rail, ``v`` the projection of ``ref`` perpendicular to
    it, ``w = t x v``.  The slide parameter ``s`` in ``[0, length]`` m.
    """

    name: str
    p0: np.ndarray
    p1: np.ndarray
    ref: np.ndarray
    offsets: np.ndarray  # (m, 3) in (t, v, w)
    boresights: np.ndarray  # (m, 3) in (t, v, w)

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.asarray(self.p1) - np.asarray(self.p0)))

    def station(self, s: float, rot: float = 0.0, tilt: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """World positions (m, 3) and unit boresights (m, 3) of a station at ``s`` [m].

        ``rot`` [rad] rotates the station about the rail axis; ``tilt`` [rad] tips the
        boresights towards ``+t`` (along the rail).
        """
        t, v, w = _perp_basis(np.asarray(self.p1) - np.asarray(self.p0), self.ref)
        c, sn = np.cos(rot), np.sin(rot)
        v2, w2 = c * v + sn * w, -sn * v + c * w
        M = np.stack([t, v2, w2], axis=1)  # columns: rail frame -> world
        centre = np.asarray(self.p0, float) + s * t
        pos = centre + self.offsets @ M.T
        # Template boresights are perpendicular to the rail; tilt tips them towards +t.
        perp = np.asarray(self.boresights, float).copy()
        perp[:, 0] = 0.0
        perp /= np.maximum(np.linalg.norm(perp, axis=1, keepdims=True), 1e-12)
        b_use = np.cos(tilt) * perp + np.sin(tilt) * np.array([1.0, 0.0, 0.0])
        bw = b_use @ M.T
        return pos, bw / np.linalg.norm(bw, axis=1, keepdims=True)


READINGS = ("diagonal", "axis-aligned")


def _square_station(half: float, reading: str = "diagonal") -> tuple[np.ndarray, np.ndarray]:
    """Four anchors on a square cross-section of half-side ``half`` [m], in the rail frame.

    ``"diagonal"``: at the corners, facing outward along the diagonals; ``"axis-aligned"``:
    at the face centres, facing outward along the face normals.
    """
    if reading == "diagonal":
        d = np.array([[0.0, 1.0, 1.0], [0.0, 1.0, -1.0], [0.0, -1.0, 1.0], [0.0, -1.0, -1.0]])
        return d * half, d / np.sqrt(2.0)
    if reading == "axis-aligned":
        d = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
        return d * half, d.copy()
    raise ConfigError(f"reading must be one of {READINGS}, got {reading!r}")


@dataclass
class Structure:
    """Bars (for drawing / ray casting), rails for anchors, inspection space and radio."""

    name: str
    bars: list[Bar]
    rails: list[Rail]
    space_lo: tuple[float, float, float]
    space_hi: tuple[float, float, float]
    step: float = 1.0
    link: LinkModel = field(default_factory=LinkModel)
    k: int = 3
    stations_per_rail: list[int] = field(default_factory=list)
    reference: dict = field(default_factory=dict)  # e.g. the seed's published coverage

    def axes(self, step: float | None = None):
        return grid_axes(self.space_lo, self.space_hi, step or self.step)

    def points(self, step: float | None = None) -> np.ndarray:
        xs, ys, zs = self.axes(step)
        return np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)


def jib_crane(range_m: float = 30.0, beamwidth_deg: float = 90.0, reading: str = "diagonal") -> Structure:
    """The seed's jib crane, reconstructed as documented in the module docstring.

    ``reading`` picks how the four anchors of a station face (``"diagonal"`` or
    ``"axis-aligned"``, see the module docstring).
    """
    half = 1.0
    off, bor = _square_station(half, reading)
    mast_axis = (15.0, 8.0)
    jib_z = 70.0
    bars = []
    # Mast and jib as four chords each (lattice corners), radius 0.1 m.
    for dx in (-half, half):
        for dy in (-half, half):
            bars.append(Bar((mast_axis[0] + dx, mast_axis[1] + dy, 0.0), (mast_axis[0] + dx, mast_axis[1] + dy, 72.0), 0.1))
        for dz in (-half, half):
            bars.append(Bar((15.0 + dx, 2.0, jib_z + dz), (15.0 + dx, 78.0, jib_z + dz), 0.1))
    rails = [
        Rail("mast", np.array([15.0, 8.0, 5.0]), np.array([15.0, 8.0, 65.0]), np.array([1.0, 0.0, 0.0]), off, bor),
        Rail("jib", np.array([15.0, 15.0, jib_z]), np.array([15.0, 75.0, jib_z]), np.array([1.0, 0.0, 0.0]), off, bor),
    ]
    link = LinkModel(max_range=range_m, anchor_pattern=CosN(beamwidth_deg))
    return Structure("jib-crane", bars, rails, (0.0, 0.0, 0.0), (30.0, 80.0, 80.0), 1.0, link, 3,
                     [5, 5], {"seed_coverage": 0.913, "seed_modules": 40, "reading": reading})


def girder_bridge(range_m: float = 30.0, beamwidth_deg: float = 90.0) -> Structure:
    """A generic two-girder bridge (assumed geometry, the seed only names bridges).

    Deck 80 m long (x) and 10 m wide (girders at y = 0 and y = 10, z = 15 m) on two
    piers at x = 25 and x = 55.  The inspection space is the GPS-denied volume under and
    beside the deck, ``x in [0, 80], y in [-10, 20], z in [0, 14]``.  Stations of 4
    anchors (square of 1 m) slide along each girder's 78 m rail and up two of the
    piers (z 1..13 m); default one station per rail = 16 anchors.  Piers and girders
    are obstacles for the ray-cast check of the final layout.
    """
    half = 0.5
    off, bor = _square_station(half)
    bars = [
        Bar((0.0, 0.0, 15.0), (80.0, 0.0, 15.0), 0.6),
        Bar((0.0, 10.0, 15.0), (80.0, 10.0, 15.0), 0.6),
    ]
    for px in (25.0, 55.0):
        for py in (0.0, 10.0):
            bars.append(Bar((px, py, 0.0), (px, py, 15.0), 0.8))
    rails = [
        Rail("girder-south", np.array([1.0, 0.0, 14.0]), np.array([79.0, 0.0, 14.0]), np.array([0.0, 1.0, 0.0]), off, bor),
        Rail("girder-north", np.array([1.0, 10.0, 14.0]), np.array([79.0, 10.0, 14.0]), np.array([0.0, 1.0, 0.0]), off, bor),
        # Piers give the height spread that deck-only layouts lack (flat -> poor z).
        Rail("pier-25-south", np.array([25.0, 0.0, 1.0]), np.array([25.0, 0.0, 13.0]), np.array([1.0, 0.0, 0.0]), off, bor),
        Rail("pier-55-north", np.array([55.0, 10.0, 1.0]), np.array([55.0, 10.0, 13.0]), np.array([1.0, 0.0, 0.0]), off, bor),
    ]
    link = LinkModel(max_range=range_m, anchor_pattern=CosN(beamwidth_deg), obstacles=list(bars))
    return Structure("girder-bridge", bars, rails, (0.0, -10.0, 0.0), (80.0, 20.0, 14.0), 1.0, link, 3, [1, 1, 1, 1])


class StructureProblem:
    """Decision vector -> anchors -> k-coverage of the structure's grid (picklable).

    Parameters
    ----------
    structure : the :class:`Structure`
    stations_per_rail : number of stations on each rail (seed: [5, 5])
    freedom : ``"seed"`` (one slide variable per station, the seed's 10 variables),
        ``"rotate"`` (+ rotation about the bar per station), or ``"rotate-tilt"``
        (+ boresight tilt along the bar per station)
    step : grid resolution [m] (structure's default when None)
    objective : ``"coverage"`` (the seed's: fraction of points with >= k links) or
        ``"geometric"`` (fraction with >= k links AND PDOP <= ``pdop_max``)
    station_rotation : common rotation [rad] of every station about its bar, added to the
        per-station rotation (0: the structure's reading as built); used to attribute a
        gain to orientation alone with the seed's 10 variables
    """

    def __init__(self, structure: Structure, stations_per_rail=None, freedom: str = "seed", step=None,
                 objective: str = "coverage", pdop_max: float = 5.0, station_rotation: float = 0.0):
        if freedom not in ("seed", "rotate", "rotate-tilt"):
            raise ConfigError(f"freedom must be seed|rotate|rotate-tilt, got {freedom!r}")
        if objective not in ("coverage", "geometric"):
            raise ConfigError(f"objective must be coverage|geometric, got {objective!r}")
        self.objective = objective
        self.pdop_max = float(pdop_max)
        self.structure = structure
        self.spr = list(stations_per_rail or structure.stations_per_rail)
        if len(self.spr) != len(structure.rails):
            raise ConfigError("stations_per_rail needs one count per rail")
        self.freedom = freedom
        self.station_rotation = float(station_rotation)
        self.axes = structure.axes(step)
        self.lut = structure.link.reach_lut()
        self.sphere = lobe_sphere(self.lut)
        self.k = structure.k
        self.station_rails = [r for r, n in enumerate(self.spr) for _ in range(n)]
        self.n_stations = len(self.station_rails)
        self.per = {"seed": 1, "rotate": 2, "rotate-tilt": 3}[freedom]

    @property
    def n_points(self) -> int:
        return int(np.prod([len(a) for a in self.axes]))

    @property
    def bounds(self) -> list[tuple[float, float]]:
        b = []
        for r in self.station_rails:
            b.append((0.0, self.structure.rails[r].length))
        if self.per >= 2:
            b += [(-np.pi / 4, np.pi / 4)] * self.n_stations  # square station: 90 deg symmetry
        if self.per >= 3:
            b += [(-np.pi / 3, np.pi / 3)] * self.n_stations
        return b

    def decode(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Anchors (N, 3) and boresights (N, 3) of a decision vector."""
        x = np.asarray(x, dtype=float)
        n = self.n_stations
        pos, bor = [], []
        for i, r in enumerate(self.station_rails):
            rot = self.station_rotation + (x[n + i] if self.per >= 2 else 0.0)
            tilt = x[2 * n + i] if self.per >= 3 else 0.0
            p, b = self.structure.rails[r].station(x[i], rot, tilt)
            pos.append(p)
            bor.append(b)
        return np.vstack(pos), np.vstack(bor)

    def counts(self, x) -> np.ndarray:
        a, b = self.decode(x)
        return count_links_grid(self.axes, a, b, self.lut, self.sphere)

    def coverage(self, x) -> float:
        c = self.counts(x)
        return float(np.count_nonzero(c >= self.k)) / c.shape[0]

    def geometric_coverage(self, x) -> float:
        """Fraction of points with >= k links and PDOP <= ``pdop_max``."""
        from uwbimu.design.placement import pdop_from_g6

        a, b = self.decode(x)
        c, g6 = geometry_grid(self.axes, a, b, self.lut, self.sphere)
        ok = c >= self.k
        pd_ = pdop_from_g6(g6[ok].astype(np.float64), cap=np.inf)
        return float(np.count_nonzero(pd_ <= self.pdop_max)) / c.shape[0]

    def __call__(self, x) -> float:
        """Objective to minimise: ``1 - coverage`` (or ``1 - geometric coverage``)."""
        if self.objective == "geometric":
            return 1.0 - self.geometric_coverage(x)
        return 1.0 - self.coverage(x)
