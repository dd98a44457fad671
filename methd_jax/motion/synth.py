"""Synthetic walk-and-interact trajectories in the lab, with the thesis dataset's statistics.

Each trajectory (thesis §4.3.1): the participant stands, walks freely along waypoints that keep clear
of the lab's obstacles, in segments of different styles (normal, slow, fast, backwards,
side-stepping), sometimes pausing to look around; then decelerates, stops at a random place, raises
the wrist toward a virtual object, and triggers the haptic request. Trajectory ``k + 1`` starts
where trajectory ``k`` ended, as consecutive recordings do. Everything is drawn from one
``numpy.random.Generator`` seeded by ``seed``: the same seed gives the same data.

This is offline data generation on the host (numpy), not part of the jitted hot path.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from methd_jax.motion.trajectory import (
    RATE_HZ,
    Trajectory,
    gaussian_smooth,
    quat_from_yaw_pitch,
    yaw_from_quat,
)

# Walking styles: (name, probability, speed range m/s, body yaw relative to the walking direction).
STYLES = (
    ("normal", 0.55, (0.75, 1.0), 0.0),
    ("slow", 0.15, (0.6, 0.75), 0.0),
    ("fast", 0.06, (1.1, 1.6), 0.0),
    ("backwards", 0.12, (0.6, 0.75), math.pi),
    ("side-step", 0.12, (0.55, 0.7), math.pi / 2),  # sign drawn per segment
)


@dataclasses.dataclass(frozen=True)
class SynthConfig:
    """Parameters of the generator; the defaults reproduce the thesis dataset's statistics."""

    path_length_mean: float = 11.5
    """Mean walked distance per trajectory, m (gamma distributed)."""
    path_length_sd: float = 6.6
    """Standard deviation of the walked distance, m."""
    path_length_range: tuple[float, float] = (1.5, 40.0)
    """Walked distances are clipped to this range, m."""
    segment_length: tuple[float, float] = (1.5, 6.0)
    """Range of straight waypoint-to-waypoint distances, m."""
    clearance: float = 0.5
    """Distance users keep from obstacles and walls, m."""
    accel: tuple[float, float] = (0.9, 1.4)
    """Range of (per-trajectory) walking acceleration and deceleration, m/s^2."""
    pause_probability: float = 0.2
    """Probability of pausing (to look around) at a waypoint."""
    pause_duration: tuple[float, float] = (0.5, 2.5)
    """Range of pause durations, s."""
    style_persistence: float = 0.7
    """Probability that a segment keeps the trajectory's primary walking style."""
    pace_exponent: float = 0.4
    """Longer walks are walked faster: pace scales with (length / mean length) ** this."""
    start_wait: tuple[float, float] = (1.0, 2.5)
    """Standing time before walking off, s."""
    stop_wait: tuple[float, float] = (0.6, 1.8)
    """Standing time between stopping and raising the arm, s."""
    raise_duration: tuple[float, float] = (0.5, 1.0)
    """Time to raise the wrist toward the virtual object before the request, s."""
    tail: float = 1.2
    """Recording kept after the request while the user holds the touch, s. (The thesis's mean
    speed, 0.5 m/s, is below its mean path over mean duration, 11.5 m / 21.9 s: its recordings
    went on past the request.)"""
    max_speed: float = 1.85
    """Hard cap on walking speed, m/s (the thesis's fastest clean sample was 1.9 m/s)."""
    styles: tuple = STYLES
    """Walking styles: (name, probability, speed range m/s, body yaw relative to walking direction)."""
    participants: tuple[float, ...] = (1.70, 1.78, 1.86)
    """Head-marker heights of the (three) participants, m; they record in blocks of 50."""
    noise: float = 0.0003
    """Standard deviation of the tracking noise added to positions, m."""
    gap: tuple[float, float] = (3.0, 15.0)
    """Time between consecutive recordings, s."""
    hip_clearance: float = 0.87
    """Having stopped, the participant turns to face a virtual object placed where the robot can
    present it: the first heading (the walking direction, then turned by 20, 40, ... degrees) whose
    HIP (``HipConfig`` defaults) is this far from obstacles and walls (the robot's radius plus 0.1 m).
    0 keeps the walking direction."""

    def __post_init__(self):
        if not (self.path_length_mean > 0 and self.path_length_sd > 0 and self.clearance >= 0):
            raise ValueError(f"SynthConfig: lengths must be positive, got {self}")
        for name in ("path_length_range", "segment_length", "accel", "pause_duration", "raise_duration"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"SynthConfig.{name} must be an ordered positive range, got {(lo, hi)}")


class _Room:
    """The walkable area: a clearance grid of a floor, queried with numpy."""

    def __init__(self, floor, clearance: float, resolution: float = 0.05):
        import jax
        import jax.numpy as jnp

        from methd_jax import floors

        b = np.asarray(floor.bounds, np.float64)
        self.lo, self.res = b[:2], resolution
        nx, ny = (np.ceil((b[2:] - b[:2]) / resolution).astype(int)) + 1
        gx, gy = np.meshgrid(
            np.arange(nx) * resolution + b[0], np.arange(ny) * resolution + b[1], indexing="ij"
        )
        pts = jnp.asarray(np.stack([gx, gy], -1).reshape(-1, 2), jnp.float32)
        sd = jax.jit(jax.vmap(floors.signed_distance, (None, 0)))(floor, pts)
        self.sd = np.asarray(sd).reshape(nx, ny)
        # distance to the room's own bounds as well (floors without walls)
        edge = np.minimum(np.minimum(gx - b[0], b[2] - gx), np.minimum(gy - b[1], b[3] - gy))
        self.sd = np.minimum(self.sd, edge)
        self.clearance = clearance
        self.bounds = b

    def clear(self, xy: np.ndarray, clearance: float | None = None) -> np.ndarray:
        idx = np.rint((np.asarray(xy) - self.lo) / self.res).astype(int)
        idx = np.clip(idx, 0, np.array(self.sd.shape) - 1)
        return self.sd[idx[..., 0], idx[..., 1]] >= (self.clearance if clearance is None else clearance)

    def segment_clear(self, a: np.ndarray, b: np.ndarray, clearance: float | None = None) -> bool:
        """Is the segment clear beyond its first 0.25 m? (A walk may start at the edge of the margin,
        where the last one stopped.)"""
        length = float(np.linalg.norm(b - a))
        n = max(2, int(length / (0.5 * self.res)) + 1)
        u = np.linspace(0, 1, n)
        pts = a + u[u * length >= min(0.25, length)][:, None] * (b - a)
        return bool(np.all(self.clear(pts, clearance)))

    def random_free(self, rng) -> np.ndarray:
        for _ in range(10_000):
            p = rng.uniform(self.bounds[:2], self.bounds[2:])
            if self.clear(p):
                return p
        raise ValueError("the floor has no free space for users (clearance too large?)")


def _waypoints(rng, room: _Room, start: np.ndarray, length: float, cfg: SynthConfig) -> np.ndarray:
    """A polyline from ``start`` through free space whose length is ``length`` (or what fits)."""
    pts = [start]
    total = 0.0
    heading = rng.uniform(-math.pi, math.pi)
    while total < length - 1e-6:
        for attempt in range(300):
            # mostly keep going, sometimes turn sharply (people change their minds); when boxed in,
            # accept any direction and then a smaller margin rather than standing still
            turn = rng.normal(0, 0.8) if attempt < 100 else rng.uniform(-math.pi, math.pi)
            margin = room.clearance if attempt < 200 else 0.5 * room.clearance
            d = rng.uniform(*cfg.segment_length)
            d = min(d, length - total) if length - total > 0.3 else d
            h = heading + turn
            q = pts[-1] + d * np.array([math.cos(h), math.sin(h)])
            if room.clear(q, margin) and room.segment_clear(pts[-1], q, margin):
                break
        else:
            break  # nowhere to go at all: end the walk here
        pts.append(q)
        total += d
        heading = h
    return np.asarray(pts)


def _speed_profile(rng, seg_len: np.ndarray, vmax: np.ndarray, stops: np.ndarray, accel: float):
    """Arc-length knots and speeds of an acceleration-limited walk.

    ``vmax[i]`` caps segment ``i``; ``stops[j]`` says the walker stops at waypoint ``j`` (the first
    and last always). Returns (s, v) on a fine arc-length grid with forward/backward passes applied.
    """
    ds = 0.01
    bounds = np.concatenate([[0.0], np.cumsum(seg_len)])
    s = np.arange(0.0, bounds[-1] + ds / 2, ds)
    s[-1] = bounds[-1]
    seg = np.clip(np.searchsorted(bounds, s, side="right") - 1, 0, len(seg_len) - 1)
    cap = vmax[seg]
    # speed drops at corners are handled by stops or by the smoothing of positions afterwards
    v = cap.copy()
    stop_idx = np.searchsorted(s, bounds[stops] - 1e-9)
    v[stop_idx] = 0.0
    for i in range(1, len(s)):  # forward pass: accelerate from stops
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * accel * (s[i] - s[i - 1])))
    for i in range(len(s) - 2, -1, -1):  # backward pass: decelerate into stops
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * accel * (s[i + 1] - s[i])))
    return s, v, stop_idx


def _facing(room: _Room, xy: np.ndarray, yaw: float, clearance: float) -> float:
    """The heading nearest ``yaw`` (in 20 degree steps) whose HIP has ``clearance``; else ``yaw``."""
    from methd_jax.motion.features import HipConfig

    hip = HipConfig()
    for k in range(19):
        turn = math.radians(20 * ((k + 1) // 2)) * (1 if k % 2 else -1)
        h = yaw + turn
        c, s = math.cos(h), math.sin(h)
        spot = xy + np.array(hip.offset(c, s))
        if room.clear(spot, clearance):
            return h
    return yaw


def _one(rng, room: _Room, start_xy: np.ndarray, start_yaw: float, cfg: SynthConfig, height: float):
    """One trajectory as arrays (time, head (T, 7), wrist (T, 7), request time)."""
    k = (cfg.path_length_mean / cfg.path_length_sd) ** 2
    length = float(np.clip(rng.gamma(k, cfg.path_length_mean / k), *cfg.path_length_range))
    pts = _waypoints(rng, room, start_xy, length, cfg)
    if len(pts) < 2:  # nowhere to go: a short shuffle on the spot
        pts = np.stack([start_xy, start_xy + 1e-3])
    seg_vec = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg_vec, axis=1)
    n_seg = len(seg_len)

    names, probs, speeds, offsets = zip(*cfg.styles, strict=True)
    probs = np.asarray(probs) / sum(probs)
    primary = rng.choice(len(probs), p=probs)
    style = np.where(
        rng.random(n_seg) < cfg.style_persistence, primary, rng.choice(len(probs), size=n_seg, p=probs)
    )
    # this recording's overall pace; long walks are walked faster (durations vary less than paths),
    # but even a few steps are walked at a normal pace
    pace = (max(seg_len.sum(), 0.5) / cfg.path_length_mean) ** cfg.pace_exponent
    tempo = rng.uniform(0.9, 1.1) * max(pace, 0.7)
    vmax = np.array([rng.uniform(*speeds[i]) for i in style]) * tempo
    vmax = np.minimum(vmax, cfg.max_speed)
    body_offset = np.array(
        [offsets[i] * (rng.choice([-1, 1]) if names[i] == "side-step" else 1) for i in style]
    )
    stops = np.zeros(n_seg + 1, bool)
    stops[[0, -1]] = True
    stops[1:-1] = rng.random(n_seg - 1) < cfg.pause_probability
    # a change of style (say, to walking backwards) goes through a stop, as a person turns around
    stops[1:-1] |= body_offset[1:] != body_offset[:-1]
    accel = rng.uniform(*cfg.accel)
    s, v, stop_idx = _speed_profile(rng, seg_len, vmax, stops, accel)

    # time along the path: dt = ds / mean speed of the cell, plus dwell times at stops
    dwell = np.zeros(len(s))
    dwell[stop_idx[1:-1]] = rng.uniform(*cfg.pause_duration, size=len(stop_idx) - 2)
    dwell[0] = rng.uniform(*cfg.start_wait)
    vm = 0.5 * (v[1:] + v[:-1])
    dt_cell = np.diff(s) / np.maximum(vm, 1e-6)
    # knots: (t, s) with a flat piece for every dwell
    t_knots, s_knots = [0.0], [0.0]
    t = 0.0
    for i in range(len(s)):
        if dwell[i] > 0:
            t += dwell[i]
            t_knots.append(t)
            s_knots.append(s[i])
        if i < len(s) - 1:
            t += dt_cell[i]
            t_knots.append(t)
            s_knots.append(s[i + 1])
    t_walk_end = t
    t_stop_wait = rng.uniform(*cfg.stop_wait)
    t_raise = rng.uniform(*cfg.raise_duration)
    t_request = t_walk_end + t_stop_wait + t_raise
    t_end = t_request + cfg.tail
    n = math.floor(t_end * RATE_HZ) + 1
    time = np.arange(n) / RATE_HZ
    request_time = math.ceil(t_request * RATE_HZ - 1e-9) / RATE_HZ  # on a sample
    s_t = np.interp(time, t_knots, s_knots)

    # position along the polyline, corners rounded by a 0.15 s Gaussian
    bounds = np.concatenate([[0.0], np.cumsum(seg_len)])
    seg_t = np.clip(np.searchsorted(bounds, s_t, side="right") - 1, 0, n_seg - 1)
    frac = (s_t - bounds[seg_t]) / np.maximum(seg_len[seg_t], 1e-9)
    xy = pts[seg_t] + frac[:, None] * seg_vec[seg_t]
    xy = gaussian_smooth(xy, 0.15 * RATE_HZ)

    # body yaw: walking direction plus the style's offset, turned smoothly; held while standing
    vel = np.gradient(xy, 1 / RATE_HZ, axis=0)
    speed = np.linalg.norm(vel, axis=1)
    walk_dir = np.arctan2(vel[:, 1], vel[:, 0])
    body = walk_dir + body_offset[seg_t]
    moving = speed > 0.15
    body_vec = np.stack([np.cos(body), np.sin(body)], 1)
    first = np.argmax(moving) if moving.any() else 0
    hold = np.array([math.cos(start_yaw), math.sin(start_yaw)])
    for i in range(n):  # hold the last heading while standing
        if moving[i]:
            hold = body_vec[i]
        elif i >= first or not moving.any():
            body_vec[i] = hold
        else:  # before walking off: turn from the start yaw toward the first heading
            body_vec[i] = np.array([math.cos(start_yaw), math.sin(start_yaw)])
    if cfg.hip_clearance > 0:
        final = _facing(room, xy[-1], math.atan2(body_vec[-1, 1], body_vec[-1, 0]), cfg.hip_clearance)
        body_vec[time >= t_walk_end] = [math.cos(final), math.sin(final)]
    body_vec = gaussian_smooth(body_vec, 0.25 * RATE_HZ)
    body_yaw = np.arctan2(body_vec[:, 1], body_vec[:, 0])

    # head: body yaw plus look-arounds (more of them while standing), a slow nod, a step bob
    look = np.zeros(n)
    n_looks = rng.poisson(time[-1] / 6.0)
    for _ in range(n_looks):
        c = rng.uniform(0, t_walk_end + t_stop_wait)
        w = rng.uniform(0.5, 1.5)
        look += rng.uniform(-1.0, 1.0) * np.exp(-0.5 * ((time - c) / w) ** 2)
    look *= np.where(time < t_walk_end + t_stop_wait, 1.0, 0.0)  # face the object at the end
    look = gaussian_smooth(look, 0.2 * RATE_HZ)
    head_yaw = body_yaw + look
    step_hz = 1.6 + 0.6 * np.clip(speed, 0, 1.8) / 1.8
    phase = np.cumsum(2 * math.pi * step_hz / RATE_HZ)
    pitch = gaussian_smooth(rng.normal(0, 0.05, n), 0.8 * RATE_HZ) * 8
    z = height + 0.015 * np.clip(speed, 0, 1.2) * np.sin(2 * phase)
    head = np.concatenate([xy, z[:, None], quat_from_yaw_pitch(head_yaw, pitch)], 1)

    # wrist: hanging at the right side and swinging while walking, then raised toward the object
    raise_start = t_request - t_raise
    u = np.clip((time - raise_start) / t_raise, 0, 1)
    lift = u * u * (3 - 2 * u)  # smoothstep
    swing = 0.15 * np.clip(speed, 0, 1.2) * np.sin(phase)
    fwd = (1 - lift) * (0.05 + swing) + lift * 0.5
    lat = (1 - lift) * -0.22 + lift * -0.15
    dz = (1 - lift) * -0.8 + lift * -0.3
    c, s_ = np.cos(body_yaw), np.sin(body_yaw)
    wxy = xy + np.stack([c * fwd - s_ * lat, s_ * fwd + c * lat], 1)
    wrist = np.concatenate(
        [wxy, (z + dz)[:, None], quat_from_yaw_pitch(body_yaw, -1.2 * lift + 0.3 * swing)], 1
    )
    head[:, :3] += rng.normal(0, cfg.noise, (n, 3))
    wrist[:, :3] += rng.normal(0, cfg.noise, (n, 3))
    return time, head, wrist, request_time


def synthesize(
    n: int = 442,
    seed: int = 0,
    *,
    config: SynthConfig = SynthConfig(),
    floor=None,
    progress=None,
) -> list[Trajectory]:
    """``n`` consecutive walk-and-interact trajectories in ``floor`` (default: the lab twin).

    Args:
      n: number of trajectories (the thesis recorded 442).
      seed: the generator's seed; the same seed gives the same trajectories.
      config: generator parameters (defaults match the thesis dataset's statistics).
      floor: a :class:`methd_jax.floors.Floor` to walk in (a single floor, not a batch).
      progress: optional callable ``progress(done, total)`` for long runs.
    """
    if n < 1:
        raise ValueError(f"synthesize needs n >= 1, got {n}")
    from methd_jax import floors

    floor = floors.lab() if floor is None else floor
    room = _Room(floor, config.clearance)
    rng = np.random.default_rng(seed)
    xy = room.random_free(rng)
    yaw = rng.uniform(-math.pi, math.pi)
    start_ns = 1_748_772_000 * 10**9 + int(seed) * 86_400 * 10**9  # 2025-06-01 10:00 UTC + seed days
    out = []
    for i in range(n):
        height = config.participants[(i // 50) % len(config.participants)]
        time, head, wrist, req = _one(rng, room, xy, yaw, config, height)
        out.append(Trajectory(f"traj_{i:04d}", time, head, wrist, req, start_ns))
        xy = head[-1, :2].copy()
        yaw = float(yaw_from_quat(head[-1, 3:]))
        start_ns += round((time[-1] + rng.uniform(*config.gap)) * 1e9)
        if progress is not None:
            progress(i + 1, n)
    return out
