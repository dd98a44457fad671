"""A stopping rule cheap enough to judge every action PPO trains on: the shield teacher.

The deployment's safety layer (:mod:`methd_jax.evaluation.safety_layer`) sweeps the footprint
along the command's arc and costs 2-20x a training step, so PPO cannot ask it about every
transition. This rule keeps what matters most for a base driving at furniture: along the direction
of the commanded linear velocity, how far the footprint can translate before it meets a scan
point, and the largest speed from which the base, reacting after a lag and then braking, stops a
margin short of it. PPO's shield term (:attr:`train.ppo.PPOConfig.shield_scale`) pulls the
policy's mean action toward the action whose command is the commanded one slowed to that speed,
where it is slower: a supervised signal on every step near an obstacle instead of a penalty after
a contact. The turn rate is left alone (a turning rectangle's corners are what the margin is for).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from methd_jax.geometry import KAIROS, scan_points


@dataclasses.dataclass(frozen=True)
class ShieldConfig:
    """The stopping rule's margin and the braking it assumes."""

    margin: float = 0.1
    """Distance the base is to stop short of a scan point in its way, m."""
    deceleration: float = 2.0
    """Braking the rule counts on, m/s^2 (the base's servos manage 3; the rest is room for a
    policy that follows the rule only roughly)."""
    reaction: float = 0.12
    """Seconds the base keeps its speed before braking: the servos' 0.1 s lag and a control step."""

    def __post_init__(self):
        if self.margin < 0:
            raise ValueError(f"shield margin must be >= 0, got {self.margin}")
        if not (self.deceleration > 0 and self.reaction >= 0):
            raise ValueError(
                f"shield deceleration must be > 0 and reaction >= 0, got {self.deceleration}, {self.reaction}"
            )


def _slab(points: jax.Array, direction: jax.Array, half: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per point, the translations (enter, leave) along ``direction`` between which it lies in the
    box ``|x| <= half[0], |y| <= half[1]`` (enter > leave: never)."""
    # the point relative to the box after a translation t is p - t u; per axis it lies within the
    # slab for t between (p - h) / u and (p + h) / u (every t, or none, when u is 0 on that axis)
    u = jnp.where(jnp.abs(direction) < 1e-9, 1e-9, direction)
    a, b = (points - half) / u, (points + half) / u
    return jnp.max(jnp.minimum(a, b), axis=-1), jnp.min(jnp.maximum(a, b), axis=-1)


def free_distance(points: jax.Array, direction: jax.Array, body: jax.Array) -> jax.Array:
    """How far the footprint ``|x| <= body[0], |y| <= body[1]`` translates along the unit
    ``direction`` before it meets one of ``points`` (P, 2), all in the footprint's frame; ``inf``
    when none lies in its way. A point already inside the footprint counts as met at 0 if the
    direction leads toward it (``direction . point > 0``) and is passed by otherwise (the base may
    back away)."""
    enter, leave = _slab(points, direction, body)
    ahead = (enter <= leave) & (enter >= 0.0)
    inside = (enter < 0.0) & (leave > 0.0)
    d = jnp.where(ahead, enter, jnp.inf)
    d = jnp.where(inside, jnp.where(points @ direction > 0.0, 0.0, jnp.inf), d)
    return jnp.min(d)


def stopping_speed(distance: jax.Array, deceleration: float, reaction: float) -> jax.Array:
    """The largest speed v with ``v * reaction + v^2 / (2 * deceleration) <= distance``."""
    d = jnp.maximum(distance, 0.0)
    return deceleration * (jnp.sqrt(reaction**2 + 2.0 * d / deceleration) - reaction)


def safe_command(command: jax.Array, ranges: jax.Array, config: ShieldConfig) -> tuple[jax.Array, jax.Array]:
    """``command`` (robot-frame vx, vy, wz) with its linear part slowed to the stopping speed along
    its direction, given a full-circle scan ``ranges`` from the base's centre (rays as
    :func:`methd_jax.geometry.ray_angles`); and the factor it was slowed by (1: not at all)."""
    speed = jnp.linalg.norm(command[:2])
    direction = command[:2] / jnp.maximum(speed, 1e-9)
    free = free_distance(scan_points(ranges), direction, jnp.asarray(KAIROS.half_extents))
    allowed = stopping_speed(jnp.minimum(free, 1e3) - config.margin, config.deceleration, config.reaction)
    scale = jnp.where(speed > 1e-6, jnp.minimum(1.0, allowed / jnp.maximum(speed, 1e-9)), 1.0)
    return command.at[:2].multiply(scale), scale
