"""Static background of an MMAUD site as a few primitives, with vectorised ray casting.

MMAUD's rig stands on a rooftop or in a car park and looks up at the sky (``docs/simulation_sources.md``
section 0 [V S1]). What a LiDAR sees besides the drone is the roof slab (beyond about
h / tan 7 deg ~ 10 m for the Mid-360), parapets, HVAC boxes, stair housings, neighbouring facades
and, in the car park, cars, lamp posts and trees; the sky returns nothing (section 5.4 [E from S1]).

Frame: the rig frame, z up, origin on the roof surface (ground z = 0) under the rig; metres.
A scene is a list of primitives, each with a diffuse reflectivity at 905 nm:

- :class:`Plane`: an infinite horizontal plane seen from above (street level, open ground);
- :class:`Box`: an axis-aligned box (the roof's own building, parapets, HVAC, facades, cars);
- :class:`Cylinder`: a vertical cylinder with a top cap (poles, lamp posts, tanks, tree trunks);
- :class:`Sphere`: a sphere (tree crowns).

:meth:`Scene.cast` returns the first hit of every ray. It is fast because each ray is tested only
against the primitives whose angular bounding box (as seen from the ray origin) contains the ray's
direction; the candidates are looked up in a 1-degree azimuth x elevation grid built once per origin.

The presets (:func:`rooftop_scene`, :func:`carpark_scene`) are fixed, seed-independent layouts
that keep the MMAUD flight region (x in [-2, 8], y in [-5, 25], z in [0.5, 25] m) clear;
:meth:`Scene.jittered` moves the movable primitives a little with a seeded generator to vary
the background between simulated recordings. Layout numbers are estimates [E] chosen so that a
Mid-360 frame holds a few thousand background returns, as the real UG2 frames do (3,900-4,400
of ~20,000 in the MMAUD UG2 validation sample, ``docs/simulation_sources.md`` section 5 [M]), with a
similar elevation spread
(most returns within a few degrees of the horizon, ground at 8-40 m, facades up to ~50 deg).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

#: Rays must travel at least this far (m) before a hit counts (avoids self-hits at the origin).
_T_MIN = 1e-4
#: The flight region of MMAUD drones (docs/simulation_sources.md section 0 [V S2, S3]); presets keep it clear.
FLIGHT_REGION = ((-2.0, -5.0, 0.5), (8.0, 25.0, 25.0))


def _no_hit(n: int, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    return np.full(n, np.inf, dtype=dtype), np.zeros(n, dtype=dtype)


@dataclass(frozen=True)
class Plane:
    """Infinite horizontal plane at ``height``, hit only from above (e.g. the street below a roof)."""

    height: float
    reflectivity: float
    movable: bool = False

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each unit ray to the plane (inf if missed) and the incidence cosine."""
        t, cos = _no_hit(len(directions), directions.dtype)
        dz = directions[:, 2]
        down = dz < 0
        if origin[2] > self.height:
            t[down] = (self.height - float(origin[2])) / dz[down]
            cos[down] = -dz[down]
        return t, cos

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo, hi)."""
        return np.array([-np.inf, -np.inf, self.height]), np.array([np.inf, np.inf, self.height])


@dataclass(frozen=True)
class Box:
    """Axis-aligned box from corner ``lo`` to corner ``hi`` (x, y, z)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    reflectivity: float
    movable: bool = True

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slab test: entry distance (inf if missed or if the origin is inside) and the incidence cosine."""
        dtype = directions.dtype
        lo = (np.asarray(self.lo) - origin).astype(dtype)
        hi = (np.asarray(self.hi) - origin).astype(dtype)
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = 1.0 / directions
            t1, t2 = lo * inverse, hi * inverse
        near, far = np.minimum(t1, t2), np.maximum(t1, t2)
        t_enter, t_exit = near.max(axis=1), far.min(axis=1)
        hit = (t_enter <= t_exit) & (t_enter > _T_MIN)
        t, cos = _no_hit(len(directions), dtype)
        t[hit] = t_enter[hit]
        face = near[hit].argmax(axis=1)  # the slab entered last is the face hit
        cos[hit] = np.abs(directions[hit][np.arange(face.size), face])
        return t, cos

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.lo, dtype=float), np.array(self.hi, dtype=float)

    def moved(self, shift: np.ndarray, height_scale: float, reflectivity_scale: float) -> Box:
        """A copy shifted horizontally, its top scaled about its base, its reflectivity scaled."""
        lo, hi = np.array(self.lo) + [shift[0], shift[1], 0.0], np.array(self.hi) + [shift[0], shift[1], 0.0]
        hi[2] = lo[2] + (hi[2] - lo[2]) * height_scale
        return replace(
            self, lo=tuple(lo), hi=tuple(hi), reflectivity=_scaled(self.reflectivity, reflectivity_scale)
        )


@dataclass(frozen=True)
class Cylinder:
    """Vertical cylinder (axis along z) with a top cap; its bottom is assumed to rest on something."""

    center: tuple[float, float]
    radius: float
    z_range: tuple[float, float]
    reflectivity: float
    movable: bool = True

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of the side or of the top cap (inf if missed) and the incidence cosine."""
        dtype = directions.dtype
        ox, oy = float(origin[0] - self.center[0]), float(origin[1] - self.center[1])
        z0, z1 = self.z_range
        dx, dy, dz = directions[:, 0], directions[:, 1], directions[:, 2]
        t, cos = _no_hit(len(directions), dtype)
        # side: |o_xy + t d_xy| = r, nearer root
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            t_side = (-b - np.sqrt(disc)) / a
        z_side = float(origin[2]) + t_side * dz
        side = (disc > 0) & (t_side > _T_MIN) & (z_side >= z0) & (z_side <= z1)
        t[side] = t_side[side]
        radial_x, radial_y = ox + t_side[side] * dx[side], oy + t_side[side] * dy[side]
        cos[side] = np.abs(radial_x * dx[side] + radial_y * dy[side]) / self.radius
        # top cap, seen from above
        if origin[2] > z1:
            with np.errstate(divide="ignore", invalid="ignore"):
                t_cap = (z1 - float(origin[2])) / dz
            cap_x, cap_y = ox + t_cap * dx, oy + t_cap * dy
            cap = (dz < 0) & (cap_x * cap_x + cap_y * cap_y <= self.radius**2) & (t_cap < t)
            t[cap] = t_cap[cap]
            cos[cap] = -dz[cap]
        return t, cos

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        (cx, cy), r = self.center, self.radius
        return np.array([cx - r, cy - r, self.z_range[0]]), np.array([cx + r, cy + r, self.z_range[1]])

    def moved(self, shift: np.ndarray, height_scale: float, reflectivity_scale: float) -> Cylinder:
        z0, z1 = self.z_range
        return replace(
            self,
            center=(self.center[0] + shift[0], self.center[1] + shift[1]),
            z_range=(z0, z0 + (z1 - z0) * height_scale),
            reflectivity=_scaled(self.reflectivity, reflectivity_scale),
        )


@dataclass(frozen=True)
class Sphere:
    """Sphere (a tree crown in the car park)."""

    center: tuple[float, float, float]
    radius: float
    reflectivity: float
    movable: bool = True

    def intersect(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearer intersection (inf if missed or if the origin is inside) and the incidence cosine."""
        dtype = directions.dtype
        rel = (origin - np.asarray(self.center)).astype(dtype)
        b = directions @ rel
        c = float(rel @ rel) - self.radius**2
        disc = b * b - c
        t, cos = _no_hit(len(directions), dtype)
        t_hit = -b - np.sqrt(np.maximum(disc, 0))
        hit = (disc > 0) & (t_hit > _T_MIN) & (c > 0)
        t[hit] = t_hit[hit]
        normal = rel + t_hit[hit, None] * directions[hit]
        cos[hit] = np.abs(np.einsum("ij,ij->i", normal, directions[hit])) / self.radius
        return t, cos

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        c, r = np.asarray(self.center, dtype=float), self.radius
        return c - r, c + r

    def moved(self, shift: np.ndarray, height_scale: float, reflectivity_scale: float) -> Sphere:
        del height_scale  # a crown keeps its height
        cx, cy, cz = self.center
        return replace(
            self,
            center=(cx + shift[0], cy + shift[1], cz),
            reflectivity=_scaled(self.reflectivity, reflectivity_scale),
        )


Primitive = Plane | Box | Cylinder | Sphere


def _scaled(reflectivity: float, scale: float) -> float:
    return float(np.clip(reflectivity * scale, 0.01, 1.0))


# ---------------------------------------------------------------------------------- angular index


@dataclass
class _AngularIndex:
    """Which primitives a ray from one origin may hit, per (elevation, azimuth) cell.

    Each primitive's angular bounding box as seen from the origin (conservative: computed from its
    axis-aligned box) marks the cells it overlaps; a ray is then tested only against the primitives
    of its own cell.
    """

    resolution: float  #: cell size (rad)
    candidates: np.ndarray  #: primitives x cells, bool
    any_candidate: np.ndarray  #: cells, bool

    @property
    def n_azimuth(self) -> int:
        return int(round(2 * np.pi / self.resolution))

    def cells(self, directions: np.ndarray) -> np.ndarray:
        """Cell index of each unit direction."""
        azimuth = np.arctan2(directions[:, 1], directions[:, 0])
        elevation = np.arcsin(np.clip(directions[:, 2], -1.0, 1.0))
        n_az = self.n_azimuth
        n_el = self.candidates.shape[1] // n_az
        i_az = np.clip(((azimuth + np.pi) / self.resolution).astype(np.int64), 0, n_az - 1)
        i_el = np.clip(((elevation + np.pi / 2) / self.resolution).astype(np.int64), 0, n_el - 1)
        return i_el * n_az + i_az


def _angular_bounds(lo: np.ndarray, hi: np.ndarray, origin: np.ndarray) -> tuple[float, float, float, float]:
    """(azimuth_lo, azimuth_hi, elevation_lo, elevation_hi) of a box seen from ``origin``, in radians.

    The azimuth bounds are (-inf, inf) when the box surrounds the origin horizontally (every azimuth).
    Elevation bounds use the nearest and farthest horizontal distances, so they hold for every point
    of the box (its corners alone would not bound a horizontal edge passing over the origin).
    """
    rel_lo, rel_hi = lo - origin, hi - origin
    gap_x = max(rel_lo[0], 0.0, -rel_hi[0])
    gap_y = max(rel_lo[1], 0.0, -rel_hi[1])
    d_min = float(np.hypot(gap_x, gap_y))
    d_max = float(np.hypot(max(abs(rel_lo[0]), abs(rel_hi[0])), max(abs(rel_lo[1]), abs(rel_hi[1]))))
    z_lo, z_hi = float(rel_lo[2]), float(rel_hi[2])
    el_hi = np.arctan2(z_hi, d_min if z_hi >= 0 else d_max)
    el_lo = np.arctan2(z_lo, d_max if z_lo >= 0 else d_min)
    if d_min <= 0.0 or not np.isfinite(d_max):
        return -np.inf, np.inf, float(el_lo), float(el_hi)
    corners_x = np.array([rel_lo[0], rel_hi[0], rel_lo[0], rel_hi[0]])
    corners_y = np.array([rel_lo[1], rel_lo[1], rel_hi[1], rel_hi[1]])
    centre = np.arctan2(corners_y.mean(), corners_x.mean())
    offsets = np.angle(np.exp(1j * (np.arctan2(corners_y, corners_x) - centre)))
    return float(centre + offsets.min()), float(centre + offsets.max()), float(el_lo), float(el_hi)


def _plane_bounds(plane: Plane, origin: np.ndarray) -> tuple[float, float, float, float] | None:
    if origin[2] <= plane.height:
        return None
    return -np.inf, np.inf, -np.pi / 2, 0.0


def _build_index(primitives: list[Primitive], origin: np.ndarray, resolution_deg: float) -> _AngularIndex:
    resolution = np.radians(resolution_deg)
    n_az, n_el = int(round(360 / resolution_deg)), int(round(180 / resolution_deg))
    margin = 1e-3  # rad; covers float32 rounding of ray angles
    candidates = np.zeros((len(primitives), n_el, n_az), dtype=bool)
    for k, primitive in enumerate(primitives):
        if isinstance(primitive, Plane):
            bounds = _plane_bounds(primitive, origin)
        else:
            bounds = _angular_bounds(*primitive.bounds(), origin)
        if bounds is None:
            continue
        az_lo, az_hi, el_lo, el_hi = bounds
        e0 = max(int(np.floor((el_lo + np.pi / 2 - margin) / resolution)), 0)
        e1 = min(int(np.floor((el_hi + np.pi / 2 + margin) / resolution)), n_el - 1)
        if np.isfinite(az_lo):
            a0 = int(np.floor((az_lo + np.pi - margin) / resolution))
            a1 = int(np.floor((az_hi + np.pi + margin) / resolution))
            columns = np.arange(a0, a1 + 1) % n_az
        else:
            columns = np.arange(n_az)
        candidates[k, e0 : e1 + 1, columns] = True
    candidates = candidates.reshape(len(primitives), -1)
    return _AngularIndex(resolution, candidates, candidates.any(axis=0))


# ------------------------------------------------------------------------------------------ scene


@dataclass
class Scene:
    """A static background: primitives and a cached angular index per ray origin."""

    name: str
    primitives: list[Primitive]
    index_resolution_deg: float = 1.0  #: cell size of the candidate grid; a speed knob only
    _indices: dict[tuple[float, float, float], _AngularIndex] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hit of each ray from ``origin`` (3,) along unit ``directions`` (N x 3).

        Returns ranges (N,; inf where nothing is hit, i.e. the sky), the diffuse reflectivity of the
        surface hit (0 where missed) and the cosine of the incidence angle (0 where missed), all in
        the dtype of ``directions`` (float32 is faster and precise to well below a millimetre at 500 m).
        The origin must lie outside every primitive.
        """
        origin = np.asarray(origin, dtype=np.float64)
        directions = np.asarray(directions)
        if directions.dtype not in (np.float32, np.float64):
            directions = directions.astype(np.float64)
        n = len(directions)
        ranges = np.full(n, np.inf, dtype=directions.dtype)
        reflectivity = np.zeros(n, dtype=directions.dtype)
        incidence = np.zeros(n, dtype=directions.dtype)
        if n == 0 or not self.primitives:
            return ranges, reflectivity, incidence
        index = self._index(origin)
        cells = index.cells(directions)
        rays = np.flatnonzero(index.any_candidate[cells])
        cells = cells[rays]
        for k, primitive in enumerate(self.primitives):
            mine = rays[index.candidates[k][cells]]
            if mine.size == 0:
                continue
            t, cos = primitive.intersect(origin, directions[mine])
            nearer = t < ranges[mine]
            hit = mine[nearer]
            ranges[hit] = t[nearer]
            reflectivity[hit] = primitive.reflectivity
            incidence[hit] = cos[nearer]
        return ranges, reflectivity, incidence

    def _index(self, origin: np.ndarray) -> _AngularIndex:
        key = (float(origin[0]), float(origin[1]), float(origin[2]))
        if key not in self._indices:
            self._indices[key] = _build_index(self.primitives, origin, self.index_resolution_deg)
        return self._indices[key]

    def jittered(
        self,
        rng: np.random.Generator,
        shift_m: float = 1.5,
        height_scale: float = 0.2,
        reflectivity_scale: float = 0.25,
        keep_clear: tuple[tuple[float, float, float], tuple[float, float, float]] = FLIGHT_REGION,
    ) -> Scene:
        """A copy whose movable primitives are shifted (uniform +-``shift_m`` in x and y), their heights
        scaled by 1 +- ``height_scale`` and reflectivities by 1 +- ``reflectivity_scale`` [E].

        A primitive that would then reach into ``keep_clear`` (the flight region) stays where it was.
        """
        clear_lo, clear_hi = np.asarray(keep_clear[0]), np.asarray(keep_clear[1])
        moved: list[Primitive] = []
        for primitive in self.primitives:
            if not primitive.movable or isinstance(primitive, Plane):
                moved.append(primitive)
                continue
            candidate = primitive.moved(
                rng.uniform(-shift_m, shift_m, size=2),
                1.0 + rng.uniform(-height_scale, height_scale),
                1.0 + rng.uniform(-reflectivity_scale, reflectivity_scale),
            )
            lo, hi = candidate.bounds()
            overlaps = bool(np.all(lo < clear_hi) and np.all(hi > clear_lo))
            moved.append(primitive if overlaps else candidate)
        return Scene(self.name, moved, self.index_resolution_deg)


# ---------------------------------------------------------------------------------------- presets

#: Diffuse reflectivities at 905 nm [E, typical published LiDAR-target values]: weathered concrete
#: 0.2-0.35, asphalt 0.08-0.15, painted walls 0.3-0.6, glass facades low (specular), foliage 0.4-0.5,
#: car paint 0.1-0.8, galvanised metal 0.3-0.5.
CONCRETE, ASPHALT, WALL, FACADE, FOLIAGE, METAL, CAR = 0.25, 0.12, 0.40, 0.22, 0.45, 0.35, 0.35


def rooftop_scene() -> Scene:
    """MMAUD's rooftop site as a fixed layout [E from the S1 figures and the real UG2 frames].

    The rig stands on a flat roof 20 m above the street, 9 m from the roof's west and south edges
    and about 14 m / 30 m from its east and north edges (so the flight region, which extends to
    +y, is over the roof), with a 1.1 m parapet along every edge, HVAC units, a stair housing, a
    water tank and antenna masts on the roof, and five neighbouring buildings 35-75 m away.
    """
    roof_lo, roof_hi, parapet = (-9.0, -9.0), (14.0, 30.0), (0.3, 1.1)  # edges (m); thickness, height
    (x0, y0), (x1, y1), (w, h) = roof_lo, roof_hi, parapet
    primitives: list[Primitive] = [
        Plane(-20.0, ASPHALT),  # the street
        Box((x0, y0, -20.0), (x1, y1, 0.0), CONCRETE, movable=False),  # the building under the rig
        Box((x0, y0, 0.0), (x0 + w, y1, h), WALL, movable=False),  # parapets
        Box((x1 - w, y0, 0.0), (x1, y1, h), WALL, movable=False),
        Box((x0, y0, 0.0), (x1, y0 + w, h), WALL, movable=False),
        Box((x0, y1 - w, 0.0), (x1, y1, h), WALL, movable=False),
        Box((-7.5, -7.0, 0.0), (-4.5, -4.5, 1.8), METAL),  # HVAC
        Box((10.0, -4.0, 0.0), (12.5, -1.0, 1.6), METAL),  # HVAC
        Box((10.5, 12.0, 0.0), (13.0, 17.0, 2.2), METAL),  # HVAC
        Box((-8.0, 8.0, 0.0), (-4.0, 13.0, 3.2), WALL),  # stair housing
        Box((9.5, 19.0, 0.0), (13.5, 26.0, 3.5), WALL),  # plant room
        Cylinder((-6.0, 22.0), 1.4, (0.0, 3.0), METAL),  # water tank
        Cylinder((12.5, 27.0), 0.08, (0.0, 6.0), METAL),  # antenna masts
        Cylinder((-6.0, -5.75), 0.06, (1.8, 5.0), METAL),  # (on the first HVAC unit)
        Box((40.0, -30.0, -20.0), (60.0, 0.0, 6.0), FACADE),  # neighbouring buildings
        Box((-55.0, 0.0, -20.0), (-35.0, 22.0, 8.0), FACADE),
        Box((-10.0, 55.0, -20.0), (25.0, 75.0, 18.0), FACADE),
        Box((26.0, 26.0, -20.0), (34.0, 34.0, 35.0), WALL),  # a tower
        Box((-30.0, -50.0, -20.0), (-10.0, -35.0, 3.0), WALL),
    ]
    return Scene("rooftop", primitives)


def carpark_scene() -> Scene:
    """MMAUD's car-park site as a fixed layout [E from the S1 figures].

    Open asphalt around the rig, rows of parked cars, lamp posts and trees along the edges, and
    low buildings 30-60 m away.
    """
    primitives: list[Primitive] = [Plane(0.0, ASPHALT)]
    car = (4.5, 1.8, 1.5)  # length, width, height (m)
    for x, y0, count in ((-7.0, -10.0, 9), (11.0, -10.0, 9), (15.0, -10.0, 9)):
        for i in range(count):
            y = y0 + i * 4.5
            primitives.append(Box((x, y, 0.0), (x + car[1], y + car[0] * 0.9, car[2]), CAR))
    for x, y in ((-10.0, -8.0), (-10.0, 10.0), (-10.0, 28.0), (19.0, -8.0), (19.0, 10.0), (19.0, 28.0)):
        primitives.append(Cylinder((x, y), 0.1, (0.0, 8.0), METAL))  # lamp posts
    for x, y in ((-13.0, -2.0), (-13.0, 17.0), (-12.0, 35.0), (22.0, 0.0), (22.0, 20.0), (5.0, 34.0)):
        primitives.append(Cylinder((x, y), 0.25, (0.0, 3.0), WALL * 0.5))  # trunks (bark ~0.2)
        primitives.append(Sphere((x, y, 5.0), 2.5, FOLIAGE))  # crowns
    primitives += [
        Box((35.0, -15.0, 0.0), (50.0, 10.0, 12.0), FACADE),
        Box((-45.0, 0.0, 0.0), (-32.0, 25.0, 9.0), FACADE),
        Box((-5.0, 50.0, 0.0), (20.0, 62.0, 15.0), FACADE),
        Box((-20.0, -45.0, 0.0), (10.0, -35.0, 8.0), WALL),
    ]
    return Scene("carpark", primitives)


SCENES = {"rooftop": rooftop_scene, "carpark": carpark_scene}


def make_scene(name: str = "rooftop", rng: np.random.Generator | None = None) -> Scene:
    """A preset scene; with ``rng``, its movable primitives are jittered (see :meth:`Scene.jittered`)."""
    try:
        scene = SCENES[name]()
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; known: {sorted(SCENES)}") from None
    return scene if rng is None else scene.jittered(rng)
