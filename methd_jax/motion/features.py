"""Derived user features at the 50 Hz control rate, packed for indexing on device.

From the head marker (the thesis had no body tracking): the 2D pose ``(x, y, yaw)``, velocities
``(vx, vy, w)`` and accelerations, both in the world frame and in the user's own frame (x forward),
the haptic interaction pose (HIP) the robot should occupy, the wrist height, and the request step.
:class:`MotionBank` holds them as fixed-shape arrays ``(N, T_max, ...)`` padded after each
trajectory's end with the user standing still, plus lengths, so that an environment can read any
trajectory at any step inside ``jit``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from methd_jax.control import CONTROL_HZ
from methd_jax.motion.trajectory import RATE_HZ, Trajectory, gaussian_smooth, yaw_from_quat


@dataclasses.dataclass(frozen=True)
class HipConfig:
    """Where the robot base should be for a haptic interaction, relative to the user.

    The thesis places the HIP in front of the user with a lateral offset for natural reaching
    (Fig. 4.5) but gives no numbers; these defaults put the base 2 m ahead (clear of the 1.77 m
    critical distance) and 0.3 m to the user's right (the wrist marker's side), facing the user.
    """

    distance: float = 2.0
    """Metres ahead of the user."""
    lateral: float = -0.3
    """Metres to the user's left (negative: right)."""
    yaw_offset: float = math.pi
    """Robot yaw relative to the user's heading (pi: facing the user)."""
    heading_smoothing: float = 0.5
    """Standard deviation (s) of the Gaussian that steadies the user heading used for the HIP, so
    that glancing around does not swing the HIP."""

    def offset(self, c, s):
        """(dx, dy) from a user to their HIP, for a heading of cosine ``c`` and sine ``s`` (floats,
        numpy or JAX arrays alike)."""
        return c * self.distance - s * self.lateral, s * self.distance + c * self.lateral


def user_features(traj: Trajectory, hip: HipConfig = HipConfig()) -> dict[str, np.ndarray]:
    """Per-step features of one trajectory at ``CONTROL_HZ`` (numpy, float64).

    Positions are lightly smoothed (Gaussian, 20 ms) before decimation from 100 Hz to 50 Hz so that
    sub-millimetre tracking noise does not turn into velocity noise; derivatives are central.
    """
    step = round(RATE_HZ / CONTROL_HZ)
    xy = gaussian_smooth(traj.head[:, :2], 2.0)[::step]
    heading_vec = np.stack(
        [np.cos(yaw_from_quat(traj.head[:, 3:])), np.sin(yaw_from_quat(traj.head[:, 3:]))], 1
    )
    yaw_vec = gaussian_smooth(heading_vec, 2.0)[::step]
    yaw = np.arctan2(yaw_vec[:, 1], yaw_vec[:, 0])
    dt = 1.0 / CONTROL_HZ
    n = len(xy)
    if n < 3:
        raise ValueError(f"{traj.name}: too short for features ({len(traj.time)} samples)")
    yaw_unwrapped = np.unwrap(yaw)
    vel_w = np.concatenate([np.gradient(xy, dt, axis=0), np.gradient(yaw_unwrapped, dt)[:, None]], 1)
    acc_w = np.gradient(vel_w, dt, axis=0)
    c, s = np.cos(yaw), np.sin(yaw)

    def local(v):
        return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)

    steady = gaussian_smooth(yaw_vec, hip.heading_smoothing * CONTROL_HZ)
    h_yaw = np.arctan2(steady[:, 1], steady[:, 0])
    ch, sh = np.cos(h_yaw), np.sin(h_yaw)
    hip_xy = xy + np.stack(hip.offset(ch, sh), 1)
    hip_yaw = np.arctan2(np.sin(h_yaw + hip.yaw_offset), np.cos(h_yaw + hip.yaw_offset))
    wrist_z = (
        gaussian_smooth(traj.wrist[:, 2:3], 2.0)[::step, 0]
        - gaussian_smooth(traj.head[:, 2:3], 2.0)[::step, 0]
    )
    request_step = min(n - 1, math.ceil(traj.request_time * CONTROL_HZ - 1e-6))
    return {
        "pose": np.concatenate([xy, yaw[:, None]], 1),
        "vel_world": vel_w,
        "vel_local": local(vel_w),
        "acc_world": acc_w,
        "acc_local": local(acc_w),
        "hip": np.concatenate([hip_xy, hip_yaw[:, None]], 1),
        "wrist_height": wrist_z,
        "request_step": np.int32(request_step),
        "length": np.int32(n),
    }


@struct.dataclass
class MotionBank:
    """Trajectories as padded arrays at 50 Hz; index ``[traj, step]`` on device.

    After ``length[i]`` the user stands at the last pose with zero velocity and acceleration.
    Angles are wrapped to [-pi, pi). The user frame has x forward (along the head's heading).
    """

    pose: jax.Array  # (N, T, 3) x, y, yaw of the head in the world
    vel_world: jax.Array  # (N, T, 3) vx, vy (m/s) and yaw rate (rad/s), world frame
    vel_local: jax.Array  # (N, T, 3) the same in the user's frame
    acc_world: jax.Array  # (N, T, 3) their time derivatives, world frame
    acc_local: jax.Array  # (N, T, 3) the same in the user's frame
    hip: jax.Array  # (N, T, 3) haptic interaction pose x, y, yaw (world)
    wrist_height: jax.Array  # (N, T) wrist minus head height, m (rises to about -0.3 at the reach)
    request_step: jax.Array  # (N,) int32 first step at or after the haptic request
    length: jax.Array  # (N,) int32 number of recorded steps

    @property
    def num_trajectories(self) -> int:
        return self.pose.shape[0]

    @property
    def max_steps(self) -> int:
        return self.pose.shape[1]

    @classmethod
    def from_trajectories(
        cls, trajectories: Sequence[Trajectory], hip: HipConfig = HipConfig(), max_steps: int | None = None
    ) -> MotionBank:
        """Derives and packs the features of ``trajectories`` (padding to the longest, or ``max_steps``)."""
        if not trajectories:
            raise ValueError("MotionBank needs at least one trajectory")
        feats = [user_features(t, hip) for t in trajectories]
        longest = max(int(f["length"]) for f in feats)
        T = longest if max_steps is None else max_steps
        if T < longest:
            raise ValueError(f"max_steps {T} is shorter than the longest trajectory ({longest} steps)")
        fields = {}
        for key in ("pose", "vel_world", "vel_local", "acc_world", "acc_local", "hip", "wrist_height"):
            arrs = []
            for f in feats:
                a = f[key]
                if key in ("pose", "hip", "wrist_height"):  # hold the last value
                    pad = np.repeat(a[-1:], T - len(a), 0)
                else:  # standing still
                    pad = np.zeros((T - len(a), *a.shape[1:]))
                arrs.append(np.concatenate([a, pad], 0))
            fields[key] = jnp.asarray(np.stack(arrs), jnp.float32)
        fields["request_step"] = jnp.asarray([f["request_step"] for f in feats], jnp.int32)
        fields["length"] = jnp.asarray([f["length"] for f in feats], jnp.int32)
        return cls(**fields)

    def at(self, traj: jax.Array, step: jax.Array) -> dict[str, jax.Array]:
        """Features of trajectory ``traj`` at ``step`` (clamped to the padded range); jittable."""
        step = jnp.clip(step, 0, self.max_steps - 1)
        return {
            "pose": self.pose[traj, step],
            "vel_world": self.vel_world[traj, step],
            "vel_local": self.vel_local[traj, step],
            "acc_world": self.acc_world[traj, step],
            "acc_local": self.acc_local[traj, step],
            "hip": self.hip[traj, step],
            "wrist_height": self.wrist_height[traj, step],
            "requested": step >= self.request_step[traj],
            "ended": step >= self.length[traj] - 1,
        }

    def take(self, indices: Sequence[int]) -> MotionBank:
        """A bank of the given trajectories (e.g. a train or test split)."""
        idx = jnp.asarray(np.asarray(indices, np.int32))
        return jax.tree.map(lambda a: a[idx], self)
