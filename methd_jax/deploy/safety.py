"""A final-stage safety layer in the spirit of nav2's collision monitor ("approach" behaviour).

The commanded twist is held over a short horizon and the footprint (the base's rectangle plus a
margin) is swept along the resulting arc against the latest scan's points and the users, who are
extrapolated at their current velocity. The command is scaled down by the largest factor that
keeps the sweep clear (0: stop). For static points scaling is exact: at factor s the robot covers
in the horizon T what the full command covers in s*T, so s = (last clear sample time) / T. Each
point's path in the base's frame is tested between consecutive samples, not only at them
(:func:`segment_meets_box`), so a corner cannot pass a point unseen between two samples.

When the command's own sweep is blocked, the same test is run for a few neighbours of it: its
linear velocity turned by +-``slide_angles``, each with and without its yaw rate. Of these, each
scaled to its own clear factor, the one closest to the command is sent (the distance in
(vx, vy, r * wz), r the footprint's half-diagonal, so a yaw rate counts as the corners' speed):
the smallest change to the command that keeps the sweep clear, among the candidates. A base
commanded into a wall at an angle slides along it instead of stopping (stopping near a wall lets
a walking user corner the robot), and a base that would swing a corner into furniture while
turning keeps its turn and steers off, or drives on without it. Ties go to the earlier candidate:
the command itself, then the command without its turn, then the turned ones in the order of
``slide_angles``.

For moving users the factors are tried from the chosen candidate's clear factor downwards; a factor
is refused when it brings the robot inside a user's collision distance and closer than standing
still would, so stopping is always allowed and moving away from a user who is already too close is
too.

Points already inside the footprint at t = 0 are ignored (self-returns or a collision that has
already happened): what is checked is what the command would newly hit. Points inside the margin
but outside the footprint at t = 0 are checked against the footprint itself, so the robot may
move away from a close wall but never into it.

The sweep takes the base to move as commanded, but a base carries its own velocity for a while
(its servos' response time, its finite deceleration): told to turn away from a table, it can still
slide into it. So the factor is finally lowered (halved, then zero) until the base, given the
scaled command for one control period and then braking for the horizon, stays clear of the scan
along the path :func:`coast` predicts from its measured velocity; when no factor does, it brakes.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class SafetyConfig:
    """Parameters of the collision monitor."""

    enabled: bool = True
    horizon: float = 1.0
    """Seconds the command is projected forward."""
    time_step: float = 0.01
    """Sampling of the sweep, s (0.01 s at 3 m/s is 3 cm, inside the margin), and the integration
    step of :func:`coast`."""
    margin: float = 0.05
    """Added to every side of the footprint, m."""
    user_distance: float | None = None
    """Robot-centre to user distance never to be entered, m (default: the policy's d_coll, 1.37 m)."""
    user_steps: int = 20
    """Scale factors tried against moving users."""
    slide_angles: tuple[float, ...] = (30.0, 60.0)
    """Degrees, each in (0, 90): a blocked command's linear velocity is also tried turned by plus
    and minus each (empty: the command is only scaled)."""
    deceleration: float = 3.0
    """How hard the base brakes along each of its own axes, m/s^2 (the Kairos model's servo
    limit). With ``yaw_deceleration`` and ``response_time`` it predicts how far the base coasts
    (see :func:`coast`)."""
    yaw_deceleration: float = 6.0
    """How hard the base stops turning, rad/s^2."""
    response_time: float = 0.1
    """Time constant of the base's velocity servos, s."""

    def __post_init__(self):
        if not (self.horizon > 0 and 0 < self.time_step <= self.horizon):
            raise ValueError(f"need 0 < time_step <= horizon, got {self.time_step} and {self.horizon}")
        if self.margin < 0 or (self.user_distance is not None and self.user_distance <= 0):
            raise ValueError("margin must be >= 0 and user_distance > 0")
        if self.user_steps < 1:
            raise ValueError("user_steps must be >= 1")
        if not all(0.0 < float(a) < 90.0 for a in self.slide_angles):
            raise ValueError(f"slide_angles must each lie in (0, 90) degrees, got {self.slide_angles!r}")
        for name in ("deceleration", "yaw_deceleration", "response_time"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")

    def turns(self) -> np.ndarray:
        """(K, 3) rows (cos, sin, keep yaw) of the candidates in the order ties are broken: the command,
        the command without its yaw rate, then +-each slide angle with and without it."""
        rows = [(1.0, 0.0, 1.0)]
        if self.slide_angles:
            rows.append((1.0, 0.0, 0.0))
        for a in np.deg2rad(np.asarray(self.slide_angles, np.float64)):
            c, s = float(np.cos(a)), float(np.sin(a))
            rows += [(c, s, 1.0), (c, -s, 1.0), (c, s, 0.0), (c, -s, 0.0)]
        return np.asarray(rows)


def candidates(command, turns):
    """The candidate commands ``(K, 3)`` of ``turns`` (see :meth:`SafetyConfig.turns`); numpy or JAX."""
    c, s, keep = turns[:, 0], turns[:, 1], turns[:, 2]
    vx, vy, wz = command[0], command[1], command[2]
    return (c * vx - s * vy, s * vx + c * vy, keep * wz)


def change(command, turns, scales, radius):
    """Squared distance in (vx, vy, radius * wz) from ``command`` to each candidate scaled by its
    factor, in closed form so that mirrored candidates tie exactly; numpy or JAX."""
    speed2 = command[0] ** 2 + command[1] ** 2
    turn2 = (radius * command[2]) ** 2
    return speed2 * (1.0 + scales**2 - 2.0 * scales * turns[:, 0]) + turn2 * (scales * turns[:, 2] - 1.0) ** 2


def arc(command: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses (x, y, yaw) ``(..., 3)`` reached from the origin after ``t`` s of a constant robot-frame
    twist (vx, vy, wz); ``command`` (3,) gives ``t.shape + (3,)``, ``command`` (K, 3) gives
    ``(K,) + t.shape + (3,)``."""
    command = np.asarray(command, np.float64)
    if command.ndim == 1:
        return arc(command[None], t)[0]
    t = np.asarray(t, np.float64)
    shape = (len(command),) + (1,) * t.ndim
    vx, vy, wz = (command[:, i].reshape(shape) for i in range(3))
    th = wz * t
    straight = np.abs(wz) < 1e-9
    w = np.where(straight, 1.0, wz)
    s, c = np.sin(th), np.cos(th)
    x = np.where(straight, vx * t, (vx * s + vy * (c - 1.0)) / w)
    y = np.where(straight, vy * t, (vx * (1.0 - c) + vy * s) / w)
    return np.stack(np.broadcast_arrays(x, y, th), -1)


def coast(velocity, commands, config: SafetyConfig, period: float) -> np.ndarray:
    """Poses (x, y, yaw) ``(T, 3)`` after each of ``commands`` (T, 3), robot-frame twists held
    ``period`` s each, of a base now at the origin moving at the robot-frame ``velocity``: per
    robot axis the servo accelerates by ``(command - velocity) / response_time``, at most
    ``deceleration`` (``yaw_deceleration``), integrated by explicit Euler at ``time_step`` (as
    :func:`methd_jax.robot.predict` does for the simulated base)."""
    # plain floats: a few hundred substeps of scalar arithmetic are cheaper than numpy's per-call cost
    gain, lin, yaw = 1.0 / config.response_time, config.deceleration, config.yaw_deceleration
    h = config.time_step
    substeps = max(1, round(period / h))
    x = y = th = 0.0
    vx, vy, w = (float(v) for v in velocity)
    out = np.empty((len(commands), 3))
    for i, (cx, cy, cw) in enumerate(np.asarray(commands, np.float64).tolist()):
        for _ in range(substeps):
            c, s = math.cos(th), math.sin(th)
            ax = min(max(gain * (cx - (c * vx + s * vy)), -lin), lin)  # along the robot's own axes
            ay = min(max(gain * (cy - (-s * vx + c * vy)), -lin), lin)
            aw = min(max(gain * (cw - w), -yaw), yaw)
            vx, vy, w = vx + h * (c * ax - s * ay), vy + h * (s * ax + c * ay), w + h * aw
            x, y, th = x + h * vx, y + h * vy, th + h * w
        out[i] = (x, y, th)
    return out


def _local(poses: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y), each (..., P): ``points`` (P, 2) in the frame of each pose (..., 3)."""
    c, s = np.cos(poses[..., 2:3]), np.sin(poses[..., 2:3])
    dx = points[:, 0] - poses[..., 0:1]
    dy = points[:, 1] - poses[..., 1:2]
    return c * dx + s * dy, -s * dx + c * dy


def reach(command, radius: float, horizon: float, xp=np):
    """How far from the base's centre a footprint of half-diagonal ``radius`` can get in ``horizon``
    s of ``command``: the radius plus the centre's path plus the corners' turn (points beyond it
    cannot stop the sweep); numpy, or JAX with ``xp=jax.numpy``."""
    return radius + (xp.hypot(command[0], command[1]) + abs(command[2]) * radius) * horizon


def segment_meets_box(start, end, half, xp=np):
    """(...): whether the segment ``start`` -> ``end`` (..., 2) meets the box |x| <= half[0],
    |y| <= half[1] (the slab test); numpy, or JAX with ``xp=jax.numpy``.

    A sweep tests each point's path in the base's frame between consecutive samples, not only the
    samples: a corner can pass a point between two samples, and within a sample the path is a
    straight segment up to the turn of one sample (0.02 rad at 2 rad/s: 0.04 mm at the corners)."""
    d = end - start
    moving = xp.abs(d) > 1e-12
    step = xp.where(moving, d, 1.0)
    a, b = (-half - start) / step, (half - start) / step
    within = xp.abs(start) <= half  # a coordinate that does not change is inside its slab or never
    lo = xp.where(moving, xp.minimum(a, b), xp.where(within, -xp.inf, xp.inf))
    hi = xp.where(moving, xp.maximum(a, b), xp.where(within, xp.inf, -xp.inf))
    return xp.maximum(xp.max(lo, axis=-1), 0.0) <= xp.minimum(xp.min(hi, axis=-1), 1.0)


class CollisionMonitor:
    """Scales robot-frame commands so that the footprint stays clear over the horizon."""

    def __init__(
        self,
        length: float,
        width: float,
        num_rays: int,
        user_distance: float,
        config=SafetyConfig(),
        period: float = 0.02,
    ):
        """``period``: the control period, s (how long the base holds each command)."""
        self.config = config
        self.period = period
        self.brake_steps = round(config.horizon / period)
        self.body = np.array([0.5 * length, 0.5 * width])
        self.half = self.body + config.margin
        self.reach_radius = float(np.hypot(*self.half))
        angles = 2.0 * np.pi * np.arange(num_rays) / num_rays
        self.directions = np.stack([np.cos(angles), np.sin(angles)], -1)
        self.times = np.arange(1, round(config.horizon / config.time_step) + 1) * config.time_step
        self.user_distance = config.user_distance or user_distance
        self.fractions = np.linspace(1.0, 0.0, config.user_steps + 1)
        self.turns = config.turns()

    def points(self, ranges: np.ndarray, command: np.ndarray) -> np.ndarray:
        """Points (P, 2) of the monitor's own rays (``ranges``) the sweep of ``command`` could reach."""
        near = np.isfinite(ranges) & (ranges < self._reach(command))
        return ranges[near, None] * self.directions[near]

    def _reach(self, command: np.ndarray) -> float:
        return reach(command, self.reach_radius, self.config.horizon)

    @staticmethod
    def _inside(poses: np.ndarray, points: np.ndarray, half: np.ndarray) -> np.ndarray:
        """(T, P): point p inside the rectangle of half-sizes ``half`` at pose t."""
        qx, qy = _local(poses, points)
        return (np.abs(qx) <= half[0]) & (np.abs(qy) <= half[1])

    def _new_points(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The points a motion can newly hit and the half-sizes (hx, hy), each (P,), of the box each
        must stay out of: points inside the footprint are dropped (a contact that has happened),
        points inside the margin are held to the footprint itself, the rest to footprint + margin."""
        origin = np.zeros((1, 3))
        in_body = self._inside(origin, points, self.body)[0]
        in_margin = self._inside(origin, points, self.half)[0] & ~in_body
        points, in_margin = points[~in_body], in_margin[~in_body]
        hx = np.where(in_margin, self.body[0], self.half[0])
        hy = np.where(in_margin, self.body[1], self.half[1])
        return points, hx, hy

    def obstacle_scale(self, command: np.ndarray, points: np.ndarray) -> float:
        """The largest s in [0, 1] whose sweep hits no new scan point."""
        return float(self.obstacle_scales(np.asarray(command)[None], points)[0])

    def obstacle_scales(self, commands: np.ndarray, points: np.ndarray) -> np.ndarray:
        """:meth:`obstacle_scale` of each of ``commands`` (K, 3), swept together: (K,)."""
        scales = np.ones(len(commands))
        if len(points) == 0 or len(commands) == 0:
            return scales
        points, hx, hy = self._new_points(points)
        if len(points) == 0:
            return scales
        todo = np.arange(len(commands))  # the candidates not yet blocked
        px = np.broadcast_to(points[:, 0], (len(todo), len(points)))  # each point one sample earlier
        py = np.broadcast_to(points[:, 1], (len(todo), len(points)))
        chunk = 10  # samples swept at a time: a blocked sweep (most of them) stops early
        for lo in range(0, len(self.times), chunk):
            qx, qy = _local(arc(commands[todo], self.times[lo : lo + chunk]), points)  # (k, t, P) each
            bx = np.concatenate([px[:, None], qx[:, :-1]], 1)
            by = np.concatenate([py[:, None], qy[:, :-1]], 1)
            # only a segment whose bounding box meets the box can meet it: the slab test runs on those
            near = (np.minimum(bx, qx) <= hx) & (np.maximum(bx, qx) >= -hx)
            near &= (np.minimum(by, qy) <= hy) & (np.maximum(by, qy) >= -hy)
            k, t, p = np.nonzero(near)
            start, end = np.stack([bx[k, t, p], by[k, t, p]], -1), np.stack([qx[k, t, p], qy[k, t, p]], -1)
            hit = segment_meets_box(start, end, np.stack([hx[p], hy[p]], -1))
            first = np.full(len(todo), len(self.times))
            np.minimum.at(first, k[hit], t[hit])  # each candidate's first colliding step in the chunk
            blocked = first < len(self.times)
            # the sample before the first colliding step is clear
            scales[todo[blocked]] = (lo + first[blocked]) * self.config.time_step / self.config.horizon
            todo, px, py = todo[~blocked], qx[~blocked, -1], qy[~blocked, -1]
            if len(todo) == 0:
                break
        return scales

    def slide(self, command: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, float]:
        """(candidate, its clear factor): the command and :meth:`obstacle_scale` unless that blocks it,
        else the scaled candidate closest to the command (see the module docstring)."""
        s0 = self.obstacle_scale(command, points)
        if s0 == 1.0 or len(self.turns) == 1:
            return command, s0
        cands = np.stack(candidates(command, self.turns), -1)
        r = self.reach_radius
        # a candidate whose cost cannot beat the command's own scaled cost even unblocked is not
        # swept (exact: a later candidate wins only when strictly better)
        speed2, turn2 = command[0] ** 2 + command[1] ** 2, (r * command[2]) ** 2
        c, keep = self.turns[:, 0], self.turns[:, 2]
        denominator = speed2 + turn2 * keep  # the scale that minimises each candidate's cost
        ideal = np.clip((speed2 * c + turn2 * keep) / np.where(denominator > 0, denominator, 1.0), 0, 1)
        floor = change(command, self.turns, ideal, r) - 1e-9 * (speed2 + turn2)
        scales = np.full(len(cands), s0)
        cost = np.full(len(cands), np.inf)
        cost[0] = change(command, self.turns[:1], np.array([s0]), r)[0]
        todo = np.flatnonzero(floor < cost[0])
        todo = todo[todo > 0]
        scales[todo] = self.obstacle_scales(cands[todo], points)
        cost[todo] = change(command, self.turns[todo], scales[todo], r)
        k = int(np.argmin(cost))  # ties to the earlier candidate
        return cands[k], float(scales[k])

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

    def path_clear(self, poses: np.ndarray, points: np.ndarray) -> bool:
        """Whether the footprint plus margin, moving from the origin through ``poses`` (T, 3), newly
        meets none of ``points`` between one pose and the next (the sweep's test on any path)."""
        points, hx, hy = self._new_points(points)
        if len(points) == 0:
            return True
        qx, qy = _local(poses, points)  # (T, P)
        end = np.stack([qx, qy], -1)
        start = np.concatenate([points[None], end[:-1]])
        return not np.any(segment_meets_box(start, end, np.stack([hx, hy], -1)[None]))

    def brake_scale(
        self, command: np.ndarray, upper: float, velocity: np.ndarray, points: np.ndarray
    ) -> float:
        """The first of ``upper``, half of it and 0 at which the base, given ``command`` times it
        for one control period and then braking for the horizon, stays clear of ``points`` (every
        return, robot frame) along the path :func:`coast` predicts from ``velocity``; 0 if none."""
        for factor in (upper, 0.5 * upper, 0.0):
            commands = np.zeros((1 + self.brake_steps, 3))
            commands[0] = factor * command
            poses = coast(velocity, commands, self.config, self.period)
            extent = self.reach_radius + np.max(np.linalg.norm(poses[:, :2], axis=1)) + 0.01
            if self.path_clear(poses, points[np.linalg.norm(points, axis=1) < extent]):
                return factor
        return 0.0

    def __call__(
        self, command, ranges, users, velocities, scan=None, velocity=None
    ) -> tuple[np.ndarray, str | None]:
        """(filtered command, what limited it: None, "obstacle" or "user").

        ``scan`` (M, 2): the sensor's own returns in the robot frame at its full resolution (see
        :func:`methd_jax.deploy.mcap_replay.scan_points`); when given, obstacles are checked against
        it instead of ``ranges``, so a pole thinner than the gap between the policy's rays is seen.
        ``velocity``: the base's robot-frame velocity (vx, vy, wz); without it the base is taken to
        be at rest."""
        command = np.asarray(command, np.float64)
        if not self.config.enabled or not np.any(command):
            return command, None
        if scan is None:
            ok = np.isfinite(ranges)
            every = ranges[ok, None] * self.directions[ok]
        else:
            every = np.asarray(scan, np.float64)
        points = every[np.linalg.norm(every, axis=1) < self._reach(command)]
        chosen, s_obstacle = self.slide(command, points)
        s_user = self.user_scale(chosen, s_obstacle, users, velocities)
        v = np.zeros(3) if velocity is None else np.asarray(velocity, np.float64)
        s = self.brake_scale(chosen, s_user, v, every)
        changed = s_obstacle < 1.0 or s < s_user or not np.array_equal(chosen, command)
        reason = "user" if s_user < s_obstacle and s == s_user else ("obstacle" if changed else None)
        return chosen * s, reason
