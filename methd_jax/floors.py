"""Floors: the static obstacles a robot drives among, as fixed-capacity pytrees.

A :class:`Floor` holds circles (cylinders seen from above) and convex polygons (boxes, triangles,
walls), padded to a static capacity with validity masks so that thousands of different floors batch
under ``jax.vmap``. Floors come from plain primitives (:meth:`Floor.from_primitives`, validated on
the host), from the procedural generator (:func:`generate`, the thesis's "tower floors" made fresh on
device), or from the lab twin asset (:func:`lab`).

Conventions: polygons are stored counter-clockwise; a polygon with fewer vertices than the capacity
repeats its last vertex, which adds only zero-length edges, so kernels need no vertex mask to be
correct (the mask is kept for export and inspection). ``bounds`` is the free interior
``(xmin, ymin, xmax, ymax)`` in which robots and users may be placed.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import json
import math
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


def _assets() -> Path:
    """The data folder: the checkout's ``assets/``, installed as the package ``methd_jax.assets``
    (a wheel carries it; an editable install maps it to the checkout)."""
    try:
        return Path(str(importlib.resources.files("methd_jax.assets")))
    except ModuleNotFoundError:  # run from a checkout that was never installed
        return Path(__file__).resolve().parent.parent / "assets"


ASSETS = _assets()
LAB_ASSET = ASSETS / "lab_floor.json"


class FloorSpecError(ValueError):
    """A floor description that cannot be turned into a valid :class:`Floor`."""


@struct.dataclass
class Floor:
    """Static obstacles of one floor (add a leading batch axis with ``jax.vmap``)."""

    circles: jax.Array  # (C, 3) centre x, y and radius, metres
    circle_mask: jax.Array  # (C,) bool, True where the circle exists
    polygons: jax.Array  # (P, V, 2) convex, counter-clockwise, padded by repeating the last vertex
    polygon_mask: jax.Array  # (P,) bool, True where the polygon exists
    vertex_mask: jax.Array  # (P, V) bool, True for a polygon's own (not padding) vertices
    bounds: jax.Array  # (4,) free interior xmin, ymin, xmax, ymax

    @property
    def capacity(self) -> tuple[int, int, int]:
        """Static sizes ``(max circles, max polygons, vertices per polygon)``."""
        return (self.circles.shape[-2], self.polygons.shape[-3], self.polygons.shape[-2])

    @classmethod
    def from_primitives(
        cls,
        circles: Sequence[Sequence[float]] = (),
        polygons: Sequence[Sequence[Sequence[float]]] = (),
        *,
        bounds: Sequence[float] | None = None,
        max_circles: int | None = None,
        max_polygons: int | None = None,
        max_vertices: int | None = None,
    ) -> Floor:
        """Builds a floor from ``circles=[(x, y, r), ...]`` and convex ``polygons=[[(x, y), ...]]``.

        Polygons may be given in either winding order; they are stored counter-clockwise. Capacities
        default to the number given (at least one slot, so that array shapes are never empty).
        Everything is checked here, on the host, and a bad obstacle is named in the error.
        """
        circ = _check_circles(circles)
        polys = [_check_polygon(i, p) for i, p in enumerate(polygons)]
        max_circles = max(1, len(circ)) if max_circles is None else max_circles
        max_polygons = max(1, len(polys)) if max_polygons is None else max_polygons
        longest = max((len(p) for p in polys), default=3)
        max_vertices = max(3, longest) if max_vertices is None else max_vertices
        if len(circ) > max_circles:
            raise FloorSpecError(
                f"{len(circ)} circles exceed the capacity of {max_circles} (circle {max_circles} "
                "is the first that does not fit)"
            )
        if len(polys) > max_polygons:
            raise FloorSpecError(
                f"{len(polys)} polygons exceed the capacity of {max_polygons} (polygon "
                f"{max_polygons} is the first that does not fit)"
            )
        for i, p in enumerate(polys):
            if len(p) > max_vertices:
                raise FloorSpecError(
                    f"polygon {i} has {len(p)} vertices, more than the capacity of {max_vertices}"
                )

        c_arr = np.zeros((max_circles, 3), np.float32)
        c_mask = np.zeros(max_circles, bool)
        if len(circ):
            c_arr[: len(circ)] = circ
            c_mask[: len(circ)] = True
        p_arr = np.zeros((max_polygons, max_vertices, 2), np.float32)
        p_mask = np.zeros(max_polygons, bool)
        v_mask = np.zeros((max_polygons, max_vertices), bool)
        for i, p in enumerate(polys):
            p_arr[i, : len(p)] = p
            p_arr[i, len(p) :] = p[-1]
            p_mask[i] = True
            v_mask[i, : len(p)] = True

        if bounds is None:
            pts = [c[:2] - c[2] for c in circ] + [c[:2] + c[2] for c in circ]
            pts += [v for p in polys for v in p]
            if not pts:
                raise FloorSpecError("an empty floor needs explicit bounds=(xmin, ymin, xmax, ymax)")
            pts = np.asarray(pts)
            bounds = (*pts.min(0), *pts.max(0))
        b = np.asarray(bounds, np.float64)
        if b.shape != (4,) or not np.all(np.isfinite(b)) or b[0] >= b[2] or b[1] >= b[3]:
            raise FloorSpecError(f"bounds must be finite (xmin, ymin, xmax, ymax), got {bounds}")
        return cls(
            circles=jnp.asarray(c_arr),
            circle_mask=jnp.asarray(c_mask),
            polygons=jnp.asarray(p_arr),
            polygon_mask=jnp.asarray(p_mask),
            vertex_mask=jnp.asarray(v_mask),
            bounds=jnp.asarray(b, jnp.float32),
        )

    def pad(self, max_circles: int, max_polygons: int, max_vertices: int) -> Floor:
        """The same floor with larger capacity, so it batches with floors of that capacity."""
        C, P, V = self.capacity
        if self.circles.ndim != 2:
            raise ValueError("pad() takes a single floor, not a batch")
        if max_circles < C or max_polygons < P or max_vertices < V:
            raise ValueError(
                f"cannot shrink capacity {(C, P, V)} to {(max_circles, max_polygons, max_vertices)}"
            )
        last = self.polygons[:, -1:, :]
        polys = jnp.concatenate([self.polygons, jnp.repeat(last, max_vertices - V, 1)], 1)
        polys = jnp.concatenate([polys, jnp.zeros((max_polygons - P, max_vertices, 2))], 0)
        vmask = jnp.pad(self.vertex_mask, ((0, max_polygons - P), (0, max_vertices - V)))
        return Floor(
            circles=jnp.pad(self.circles, ((0, max_circles - C), (0, 0))),
            circle_mask=jnp.pad(self.circle_mask, (0, max_circles - C)),
            polygons=polys,
            polygon_mask=jnp.pad(self.polygon_mask, (0, max_polygons - P)),
            vertex_mask=vmask,
            bounds=self.bounds,
        )

    def primitives(self) -> tuple[list[tuple[float, float, float]], list[list[tuple[float, float]]]]:
        """The valid circles and polygons as plain Python lists (host side, single floor)."""
        if self.circles.ndim != 2:
            raise ValueError("primitives() takes a single floor, not a batch")
        circ = np.asarray(self.circles)[np.asarray(self.circle_mask)]
        polys, vm = np.asarray(self.polygons), np.asarray(self.vertex_mask)
        pm = np.asarray(self.polygon_mask)
        circles = [tuple(map(float, c)) for c in circ]
        polygons = [[tuple(map(float, v)) for v in polys[i][vm[i]]] for i in np.flatnonzero(pm)]
        return circles, polygons


# ----------------------------------------------------------------------------------------------
# Host-side validation


def _check_circles(circles) -> np.ndarray:
    out = []
    for i, c in enumerate(circles):
        try:
            arr = np.asarray(c, np.float64)
        except (TypeError, ValueError) as e:
            raise FloorSpecError(f"circle {i} is not a triple of numbers (x, y, r): {c!r}") from e
        if arr.shape != (3,):
            raise FloorSpecError(f"circle {i} must be (x, y, r), got {c!r}")
        if not np.all(np.isfinite(arr)):
            raise FloorSpecError(f"circle {i} has a non-finite coordinate: {c!r}")
        if arr[2] <= 0:
            raise FloorSpecError(f"circle {i} has a non-positive radius {arr[2]}")
        out.append(arr)
    return np.asarray(out, np.float64).reshape(-1, 3)


def _check_polygon(i: int, poly) -> np.ndarray:
    try:
        p = np.asarray(poly, np.float64)
    except (TypeError, ValueError) as e:
        raise FloorSpecError(f"polygon {i} is not a list of (x, y) vertices: {poly!r}") from e
    if p.ndim != 2 or p.shape[1] != 2:
        raise FloorSpecError(f"polygon {i} must be a list of (x, y) vertices, got shape {p.shape}")
    if len(p) < 3:
        raise FloorSpecError(f"polygon {i} has {len(p)} vertices; a polygon needs at least 3")
    if not np.all(np.isfinite(p)):
        raise FloorSpecError(f"polygon {i} has a non-finite coordinate")
    edges = np.roll(p, -1, 0) - p
    lengths = np.linalg.norm(edges, axis=1)
    scale = max(1.0, float(np.abs(p).max()))
    if np.any(lengths < 1e-6 * scale):
        j = int(np.argmin(lengths))
        raise FloorSpecError(f"polygon {i} is degenerate: vertices {j} and {(j + 1) % len(p)} coincide")
    area2 = float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
    if abs(area2) < 1e-9 * scale**2:
        raise FloorSpecError(f"polygon {i} is degenerate: it has zero area")
    if area2 < 0:  # clockwise: store counter-clockwise
        p = p[::-1].copy()
        edges = np.roll(p, -1, 0) - p
    turn = edges[:, 0] * np.roll(edges[:, 1], -1) - edges[:, 1] * np.roll(edges[:, 0], -1)
    if np.any(turn < -1e-9 * scale**2):
        raise FloorSpecError(f"polygon {i} is not convex (it turns clockwise at a vertex)")
    # All left turns but winding more than once around (a pentagram) is not convex either.
    headings = np.arctan2(edges[:, 1], edges[:, 0])
    total = np.sum((np.roll(headings, -1) - headings) % (2 * math.pi))
    if total > 2 * math.pi + 1e-6:
        raise FloorSpecError(f"polygon {i} is not convex (it winds around more than once)")
    return p


# ----------------------------------------------------------------------------------------------
# Procedural floors


@dataclasses.dataclass(frozen=True)
class FloorConfig:
    """Procedural floor ("tower floor") parameters. Static: it fixes array shapes."""

    room_size: tuple[float, float] = (10.0, 14.0)
    """Range of the interior's side lengths (each side drawn independently), metres."""
    wall_thickness: float = 0.2
    """Thickness of the four outer walls, metres (0 builds a floor without walls)."""
    num_circles: tuple[int, int] = (12, 12)
    """Inclusive range of the number of cylinders; the upper end is the circle capacity."""
    circle_radius: tuple[float, float] = (0.15, 0.6)
    """Range of cylinder radii, metres."""
    num_polygons: tuple[int, int] = (12, 12)
    """Inclusive range of the number of boxes and triangles; the upper end (+4 walls) is capacity."""
    triangle_fraction: float = 0.5
    """Probability that a polygon is a triangle rather than a rotated box."""
    box_side: tuple[float, float] = (0.3, 1.6)
    """Range of box side lengths, metres."""
    triangle_radius: tuple[float, float] = (0.3, 0.9)
    """Range of a triangle's circumradius, metres."""

    def __post_init__(self):
        def check_range(name, lo, hi, low_ok):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi and lo >= low_ok):
                raise ValueError(f"FloorConfig.{name} must be an ordered range >= {low_ok}, got {(lo, hi)}")

        check_range("room_size", *self.room_size, 1.0)
        check_range("num_circles", *self.num_circles, 0)
        check_range("num_polygons", *self.num_polygons, 0)
        check_range("circle_radius", *self.circle_radius, 1e-3)
        check_range("box_side", *self.box_side, 1e-3)
        check_range("triangle_radius", *self.triangle_radius, 1e-3)
        if not 0 <= self.triangle_fraction <= 1:
            raise ValueError(f"FloorConfig.triangle_fraction must be in [0, 1], got {self.triangle_fraction}")
        if self.wall_thickness < 0:
            raise ValueError(f"FloorConfig.wall_thickness must be >= 0, got {self.wall_thickness}")
        biggest = max(2 * self.circle_radius[1], math.sqrt(2) * self.box_side[1], 2 * self.triangle_radius[1])
        if biggest >= self.room_size[0]:
            raise ValueError(f"obstacles up to {biggest:.2f} m do not fit a room of {self.room_size[0]} m")

    @property
    def has_walls(self) -> bool:
        return self.wall_thickness > 0

    @property
    def capacity(self) -> tuple[int, int, int]:
        """``(max circles, max polygons, vertices)`` of the floors this config generates."""
        return (max(1, self.num_circles[1]), max(1, self.num_polygons[1] + 4 * self.has_walls), 4)


def walls(bounds: jax.Array, thickness: float) -> jax.Array:
    """Four wall boxes ``(4, 4, 2)`` (counter-clockwise) just outside the interior ``bounds``."""
    x0, y0, x1, y1 = bounds[0], bounds[1], bounds[2], bounds[3]
    t = thickness

    def box(ax, ay, bx, by):
        return jnp.stack([jnp.stack([ax, ay]), jnp.stack([bx, ay]), jnp.stack([bx, by]), jnp.stack([ax, by])])

    return jnp.stack(
        [
            box(x0 - t, y0 - t, x1 + t, y0),  # south
            box(x0 - t, y1, x1 + t, y1 + t),  # north
            box(x0 - t, y0, x0, y1),  # west
            box(x1, y0, x1 + t, y1),  # east
        ]
    )


def generate(key: jax.Array, cfg: FloorConfig = FloorConfig()) -> Floor:
    """A random floor of cylinders, rotated boxes and triangles inside four walls.

    Every obstacle lies wholly inside the interior. Pure and jittable; ``jax.vmap`` over keys gives
    a batch of distinct floors in one call. ``cfg`` must be passed as a static (closed-over) value.
    """
    C = cfg.capacity[0]
    nP = cfg.num_polygons[1]
    k = jax.random.split(key, 12)
    size = jax.random.uniform(k[0], (2,), minval=cfg.room_size[0], maxval=cfg.room_size[1])
    half = 0.5 * size
    bounds = jnp.concatenate([-half, half])

    # Cylinders, centred so that they lie inside the interior.
    r = jax.random.uniform(k[1], (C,), minval=cfg.circle_radius[0], maxval=cfg.circle_radius[1])
    u = jax.random.uniform(k[2], (C, 2), minval=-1.0, maxval=1.0)
    centres = u * (half - r[:, None])
    n_c = jax.random.randint(k[3], (), cfg.num_circles[0], cfg.num_circles[1] + 1)
    circle_mask = jnp.arange(C) < n_c
    if cfg.num_circles[1] == 0:
        circle_mask = jnp.zeros((C,), bool)

    # Boxes and triangles around the origin, rotated, then placed inside the interior.
    sides = jax.random.uniform(k[4], (nP, 2), minval=cfg.box_side[0], maxval=cfg.box_side[1])
    box = 0.5 * sides[:, None, :] * jnp.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    # Triangle vertices at three well separated angles on a circle: convex and never degenerate.
    gaps = jax.random.uniform(k[5], (nP, 3), minval=0.5, maxval=1.5)
    ang = jnp.cumsum(2 * jnp.pi * gaps / gaps.sum(1, keepdims=True), 1)
    rad = jax.random.uniform(k[6], (nP, 1), minval=cfg.triangle_radius[0], maxval=cfg.triangle_radius[1])
    tri = rad[..., None] * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
    tri = jnp.concatenate([tri, tri[:, 2:3]], 1)
    is_tri = jax.random.bernoulli(k[7], cfg.triangle_fraction, (nP,))
    shape = jnp.where(is_tri[:, None, None], tri, box)
    theta = jax.random.uniform(k[8], (nP,), maxval=2 * jnp.pi)
    c, s = jnp.cos(theta)[:, None], jnp.sin(theta)[:, None]
    shape = jnp.stack([c * shape[..., 0] - s * shape[..., 1], s * shape[..., 0] + c * shape[..., 1]], -1)
    extent = jnp.max(jnp.abs(shape), axis=1)  # (nP, 2) half-extent of each shape's bounding box
    u = jax.random.uniform(k[9], (nP, 2), minval=-1.0, maxval=1.0)
    polys = shape + (u * (half - extent))[:, None, :]
    vmask = jnp.where(is_tri[:, None], jnp.array([True, True, True, False]), True)
    n_p = jax.random.randint(k[10], (), cfg.num_polygons[0], cfg.num_polygons[1] + 1)
    poly_mask = jnp.arange(nP) < n_p

    if cfg.has_walls:
        polys = jnp.concatenate([polys, walls(bounds, cfg.wall_thickness)], 0)
        vmask = jnp.concatenate([vmask, jnp.ones((4, 4), bool)], 0)
        poly_mask = jnp.concatenate([poly_mask, jnp.ones((4,), bool)], 0)
    if nP == 0 and not cfg.has_walls:  # keep one empty slot so shapes are never zero-sized
        polys, vmask, poly_mask = jnp.zeros((1, 4, 2)), jnp.zeros((1, 4), bool), jnp.zeros((1,), bool)
    return Floor(
        circles=jnp.concatenate([centres, r[:, None]], 1),
        circle_mask=circle_mask,
        polygons=polys,
        polygon_mask=poly_mask,
        vertex_mask=vmask,
        bounds=bounds,
    )


def generate_batch(key: jax.Array, n: int, cfg: FloorConfig = FloorConfig()) -> Floor:
    """``n`` distinct floors from one jitted call (a leading batch axis on every field)."""
    return _generate_batch(key, n, cfg)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _generate_batch(key, n, cfg):
    return jax.vmap(lambda k: generate(k, cfg))(jax.random.split(key, n))


# ----------------------------------------------------------------------------------------------
# The lab twin


MAX_ROOM = 1000.0
"""Largest side of a floor read from a file, m (float32 keeps millimetres up to about this size)."""


def lab(path: str | Path = LAB_ASSET, **capacity) -> Floor:
    """The 11 m x 13 m lab twin from its JSON asset (see ``assets/README.md`` for the layout).

    Keyword ``max_circles`` / ``max_polygons`` / ``max_vertices`` pad it to a batch's capacity.
    """
    path = Path(path)
    try:
        spec = json.loads(path.read_text())
    except FileNotFoundError:
        raise FloorSpecError(f"{path}: lab floor asset not found") from None
    except json.JSONDecodeError as e:
        raise FloorSpecError(f"{path}: not valid JSON ({e})") from None
    try:
        size, thickness, obstacles = spec["size"], spec["wall_thickness"], spec["obstacles"]
        ok_size = (
            isinstance(size, list)
            and len(size) == 2
            and all(isinstance(v, int | float) and 1.0 <= v <= MAX_ROOM for v in size)
        )
        if not ok_size:
            raise FloorSpecError(
                f"{path}: size must be two side lengths in [1, {MAX_ROOM:g}] m, got {size!r}"
            )
        if not (isinstance(thickness, int | float) and 0 <= thickness <= 10):
            raise FloorSpecError(f"{path}: wall_thickness must be in [0, 10] m, got {thickness!r}")
        if not (isinstance(obstacles, list) and all(isinstance(o, dict) for o in obstacles)):
            raise FloorSpecError(f"{path}: obstacles must be a list of objects, got {obstacles!r}")
        half = 0.5 * np.asarray(size, np.float64)
        bounds = np.concatenate([-half, half])
        circles = [o["circle"] for o in spec["obstacles"] if "circle" in o]
        polygons = [o["polygon"] for o in spec["obstacles"] if "polygon" in o]
        polygons += [p.tolist() for p in np.asarray(walls(jnp.asarray(bounds), thickness))]
    except (KeyError, TypeError) as e:
        raise FloorSpecError(f"{path}: missing or malformed field {e}") from None
    try:
        return Floor.from_primitives(circles, polygons, bounds=bounds, **capacity)
    except FloorSpecError as e:
        raise FloorSpecError(f"{path}: {e}") from None


# ----------------------------------------------------------------------------------------------
# Free-space queries


def signed_distance(floor: Floor, xy: jax.Array) -> jax.Array:
    """Distance from point ``xy`` ``(2,)`` to the nearest obstacle; negative inside one."""
    d_circ = jnp.linalg.norm(floor.circles[:, :2] - xy, axis=-1) - floor.circles[:, 2]
    d_circ = jnp.min(jnp.where(floor.circle_mask, d_circ, jnp.inf))

    v0 = floor.polygons - xy  # (P, V, 2) vertices relative to the point
    v1 = jnp.roll(v0, -1, axis=1)
    e = v1 - v0
    ee = jnp.sum(e * e, -1)
    # Distance to each edge segment (zero-length padding edges reduce to their vertex).
    t = jnp.clip(-jnp.sum(v0 * e, -1) / jnp.where(ee > 0, ee, 1.0), 0.0, 1.0)
    closest = v0 + t[..., None] * e
    d_edge = jnp.min(jnp.linalg.norm(closest, axis=-1), axis=-1)
    # Inside a counter-clockwise polygon the point is left of (or on) every edge.
    inside = jnp.all(e[..., 0] * (-v0[..., 1]) - e[..., 1] * (-v0[..., 0]) >= 0, axis=-1)
    d_poly = jnp.where(inside, -d_edge, d_edge)
    d_poly = jnp.min(jnp.where(floor.polygon_mask, d_poly, jnp.inf))
    return jnp.minimum(d_circ, d_poly)


def is_free(floor: Floor, xy: jax.Array, radius: float | jax.Array) -> jax.Array:
    """True where a disc of ``radius`` at ``xy`` lies inside the bounds and touches no obstacle."""
    b = floor.bounds
    inside = (xy[0] - radius >= b[0]) & (xy[1] - radius >= b[1])
    inside &= (xy[0] + radius <= b[2]) & (xy[1] + radius <= b[3])
    return inside & (signed_distance(floor, xy) >= radius)


def clearance(floor: Floor, xy: jax.Array) -> jax.Array:
    """Distance from ``xy`` (2,) to the nearest obstacle or edge of the bounds; negative outside."""
    b = floor.bounds
    to_bounds = jnp.min(jnp.stack([xy[0] - b[0], xy[1] - b[1], b[2] - xy[0], b[3] - xy[1]]))
    return jnp.minimum(signed_distance(floor, xy), to_bounds)


def obstacle_discs(floor: Floor, widen: float = 0.0) -> tuple[jax.Array, jax.Array]:
    """``(discs (C + 3P, 3), mask (C + 3P,))``: the obstacles inside the interior as discs (x, y,
    radius) widened by ``widen``. A cylinder is its own disc; a box is three equal discs along its
    long side that together cover it (one disc would make a long bench a wide one); any other
    polygon one disc about its vertices' mean through its farthest vertex. The walls (polygons
    whose centre lies outside the interior) are left out: a disc round a wall would cover the room."""
    own = floor.vertex_mask
    n = jnp.maximum(jnp.sum(own, 1), 1)
    centre = jnp.sum(jnp.where(own[..., None], floor.polygons, 0.0), 1) / n[:, None]
    reach = jnp.max(jnp.where(own, jnp.linalg.norm(floor.polygons - centre[:, None], axis=-1), 0.0), 1)
    p = floor.polygons
    e0, e1 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 1]
    l0, l1 = jnp.linalg.norm(e0, axis=-1), jnp.linalg.norm(e1, axis=-1)
    long_ = jnp.where((l0 >= l1)[:, None], e0, e1)  # the long side, as a vector
    length, width = jnp.maximum(l0, l1), jnp.minimum(l0, l1)
    is_box = n == 4
    offsets = jnp.array([-1.0, 0.0, 1.0]) / 3.0
    centres = centre[:, None] + jnp.where(is_box[:, None, None], offsets[None, :, None] * long_[:, None], 0.0)
    radius = jnp.where(is_box, jnp.hypot(length / 6.0, width / 2.0), reach)
    b = floor.bounds
    inside = (centre[:, 0] > b[0]) & (centre[:, 0] < b[2]) & (centre[:, 1] > b[1]) & (centre[:, 1] < b[3])
    pmask = floor.polygon_mask & inside
    pmask = jnp.stack([pmask & is_box, pmask, pmask & is_box], 1)  # one disc for a non-box
    polys = jnp.concatenate([centres, jnp.broadcast_to(radius[:, None, None], (*centres.shape[:2], 1))], -1)
    discs = jnp.concatenate([floor.circles, polys.reshape(-1, 3)], 0) + jnp.array([0.0, 0.0, widen])
    return discs, jnp.concatenate([floor.circle_mask, pmask.reshape(-1)])


def push_clear(
    floor: Floor,
    xy: jax.Array,
    radius: float,
    *,
    avoid: jax.Array | None = None,
    avoid_radius: float = 0.0,
    iterations: int = 4,
) -> jax.Array:
    """``xy`` (2,) moved out of obstacles until a disc of ``radius`` is free, and away from every
    point of ``avoid`` (K, 2) to ``avoid_radius``: alternating steps along the gradient of
    :func:`clearance` and away from the points. Exact in one step next to a single obstacle; among
    several, each step only reduces the overlap, so a point in a gap too narrow for the disc ends
    where the overlaps balance. Points already clear do not move."""
    # central differences, not autodiff: the distance has kinks (vertices, ties between obstacles,
    # a wall's edge on the bounds) where its derivative is undefined
    h = jnp.array([[1e-3, 0.0], [-1e-3, 0.0], [0.0, 1e-3], [0.0, -1e-3]])
    start = xy
    for _ in range(iterations):
        d = clearance(floor, xy)
        c = jax.vmap(lambda p: clearance(floor, p))(xy + h)
        g = jnp.stack([c[0] - c[1], c[2] - c[3]])
        g = g / jnp.maximum(jnp.linalg.norm(g), 1e-9)
        xy = xy + jnp.maximum(radius - d, 0.0) * g
        if avoid is not None:
            away = xy - avoid
            dist = jnp.linalg.norm(away, axis=-1, keepdims=True)
            push = jnp.maximum(avoid_radius - dist, 0.0) * away / jnp.maximum(dist, 1e-6)
            xy = xy + jnp.sum(push, axis=0)
    return jnp.where(jnp.all(jnp.isfinite(xy)), xy, start)


# ----------------------------------------------------------------------------------------------
# MJCF export


def _is_rectangle(p: np.ndarray) -> bool:
    if len(p) != 4:
        return False
    e = np.roll(p, -1, 0) - p
    dots = np.abs(np.sum(e * np.roll(e, -1, 0), 1)) / np.prod(
        [np.linalg.norm(e, axis=1), np.linalg.norm(np.roll(e, -1, 0), axis=1)], axis=0
    )
    return bool(np.all(dots < 1e-5))  # float32 corners of rotated boxes are off by ~2e-6


def to_mjcf(
    floor: Floor,
    *,
    height: float = 1.0,
    circle_geom: str = "cylinder",
    model_name: str = "floor",
) -> str:
    """An MJCF scene of the floor's obstacles, standing on z = 0 and ``height`` tall.

    Circles become ``cylinder`` geoms (or ``capsule``: MJX's ray caster has no cylinder, and a tall
    capsule answers horizontal rays at mid-height the same); rectangles become rotated ``box`` geoms;
    other polygons become prism meshes. A material is attached because ``mjx.ray`` needs one.
    """
    if circle_geom not in ("cylinder", "capsule"):
        raise ValueError(f"circle_geom must be 'cylinder' or 'capsule', got {circle_geom!r}")
    circles, polygons = floor.primitives()
    h = 0.5 * height
    assets, geoms = [], []
    for i, (x, y, r) in enumerate(circles):
        half = h if circle_geom == "cylinder" else 2.0 * height  # capsule caps far above rays
        geoms.append(
            f'<geom name="circle{i}" type="{circle_geom}" pos="{x:.9g} {y:.9g} {h:.9g}" '
            f'size="{r:.9g} {half:.9g}" material="obstacle"/>'
        )
    for i, p in enumerate(polygons):
        p = np.asarray(p, np.float64)
        if _is_rectangle(p):
            e0, e1 = p[1] - p[0], p[2] - p[1]
            centre = p.mean(0)
            yaw = math.atan2(e0[1], e0[0])
            geoms.append(
                f'<geom name="polygon{i}" type="box" pos="{centre[0]:.9g} {centre[1]:.9g} {h:.9g}" '
                f'size="{np.linalg.norm(e0) / 2:.9g} {np.linalg.norm(e1) / 2:.9g} {h:.9g}" '
                f'euler="0 0 {yaw:.12g}" material="obstacle"/>'
            )
        else:
            centre = p.mean(0)
            local = p - centre
            verts = " ".join(f"{x:.9g} {y:.9g} {z:.9g}" for z in (-h, h) for x, y in local)
            assets.append(f'<mesh name="prism{i}" vertex="{verts}"/>')
            geoms.append(
                f'<geom name="polygon{i}" type="mesh" mesh="prism{i}" '
                f'pos="{centre[0]:.9g} {centre[1]:.9g} {h:.9g}" material="obstacle"/>'
            )
    b = np.asarray(floor.bounds, np.float64)
    cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
    sx, sy = (b[2] - b[0]) / 2 + 1, (b[3] - b[1]) / 2 + 1
    nl = "\n    "
    return f"""<mujoco model="{model_name}">
  <compiler angle="radian"/>
  <asset>
    <material name="obstacle" rgba="0.55 0.57 0.62 1"/>
    <material name="ground" rgba="0.9 0.9 0.88 1"/>
    {nl.join(assets)}
  </asset>
  <worldbody>
    <light pos="{cx:.6g} {cy:.6g} 8" dir="0 0 -1" directional="true"/>
    <geom name="ground" type="plane" pos="{cx:.6g} {cy:.6g} 0" size="{sx:.6g} {sy:.6g} 0.1"
          material="ground" group="3"/>
    {nl.join(geoms)}
  </worldbody>
</mujoco>
"""
