"""The reward terms of thesis eqs. 4.6-4.17, each a pure function, and the weight presets.

Every function returns the *unweighted* term; :func:`terms` evaluates all of them and
:class:`RewardWeights` holds Table 4.1 (SU) and Table 4.3 (NavRL). Environments report each weighted
term in ``metrics`` so that training curves show them separately.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from methd_jax.distances import COLLISION_DISTANCE, CRITICAL_DISTANCE
from methd_jax.geometry import rotate, scan_points, to_local


@dataclasses.dataclass(frozen=True)
class SafetyConfig:
    """Distances of thesis §4.2.1 and Table 4.1."""

    collision_distance: float = COLLISION_DISTANCE
    """d_coll: robot radius 0.77 m + 0.6 m, m."""
    critical_distance: float = CRITICAL_DISTANCE
    """d_crit, m."""
    inflation_distance: float = 0.5
    """d_i: width of the obstacle inflation layer beyond the robot's boundary, m."""
    goal_distance: float = 0.01
    """epsilon_d of r_g, m."""
    goal_yaw: float = 0.0087
    """epsilon_omega of r_g, rad."""
    goal_hold: float = 0.1
    """t_g of r_g: how long the goal tolerance must be held, s."""
    yaw_radius: float = 1.0
    """r_omega pays for the goal's yaw within this distance of the goal, falling linearly to 0 there
    (the thesis: 1 m). The evaluation's navigator turns at 1 rad/s after the request, so a base that
    arrives facing away loses seconds however near it is."""
    collision_margin: float = 0.0
    """p_o fires when a ray is shorter than b_r plus this, m (the thesis: 0). With a few rays a
    corner touches an obstacle a few cm before any ray crosses the boundary; a margin makes the
    sparse test at least as strict as the evaluation's 720-ray one."""
    stopping_margin: float = 0.05
    """p_s (beyond the thesis): the clearance the footprint keeps from every scan point along the
    path on which the base would stop if it braked now, m."""
    deceleration: float = 3.0
    """How hard the base brakes along each of its own axes for p_s, m/s^2 (its servo limit)."""
    yaw_deceleration: float = 6.0
    """How hard the base stops turning for p_s, rad/s^2 (its servo limit)."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"safety.{f.name} must be a finite number >= 0, got {value!r}")
        for name in ("yaw_radius", "deceleration", "yaw_deceleration"):
            if not getattr(self, name) > 0:
                raise ValueError(f"safety.{name} must be positive, got {getattr(self, name)!r}")


@dataclasses.dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (thesis Table 4.1; NavRL differs only in ``q_r``)."""

    distance: float = 1.0
    goal: float = 50.0
    yaw: float = 8.0
    obstacle_collision: float = -900.0
    user_collision: float = -1000.0
    critical_zone: float = -20.0
    inflation: float = -0.5
    action_smoothness: float = -0.25
    velocity: float = -2.0
    acceleration: float = -0.0015
    stopping: float = 0.0
    """p_s, beyond the thesis (0): per metre by which the base could not brake clear of the scan."""


SU_WEIGHTS = RewardWeights()
"""Table 4.1."""
NAV_WEIGHTS = RewardWeights(acceleration=-0.0000075)
"""Table 4.3."""


def unsafe(user_distances: jax.Array, inflation: jax.Array, safety: SafetyConfig) -> jax.Array:
    """s_unsafe: the robot is inside a user's critical distance or the obstacle inflation layer."""
    in_layer = jnp.any(inflation < safety.inflation_distance)
    return jnp.any(user_distances < safety.critical_distance) | in_layer


def distance_reward(d_goal: jax.Array, is_unsafe: jax.Array) -> jax.Array:
    """r_d (4.6): 3 - d_g, withheld (0) while unsafe unless it is negative."""
    r = 3.0 - d_goal
    return jnp.where(is_unsafe & (r > 0), 0.0, r)


def goal_reward(d_goal, dyaw, held, is_unsafe, safety: SafetyConfig) -> jax.Array:
    """r_g (4.7): 1 once the pose has been held within (1 cm, 0.5 deg) for 0.1 s, and safe."""
    ok = (d_goal < safety.goal_distance) & (jnp.abs(dyaw) < safety.goal_yaw) & (held >= safety.goal_hold)
    return jnp.where(ok & ~is_unsafe, 1.0, 0.0)


def yaw_reward(d_goal, dyaw, is_unsafe, radius: float = 1.0) -> jax.Array:
    """r_omega (4.8): exp(-3 |dyaw|) * max(1 - d_g / radius, 0) unless unsafe (the thesis: radius 1 m)."""
    return jnp.where(is_unsafe, 0.0, jnp.exp(-3.0 * jnp.abs(dyaw)) * jnp.maximum(1.0 - d_goal / radius, 0.0))


def obstacle_collision(ranges: jax.Array, boundary: jax.Array) -> jax.Array:
    """p_o (4.9): 1 if any LiDAR range is shorter than the robot's boundary along that ray."""
    return jnp.any(ranges < boundary).astype(jnp.float32)


def user_collisions(user_distances: jax.Array, safety: SafetyConfig) -> jax.Array:
    """sum_n p_u^n (4.10): users closer than d_coll."""
    return jnp.sum(user_distances < safety.collision_distance).astype(jnp.float32)


def critical_zone(user_distances: jax.Array, safety: SafetyConfig) -> jax.Array:
    """sum_n p_c^n (4.11): users closer than d_crit."""
    return jnp.sum(user_distances < safety.critical_distance).astype(jnp.float32)


def inflation_penalty(inflation: jax.Array, safety: SafetyConfig) -> jax.Array:
    """p_i (4.12): sum over rays of max((d_i - f(l)) / d_i, 0), f(l) from eq. 4.13."""
    d = safety.inflation_distance
    return jnp.sum(jnp.maximum((d - inflation) / d, 0.0))


STOP_SAMPLES = 4
"""Poses sampled along the stopping path of :func:`stopping_path`."""


def stopping_path(velocity: jax.Array, deceleration: float, yaw_deceleration: float) -> jax.Array:
    """Poses (x, y, yaw) ``(STOP_SAMPLES, 3)``, in the base's present frame, through which a base
    moving at the robot-frame ``velocity`` (vx, vy, wz) passes when it brakes at once; the last is
    where it comes to rest. As the base's servos do (:func:`methd_jax.robot.predict`), each brakes
    along its own robot axis, at most ``deceleration`` per axis and ``yaw_deceleration``, while
    the base's momentum keeps its direction in the world as the base turns under it. Integrated
    over equal slices of the longest the stop can take (``|v| / deceleration`` or ``|wz| /
    yaw_deceleration``), each slice braking no further than to rest."""
    w = velocity[2]
    stop = jnp.maximum(jnp.linalg.norm(velocity[:2]) / deceleration, jnp.abs(w) / yaw_deceleration)
    dt = stop / STOP_SAMPLES
    safe_dt = jnp.maximum(dt, 1e-9)

    def yaw_at(t):
        t = jnp.minimum(t, jnp.abs(w) / yaw_deceleration)
        return w * t - jnp.sign(w) * 0.5 * yaw_deceleration * t**2

    def slice_(carry, k):
        xy, v = carry  # v: the linear velocity in the start frame
        th = yaw_at((k + 0.5) * dt)
        axis = rotate(-th, v)
        braked = jnp.sign(axis) * jnp.maximum(jnp.abs(axis) - deceleration * safe_dt, 0.0)
        v_next = rotate(th, braked)
        xy = xy + 0.5 * dt * (v + v_next)
        return (xy, v_next), jnp.concatenate([xy, yaw_at((k + 1.0) * dt)[None]])

    k = jnp.arange(STOP_SAMPLES, dtype=jnp.float32)
    _, poses = jax.lax.scan(slice_, (jnp.zeros(2), velocity[:2].astype(jnp.float32)), k)
    return poses


def box_distance(points: jax.Array, half: jax.Array) -> jax.Array:
    """Signed distance of ``points`` (..., 2) from the box |x| <= half[0], |y| <= half[1] (< 0 inside)."""
    q = jnp.abs(points) - half
    return jnp.linalg.norm(jnp.maximum(q, 0.0), axis=-1) + jnp.minimum(jnp.max(q, axis=-1), 0.0)


def stopping_overlap(
    ranges: jax.Array, velocity: jax.Array, half: jax.Array, safety: SafetyConfig
) -> jax.Array:
    """p_s: how far (m) the footprint (half extents ``half``) comes within ``safety.stopping_margin``
    of a scan point anywhere on its :func:`stopping_path` from ``velocity``, 0 if it stays clear.

    ``ranges`` (R,) are the true full-circle scan (rays as :func:`methd_jax.geometry.ray_angles`,
    ``inf`` where nothing is hit).
    Unlike p_i, which sees only where the base is, this grows with the speed toward an obstacle:
    at 3 m/s the base needs 1.5 m to stop, so driving at a table 1 m away costs before the contact
    does. At rest it is the present clearance's shortfall. A point's depth inside the footprint is
    its distance to the nearest face, so the term saturates at half the base's width plus the
    margin."""
    points = scan_points(ranges)
    poses = jnp.concatenate(
        [jnp.zeros((1, 3)), stopping_path(velocity, safety.deceleration, safety.yaw_deceleration)]
    )
    local = jax.vmap(to_local, (0, None))(poses, points)  # (P, R, 2)
    clearance = jnp.min(box_distance(local, half))
    return jnp.maximum(safety.stopping_margin - clearance, 0.0)


def action_smoothness(a: jax.Array, a1: jax.Array, a2: jax.Array) -> jax.Array:
    """p_a (4.14): ||a_t - a_{t-1}||^2 + ||a_t - 2 a_{t-1} + a_{t-2}||^2."""
    return jnp.sum((a - a1) ** 2) + jnp.sum((a - 2 * a1 + a2) ** 2)


def velocity_penalty(v: jax.Array) -> jax.Array:
    """p_v (4.15): ||v_r||^2 (robot velocity, m/s and rad/s)."""
    return jnp.sum(v**2)


def acceleration_penalty(q: jax.Array) -> jax.Array:
    """p_q (4.16): ||q_r||^2 (robot acceleration)."""
    return jnp.sum(q**2)


def terms(
    *,
    ranges: jax.Array,
    boundary: jax.Array,
    inflation_scale: jax.Array,
    user_distances: jax.Array,
    d_goal: jax.Array,
    dyaw: jax.Array,
    held: jax.Array,
    action: jax.Array,
    prev_action: jax.Array,
    prev_prev_action: jax.Array,
    velocity: jax.Array,
    acceleration: jax.Array,
    safety: SafetyConfig,
    d_path: jax.Array | None = None,
    stopping: jax.Array | None = None,
) -> dict[str, jax.Array]:
    """All unweighted terms of eq. 4.17 for one step.

    ``ranges`` are the true, unclamped ranges; ``boundary`` (b_r) and ``inflation_scale`` are the
    per-ray constants of :meth:`methd_jax.geometry.Footprint.ray_geometry`. ``d_path``, where
    given, replaces the straight ``d_goal`` in r_d only (the way to the goal round obstacles).
    ``stopping`` is p_s (:func:`stopping_overlap`), 0 where not given.
    """
    inflation = (ranges - boundary) * inflation_scale  # f(l) of eq. 4.13
    bad = unsafe(user_distances, inflation, safety)
    return {
        "distance": distance_reward(d_goal if d_path is None else d_path, bad),
        "goal": goal_reward(d_goal, dyaw, held, bad, safety),
        "yaw": yaw_reward(d_goal, dyaw, bad, safety.yaw_radius),
        "obstacle_collision": obstacle_collision(ranges, boundary + safety.collision_margin),
        "user_collision": user_collisions(user_distances, safety),
        "critical_zone": critical_zone(user_distances, safety),
        "inflation": inflation_penalty(inflation, safety),
        "action_smoothness": action_smoothness(action, prev_action, prev_prev_action),
        "velocity": velocity_penalty(velocity),
        "acceleration": acceleration_penalty(acceleration),
        "stopping": jnp.float32(0.0) if stopping is None else stopping,
    }


def total(unweighted: dict[str, jax.Array], weights: RewardWeights) -> tuple[jax.Array, dict[str, jax.Array]]:
    """R_t (4.17) and the weighted terms, keyed ``reward/<term>``."""
    weighted = {f"reward/{k}": v * getattr(weights, k) for k, v in unweighted.items()}
    return sum(weighted.values()), weighted
