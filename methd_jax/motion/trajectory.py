"""One recorded walk-and-interact sequence: head and wrist poses at 100 Hz and the request time."""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np

RATE_HZ = 100.0
"""Sample rate of recordings (Qualisys, thesis §4.3.1)."""
GLITCH_SPEED = 2.0
"""Head speeds above this between consecutive samples are tracking errors (thesis §4.3.1), m/s."""


class MotionDataError(ValueError):
    """A recording that cannot be used; the message names the file and the problem."""


class TrackingGlitchWarning(UserWarning):
    """Samples were repaired because the head jumped faster than a person can move."""


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """A walk-and-interact sequence. Poses are ``x, y, z, qx, qy, qz, qw`` in the world frame (metres)."""

    name: str
    time: np.ndarray  # (T,) seconds since the first sample, uniform at RATE_HZ
    head: np.ndarray  # (T, 7) head marker pose
    wrist: np.ndarray  # (T, 7) wrist marker pose
    request_time: float  # seconds since the first sample of the first True on /haptic_request
    start_ns: int = 0  # absolute time of the first sample, nanoseconds

    def __post_init__(self):
        T = len(self.time)
        if self.head.shape != (T, 7) or self.wrist.shape != (T, 7):
            raise MotionDataError(
                f"{self.name}: head {self.head.shape} and wrist {self.wrist.shape} must be ({T}, 7)"
            )
        if not 0.0 <= self.request_time <= self.time[-1] + 1e-9:
            raise MotionDataError(
                f"{self.name}: request at {self.request_time:.3f} s lies outside the recording "
                f"(0 to {self.time[-1]:.3f} s)"
            )

    @property
    def request_index(self) -> int:
        """Index of the first sample at or after the request."""
        return int(np.searchsorted(self.time, self.request_time - 1e-9))

    @property
    def duration(self) -> float:
        """Seconds from the first sample to the request."""
        return float(self.request_time)


def yaw_from_quat(q: np.ndarray) -> np.ndarray:
    """Heading (rotation about world z) of quaternions ``(..., 4)`` in x, y, z, w order."""
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def quat_from_yaw_pitch(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray | float = 0.0) -> np.ndarray:
    """Quaternions ``(..., 4)`` (x, y, z, w) of intrinsic z-y-x rotations (yaw, then pitch, then roll)."""
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cr, sr = np.cos(np.asarray(roll) / 2), np.sin(np.asarray(roll) / 2)
    return np.stack(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ],
        -1,
    )


def repair_glitches(name: str, time: np.ndarray, poses: np.ndarray, topic: str) -> np.ndarray:
    """Replaces samples reached at more than ``GLITCH_SPEED`` from the last good one by interpolation.

    Positions are interpolated linearly and orientations by normalised linear interpolation between
    the good samples around each glitch. Emits one :class:`TrackingGlitchWarning` with the count.
    """

    def plausible(a, b):
        return np.linalg.norm(poses[b, :2] - poses[a, :2]) <= GLITCH_SPEED * abs(time[b] - time[a]) + 1e-9

    # the anchor is the first sample that its next two agree with, so that a glitch in the very
    # first samples is judged against the track rather than the track against the glitch
    anchor = next((i for i in range(len(time) - 2) if plausible(i, i + 1) and plausible(i + 1, i + 2)), 0)
    good = np.ones(len(time), bool)
    for order in (range(anchor + 1, len(time)), range(anchor - 1, -1, -1)):
        last = anchor
        for i in order:
            if plausible(last, i):
                last = i
            else:
                good[i] = False
    bad = int((~good).sum())
    if bad == 0:
        return poses
    fixed = poses.copy()
    for k in range(7):
        fixed[~good, k] = np.interp(time[~good], time[good], poses[good, k])
    q = fixed[:, 3:]
    fixed[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    warnings.warn(
        f"{name}: repaired {bad} tracking glitch sample(s) on {topic} (speed > {GLITCH_SPEED} m/s) "
        "by interpolation",
        TrackingGlitchWarning,
        stacklevel=3,
    )
    return fixed


def gaussian_smooth(x: np.ndarray, sigma_samples: float) -> np.ndarray:
    """Gaussian filter along axis 0 with edge values held (no shrinking at the ends)."""
    if sigma_samples <= 0:
        return x
    r = math.ceil(3 * sigma_samples)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_samples) ** 2)
    k /= k.sum()
    pad = np.concatenate([np.repeat(x[:1], r, 0), x, np.repeat(x[-1:], r, 0)], 0)
    flat = pad.reshape(len(pad), -1)
    out = np.stack([np.convolve(flat[:, j], k, mode="valid") for j in range(flat.shape[1])], 1)
    return out.reshape(x.shape)
