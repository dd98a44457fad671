"""The deployment's safety layer as a pure JAX function, for the evaluation's "DRL + safety layer".

:class:`methd_jax.deploy.safety.CollisionMonitor` (numpy, on the robot) holds the command over a
horizon, sweeps the footprint plus a margin along the arc against the scan's points and the users
(extrapolated at their velocity), scales the command down to the largest clear factor, and lowers
that factor further unless the base could still brake clear from its present velocity. This
module computes the same factor inside ``jit`` so that the behaviour engine can put the layer
between a trained policy and the base; ``tests/test_evaluation.py`` checks it against the numpy
monitor on random scenes. Everything is in the robot frame at the moment of the command.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from methd_jax import robot as robot_lib
from methd_jax.control import CONTROL_DT
from methd_jax.deploy.safety import SafetyConfig, candidates, change, reach, segment_meets_box
from methd_jax.geometry import KAIROS, scan_points, to_local
from methd_jax.robot import Servo


def _times(config: SafetyConfig) -> np.ndarray:
    return np.arange(1, round(config.horizon / config.time_step) + 1) * config.time_step


def arc(command: jax.Array, t: jax.Array) -> jax.Array:
    """Poses (x, y, yaw) ``(..., 3)`` reached from the origin after times ``t`` under a constant
    robot-frame twist (vx, vy, wz)."""
    vx, vy, wz = command[0], command[1], command[2]
    th = wz * t
    turning = jnp.abs(wz) > 1e-6
    w = jnp.where(turning, wz, 1.0)
    s, c = jnp.sin(th), jnp.cos(th)
    x = jnp.where(turning, (vx * s + vy * (c - 1.0)) / w, vx * t)
    y = jnp.where(turning, (vx * (1.0 - c) + vy * s) / w, vy * t)
    return jnp.stack([x, y, th], -1)


CHUNK = 24
"""Scan points swept at a time: the nearest first, only as many chunks as the command can reach."""


def sorted_points(ranges: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A full-circle scan's ranges (rays as :func:`methd_jax.geometry.ray_angles`) as points in the
    robot frame, nearest first and padded to whole chunks: (ranges (R',), points (R', 2)); no return
    (and the padding) counts as 1 km away."""
    far = jnp.where(jnp.isfinite(ranges), ranges, 1e3)
    order = jnp.argsort(far)
    far, pts = far[order], scan_points(ranges)[order]
    pad = -ranges.shape[0] % CHUNK
    return jnp.pad(far, (0, pad), constant_values=1e3), jnp.pad(pts, ((0, pad), (0, 0)), constant_values=1e3)


def _radius(margin: float) -> float:
    return float(np.hypot(0.5 * KAIROS.length + margin, 0.5 * KAIROS.width + margin))


def obstacle_scale(command: jax.Array, ranges: jax.Array, horizon: float, time_step: float, margin: float):
    """The largest s in [0, 1] whose sweep of ``command`` over ``horizon`` hits no new scan point.

    ``ranges``: a full-circle scan from the base's centre (rays as
    :func:`methd_jax.geometry.ray_angles`). Exact for static points: at factor s the base covers in
    the horizon what the full command covers in s times it, so s is the last clear sample's time over
    the horizon. Points inside the footprint at t = 0 are ignored (a contact that has happened);
    points inside the margin are checked against the footprint itself, so the base may back away
    from a close wall but not drive into it.
    """
    return sweep(command, *sorted_points(ranges), horizon, time_step, margin)


def sweep(command, ranges, points, horizon: float, time_step: float, margin: float) -> jax.Array:
    """:func:`obstacle_scale` on the scan of :func:`sorted_points`: the first sample of the arc that
    newly meets a point (:func:`first_hit`), as a share of the horizon; 1 if none does."""
    steps = max(1, round(horizon / time_step))
    times = time_step * jnp.arange(1, steps + 1)
    poses = arc(command, times)
    first = first_hit(poses, ranges, points, margin, reach(command, _radius(margin), times, jnp))
    return jnp.where(first < steps, first / steps, 1.0)


BLOCK = 10
"""Samples of a path tested at a time: the search stops at the first block that holds a hit."""


def first_hit(poses, ranges, points, margin: float, extents) -> jax.Array:
    """The index of the first of ``poses`` (T, 3) (in the frame of the scan of
    :func:`sorted_points`) at which the footprint plus ``margin``, moving from the origin, newly
    meets a scan point between the previous pose and this one; T if it meets none. Points within
    the footprint at the origin are ignored and points within the margin are tested against the
    footprint itself (see :func:`obstacle_scale`).

    ``extents`` (T,), nondecreasing: how far from the origin any part of the footprint plus margin
    gets up to each pose. The path is tested BLOCK samples at a time, each block against only the
    nearest points its extent reaches (a point beyond it cannot be met by then), and the search
    stops at the first block with a hit: a base stopped early by a wall tests the few samples and
    points before the contact, not the whole horizon against every point it could reach."""
    body = jnp.asarray(KAIROS.half_extents)
    half = body + margin
    steps = poses.shape[0]
    blocks = -(-steps // BLOCK)
    pad = blocks * BLOCK - steps
    # the origin first, so each sample's segment starts at the sample before it
    path = jnp.concatenate([jnp.zeros((1, 3), poses.dtype), poses, jnp.repeat(poses[-1:], pad, 0)])
    reached = jnp.concatenate([extents, jnp.repeat(extents[-1:], pad)])

    def block_hits(b):  # (BLOCK,) whether a point is newly met at each sample of block b
        segment = jax.lax.dynamic_slice_in_dim(path, b * BLOCK, BLOCK + 1)
        needed = jnp.sum(ranges <= reached[b * BLOCK + BLOCK - 1] + 0.01)  # 1 cm for rounding
        chunks = (needed + CHUNK - 1) // CHUNK

        def hits(c):
            pts = jax.lax.dynamic_slice_in_dim(points, c * CHUNK, CHUNK)
            valid = c * CHUNK + jnp.arange(CHUNK) < needed
            in_body = jnp.all(jnp.abs(pts) <= body, -1)
            in_margin = jnp.all(jnp.abs(pts) <= half, -1) & ~in_body
            local = jax.vmap(to_local, (0, None))(segment, pts)  # (BLOCK + 1, CHUNK, 2)
            hit = segment_meets_box(local[:-1], local[1:], half, jnp) & valid & ~in_body & ~in_margin
            hit |= segment_meets_box(local[:-1], local[1:], body, jnp) & valid & in_margin
            return jnp.any(hit, axis=1)

        _, hit = jax.lax.while_loop(
            lambda ch: ch[0] < chunks,
            lambda ch: (ch[0] + 1, ch[1] | hits(ch[0])),
            (0, jnp.zeros(BLOCK, bool)),
        )
        return hit & (b * BLOCK + jnp.arange(BLOCK) < steps)

    def next_block(state):
        b, _ = state
        hit = block_hits(b)
        return b + 1, jnp.where(jnp.any(hit), b * BLOCK + jnp.argmax(hit), steps)

    _, first = jax.lax.while_loop(
        lambda state: (state[0] < blocks) & (state[1] == steps), next_block, (0, jnp.int32(steps))
    )
    return first


def path_extents(poses, margin: float) -> jax.Array:
    """(T,): how far from the origin any part of the footprint plus ``margin`` gets up to each of
    ``poses``: its half-diagonal plus the farthest centre so far (turning moves no point farther
    from the centre)."""
    return _radius(margin) + jax.lax.cummax(jnp.linalg.norm(poses[:, :2], axis=1))


def slide(command: jax.Array, near: tuple, config: SafetyConfig) -> tuple[jax.Array, jax.Array]:
    """(candidate, its clear factor) as :meth:`methd_jax.deploy.safety.CollisionMonitor.slide`: the
    command and :func:`obstacle_scale` unless that blocks it, else the candidate of
    :meth:`SafetyConfig.turns`, scaled to its own clear factor, closest to the command. ``near``:
    the scan as :func:`sorted_points` gives it."""
    turns = config.turns()

    def scale(c):
        return sweep(c, *near, config.horizon, config.time_step, config.margin)

    s0 = scale(command)
    if len(turns) == 1:
        return command, s0
    radius = _radius(config.margin)
    t = jnp.asarray(turns, jnp.float32)

    def search():  # the neighbours' sweeps only when the command's own is blocked
        cands = jnp.stack(candidates(command, t), -1)
        # one after another, not vmapped: each sweep then stops at its own first contact
        scales = jnp.concatenate([s0[None], jax.lax.map(scale, cands[1:])])
        k = jnp.argmin(change(command, t, scales, radius))
        return cands[k], scales[k]

    return jax.lax.cond(s0 < 1.0, search, lambda: (command, s0))


def user_scale(
    command: jax.Array,
    upper: jax.Array,
    users: jax.Array,
    velocities: jax.Array,
    present: jax.Array,
    user_distance: float,
    config: SafetyConfig,
) -> jax.Array:
    """The largest s <= ``upper`` (from the monitor's grid) that takes the base into no present
    user's collision distance (users (N, 2) and velocities (N, 2) in the robot frame), unless the
    base would be closer standing still."""
    times = _times(config)
    future = users[None] + times[:, None, None] * velocities[None]  # (T, N, 2)
    still = jnp.linalg.norm(future, axis=-1)
    scales = upper * np.linspace(1.0, 0.0, config.user_steps + 1)  # (S,), descending to 0
    robot = arc(command, scales[:, None] * times[None])[..., None, :2]  # (S, T, 1, 2)
    d = jnp.linalg.norm(future[None] - robot, axis=-1)  # (S, T, N)
    bad = jnp.any((d < user_distance) & (d < still[None] - 1e-9) & present, axis=(1, 2))
    return jnp.where(jnp.all(bad), 0.0, scales[jnp.argmin(bad)])


def brake_scale(command, upper, velocity, ranges, points, servo: Servo, horizon: float, margin: float):
    """The first of ``upper``, half of it and 0 at which the base, given ``command`` times it for
    one control period and then braking for ``horizon``, stays clear of the scan of
    :func:`sorted_points` along the path :func:`methd_jax.robot.predict` gives from its robot-frame
    ``velocity``; 0 if none (see :meth:`methd_jax.deploy.safety.CollisionMonitor.brake_scale`)."""
    brake = round(horizon / CONTROL_DT)

    def stoppable(factor):
        commands = jnp.zeros((1 + brake, 3)).at[0].set(factor * command)
        poses = robot_lib.predict(servo, velocity, commands)
        return first_hit(poses, ranges, points, margin, path_extents(poses, margin)) == poses.shape[0]

    # half is tried only if the whole fails; 0 needs no check, as it is the answer either way
    upper = jnp.asarray(upper, jnp.float32)

    def half():
        return jax.lax.cond(stoppable(0.5 * upper), lambda: 0.5 * upper, lambda: jnp.zeros_like(upper))

    return jax.lax.cond(stoppable(upper), lambda: upper, half)


def servo(config: SafetyConfig) -> Servo:
    """The base's servos as ``config`` describes them, for :func:`brake_scale`."""
    gain = 1.0 / config.response_time
    return Servo(
        gain=(gain, gain, gain),
        limit=(config.deceleration, config.deceleration, config.yaw_deceleration),
        timestep=config.time_step,
    )


def filter_command(
    command: jax.Array,
    ranges: jax.Array,
    users: jax.Array,
    velocities: jax.Array,
    present: jax.Array,
    user_distance: float,
    config: SafetyConfig | None = None,
    velocity: jax.Array | None = None,
) -> jax.Array:
    """``command`` scaled as :class:`methd_jax.deploy.safety.CollisionMonitor` scales it (``config``:
    default :class:`SafetyConfig`; ``velocity``: the base's robot-frame velocity, default at rest)."""
    config = config or SafetyConfig()
    if not config.enabled:
        return command
    near = sorted_points(ranges)  # sorted once for the sweeps and the brake check
    chosen, s = slide(command, near, config)
    s = user_scale(chosen, s, users, velocities, present, user_distance, config)
    velocity = jnp.zeros(3) if velocity is None else velocity
    s = brake_scale(chosen, s, velocity, *near, servo(config), config.horizon, config.margin)
    return jnp.where(jnp.any(command != 0), chosen * s, command)
