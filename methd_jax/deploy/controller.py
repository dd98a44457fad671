"""The deployed controller: one 50 Hz tick of robot inputs -> a safe velocity command.

``Controller.tick`` never raises: a watchdog turns stale, missing or invalid inputs into a zero
command with a counted reason, and the safety layer (:mod:`methd_jax.deploy.safety`) scales the
policy's command so the footprint stays clear of the scan and the users over a short horizon.
Every intervention is counted in ``Controller.interventions``.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from methd_jax.deploy import observation
from methd_jax.deploy.policy import ROBOT_LIMITS, DeployError, NumpyPolicy, OnnxPolicy, load_manifest
from methd_jax.deploy.safety import CollisionMonitor, SafetyConfig


@dataclasses.dataclass
class Inputs:
    """One tick of inputs, world frame unless said otherwise; stamps in seconds on the clock that
    ``Controller.tick(now=...)`` uses (None: not checked for age).

    ``ranges`` (num_rays,) LiDAR ranges in the robot frame, ray i at 2*pi*i/num_rays counter-clockwise
    from +x (inf or above range: no return); ``robot_pose`` (x, y, yaw); ``velocity`` (vx, vy, wz) in
    the robot frame; ``acceleration`` likewise, or None to difference successive velocities;
    ``users`` (N, 6) x, y, yaw, vx, vy, wz; ``goal`` (x, y, yaw); ``scan_points`` (M, 2) the
    LiDAR's returns at its own full resolution in the robot frame (None: the safety layer checks
    the policy's rays only, and a pole between two of them goes unseen).
    """

    ranges: np.ndarray | None
    robot_pose: np.ndarray | None
    velocity: np.ndarray | None
    users: np.ndarray | None
    goal: np.ndarray | None
    acceleration: np.ndarray | None = None
    scan_points: np.ndarray | None = None
    scan_stamp: float | None = None
    odom_stamp: float | None = None
    users_stamp: float | None = None


@dataclasses.dataclass(frozen=True)
class Command:
    """A tick's result: ``twist`` (vx, vy, wz) to send, robot frame; ``policy`` the command before the
    safety layer (zero when the watchdog stopped the robot); ``reason`` why it differs (None if not)."""

    twist: np.ndarray
    policy: np.ndarray
    reason: str | None


PAUSE = 3.0
"""Control periods between two ticks beyond which the controller was paused (:meth:`Controller.resume`);
a tick or two lost to jitter is not a pause (the velocity is differenced over the periods that passed)."""


def periods_since(last_tick: float | None, now: float | None, dt: float) -> int | None:
    """Whole control periods of ``dt`` from ``last_tick`` to ``now`` (1 when either is unknown; jitter
    within a period is the loop's timing, not the motion's), or None after a pause (:data:`PAUSE`)."""
    if now is None or last_tick is None:
        return 1
    if now - last_tick > PAUSE * dt:
        return None
    return max(1, round((now - last_tick) / dt))


@dataclasses.dataclass(frozen=True)
class WatchdogConfig:
    max_age: float = 0.2
    """Inputs older than this (s) stop the robot (a 10 Hz LiDAR is 0.1 s old at worst)."""


class Controller:
    """Loads a deployment folder (``python -m train.export``) with numpy and onnxruntime only."""

    def __init__(
        self,
        path: str | Path,
        *,
        backend: str = "onnx",
        safety: SafetyConfig | None = None,
        watchdog: WatchdogConfig = WatchdogConfig(),
    ):
        self.manifest = load_manifest(path)
        if self.manifest["action"].get("frame") != "robot":
            raise DeployError(
                f"{path}: a {self.manifest['env']!r} policy does not drive the base (its action is no "
                "velocity command in the robot frame); a GuideRL policy sets the goal of a 'nav' policy"
            )
        if backend == "onnx":
            self.policy = OnnxPolicy(self.manifest)
        elif backend == "numpy":
            self.policy = NumpyPolicy(self.manifest)
        else:
            raise DeployError(f"unknown backend {backend!r}; use 'onnx' or 'numpy'")
        self.deployment = d = self.manifest["deployment"]
        self.num_rays = d["lidar"]["num_rays"]
        self.num_users = d["num_users"]
        self.dt = 1.0 / d["control_hz"]
        self.watchdog = watchdog
        fp = d["footprint"]
        self.monitor = CollisionMonitor(
            fp["length"],
            fp["width"],
            self.num_rays,
            d["collision_distance"],
            safety or SafetyConfig(),
            period=self.dt,
        )
        self.interventions: collections.Counter[str] = collections.Counter()
        self.ticks = 0
        self.reset()

    def reset(self):
        """Forget the action history and the last velocity: the next tick starts them from the
        base's own motion (see :meth:`resume`)."""
        self.actions = np.zeros((2, 3))
        self.last_velocity: np.ndarray | None = None
        self.last_tick: float | None = None

    def resume(self, velocity: np.ndarray):
        """Start the history from the base's robot-frame ``velocity``: the previous actions those
        that command it and no acceleration this tick. Training never pauses its policy; a history
        from before a pause (a watchdog stop, or a behaviour that drove the base meanwhile) would
        feed the whole change since as one tick's acceleration and blend the actions of back then
        into the command. At rest this is the zero history of an episode's start."""
        scale = np.asarray(self.deployment["action"]["scale"], np.float64)
        self.actions = np.tile(np.clip(velocity / scale, -1.0, 1.0), (2, 1))
        self.last_velocity = velocity

    # -- the watchdog --------------------------------------------------------------------------

    def _check(self, x: Inputs, now: float | None) -> str | None:
        shapes = {
            "ranges": (self.num_rays,),
            "robot_pose": (3,),
            "velocity": (3,),
            "users": (self.num_users, 6),
            "goal": (3,),
        }
        if x.acceleration is not None:
            shapes["acceleration"] = (3,)
        for name, shape in shapes.items():
            value = getattr(x, name)
            if value is None:
                return f"missing_{name}"
            try:
                value = np.asarray(value, np.float64)
            except (TypeError, ValueError):
                return f"invalid_{name}"
            if value.size == 0:
                return f"empty_{name}"
            if value.shape != shape:
                return f"shape_{name}"
            if name == "ranges":
                if np.isnan(value).any():
                    return "nan_ranges"
                if (value < 0).any():
                    return "negative_ranges"
                if np.mean(value == 0) > 0.5:  # a blinded or failed sensor, not a scene
                    return "zero_ranges"
            elif not np.isfinite(value).all():
                return f"nan_{name}"
        if x.scan_points is not None:
            try:
                points = np.asarray(x.scan_points, np.float64)
            except (TypeError, ValueError):
                return "invalid_scan_points"
            if points.ndim != 2 or points.shape[1] != 2:
                return "shape_scan_points"
            if not np.isfinite(points).all():
                return "nan_scan_points"
        if now is not None:
            for name in ("scan", "odom", "users"):
                stamp = getattr(x, f"{name}_stamp")
                # a stamp from the future (beyond clock jitter) is as untrustworthy as an old one
                if stamp is not None and not (-self.watchdog.max_age <= now - stamp <= self.watchdog.max_age):
                    return f"stale_{name}"
        return None

    # -- one tick ------------------------------------------------------------------------------

    def tick(self, x: Inputs, now: float | None = None) -> Command:
        """The command for this tick (never raises; see ``interventions`` for what was stopped)."""
        self.ticks += 1
        try:
            problem = self._check(x, now)
            if problem is not None:
                return self._stop(f"watchdog:{problem}")
            velocity = np.asarray(x.velocity, np.float64)
            periods = periods_since(self.last_tick, now, self.dt)
            self.last_tick = now
            if self.last_velocity is None or periods is None:
                self.resume(velocity)
                periods = 1
            accel = (
                np.asarray(x.acceleration, np.float64)
                if x.acceleration is not None
                else (velocity - self.last_velocity) / (periods * self.dt)
            )
            obs = observation.observe(
                self.deployment,
                ranges=np.asarray(x.ranges, np.float64),
                robot_pose=np.asarray(x.robot_pose, np.float64),
                velocity=velocity,
                acceleration=accel,
                actions=self.actions,
                users=np.asarray(x.users, np.float64),
                goal=np.asarray(x.goal, np.float64),
            )
            action = np.asarray(self.policy(obs), np.float64)
            if not np.isfinite(action).all():
                return self._stop("watchdog:nan_action")
            cmd = observation.command(self.deployment, action, self.actions)
            self.actions = np.stack([action, self.actions[0]])
            self.last_velocity = velocity
            pose = np.asarray(x.robot_pose, np.float64)
            users = np.asarray(x.users, np.float64)
            local = observation.to_local(pose, users[:, :2])
            local_vel = observation.rotate(-pose[2], users[:, 3:5])
            scan = None if x.scan_points is None else np.asarray(x.scan_points, np.float64)
            safe, reason = self.monitor(
                cmd, np.asarray(x.ranges, np.float64), local, local_vel, scan, velocity
            )
            safe = clamp_to_limits(safe)
            if reason is not None:
                self.interventions[f"safety:{reason}"] += 1
                reason = f"safety:{reason}"
            return Command(safe, cmd, reason)
        except Exception as e:  # the 50 Hz loop must go on; the reason names what went wrong
            return self._stop(f"error:{type(e).__name__}")

    def _stop(self, reason: str) -> Command:
        self.interventions[reason] += 1
        self.reset()
        zero = np.zeros(3)
        return Command(zero, zero, reason)


def clamp_to_limits(twist: np.ndarray) -> np.ndarray:
    """``twist`` (vx, vy, wz) within the base's limits: the linear speed scaled down to its top speed
    (direction kept), the yaw rate clipped; whatever a manifest or a policy says."""
    twist = np.asarray(twist, np.float64)
    speed = math.hypot(twist[0], twist[1])
    linear = twist[:2] * min(1.0, ROBOT_LIMITS[0] / speed) if speed > 0 else twist[:2]
    return np.array([linear[0], linear[1], np.clip(twist[2], -ROBOT_LIMITS[1], ROBOT_LIMITS[1])])


def latency(controller: Controller, ticks: int = 2000, seed: int = 0) -> dict:
    """Median, p99 and max wall time of ``tick`` in ms on random inputs (safety layer included)."""
    rng = np.random.default_rng(seed)
    n, u = controller.num_rays, controller.num_users
    times = []
    for _ in range(ticks + 50):
        x = Inputs(
            ranges=rng.uniform(0.5, 6.0, n),
            robot_pose=rng.uniform(-3, 3, 3),
            velocity=rng.uniform(-1, 1, 3),
            users=np.concatenate(
                [
                    rng.uniform(-4, 4, (u, 2)),
                    rng.uniform(-math.pi, math.pi, (u, 1)),
                    rng.uniform(-1, 1, (u, 3)),
                ],
                1,
            ),
            goal=rng.uniform(-3, 3, 3),
        )
        t0 = time.perf_counter()
        controller.tick(x)
        times.append(time.perf_counter() - t0)
    ms = 1e3 * np.asarray(times[50:])
    return {
        "ticks": ticks,
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "max_ms": float(ms.max()),
    }
