"""GuideRL on the robot: who will touch next, as the goal a NavRL controller drives to.

``GuideGoal(folder)`` loads an exported GuideRL policy (``env`` "guide") and, once per control tick,
turns the two tracked users into the user weight u_w (eq. 4.25: u_w += 0.05 a, clipped to [-1, 1])
and the goal pose between their haptic interaction points (eq. 4.22/4.23), exactly as
``envs.nav.NavEnv`` does in training: the 15 inputs of eq. 4.24 are each user's velocity and
acceleration in their own frame, u_w and the last two actions, and for a policy trained with the
wrists (``GuideConfig.wrist``; its manifest's observation has a ``wrist`` field) each user's wrist
height above the head. Hand the goal to :class:`methd_jax.deploy.Controller` of the NavRL policy as
``Inputs.goal``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from methd_jax.deploy.controller import periods_since
from methd_jax.deploy.observation import rotate, wrap_angle
from methd_jax.deploy.policy import DeployError, load_manifest, load_policy

SWITCH = 0.25
"""|u_w| beyond which the goal takes the nearer user's HIP yaw outright (as ``envs.goals``)."""


def goal_from_weight(u_w: float, hip1: np.ndarray, hip2: np.ndarray) -> np.ndarray:
    """The goal (x, y, yaw) on the segment between two HIPs: u_w = -1 user 1, +1 user 2, 0 the
    midpoint, the yaw blended by the circular mean in between (numpy twin of ``envs.goals``)."""
    hip1, hip2 = np.asarray(hip1, np.float64), np.asarray(hip2, np.float64)
    xy = hip1[:2] + 0.5 * (u_w + 1.0) * (hip2[:2] - hip1[:2])
    if u_w < -SWITCH:
        yaw = hip1[2]
    elif u_w > SWITCH:
        yaw = hip2[2]
    else:
        yaw = np.arctan2(np.sin(hip1[2]) + np.sin(hip2[2]), np.cos(hip1[2]) + np.cos(hip2[2]))
    return np.array([xy[0], xy[1], wrap_angle(yaw)])


class GuideGoal:
    """The GuideRL half of the multi-user pair: ``tick(users, hips) -> goal``; ``u_w`` after it."""

    def __init__(self, path: str | Path, *, backend: str = "onnx"):
        manifest = load_manifest(path)
        if manifest["env"] != "guide":
            raise DeployError(f"{path}: a {manifest['env']!r} policy, not a GuideRL ('guide') one")
        self.policy = load_policy(path, backend)
        self.max_delta = float(manifest["action"]["scale"][0])
        self.dt = 1.0 / float(manifest["deployment"]["control_hz"])
        self.wrist = "wrist" in manifest["observation_layout"]
        """Whether the policy reads the users' wrist heights (pass ``wrist`` to :meth:`tick`)."""
        self.reset()

    def reset(self):
        """u_w back to the midpoint, no action history (as at an episode's start)."""
        self.u_w = 0.0
        self.actions = np.zeros(2)
        self.last_velocity: np.ndarray | None = None
        self.last_tick: float | None = None

    def observation(
        self,
        users: np.ndarray,
        acceleration: np.ndarray | None = None,
        wrist: np.ndarray | None = None,
        now: float | None = None,
    ) -> np.ndarray:
        """Eq. 4.24 from ``users`` (2, 6): x, y, yaw, vx, vy, wz in the world; ``acceleration``
        (2, 3) likewise in the world, or None to difference successive velocities (over the whole
        control periods since the last call if ``now``, in s, is given; none after a pause of more
        than :data:`~methd_jax.deploy.controller.PAUSE` periods); ``wrist`` (2,): each user's wrist
        height minus head height in m, which a policy with :attr:`wrist` needs."""
        users = np.asarray(users, np.float64)
        if users.shape != (2, 6) or not np.isfinite(users).all():
            raise DeployError(f"users must be a finite (2, 6) array, got shape {users.shape}")
        velocity = users[:, 3:]
        periods = periods_since(self.last_tick, now, self.dt)
        self.last_tick = now
        if acceleration is None:
            fresh = self.last_velocity is None or periods is None
            acceleration = (
                np.zeros_like(velocity) if fresh else (velocity - self.last_velocity) / (periods * self.dt)
            )
        acceleration = np.asarray(acceleration, np.float64)
        if acceleration.shape != (2, 3) or not np.isfinite(acceleration).all():
            raise DeployError(f"acceleration must be a finite (2, 3) array, got shape {acceleration.shape}")
        self.last_velocity = velocity

        def own_frame(v):  # each user's (vx, vy) rotated into their heading; wz unchanged
            return np.concatenate([rotate(-users[:, 2], v[:, :2]), v[:, 2:]], 1)

        v, q = own_frame(velocity), own_frame(acceleration)
        parts = [v[0], v[1], q[0], q[1], [self.u_w], self.actions]
        if self.wrist:
            if wrist is None:
                raise DeployError("this GuideRL policy reads the users' wrist heights: pass wrist (2,)")
            wrist = np.asarray(wrist, np.float64)
            if wrist.shape != (2,) or not np.isfinite(wrist).all():
                raise DeployError(f"wrist must be a finite (2,) array, got shape {wrist.shape}")
            parts.append(wrist)
        elif wrist is not None:
            raise DeployError("this GuideRL policy does not read wrist heights (eq. 4.24's 15 inputs)")
        return np.concatenate(parts).astype(np.float32)

    def tick(
        self,
        users: np.ndarray,
        hips: np.ndarray,
        acceleration: np.ndarray | None = None,
        wrist: np.ndarray | None = None,
        now: float | None = None,
    ) -> np.ndarray:
        """One control tick: u_w updated from the users (see :meth:`observation`); returns the goal
        between ``hips`` (2, 3) (x, y, yaw of each user's HIP in the world)."""
        hips = np.asarray(hips, np.float64)
        if hips.shape != (2, 3) or not np.isfinite(hips).all():
            raise DeployError(f"hips must be a finite (2, 3) array, got shape {hips.shape}")
        obs = self.observation(users, acceleration, wrist, now)
        action = float(np.clip(np.asarray(self.policy(obs)).reshape(-1)[0], -1.0, 1.0))
        self.u_w = float(np.clip(self.u_w + self.max_delta * action, -1.0, 1.0))
        self.actions = np.array([action, self.actions[0]])
        return goal_from_weight(self.u_w, hips[0], hips[1])
