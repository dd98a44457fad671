"""A final-stage safety layer in the spirit of nav2's collision monitor ("approach" behaviour).

The commanded twist is held over a short horizon and the footprint (the base's rectangle plus a
margin) is swept along the resulting arc against the latest scan's points and the users, who are
extrapolated at their current velocity. The command is scaled down by the largest factor that
keeps the sweep clear (0: stop). For static points scaling is exact: at factor s the robot covers
in the horizon T what the full command covers in s*T, so s = (last clear sample time) / T. For
moving users the factors are tried from that value downwards; a factor is refused when it brings
the robot inside a user's collision distance and closer than standing still would, so stopping is
always allowed and moving away from a user who is already too close is too.

Points already inside the footprint at t = 0 are ignored (self-returns or a collision that has
already happened): what is checked is what the command would newly hit. Points inside the margin
but outside the footprint at t = 0 are checked against the footprint itself, so the robot may
move away from a close wall but never into it. The base's finite
deceleration is not modelled: the horizon (1 s by default) is chosen to cover it (3 m/s^2 stops
1.2 m/s in 0.4 s).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class SafetyConfig:
    """Parameters of the collision monitor."""

    enabled: bool = True
    horizon: float = 1.0
    """Seconds the command is projected forward."""
    time_step: float = 0.01
    """Sampling of the sweep, s (0.01 s at 3 m/s is 3 cm, inside the margin)."""
    margin: float = 0.05
    """Added to every side of the footprint, m."""
    user_distance: float | None = None
    """Robot-centre to user distance never to be entered, m (default: the policy's d_coll, 1.37 m)."""
    user_steps: int = 20
    """Scale factors tried against moving users."""

    def __post_init__(self):
        if not (self.horizon > 0 and 0 < self.time_step <= self.horizon):
            raise ValueError(f"need 0 < time_step <= horizon, got {self.time_step} and {self.horizon}")
        if self.margin < 0 or (self.user_distance is not None and self.user_distance <= 0):
            raise ValueError("margin must be >= 0 and user_distance > 0")
        if self.user_steps < 1:
            raise ValueError("user_steps must be >= 1")


def arc(command: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses (x, y, yaw) ``(..., 3)`` reached from the origin after ``t`` s of a constant robot-frame
    twist (vx, vy, wz)."""
    vx, vy, wz = command
    th = wz * t
    if abs(wz) < 1e-9:
        return np.stack([vx * t, vy * t, th], -1)
    s, c = np.sin(th), np.cos(th)
    return np.stack([(vx * s + vy * (c - 1.0)) / wz, (vx * (1.0 - c) + vy * s) / wz, th], -1)


class CollisionMonitor:
    """Scales robot-frame commands so that the footprint stays clear over the horizon."""

    def __init__(
        self, length: float, width: float, num_rays: int, user_distance: float, config=SafetyConfig()
    ):
        self.config = config
        self.body = np.array([0.5 * length, 0.5 * width])
        self.half = self.body + config.margin
        self.reach_radius = float(np.hypot(*self.half))
        angles = 2.0 * np.pi * np.arange(num_rays) / num_rays
        self.directions = np.stack([np.cos(angles), np.sin(angles)], -1)
        self.times = np.arange(1, round(config.horizon / config.time_step) + 1) * config.time_step
        self.user_distance = config.user_distance or user_distance
        self.fractions = np.linspace(1.0, 0.0, config.user_steps + 1)

    def points(self, ranges: np.ndarray, command: np.ndarray) -> np.ndarray:
        """Points (P, 2) of the monitor's own rays (``ranges``) the sweep of ``command`` could reach."""
        near = np.isfinite(ranges) & (ranges < self._reach(command))
        return ranges[near, None] * self.directions[near]

    def _reach(self, command: np.ndarray) -> float:
        speed = np.hypot(command[0], command[1]) + abs(command[2]) * self.reach_radius
        return self.reach_radius + speed * self.config.horizon

    @staticmethod
    def _inside(poses: np.ndarray, points: np.ndarray, half: np.ndarray) -> np.ndarray:
        """(T, P): point p inside the rectangle of half-sizes ``half`` at pose t."""
        c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
        dx = points[None, :, 0] - poses[:, 0:1]
        dy = points[None, :, 1] - poses[:, 1:2]
        qx, qy = c * dx + s * dy, -s * dx + c * dy
        return (np.abs(qx) <= half[0]) & (np.abs(qy) <= half[1])

    def obstacle_scale(self, command: np.ndarray, points: np.ndarray) -> float:
        """The largest s in [0, 1] whose sweep hits no new scan point."""
        if len(points) == 0:
            return 1.0
        origin = np.zeros((1, 3))
        in_body = self._inside(origin, points, self.body)[0]
        in_margin = self._inside(origin, points, self.half)[0] & ~in_body
        outside = ~in_body & ~in_margin
        if not (in_margin.any() or outside.any()):
            return 1.0
        poses = arc(command, self.times)
        hit = self._inside(poses, points[outside], self.half).any(axis=1)
        hit |= self._inside(poses, points[in_margin], self.body).any(axis=1)
        if not hit.any():
            return 1.0
        first = int(np.argmax(hit))  # the first colliding sample; the one before it is clear
        return first * self.config.time_step / self.config.horizon

    def user_scale(
        self, command: np.ndarray, upper: float, users: np.ndarray, velocities: np.ndarray
    ) -> float:
        """The largest s <= ``upper`` (from a grid) that takes the robot into no user's collision
        distance, users (N, 2) and their velocities (N, 2) in the robot frame at t = 0."""
        if len(users) == 0 or upper <= 0.0:
            return upper
        future = users[None] + self.times[:, None, None] * velocities[None]  # (T, N, 2)
        still = np.linalg.norm(future, axis=-1)
        scales = upper * self.fractions  # (S,), descending to 0
        robot = arc(command, scales[:, None] * self.times[None])[..., None, :2]  # (S, T, 1, 2)
        d = np.linalg.norm(future[None] - robot, axis=-1)  # (S, T, N)
        bad = np.any((d < self.user_distance) & (d < still[None] - 1e-9), axis=(1, 2))
        return float(scales[np.argmin(bad)]) if not bad.all() else 0.0

    def __call__(self, command, ranges, users, velocities, scan=None) -> tuple[np.ndarray, str | None]:
        """(filtered command, what limited it: None, "obstacle" or "user").

        ``scan`` (M, 2): the sensor's own returns in the robot frame at its full resolution (see
        :func:`methd_jax.deploy.mcap_replay.scan_points`); when given, obstacles are checked against
        it instead of ``ranges``, so a pole thinner than the gap between the policy's rays is seen."""
        command = np.asarray(command, np.float64)
        if not self.config.enabled or not np.any(command):
            return command, None
        if scan is None:
            points = self.points(ranges, command)
        else:
            points = scan[np.linalg.norm(scan, axis=1) < self._reach(command)]
        s_obstacle = self.obstacle_scale(command, points)
        s = self.user_scale(command, s_obstacle, users, velocities)
        reason = "user" if s < s_obstacle else ("obstacle" if s_obstacle < 1.0 else None)
        return command * s, reason
