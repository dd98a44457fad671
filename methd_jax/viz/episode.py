"""One episode as plain numpy arrays for pictures: :class:`Rollout`.

It keeps what a picture needs: the floor, the robot's pose, the LiDAR ranges the policy saw, the
users' head poses and HIPs, the goal, the user weight u_w and who requested when. The same
:class:`Rollout` feeds the matplotlib frames, the GIF, the polar scan plot and the Foxglove MCAP
export; :func:`envs.record` fills one from an environment.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from methd_jax.distances import COLLISION_DISTANCE, CRITICAL_DISTANCE
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
    collision_distance: float = COLLISION_DISTANCE  # d_coll around users, m
    critical_distance: float = CRITICAL_DISTANCE  # d_crit around users, m
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
