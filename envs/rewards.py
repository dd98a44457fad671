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

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"safety.{f.name} must be a finite number >= 0, got {value!r}")
        if not self.yaw_radius > 0:
            raise ValueError(f"safety.yaw_radius must be positive, got {self.yaw_radius!r}")


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
) -> dict[str, jax.Array]:
    """All unweighted terms of eq. 4.17 for one step.

    ``ranges`` are the true, unclamped ranges; ``boundary`` (b_r) and ``inflation_scale`` are the
    per-ray constants of :meth:`methd_jax.geometry.Footprint.ray_geometry`. ``d_path``, where
    given, replaces the straight ``d_goal`` in r_d only (the way to the goal round obstacles).
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
    }


def total(unweighted: dict[str, jax.Array], weights: RewardWeights) -> tuple[jax.Array, dict[str, jax.Array]]:
    """R_t (4.17) and the weighted terms, keyed ``reward/<term>``."""
    weighted = {f"reward/{k}": v * getattr(weights, k) for k, v in unweighted.items()}
    return sum(weighted.values()), weighted
