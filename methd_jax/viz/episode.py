"""One episode of an environment, recorded step by step as plain numpy arrays for pictures.

``record(env, key, steps, policy)`` runs a single episode under ``jit`` (one ``lax.scan``; the
world freezes once the episode ends, so every array has ``steps + 1`` rows) and keeps what a
picture needs: the floor, the robot's pose, the LiDAR ranges the policy saw, the users' head poses
and HIPs, the goal, the user weight u_w and who requested when. The same :class:`Rollout` feeds
the matplotlib frames, the GIF, the polar scan plot and the Foxglove MCAP export.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from envs.guide import GuideEnv
from envs.nav import DT, NavEnv
from methd_jax import floors
from methd_jax import robot as robot_lib
from methd_jax.floors import Floor
from methd_jax.geometry import KAIROS

OUTCOMES = ("running", "success", "obstacle collision", "user collision", "time limit")
"""``Rollout.outcome``: still running at the last recorded step, or how the episode ended."""
HIT_MARGIN = 0.15
"""Ranges this close to the observation's clamp are drawn as misses (5 noise standard deviations), m."""


@dataclasses.dataclass(frozen=True)
class Rollout:
    """Per-step arrays of one episode (row 0 is the reset); ``None`` where an env has no robot."""

    env: str  # "su", "nav" or "guide"
    floor: Floor  # host (numpy) copy of the episode's floor
    t: np.ndarray  # (T,) seconds since the reset
    users: np.ndarray  # (T, N, 3) head pose x, y, yaw of each user
    hips: np.ndarray  # (T, N, 3) each user's haptic interaction pose
    requested: np.ndarray  # (T,) bool: the request has fired
    done: np.ndarray  # (T,) bool: the episode has ended (the world is frozen from here)
    requester: int  # the user who requests
    outcome: str  # how the episode ended: see ``OUTCOMES``
    robot: np.ndarray | None = None  # (T, 3) base pose
    goal: np.ndarray | None = None  # (T, 3) goal pose of the policy
    ranges: np.ndarray | None = None  # (T, R) LiDAR ranges in the observation (noisy, clamped)
    lidar_range: float = 3.0  # the clamp of ``ranges``, m
    u_w: np.ndarray | None = None  # (T,) user weight (nav with two users, guide)
    collision_distance: float = 1.37  # d_coll around users, m
    critical_distance: float = 1.77  # d_crit around users, m
    footprint: tuple[float, float] = (KAIROS.length, KAIROS.width)

    @property
    def num_steps(self) -> int:
        return len(self.t)

    @property
    def num_users(self) -> int:
        return self.users.shape[1]

    def strided(self, stride: int) -> list[int]:
        """Every ``stride``-th step and the last: the steps an animation or an export shows."""
        if stride < 1:
            raise ValueError(f"stride must be at least 1, got {stride}")
        steps = list(range(0, self.num_steps, stride))
        return steps if steps[-1] == self.num_steps - 1 else [*steps, self.num_steps - 1]

    def hits(self, i: int) -> np.ndarray:
        """(K, 2) world points of the LiDAR returns at step ``i``. Rays read within ``HIT_MARGIN``
        of the clamp are taken as misses: the observation's noise scatters the clamp by a few cm."""
        r = self.ranges[i]
        angles = self.robot[i, 2] + 2 * np.pi * np.arange(len(r)) / len(r)
        keep = r < self.lidar_range - HIT_MARGIN
        xy = self.robot[i, :2] + r[:, None] * np.stack([np.cos(angles), np.sin(angles)], 1)
        return xy[keep]


def zero_policy(action_size: int) -> Callable[[jax.Array], jax.Array]:
    """The robot stands still (GuideRL keeps u_w): the default when no trained policy is given."""
    return lambda obs: jnp.zeros(action_size)


def record(
    env: NavEnv | GuideEnv,
    key: jax.Array,
    steps: int,
    policy: Callable[[jax.Array], jax.Array] | None = None,
) -> Rollout:
    """``steps`` control steps of one episode of ``env`` (from ``envs.make``) driven by
    ``policy(obs) -> action`` (deterministic, e.g. ``train.export.load(run)``)."""
    if steps < 1:
        raise ValueError(f"steps must be at least 1, got {steps}")
    if not isinstance(env, NavEnv | GuideEnv):
        raise TypeError(f"record needs an environment from envs.make, got {type(env).__name__}")
    policy = policy or zero_policy(env.action_size)
    is_nav = isinstance(env, NavEnv)

    def snapshot(state) -> dict:
        w = state.pipeline_state
        feats = jax.vmap(env.bank.at, (0, None))(w.users, w.t)
        out = {
            "t": w.t,
            "users": feats["pose"],
            "hips": feats["hip"],
            "requested": w.t >= w.request_step,
            "done": state.done > 0,
            "u_w": w.u_w,
            "success": state.metrics.get("success", jnp.float32(0.0)) > 0,
            "obstacle": state.metrics.get("collision_obstacle", jnp.float32(0.0)) > 0,
            "user": state.metrics.get("collision_user", jnp.float32(0.0)) > 0,
        }
        if is_nav:
            out |= {
                "robot": robot_lib.pose(w.robot),
                "goal": w.goal,
                "ranges": state.obs[env.observation_layout["lidar"]],
            }
        return out

    def body(state, _):
        nxt = env.step(state, policy(state.obs))
        ended = state.done > 0
        state = jax.tree.map(lambda old, new: jnp.where(ended, old, new), state, nxt)
        return state, snapshot(state)

    @jax.jit
    def run(key):
        state = env.reset(key)
        first = snapshot(state)
        state, rest = jax.lax.scan(body, state, None, length=steps)
        rows = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, rest)
        w = state.pipeline_state
        return rows, w.requester, (w.floor if is_nav else None)

    rows, requester, floor = run(key)
    rows = {k: np.asarray(v) for k, v in rows.items()}
    outcome = "running"
    if rows["done"].any():
        end = int(np.argmax(rows["done"]))
        flags = [rows["obstacle"][end], rows["user"][end]]
        outcome = "obstacle collision" if flags[0] else "user collision" if flags[1] else "time limit"
        # GuideRL reports no success flag: an episode it ends before the limit is a success
        if rows["success"][end] or (not is_nav and rows["requested"][end]):
            outcome = "success"
    if is_nav:
        cfg = env.config
        extra = {
            "robot": rows["robot"],
            "goal": rows["goal"],
            "ranges": rows["ranges"],
            "lidar_range": float(cfg.lidar_range),
            "collision_distance": cfg.safety.collision_distance,
            "critical_distance": cfg.safety.critical_distance,
            "u_w": rows["u_w"] if cfg.num_users == 2 else None,
        }
        name = "su" if cfg.num_users == 1 else "nav"
        floor = jax.tree.map(np.asarray, floor)
    else:  # GuideRL has no floor; its users walk in the lab twin, where the motion data lives
        floor = jax.tree.map(np.asarray, floors.lab())
        extra = {"u_w": rows["u_w"]}
        name = "guide"
    return Rollout(
        env=name,
        floor=floor,
        t=rows["t"] * DT,
        users=rows["users"],
        hips=rows["hips"],
        requested=rows["requested"],
        done=rows["done"],
        requester=int(requester),
        outcome=outcome,
        **extra,
    )
