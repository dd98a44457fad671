"""The navigator that stands in for the thesis's ROS navigation stack (Haptic, Escape, Heuristic).

Global planning is a wavefront on the floor's costmap: :func:`costmap` rasterises the floor like
nav2's inflation layer (cells closer to an obstacle than the footprint's circumscribed radius are
lethal, cells a little farther cost more the closer they are), and :func:`distance_field` relaxes
geodesic distances to the goal over 8-connected cells in a ``lax.while_loop`` (a diagonal step
only where both cells it passes between are free). Following is a local rule on that field: of
``directions`` points at the lookahead distance the lowest-cost one gives the heading (with none
reachable, the most open one), the speed falls as ``sqrt(2 a d)`` toward the goal, the yaw turns
toward the goal's yaw, and velocity and yaw rate change at most by the acceleration limits per
step. All pure and deterministic; the field is planned only when the caller asks (``lax.cond``), so
a 50 Hz loop does not pay for a plan every step.

:func:`guard` is the local planner's footprint check (nav2's collision monitor, "approach"
behaviour), the deployment safety layer's obstacle part: the command is held over a horizon, the
footprint swept along the arc against the latest scan, and the command scaled so that the sweep
stops short of the first point it would hit, or, where a turned neighbour of it is less changed at
its own clear factor, replaced by that one (it slides along a wall it would otherwise stop at);
then lowered further until the base, which carries its own velocity for a while, can still brake
clear of the scan (:func:`methd_jax.robot.predict`).
The plan and the follower only see the footprint's circumscribed disc on a 0.1 m grid; the guard
sees the rectangle and the scan, which is what keeps a base that clips a corner, overshoots a goal
beside a wall or brakes into a corner off the obstacles.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from methd_jax import floors
from methd_jax.control import CONTROL_DT
from methd_jax.deploy.safety import SafetyConfig
from methd_jax.evaluation.safety_layer import brake_scale, slide, sorted_points
from methd_jax.floors import Floor
from methd_jax.geometry import rotate, wrap_angle
from methd_jax.robot import Servo

UNREACHABLE = 1e9
"""Field value of cells the goal cannot be reached from."""


@dataclasses.dataclass(frozen=True)
class NavigatorConfig:
    """Limits and tolerances of the navigator (the thesis gives only the 0.2 m goal tolerance)."""

    max_speed: float = 1.2
    """Cruise speed, m/s (a navigation stack near people; the base itself does 3 m/s)."""
    escape_speed: float = 2.0
    """Cruise speed while escaping, m/s ("the robot quickly navigates to an escape point")."""
    escape_accel: float = 3.0
    """Acceleration while escaping, m/s^2 (the base's own limit)."""
    recovery_speed: float = 0.3
    """Speed toward open space when no path cell is within reach, m/s."""
    max_accel: float = 1.0
    """Linear acceleration limit, m/s^2."""
    brake_accel: float = 3.0
    """Deceleration limit, m/s^2 (the base's own; nav2's velocity smoother, too, brakes at a limit
    of its own): a base handed over faster than the speed it should have (a policy's dash, an
    escape) sheds the excess at this rate, not at ``max_accel``, which would carry it metres past a
    near goal."""
    max_yaw_rate: float = 1.0
    """Yaw rate limit, rad/s."""
    max_yaw_accel: float = 2.0
    """Yaw acceleration limit, rad/s^2."""
    yaw_gain: float = 2.0
    """Proportional gain of the yaw rate on the yaw error, 1/s."""
    goal_tolerance: float = 0.2
    """The goal is reached within this distance (thesis §5.2), m."""
    yaw_tolerance: float = 0.1
    """... and within this yaw error, rad."""
    resolution: float = 0.1
    """Costmap cell size, m."""
    lookahead: float = 0.5
    """Distance of the candidate points that pick the heading, m."""
    directions: int = 24
    """Candidate headings around the robot."""
    lethal_radius: float = 0.75
    """Cells nearer than this to an obstacle are lethal, m: the footprint's circumscribed radius
    (0.727 m) plus a little, because the base turns toward the goal's yaw as it drives."""
    inflation_radius: float = 1.25
    """Cells nearer than this cost more, m."""
    inflation_cost: float = 10.0
    """Cost multiplier at the lethal edge, falling linearly to 1 at ``inflation_radius``."""
    guard_horizon: float = 1.0
    """Seconds the guard holds a command for its sweep, and lets the base brake for in its check
    that the base can stop clear (3 m/s^2 stops 2 m/s in 0.7 s)."""
    guard_margin: float = 0.05
    """Added to every side of the footprint in the guard's sweep, m."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not value > 0:
                raise ValueError(f"NavigatorConfig.{f.name} must be positive, got {value}")
        if self.inflation_radius < self.lethal_radius:
            raise ValueError("inflation_radius must be at least lethal_radius")


@struct.dataclass
class Costmap:
    """Per-cell traversal cost of a floor (``inf`` where lethal); cell (i, j) is centred at
    ``origin + resolution * (j, i)`` (rows along y)."""

    cost: jax.Array  # (H, W) metres of path per metre travelled (>= 1), inf where lethal
    clearance: jax.Array  # (H, W) distance from the cell centre to the nearest obstacle or wall, m
    origin: jax.Array  # (2,) world xy of the centre of cell (0, 0)
    resolution: float = struct.field(pytree_node=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.cost.shape

    def cell(self, xy: jax.Array) -> jax.Array:
        """(row, col) of the cell holding ``xy``, clipped to the map."""
        ij = jnp.round((xy[..., ::-1] - self.origin[::-1]) / self.resolution).astype(jnp.int32)
        return jnp.clip(ij, 0, jnp.array(self.shape) - 1)

    def centres(self) -> jax.Array:
        """(H, W, 2) world xy of every cell centre."""
        h, w = self.shape
        ys = self.origin[1] + self.resolution * jnp.arange(h)
        xs = self.origin[0] + self.resolution * jnp.arange(w)
        return jnp.stack(jnp.meshgrid(xs, ys), -1)

    def lookup(self, field: jax.Array, xy: jax.Array) -> jax.Array:
        """Bilinear value of a per-cell ``field`` at ``xy`` (``UNREACHABLE`` if any corner is)."""
        f = (xy[..., ::-1] - self.origin[::-1]) / self.resolution
        hi = jnp.array(self.shape, jnp.float32) - 1.0
        f = jnp.clip(f, 0.0, hi)
        i0 = jnp.clip(jnp.floor(f).astype(jnp.int32), 0, jnp.array(self.shape) - 2)
        t = f - i0
        v00 = field[i0[..., 0], i0[..., 1]]
        v01 = field[i0[..., 0], i0[..., 1] + 1]
        v10 = field[i0[..., 0] + 1, i0[..., 1]]
        v11 = field[i0[..., 0] + 1, i0[..., 1] + 1]
        v = (1 - t[..., 0]) * ((1 - t[..., 1]) * v00 + t[..., 1] * v01) + t[..., 0] * (
            (1 - t[..., 1]) * v10 + t[..., 1] * v11
        )
        worst = jnp.maximum(jnp.maximum(v00, v01), jnp.maximum(v10, v11))
        return jnp.where(worst >= UNREACHABLE, UNREACHABLE, v)


def costmap(floor: Floor, cfg: NavigatorConfig = NavigatorConfig()) -> Costmap:
    """The costmap of ``floor`` (its bounds must be concrete: they fix the map's shape)."""
    b = np.asarray(floor.bounds, np.float64)
    res = cfg.resolution
    w = math.floor((b[2] - b[0]) / res) + 1
    h = math.floor((b[3] - b[1]) / res) + 1
    grid = Costmap(jnp.zeros((h, w)), jnp.zeros((h, w)), jnp.asarray(b[:2], jnp.float32), res)
    sdf = jax.vmap(jax.vmap(lambda p: floors.signed_distance(floor, p)))(grid.centres())
    # distance to the room's boundary counts as an obstacle too
    c = grid.centres()
    edge = jnp.minimum(
        jnp.minimum(c[..., 0] - b[0], b[2] - c[..., 0]), jnp.minimum(c[..., 1] - b[1], b[3] - c[..., 1])
    )
    sdf = jnp.minimum(sdf, edge)
    span = cfg.inflation_radius - cfg.lethal_radius
    frac = jnp.clip((cfg.inflation_radius - sdf) / jnp.maximum(span, 1e-9), 0.0, 1.0)
    cost = 1.0 + (cfg.inflation_cost - 1.0) * frac
    return grid.replace(cost=jnp.where(sdf < cfg.lethal_radius, jnp.inf, cost), clearance=sdf)


_NEIGHBOURS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]


def distance_field(grid: Costmap, goal_xy: jax.Array, keepout: jax.Array | None = None) -> jax.Array:
    """Geodesic cost-to-go (m, weighted by the costmap) from every cell to ``goal_xy``.

    ``keepout`` (K, 3) adds lethal discs (x, y, radius; radius 0 for none): the users, whom the
    thesis's navigation stack saw as obstacles. The goal's own cell is seeded even when lethal so
    that a goal hugging an obstacle is still approached as closely as the costmap allows. Jacobi
    relaxation until nothing changes.
    """
    h, w = grid.shape
    goal = grid.cell(goal_xy)
    res = grid.resolution
    step_cost = [res * math.hypot(dy, dx) for dy, dx in _NEIGHBOURS]
    cost = grid.cost
    if keepout is not None:
        c = grid.centres()
        d = jnp.linalg.norm(c[:, :, None, :] - keepout[:, :2], axis=-1)  # (H, W, K)
        cost = jnp.where(jnp.any(d < keepout[:, 2], axis=-1), jnp.inf, cost)

    # a diagonal step needs both cells it squeezes between free: cutting between two lethal cells
    # opens threads no wider than a corner, which the follower's bilinear lookahead cannot see, so
    # a base led to one paces in front of it
    free = jnp.pad(jnp.isfinite(cost), 1, constant_values=False)
    open_step = [
        free[1 + dy : 1 + dy + h, 1 : 1 + w] & free[1 : 1 + h, 1 + dx : 1 + dx + w] for dy, dx in _NEIGHBOURS
    ]

    def relax(d):
        p = jnp.pad(d, 1, constant_values=UNREACHABLE)
        best = d
        for (dy, dx), c, ok in zip(_NEIGHBOURS, step_cost, open_step, strict=True):
            nb = p[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
            nb = jnp.where(ok, nb, UNREACHABLE)
            best = jnp.minimum(best, nb + c * cost)  # entering this cell costs its own weight
        best = jnp.where(jnp.isfinite(cost), jnp.minimum(best, UNREACHABLE), UNREACHABLE)
        return best.at[goal[0], goal[1]].set(0.0)

    def body(carry):
        d, _, i = carry
        new = relax(relax(d))
        return new, jnp.any(new < d), i + 1

    d0 = jnp.full((h, w), UNREACHABLE).at[goal[0], goal[1]].set(0.0)
    d, _, _ = jax.lax.while_loop(lambda c: c[1] & (c[2] < h * w), body, (d0, jnp.bool_(True), 0))
    return d


def reached(pose: jax.Array, goal: jax.Array, cfg: NavigatorConfig) -> jax.Array:
    """The goal tolerance of §5.2: within ``goal_tolerance`` and ``yaw_tolerance``."""
    close = jnp.linalg.norm(goal[:2] - pose[:2]) < cfg.goal_tolerance
    return close & (jnp.abs(wrap_angle(goal[2] - pose[2])) < cfg.yaw_tolerance)


def follow(
    grid: Costmap,
    field: jax.Array,
    pose: jax.Array,
    previous: jax.Array,
    goal: jax.Array,
    cfg: NavigatorConfig,
) -> tuple[jax.Array, jax.Array]:
    """One control step toward ``goal`` along ``field`` at the cruise limits.

    ``previous`` is the last command in the world frame (vx, vy, wz); returns the new world-frame
    command (to pass back next step) and the same in the robot frame (for the base). A goal whose
    field is unreachable from here gets a stop.
    """
    speed, accel = cfg.max_speed, cfg.max_accel
    to_goal = goal[:2] - pose[:2]
    d_goal = jnp.linalg.norm(to_goal)
    here = grid.lookup(field, pose[:2])
    ang = 2.0 * jnp.pi * jnp.arange(cfg.directions) / cfg.directions
    pts = pose[:2] + cfg.lookahead * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
    vals = jax.vmap(lambda p: grid.lookup(field, p))(pts)
    best = pts[jnp.argmin(vals)] - pose[:2]
    # near the goal head straight for it; off the reachable cells (pushed into the inflation),
    # head for the best reachable lookahead point; with none, stop
    direct = d_goal <= cfg.lookahead
    heading = jnp.where(direct, to_goal, best)
    heading = heading / jnp.maximum(jnp.linalg.norm(heading), 1e-9)
    remaining = jnp.where(
        direct, d_goal, jnp.maximum(jnp.minimum(here, jnp.min(vals) + cfg.lookahead), d_goal)
    )
    v_max = jnp.minimum(speed, jnp.sqrt(2.0 * accel * jnp.maximum(remaining - 0.02, 0.0)))
    # no reachable lookahead point (pushed into an obstacle's lethal zone or a user's keep-out):
    # creep toward the most open one
    lost = (jnp.min(vals) >= UNREACHABLE) & ~direct
    open_pt = pts[jnp.argmax(jax.vmap(lambda p: grid.lookup(grid.clearance, p))(pts))] - pose[:2]
    open_dir = open_pt / jnp.maximum(jnp.linalg.norm(open_pt), 1e-9)
    heading = jnp.where(lost, open_dir, heading)
    v_max = jnp.where(lost, jnp.minimum(v_max, cfg.recovery_speed), v_max)
    return _ramp(pose, previous, goal, heading, v_max, d_goal, cfg, accel)


def straight(
    pose: jax.Array,
    previous: jax.Array,
    goal: jax.Array,
    cfg: NavigatorConfig,
    speed: jax.Array | float,
    accel: jax.Array | float,
) -> tuple[jax.Array, jax.Array]:
    """One control step straight at ``goal`` (commands as :func:`follow`'s), for a way the caller
    has checked clear (Escape's, :func:`segment_clear`): no plan, so the base goes where the check
    looked."""
    to_goal = goal[:2] - pose[:2]
    d_goal = jnp.linalg.norm(to_goal)
    heading = to_goal / jnp.maximum(d_goal, 1e-9)
    v_max = jnp.minimum(speed, jnp.sqrt(2.0 * accel * jnp.maximum(d_goal - 0.02, 0.0)))
    return _ramp(pose, previous, goal, heading, v_max, d_goal, cfg, accel)


def _ramp(pose, previous, goal, heading, v_max, d_goal, cfg, accel):
    """The command toward velocity ``v_max * heading`` and the goal's yaw, within the limits."""
    dt = CONTROL_DT
    v_des = jnp.where(d_goal < 0.02, 0.0, v_max) * heading
    dyaw = wrap_angle(goal[2] - pose[2])
    w_des = jnp.sign(dyaw) * jnp.minimum(
        jnp.minimum(cfg.yaw_gain * jnp.abs(dyaw), jnp.sqrt(2.0 * cfg.max_yaw_accel * jnp.abs(dyaw))),
        cfg.max_yaw_rate,
    )
    dv = v_des - previous[:2]
    slower = jnp.linalg.norm(v_des) < jnp.linalg.norm(previous[:2])
    limit = jnp.where(slower, jnp.maximum(accel, cfg.brake_accel), accel)
    dv = dv * jnp.minimum(1.0, limit * dt / jnp.maximum(jnp.linalg.norm(dv), 1e-9))
    dw = jnp.clip(w_des - previous[2], -cfg.max_yaw_accel * dt, cfg.max_yaw_accel * dt)
    world = jnp.concatenate([previous[:2] + dv, (previous[2] + dw)[None]])
    local = jnp.concatenate([rotate(-pose[2], world[:2]), world[2:]])
    return world, local


def stop(previous: jax.Array, pose: jax.Array, cfg: NavigatorConfig) -> tuple[jax.Array, jax.Array]:
    """Brake at the deceleration limits (world-frame and robot-frame commands)."""
    dt = CONTROL_DT
    v = previous[:2]
    n = jnp.linalg.norm(v)
    v = v * jnp.maximum(n - cfg.brake_accel * dt, 0.0) / jnp.maximum(n, 1e-9)
    w = jnp.sign(previous[2]) * jnp.maximum(jnp.abs(previous[2]) - cfg.max_yaw_accel * dt, 0.0)
    world = jnp.concatenate([v, w[None]])
    return world, jnp.concatenate([rotate(-pose[2], v), w[None]])


def segment_clear(grid: Costmap, start: jax.Array, end: jax.Array, skip: float = 0.3) -> jax.Array:
    """True when every costmap cell along the segment (after the first ``skip`` metres, where the
    robot itself may already be inside the inflation) is not lethal."""
    n = 32
    t = jnp.linspace(0.0, 1.0, n)
    length = jnp.linalg.norm(end - start)
    pts = start + t[:, None] * (end - start)
    ij = grid.cell(pts)
    ok = jnp.isfinite(grid.cost[ij[:, 0], ij[:, 1]]) | (t * length < skip)
    return jnp.all(ok)


def guard(
    command: jax.Array, ranges: jax.Array, cfg: NavigatorConfig, velocity: jax.Array, servo: Servo
) -> jax.Array:
    """``command`` (robot frame) slid and scaled so that the base neither sweeps into a scan point
    nor coasts into one; ``ranges`` is a full-circle scan from the base's centre (rays as
    :func:`methd_jax.geometry.ray_angles`, from the robot's heading), ``velocity`` the base's
    robot-frame velocity and ``servo`` its servos (:meth:`methd_jax.robot.Robot.servo`).

    The safety layer's obstacle check (:func:`methd_jax.evaluation.safety_layer.slide`, then
    :func:`~methd_jax.evaluation.safety_layer.brake_scale`) over ``guard_horizon`` with
    ``guard_margin``, without its users (the plan keeps them out). Points already inside the
    footprint are ignored (a contact that has happened) and points inside the margin are checked
    against the footprint itself, so the base may back away from a close wall but not drive into
    it. A base whose corner touches a wall has its margin past the wall's surface, so any motion
    along the wall sweeps the margin into the wall: scaled alone, a command 60 degrees off the
    wall's normal is held to a creep at the wall for as long as it is given (a base in a passage
    too narrow for the plan is given that command until it leaves). The command turned by the
    slide angles is also tried, as the deployment's layer does, and the one least changed at its
    own clear factor is sent.

    The sweep takes the base to move as commanded, but it carries its own velocity for a while
    (the servos' 0.1 s lag and 3 m/s^2): a base whose command turns away from a table can still
    slide into it. So the factor is then lowered (halved, then zero) until the base, given the
    scaled command for one control period and then braking for ``guard_horizon``, stays clear
    along the path :func:`methd_jax.robot.predict` gives; when no factor does, it brakes."""
    near = sorted_points(ranges)
    config = SafetyConfig(horizon=cfg.guard_horizon, time_step=CONTROL_DT, margin=cfg.guard_margin)
    chosen, s0 = slide(command, near, config)
    return chosen * brake_scale(chosen, s0, velocity, *near, servo, cfg.guard_horizon, cfg.guard_margin)
