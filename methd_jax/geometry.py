"""Planar geometry: SE(2) poses, angle wrapping, and the robot footprint.

A pose is an array ``(..., 3)`` of ``(x, y, yaw)`` in metres and radians. The robot frame has x
forward and y to the left; yaw is counter-clockwise from the world x axis.

The footprint is the CoboDeck base (Robotnik Kairos, thesis §4.2.1): a rectangle ``length`` along the
robot's x axis (1.13 m) by ``width`` along its y axis (0.91 m), centred on the LiDAR origin, with the
enclosing radius ``radius`` = 0.77 m that the thesis uses for user distances and in eq. 4.13.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

TWO_PI = 2.0 * math.pi


def wrap_angle(angle: jax.Array) -> jax.Array:
    """Wraps angles to ``[-pi, pi)``."""
    return (angle + jnp.pi) % TWO_PI - jnp.pi


def rotation(yaw: jax.Array) -> jax.Array:
    """Rotation matrices ``(..., 2, 2)`` that turn robot-frame vectors into world-frame vectors."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([jnp.stack([c, -s], -1), jnp.stack([s, c], -1)], -2)


def to_local(pose: jax.Array, points: jax.Array) -> jax.Array:
    """World points ``(..., 2)`` expressed in the frame of one ``pose`` ``(3,)`` (vmap for more)."""
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    d = points - pose[:2]
    return jnp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def to_world(pose: jax.Array, points: jax.Array) -> jax.Array:
    """Points ``(..., 2)`` given in the frame of one ``pose`` ``(3,)``, in the world frame."""
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    x, y = points[..., 0], points[..., 1]
    return jnp.stack([c * x - s * y + pose[0], s * x + c * y + pose[1]], -1)


def rotate(yaw: jax.Array, vectors: jax.Array) -> jax.Array:
    """Rotates vectors ``(..., 2)`` counter-clockwise by ``yaw`` (robot frame -> world frame)."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    x, y = vectors[..., 0], vectors[..., 1]
    return jnp.stack([c * x - s * y, s * x + c * y], -1)


def compose(a: jax.Array, b: jax.Array) -> jax.Array:
    """The pose ``a * b``: ``b`` given in the frame of ``a``, in the world frame (elementwise)."""
    xy = rotate(a[..., 2], b[..., :2]) + a[..., :2]
    return jnp.concatenate([xy, wrap_angle(a[..., 2:3] + b[..., 2:3])], -1)


def inverse(pose: jax.Array) -> jax.Array:
    """The pose ``p^-1`` with ``compose(p, inverse(p)) == 0`` (elementwise)."""
    c, s = jnp.cos(pose[..., 2]), jnp.sin(pose[..., 2])
    x, y = pose[..., 0], pose[..., 1]
    return jnp.stack([-(c * x + s * y), s * x - c * y, wrap_angle(-pose[..., 2])], -1)


def ray_angles(num_rays: int = 720) -> np.ndarray:
    """Ray angles in the sensor frame, ``2 pi i / num_rays``, counter-clockwise from x (numpy)."""
    return TWO_PI * np.arange(num_rays) / num_rays


def ray_directions(num_rays: int = 720) -> np.ndarray:
    """Unit vectors ``(num_rays, 2)`` of the rays of :func:`ray_angles` (numpy, float32)."""
    a = ray_angles(num_rays)
    return np.stack([np.cos(a), np.sin(a)], -1).astype(np.float32)


def scan_points(ranges: jax.Array) -> jax.Array:
    """A full-circle scan's ``ranges`` (R,) as points ``(R, 2)`` in the sensor frame; a ray without
    a return (``inf``) gives a point 1 km away."""
    far = jnp.where(jnp.isfinite(ranges), ranges, 1e3)
    return far[:, None] * ray_directions(ranges.shape[0])


@dataclasses.dataclass(frozen=True)
class Footprint:
    """A rectangular robot footprint centred on the LiDAR origin."""

    length: float = 1.13
    """Extent along the robot's x (forward) axis, metres."""
    width: float = 0.91
    """Extent along the robot's y (left) axis, metres."""
    radius: float = 0.77
    """Radius r of eq. 4.13 and of the user distances (thesis value; encloses the rectangle)."""

    def __post_init__(self):
        if not (self.length > 0 and self.width > 0 and self.radius > 0):
            raise ValueError(f"footprint sizes must be positive, got {self}")
        if self.radius < 0.5 * math.hypot(self.length, self.width) - 1e-9:
            raise ValueError(
                f"footprint radius {self.radius} does not enclose a {self.length} x {self.width} rectangle"
            )

    @property
    def half_extents(self) -> np.ndarray:
        """(length / 2, width / 2), float32: the rectangle is |x| <= [0], |y| <= [1] in the robot frame."""
        return np.array([0.5 * self.length, 0.5 * self.width], np.float32)

    def boundary_distance(self, angles: jax.Array) -> jax.Array:
        """b_r: distance from the centre to the rectangle's edge along each ray angle."""
        c, s = jnp.abs(jnp.cos(angles)), jnp.abs(jnp.sin(angles))
        # Each face is only reached when its cosine is non-zero; the other face then bounds it.
        to_front = jnp.where(c > 0, 0.5 * self.length / jnp.where(c > 0, c, 1.0), jnp.inf)
        to_side = jnp.where(s > 0, 0.5 * self.width / jnp.where(s > 0, s, 1.0), jnp.inf)
        return jnp.minimum(to_front, to_side)

    def inflation_scale(self, angles: jax.Array) -> jax.Array:
        """The factor of eq. 4.13: ``|sin|`` for rays that leave through a side, else ``|cos|``.

        Rays with ``|sin| * r >= w / 2`` count as leaving through a side. This is the thesis's
        approximation: its branch uses the radius r, not the exact corner angle.
        """
        s, c = jnp.abs(jnp.sin(angles)), jnp.abs(jnp.cos(angles))
        return jnp.where(s * self.radius >= 0.5 * self.width, s, c)

    def inflation_distance(self, ranges: jax.Array, angles: jax.Array) -> jax.Array:
        """f(l) of eq. 4.13: the excess range ``l - b_r`` projected onto the face it leaves from."""
        return (ranges - self.boundary_distance(angles)) * self.inflation_scale(angles)

    def ray_geometry(self, num_rays: int = 720) -> tuple[np.ndarray, np.ndarray]:
        """Per-ray constants ``(b_r, scale)`` (numpy, float32) with ``f(l) = (l - b_r) * scale``,
        evaluated once on the host so a jitted step does no trigonometry per ray."""
        a = jnp.asarray(ray_angles(num_rays), jnp.float32)
        return np.asarray(self.boundary_distance(a)), np.asarray(self.inflation_scale(a))


KAIROS = Footprint()
"""The CoboDeck base: 1.13 m long, 0.91 m wide, r = 0.77 m."""


def path_around_discs(start: jax.Array, goal: jax.Array, discs: jax.Array, mask: jax.Array) -> jax.Array:
    """Length of the way from ``start`` to ``goal`` (each ``(2,)``) around the discs ``(K, 3)``
    (x, y, radius) where ``mask`` ``(K,)`` is set: the straight distance plus, for each disc the
    segment crosses, the shortest way round that disc alone (tangent, arc, tangent) less the
    straight one. Discs are taken one at a time, so overlapping discs are each skirted on their
    own; a disc that holds the goal is ignored (it cannot be gone round), and a start inside a disc
    counts from the disc's rim. Continuous in ``start``, and equal to the straight distance as
    ``start`` reaches ``goal``."""
    straight = jnp.linalg.norm(goal - start)
    centre, radius = discs[:, :2], discs[:, 2]
    to_a, to_b = start - centre, goal - centre
    na, nb = jnp.linalg.norm(to_a, axis=-1), jnp.linalg.norm(to_b, axis=-1)
    a = jnp.maximum(na, radius)
    b = jnp.maximum(nb, radius)
    cos_t = jnp.sum(to_a * to_b, -1) / jnp.maximum(na * nb, 1e-9)
    theta = jnp.arccos(jnp.clip(cos_t, -1.0, 1.0))
    alpha = jnp.arccos(jnp.clip(radius / a, 0.0, 1.0))
    beta = jnp.arccos(jnp.clip(radius / b, 0.0, 1.0))
    tangents = jnp.sqrt(jnp.maximum(a * a - radius * radius, 0.0)) + jnp.sqrt(
        jnp.maximum(b * b - radius * radius, 0.0)
    )
    around = jnp.where(theta > alpha + beta, tangents + radius * (theta - alpha - beta), straight)
    extra = jnp.where(mask & (nb > radius), jnp.maximum(around - straight, 0.0), 0.0)
    return straight + jnp.sum(extra)
