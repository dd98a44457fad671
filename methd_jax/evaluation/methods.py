"""Positioning methods behind one interface: what the robot does in the Chase behaviour.

A method is an object with

- ``name`` (str) and ``multi_user`` (bool: whether it can run with two users),
- ``init() -> state``: its per-episode state (a pytree),
- ``chase(state, ctx: Context) -> (state, Chase)``: called every 50 Hz step while the behaviour
  engine is in Chase. :class:`Chase` either carries a robot-frame velocity ``command`` or asks the
  engine's navigator to drive to ``goal`` (``navigate``; the engine replans when the goal moves),
- optionally ``idle(state, ctx: Context) -> state``: called every other step (the engine drives the
  base), for what a method keeps watching meanwhile.

:class:`Static` and :class:`Heuristic` are the thesis's baselines (§5.3). A trained policy is a
method too, :class:`envs.evaluation.Policy`: it needs the environment's own observation and action
mapping, so it lives with the environments (this package imports nothing from them).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct
from mujoco import mjx

from methd_jax import floors
from methd_jax.control import CONTROL_HZ
from methd_jax.evaluation.navigator import Costmap
from methd_jax.floors import Floor
from methd_jax.geometry import KAIROS, wrap_angle


@struct.dataclass
class Context:
    """What a method may look at in one step."""

    robot: mjx.Data  # the base
    pose: jax.Array  # (3,) x, y, yaw
    users: dict  # per-user features of MotionBank.at, stacked (U, ...); velocities as the user moves
    present: jax.Array  # (U,) bool: users in the scene
    floor: Floor
    grid: Costmap
    step: jax.Array  # () int32 steps since the episode began
    key: jax.Array
    scan: jax.Array  # (R,) full-resolution ranges from the base's pose (what a safety layer sees)


class Chase(NamedTuple):
    command: jax.Array  # (3,) robot-frame velocity (used unless navigate)
    goal: jax.Array  # (3,) navigator goal pose (used if navigate)
    navigate: jax.Array  # () bool


def _no_goal() -> jax.Array:
    return jnp.zeros(3)


class Static:
    """Stay where the last haptic interaction (or Escape) left the robot (§5.3.1)."""

    name = "Static"
    multi_user = True

    def init(self):
        return ()

    def chase(self, state, ctx: Context):
        return state, Chase(jnp.zeros(3), _no_goal(), jnp.bool_(False))


@dataclasses.dataclass(frozen=True)
class HeuristicConfig:
    """CoboDeck's Chase Space (Mortezapoor et al.; thesis §5.3.2, Fig. 5.2) as we parametrise it.

    The thesis describes it only in words: two arcs either side of the user populated with chase
    poses oriented so the robot can drive forward or backward to the HIP, each weighted, filtered
    against the static occupancy map, the best one driven to with a slow replanning rate.
    """

    radius: float = 2.5
    """Arc radius around the user, m (beyond the 1.77 m critical distance and the 1.5 m Escape)."""
    angles: tuple[float, float] = (40.0, 140.0)
    """Each arc spans these bearings from the user's heading, degrees, on the left and the right."""
    step: float = 10.0
    """Spacing of the candidate poses along an arc, degrees."""
    clearance: float = 1.0
    """Candidates closer than this (beyond the footprint's radius) to an obstacle weigh less, m."""
    stickiness: float = 0.15
    """Extra weight of the candidate nearest the current target, so the target does not flicker."""
    replan_period: float = 1.0
    """Seconds between choices of a new chase pose (the "slow replanning rate")."""

    def bearings(self) -> jax.Array:
        one = jnp.arange(self.angles[0], self.angles[1] + 1e-6, self.step)
        return jnp.deg2rad(jnp.concatenate([one, -one]))


@struct.dataclass
class HeuristicState:
    target: jax.Array  # (3,) current chase pose
    has_target: jax.Array  # () bool


class Heuristic:
    """CoboDeck's Chase Space positioning (SU only, as in the thesis)."""

    name = "Heuristic"
    multi_user = False

    def __init__(self, config: HeuristicConfig = HeuristicConfig()):
        self.config = config
        self._period = max(1, round(config.replan_period * CONTROL_HZ))

    def init(self):
        return HeuristicState(jnp.zeros(3), jnp.bool_(False))

    def candidates(self, user_pose: jax.Array, hip: jax.Array, floor: Floor):
        """Chase poses (K, 3) and their weights (K,), zero where the footprint would not fit."""
        cfg = self.config
        bearing = self.config.bearings()
        ang = user_pose[2] + bearing
        xy = user_pose[:2] + cfg.radius * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
        to_hip = hip[:2] - xy
        yaw = jnp.arctan2(to_hip[:, 1], to_hip[:, 0])
        # drive forward or backward to the HIP: take whichever of the two is nearer the HIP's yaw
        yaw = jnp.where(jnp.abs(wrap_angle(yaw - hip[2])) > 0.5 * math.pi, wrap_angle(yaw + math.pi), yaw)
        sdf = jax.vmap(lambda p: floors.signed_distance(floor, p))(xy)
        free = jax.vmap(lambda p: floors.is_free(floor, p, KAIROS.radius))(xy)
        front = 0.5 * (1.0 + jnp.cos(bearing))  # the HIP lies ahead of the user
        room = jnp.clip((sdf - KAIROS.radius) / cfg.clearance, 0.0, 1.0)
        weight = jnp.where(free, front * (0.5 + 0.5 * room), 0.0)
        return jnp.concatenate([xy, yaw[:, None]], 1), weight

    def chase(self, state: HeuristicState, ctx: Context):
        user = ctx.users["pose"][0]
        hip = ctx.users["hip"][0]
        poses, weight = self.candidates(user, hip, ctx.floor)
        near = jnp.linalg.norm(poses[:, :2] - state.target[:2], axis=1)
        weight = weight + jnp.where(
            state.has_target & (weight > 0) & (near == jnp.min(near)), self.config.stickiness, 0.0
        )
        best = jnp.argmax(weight)
        due = (ctx.step % self._period == 0) | ~state.has_target
        choose = due & (weight[best] > 0)
        target = jnp.where(choose, poses[best], state.target)
        has = state.has_target | choose
        return HeuristicState(target, has), Chase(jnp.zeros(3), target, has)
