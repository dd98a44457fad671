"""The behaviour engine of the thesis's evaluation (§2.2.1, §5.1), in JAX at 50 Hz.

Behaviours (``MODES``):

- **Chase**: the positioning method under test drives the robot (:mod:`.methods`); the navigator
  that takes over from it starts from the base's velocity, not from the method's last command.
- **Haptic**: on a request the navigator drives the base to the requester's HIP (0.2 m, 0.1 rad);
  then **Arm** holds still for T_arm = 3.3 s and the request counts as served.
- **Escape**: whenever a user comes closer than 1.5 m (Chase or Haptic), the robot drives to an
  escape point behind it along the user->robot direction, the first free candidate of a fixed list
  (straight back first, then turned by up to 120 degrees): free of furniture, 2 m from every user,
  and with a straight way there that keeps clear of every user as they walk on; the base drives
  that straight way. After it, back to Chase (or Haptic if a request is pending). An escape that
  has not arrived after 5 s goes to Inform.
- **Inform**: no escape point exists: the users stop; the robot looks for an escape point again
  every second; after 10 s the users walk back along their trajectories until the robot is
  unstuck (thesis §5.1): until a look finds an escape point, which the robot then drives to, or
  until the users are back at their trajectories' starts, where everything resumes. A robot
  cornered where even that frees nothing can loop through Inform, as the thesis reports; an
  episode ends after 180 s regardless.

An *episode* is one test case: SU, trajectory ``k`` with the robot carried over from the
previous one; MU, a trajectory pair with the robot reset to one of four start poses and the
non-requesting user removed at the request (thesis §5.1.1). :class:`Schedule` lists them; one
``lax.while_loop``-free step function advances the whole run, so a run is ``advance`` in chunks
(for a progress bar) until every episode is done. Users replay by a playhead that the engine can
stop and reverse; their velocities follow the playhead's direction.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from mujoco import mjx

from methd_jax import floors, lidar
from methd_jax import robot as robot_lib
from methd_jax.control import CONTROL_DT, CONTROL_HZ
from methd_jax.distances import CRITICAL_DISTANCE, USER_RADIUS
from methd_jax.evaluation import navigator as nav
from methd_jax.evaluation.methods import Chase, Context
from methd_jax.floors import Floor
from methd_jax.geometry import KAIROS, rotate, to_local, wrap_angle
from methd_jax.motion.features import MotionBank

CHASE, HAPTIC, ARM, ESCAPE, INFORM = range(5)
CONTACT_RELEASE = 0.01  # m of clearance that ends a contact with an obstacle
MODES = ("Chase", "Haptic", "Arm", "Escape", "Inform")


@dataclasses.dataclass(frozen=True)
class EngineConfig:
    """Thresholds of the behaviour engine (thesis §2.2.1 and §5.1; our choices where it is silent)."""

    escape_distance: float = 1.5
    """Escape starts when a user's centre is closer than this to the robot's centre, m."""
    escape_angles: tuple[float, ...] = (0.0, 30.0, -30.0, 60.0, -60.0, 90.0, -90.0, 120.0, -120.0)
    """Escape directions tried in order, degrees from the user->robot direction ("in general"
    behind the robot; the last two let a cornered robot slip out sideways past the user)."""
    escape_distances: tuple[float, ...] = (1.5, 2.0, 1.0)
    """Escape distances tried in order for each direction, m."""
    escape_clearance: float = 2.0
    """An escape point is at least this far from every user, m."""
    escape_pass: float = 1.1
    """On the way to an escape point and standing there until ``escape_horizon``, the base's centre
    keeps this far from every user walking on at their forward velocity (the footprint's 0.77 m
    radius, a user's 0.25 m and 0.08 m to spare); a base already nearer must not come nearer, m."""
    escape_horizon: float = 2.0
    """How far ahead the users' walk is checked against an escape's way, s."""
    escape_timeout: float = 5.0
    """An escape that has not arrived by then turns into Inform, s."""
    inform_wait: float = 10.0
    """Seconds the users stand in Inform before walking back (thesis §5.1)."""
    inform_retry: float = 1.0
    """Seconds between looks for an escape point while in Inform (also while the users walk back,
    which is what frees a cornered robot)."""
    arm_time: float = 3.3
    """T_arm: the arm's move to the prop pose after the base arrives, s."""
    serve_timeout: float = 60.0
    """A request not served within this is given up (counts as not served), s."""
    episode_limit: float = 180.0
    """An episode ends at this age whatever happens, s."""
    replan_period: float = 1.0
    """The navigator replans (around the users' current positions) this often, s."""
    user_keepout: float = 1.6
    """Around each user the navigator's plans keep this clear (Escape's 1.5 m plus 0.1 m), m."""
    user_radius: float = USER_RADIUS
    """A user's body, for collisions with the robot's footprint, m."""
    critical_distance: float = CRITICAL_DISTANCE
    """d_crit of the thesis: time within it is reported as discomfort, m."""
    collision_rays: int = 720
    """Rays of the footprint-vs-obstacle collision test (as in training's p_o)."""
    navigator: nav.NavigatorConfig = dataclasses.field(default_factory=nav.NavigatorConfig)

    def __post_init__(self):
        if len(self.escape_angles) == 0 or len(self.escape_distances) == 0:
            raise ValueError("escape_angles and escape_distances must not be empty")
        for name in (
            "escape_distance",
            "escape_timeout",
            "escape_horizon",
            "inform_wait",
            "arm_time",
            "serve_timeout",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"EngineConfig.{name} must be positive, got {getattr(self, name)}")
        if not self.escape_pass >= 0:
            raise ValueError(f"EngineConfig.escape_pass must be >= 0, got {self.escape_pass}")

    def steps(self, seconds: float) -> int:
        return max(1, round(seconds * CONTROL_HZ))


@struct.dataclass
class Schedule:
    """The episodes of a run: who walks, and where the robot starts."""

    users: jax.Array  # (K, U) int32 trajectory of each user in each episode
    start: jax.Array  # (K, 3) robot start pose (used where reset)
    reset: jax.Array  # (K,) bool: put the robot at its start pose (else it stays where it is)

    @property
    def num_episodes(self) -> int:
        return self.users.shape[0]

    @property
    def num_users(self) -> int:
        return self.users.shape[1]


RESULT_FIELDS = (
    "request_time",  # s from the episode's start to the request
    "t_pos",  # s from the request to the base at the HIP (nan if never)
    "distance_to_hip",  # m from the base to the HIP at the request
    "yaw_to_hip",  # rad, |base yaw - HIP yaw| at the request (the navigator turns at 1 rad/s)
    "served",  # 1 if the arm finished while the request was active
    "escapes",  # Escape activations
    "informs",  # Inform activations
    "collisions_obstacle",  # times the base ran into an obstacle (it stops at it)
    "collisions_user",  # times the footprint touched a user's body
    "travelled",  # m the base moved
    "critical_time",  # s some user was within d_crit of the robot's centre
    "min_user_distance",  # m, closest any user came to the robot's centre
    "duration",  # s the episode lasted
)


@struct.dataclass
class EvalState:
    robot: mjx.Data
    k: jax.Array  # () int32 current episode
    t: jax.Array  # () int32 steps since the episode began
    mode: jax.Array  # () int32 behaviour
    mode_t: jax.Array  # () int32 steps in the behaviour
    resume: jax.Array  # () int32 behaviour to return to after Escape / Inform
    play: jax.Array  # (U,) int32 playheads
    direction: jax.Array  # () int32 +1 forward, 0 stopped, -1 walking back
    present: jax.Array  # (U,) bool
    requester: jax.Array  # () int32
    requested: jax.Array  # () bool
    request_t: jax.Array  # () int32
    nav_command: jax.Array  # (3,) what the navigator ramps from: its last command, world frame
    field: jax.Array  # (H, W) current plan's cost-to-go
    plan_goal: jax.Array  # (3,) goal of the current plan
    plan_t: jax.Array  # () int32 steps since the plan was made
    escape_goal: jax.Array  # (3,)
    method: object  # the method's state
    touching: jax.Array  # (2,) bool: obstacle, user contact at the last step (for counting events)
    scan: jax.Array  # (collision_rays,) ranges from the base's current pose (collisions, the guard)
    key: jax.Array  # this episode's, split at every step
    seed: jax.Array  # the run's key: episode k starts from fold_in(seed, k)
    results: dict  # name -> (K,) per-episode results


def start_poses(floor: Floor, grid: nav.Costmap, margin: float = 0.5) -> np.ndarray:
    """Four collision-free start poses (thesis §5.1.1): the free cells nearest the centres of the
    floor's quadrants with ``margin`` beyond the footprint's radius, yaw 0. (4, 3) numpy."""
    b = np.asarray(floor.bounds)
    centres = np.asarray(grid.centres()).reshape(-1, 2)
    ok = np.asarray(grid.clearance).reshape(-1) >= KAIROS.radius + margin  # obstacles and walls
    if not ok.any():
        raise ValueError("the floor has no room for the robot: no free start pose")
    cx, cy = 0.5 * (b[0] + b[2]), 0.5 * (b[1] + b[3])
    qx, qy = 0.25 * (b[2] - b[0]), 0.25 * (b[3] - b[1])
    poses = []
    for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        want = np.array([cx + sx * qx, cy + sy * qy])
        d = np.where(ok, np.linalg.norm(centres - want, axis=1), np.inf)
        poses.append([*centres[int(np.argmin(d))], 0.0])
    return np.asarray(poses, np.float32)


def _farthest_start(starts: np.ndarray, users_xy: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(starts[:, None, :2] - users_xy[None], axis=-1).min(axis=1)
    return starts[int(np.argmax(d))]


def su_schedule(bank: MotionBank, starts: np.ndarray, trajectories: np.ndarray | None = None) -> Schedule:
    """SU (§5.1.1): the trajectories in sequence, the robot carried over; it starts at the start pose
    farthest from the first user's start."""
    idx = np.arange(bank.num_trajectories) if trajectories is None else np.asarray(trajectories)
    first = np.asarray(bank.pose[int(idx[0]), 0, :2])[None]
    start = _farthest_start(starts, first)
    k = len(idx)
    return Schedule(
        users=jnp.asarray(idx[:, None], jnp.int32),
        start=jnp.asarray(np.repeat(start[None], k, 0)),
        reset=jnp.asarray(np.arange(k) == 0),
    )


def mu_schedule(bank: MotionBank, starts: np.ndarray, offset: int, trajectories=None) -> Schedule:
    """MU (§5.1.1): user 1 on trajectory k, user 2 on trajectory (k + offset) mod K, reset per pair
    with the robot at the start pose farthest from both users."""
    idx = np.arange(bank.num_trajectories) if trajectories is None else np.asarray(trajectories)
    k = len(idx)
    if k < 2:
        raise ValueError("the multi-user procedure needs at least 2 trajectories")
    if offset % k == 0:
        raise ValueError(f"a trajectory offset of {offset} pairs each trajectory with itself")
    pairs = np.stack([idx, idx[(np.arange(k) + offset) % k]], 1)
    first = np.asarray(bank.pose[:, 0, :2])
    start = np.stack([_farthest_start(starts, first[p]) for p in pairs])
    return Schedule(users=jnp.asarray(pairs, jnp.int32), start=jnp.asarray(start), reset=jnp.ones(k, bool))


def escape_point(
    pose: jax.Array,
    users_xy: jax.Array,
    users_vel: jax.Array,
    present: jax.Array,
    floor: Floor,
    grid: nav.Costmap,
    cfg: EngineConfig,
    base_vel: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """The first free escape candidate (pose (3,), found) behind the robot, away from the closest user.

    A candidate is free when the footprint fits there, the straight way to it crosses no lethal
    cell, it is ``escape_clearance`` from every user, and the base driving there (its velocity
    turning from ``base_vel``, world frame (2,), default at rest, to the escape speed toward the
    point at the escape acceleration, then parked there) keeps ``escape_pass`` from every user for
    ``escape_horizon`` while they walk on at ``users_vel`` (U, 2): a point clear of where a user
    stands but across where they walk, or one the base's momentum carries it toward a user on the
    way to, is not an escape.
    """
    d = jnp.where(present, jnp.linalg.norm(users_xy - pose[:2], axis=1), jnp.inf)
    away = pose[:2] - users_xy[jnp.argmin(d)]
    base = jnp.arctan2(away[1], away[0])
    ang = base + jnp.deg2rad(jnp.asarray(cfg.escape_angles))
    dist = jnp.asarray(cfg.escape_distances)
    a, r = jnp.meshgrid(ang, dist, indexing="ij")  # direction-major: all distances of one angle first
    heading = jnp.stack([jnp.cos(a), jnp.sin(a)], -1).reshape(-1, 2)
    r = r.reshape(-1)
    pts = pose[:2] + r[:, None] * heading
    free = jax.vmap(lambda p: floors.is_free(floor, p, KAIROS.radius))(pts)
    clear = jax.vmap(lambda p: nav.segment_clear(grid, pose[:2], p))(pts)
    du = jnp.linalg.norm(pts[:, None] - users_xy[None], axis=-1)
    far = jnp.all(jnp.where(present[None], du >= cfg.escape_clearance, True), axis=1)
    # the way (navigator.straight's): the velocity turns linearly from base_vel to the escape
    # speed toward the point, then cruises; the base parks at the point once it gets that far
    ncfg = cfg.navigator
    v0 = jnp.zeros(2) if base_vel is None else base_vel[:2]
    t = jnp.linspace(0.0, cfg.escape_horizon, round(cfg.escape_horizon * 20) + 1)  # 50 ms
    tc = t[None, :, None]
    dv = (ncfg.escape_speed * heading - v0)[:, None]  # (C, 1, 2)
    ramp = jnp.maximum(jnp.linalg.norm(dv, axis=-1, keepdims=True) / ncfg.escape_accel, 1e-6)
    tr = jnp.minimum(tc, ramp)
    at = pose[:2] + v0 * tc + dv * (tr * (tc - 0.5 * tr)) / ramp  # (C, T, 2)
    arrived = jnp.cumsum(jnp.sum((at - pose[:2]) * heading[:, None], -1) >= r[:, None], axis=1) > 0
    at = jnp.where(arrived[..., None], pts[:, None], at)
    walk = users_xy[:, None] + t[None, :, None] * users_vel[:, None]  # (U, T, 2)
    gap = jnp.linalg.norm(at[:, :, None] - walk[None].swapaxes(1, 2), axis=-1)  # (C, T, U)
    keep = jnp.minimum(cfg.escape_pass, d) - 1e-3  # a base already nearer must not come nearer
    passes = jnp.all(jnp.where(present, gap >= keep, True), axis=(1, 2))
    ok = free & clear & far & passes
    best = jnp.argmax(ok)
    return jnp.concatenate([pts[best], pose[2:3]]), jnp.any(ok)


def footprint_distance(pose: jax.Array, xy: jax.Array) -> jax.Array:
    """Distance from points ``xy`` (N, 2) to the robot's footprint rectangle (0 inside)."""
    p = to_local(pose, xy)
    dx = jnp.maximum(jnp.abs(p[:, 0]) - 0.5 * KAIROS.length, 0.0)
    dy = jnp.maximum(jnp.abs(p[:, 1]) - 0.5 * KAIROS.width, 0.0)
    return jnp.hypot(dx, dy)


class Engine:
    """Runs one positioning method through a :class:`Schedule` on one floor."""

    def __init__(self, method, bank: MotionBank, floor: Floor, cfg: EngineConfig = EngineConfig()):
        self.method = method
        self.bank = bank
        self.floor = floor
        self.cfg = cfg
        self.grid = nav.costmap(floor, cfg.navigator)
        self.robot = robot_lib.Robot()
        self._servo = self.robot.servo()
        self._boundary, _ = KAIROS.ray_geometry(cfg.collision_rays)
        self._advance = jax.jit(self._advance_impl, static_argnums=(2,))

    # -- state ---------------------------------------------------------------------------------

    def init(self, schedule: Schedule, key: jax.Array) -> EvalState:
        k = schedule.num_episodes
        u = schedule.num_users
        results = {name: jnp.zeros(k) for name in RESULT_FIELDS}
        results["t_pos"] = jnp.full(k, jnp.nan)
        results["min_user_distance"] = jnp.full(k, jnp.inf)
        results["request_time"] = jnp.full(k, jnp.nan)
        results["distance_to_hip"] = jnp.full(k, jnp.nan)
        results["yaw_to_hip"] = jnp.full(k, jnp.nan)
        state = EvalState(
            robot=self.robot.init(schedule.start[0]),
            k=jnp.int32(0),
            t=jnp.int32(0),
            mode=jnp.int32(CHASE),
            mode_t=jnp.int32(0),
            resume=jnp.int32(CHASE),
            play=jnp.zeros(u, jnp.int32),
            direction=jnp.int32(1),
            present=jnp.ones(u, bool),
            requester=jnp.int32(0),
            requested=jnp.bool_(False),
            request_t=jnp.int32(0),
            nav_command=jnp.zeros(3),
            field=jnp.full(self.grid.shape, nav.UNREACHABLE),
            plan_goal=jnp.full(3, jnp.inf),
            plan_t=jnp.int32(0),
            escape_goal=jnp.zeros(3),
            method=self.method.init(),
            touching=jnp.zeros(2, bool),
            scan=self._scan(schedule.start[0]),
            key=key,
            seed=key,
            results=results,
        )
        return self._begin(state, schedule, jnp.int32(0))

    def _begin(self, s: EvalState, schedule: Schedule, k: jax.Array) -> EvalState:
        """Set up episode ``k`` (users at their starts; the robot reset if the schedule says so)."""
        kk = jnp.minimum(k, schedule.num_episodes - 1)
        trajs = schedule.users[kk]
        reset = schedule.reset[kk]
        fresh = self.robot.init(schedule.start[kk])
        robot = jax.tree.map(lambda a, b: jnp.where(reset, a, b), fresh, s.robot)
        # a user whose recording starts on the carried-over base is in contact from the first step,
        # without either moving: the schedule put them there (after an episode that Inform's
        # retries ended before its recording did, the next recording starts where that one ends,
        # not where its user stood). Held as an ongoing contact, it counts only once they part
        # and meet again
        starts = self.bank.pose[trajs, 0, :2]
        placed = jnp.any(footprint_distance(robot_lib.pose(robot), starts) < self.cfg.user_radius)
        return s.replace(
            robot=robot,
            k=k,
            t=jnp.int32(0),
            mode=jnp.int32(CHASE),
            mode_t=jnp.int32(0),
            resume=jnp.int32(CHASE),
            play=jnp.zeros_like(s.play),
            direction=jnp.int32(1),
            present=jnp.ones_like(s.present),
            requester=jnp.argmin(self.bank.request_step[trajs]).astype(jnp.int32),
            requested=jnp.bool_(False),
            request_t=jnp.int32(0),
            nav_command=jnp.where(reset, 0.0, s.nav_command),
            plan_goal=jnp.full(3, jnp.inf),
            method=self.method.init(),
            # a base that stays where it is and stays in contact is one collision, not one per
            # episode
            touching=jnp.stack([s.touching[0] & ~reset, placed]),
            scan=jnp.where(reset, self._scan(robot_lib.pose(fresh)), s.scan),
            # each episode's noise from its own index: an episode that ran longer or shorter does
            # not re-draw the noise of every one after it
            key=jax.random.fold_in(s.seed, k),
        )

    def _scan(self, pose: jax.Array) -> jax.Array:
        return lidar.scan(self.floor, pose, num_rays=self.cfg.collision_rays)

    def _stop_at_contact(self, before: mjx.Data, after: mjx.Data, allowed: jax.Array):
        """The base stopped at the last pose of its step from ``before`` to ``after`` (straight, by
        bisection to 1/256 of the step) whose footprint overlaps obstacles by no more than
        ``allowed``; returns it and the scan from there."""
        q0, q1 = before.qpos[:3], after.qpos[:3]

        def bisect(_, bounds):
            lo, hi = bounds
            mid = 0.5 * (lo + hi)
            at = robot_lib.pose(before.replace(qpos=q0 + mid * (q1 - q0)))
            ok = self._overlap(self._scan(at)) <= allowed
            return jnp.where(ok, mid, lo), jnp.where(ok, hi, mid)

        lo, _ = jax.lax.fori_loop(0, 8, bisect, (jnp.float32(0.0), jnp.float32(1.0)))
        qpos = before.qpos.at[:3].set(q0 + lo * (q1 - q0))
        stopped = before.replace(qpos=qpos, qvel=jnp.zeros_like(before.qvel))
        return stopped, self._scan(robot_lib.pose(stopped))

    def _overlap(self, ranges: jax.Array) -> jax.Array:
        """How far, m, an obstacle reaches into the footprint along the worst ray (<= 0: clear)."""
        return jnp.max(self._boundary - ranges)

    # -- one step --------------------------------------------------------------------------------

    def _users(self, s: EvalState, trajs: jax.Array) -> dict:
        f = jax.vmap(self.bank.at)(trajs, s.play)
        d = s.direction.astype(jnp.float32)
        for name in ("vel_world", "vel_local"):
            f[name] = f[name] * d
        for name in ("acc_world", "acc_local"):
            f[name] = f[name] * jnp.abs(d)
        return f

    def step(self, s: EvalState, schedule: Schedule) -> EvalState:
        cfg = self.cfg
        ncfg = cfg.navigator
        key, k_method = jax.random.split(s.key)
        trajs = schedule.users[jnp.minimum(s.k, schedule.num_episodes - 1)]
        users = self._users(s, trajs)
        pose = robot_lib.pose(s.robot)
        hip = users["hip"][s.requester]
        res = s.results
        k = s.k
        mode, mode_t, resume = s.mode, s.mode_t, s.resume

        def enter(new_mode, cond, mode, mode_t):
            return jnp.where(cond, new_mode, mode), jnp.where(cond, 0, mode_t)

        # the request: the requester's playhead reaches its request
        fire = ~s.requested & (s.play[s.requester] >= self.bank.request_step[trajs[s.requester]])
        requested = s.requested | fire
        request_t = jnp.where(fire, s.t, s.request_t)
        solo = jnp.arange(schedule.num_users) == s.requester
        present = jnp.where(fire, solo, s.present)
        res = _set(res, "request_time", k, s.t * CONTROL_DT, fire)
        res = _set(res, "distance_to_hip", k, jnp.linalg.norm(pose[:2] - hip[:2]), fire)
        res = _set(res, "yaw_to_hip", k, jnp.abs(wrap_angle(hip[2] - pose[2])), fire)
        mode, mode_t = enter(HAPTIC, fire & (mode == CHASE), mode, mode_t)
        resume = jnp.where(fire & ((mode == ESCAPE) | (mode == INFORM)), HAPTIC, resume)

        users_xy = users["pose"][:, :2]
        dist = jnp.where(present, jnp.linalg.norm(users_xy - pose[:2], axis=1), jnp.inf)
        closest = jnp.min(dist)

        # Haptic -> Arm -> served; Escape arrival / timeout; Inform release
        arrived = nav.reached(pose, hip, ncfg)
        res = _set(res, "t_pos", k, (s.t - request_t) * CONTROL_DT, (mode == HAPTIC) & arrived)
        mode, mode_t = enter(ARM, (mode == HAPTIC) & arrived, mode, mode_t)
        served = (mode == ARM) & (mode_t >= cfg.steps(cfg.arm_time))
        escaped = (mode == ESCAPE) & (jnp.linalg.norm(s.escape_goal[:2] - pose[:2]) < ncfg.goal_tolerance)
        mode, mode_t = enter(resume, escaped, mode, mode_t)
        late = (mode == ESCAPE) & (mode_t >= cfg.steps(cfg.escape_timeout))
        res = _add(res, "informs", k, late)
        mode, mode_t = enter(INFORM, late, mode, mode_t)
        # walking back ends at the trajectories' starts; a way out found on the way ends it sooner
        # (the retry below): releasing at some distance instead left a robot cornered on the
        # user's path stuck in place, and the user walked straight back into Inform
        at_start = jnp.all((s.play == 0) | ~present)
        released = (mode == INFORM) & (s.direction < 0) & at_start
        mode, mode_t = enter(resume, released, mode, mode_t)

        # Escape trigger (Chase, Haptic) and Inform's retries
        trigger = ((mode == CHASE) | (mode == HAPTIC)) & (closest < cfg.escape_distance)
        retry = (mode == INFORM) & (mode_t > 0) & (mode_t % cfg.steps(cfg.inform_retry) == 0)

        def look():
            # in Escape the users walk on forward, whatever they did in Inform (stand, walk back)
            ahead = self.bank.vel_world[trajs, jnp.clip(s.play, 0, self.bank.max_steps - 1), :2]
            return escape_point(pose, users_xy, ahead, present, self.floor, self.grid, cfg, s.robot.qvel[:2])

        # 27 candidates' free-space and drive tests, only when needed
        goal_e, found = jax.lax.cond(trigger | retry, look, lambda: (s.escape_goal, jnp.bool_(False)))
        resume = jnp.where(trigger, mode, resume)
        to_escape = (trigger | retry) & found
        to_inform = trigger & ~found
        res = _add(res, "escapes", k, to_escape)
        res = _add(res, "informs", k, to_inform)
        escape_goal = jnp.where(to_escape, goal_e, s.escape_goal)
        mode, mode_t = enter(ESCAPE, to_escape, mode, mode_t)
        mode, mode_t = enter(INFORM, to_inform, mode, mode_t)

        # users: stop in Inform, walk back after the wait, resume otherwise
        direction = jnp.where(
            mode == INFORM, jnp.where(mode_t >= cfg.steps(cfg.inform_wait), -1, 0), 1
        ).astype(jnp.int32)

        # what drives the base
        ctx = Context(s.robot, pose, users, present, self.floor, self.grid, s.t, k_method, s.scan)

        def chase(ms):
            return self.method.chase(ms, ctx)

        watch = getattr(self.method, "idle", lambda ms, ctx: ms)

        def idle(ms):
            return watch(ms, ctx), Chase(jnp.zeros(3), jnp.zeros(3), jnp.bool_(False))

        method_state, order = jax.lax.cond(mode == CHASE, chase, idle, s.method)
        navigating = (mode == HAPTIC) | (mode == ESCAPE) | ((mode == CHASE) & order.navigate)
        goal = jnp.where(mode == HAPTIC, hip, jnp.where(mode == ESCAPE, escape_goal, order.goal))
        # Escape drives straight, the way escape_point checked against furniture and the users'
        # walk (a plan bent by the costmap's inflation drove into walking users); the rest plans
        periodic = s.plan_t >= cfg.steps(cfg.replan_period)
        moved_goal = jnp.linalg.norm(goal[:2] - s.plan_goal[:2]) > 0.1
        replan = navigating & (mode != ESCAPE) & (moved_goal | periodic | (s.mode == ESCAPE))
        keepout = jnp.concatenate([users_xy, jnp.where(present, cfg.user_keepout, 0.0)[:, None]], 1)
        field = jax.lax.cond(
            replan, lambda: nav.distance_field(self.grid, goal[:2], keepout), lambda: s.field
        )
        plan_goal = jnp.where(replan, goal, s.plan_goal)
        plan_t = jnp.where(replan, 0, s.plan_t + 1)
        _, nav_local = jax.lax.cond(
            mode == ESCAPE,
            lambda: nav.straight(pose, s.nav_command, goal, ncfg, ncfg.escape_speed, ncfg.escape_accel),
            lambda: nav.follow(self.grid, field, pose, s.nav_command, goal, ncfg),
        )
        _, brake_local = nav.stop(s.nav_command, pose, ncfg)
        # the navigator's and the brake's commands pass the footprint guard (the thesis's ROS
        # stack checked its footprint); a method's own commands are the method's responsibility
        command = jnp.where(navigating, nav_local, brake_local)
        direct = (mode == CHASE) & ~order.navigate
        command = jax.lax.cond(  # the sweep only when the base is to move (a parked base is not)
            ~direct & jnp.any(command != 0),
            lambda: nav.guard(command, s.scan, ncfg, robot_lib.velocity(s.robot), self._servo),
            lambda: command,
        )
        command = jnp.where(direct, order.command, command)
        moved = self.robot.step(s.robot, command)
        ranges = self._scan(robot_lib.pose(moved))
        # walls and furniture are solid, as the thesis's simulator made them: a step that would
        # take the footprint (deeper) into one does not happen and the base stops there, as at a
        # bumper. Without this a base pushed through the lab's wall left the room and, carried
        # over, failed every later single-user episode
        allowed = jnp.maximum(self._overlap(s.scan), 0.0)
        blocked = self._overlap(ranges) > allowed
        robot, ranges = jax.lax.cond(
            blocked, lambda: self._stop_at_contact(s.robot, moved, allowed), lambda: (moved, ranges)
        )
        new_pose = robot_lib.pose(robot)
        # the navigator and the brake ramp from the command they gave last; after a method drove
        # the base itself they ramp from the base's own velocity: a policy's last command (a
        # bang-bang one's may point the other way) is not how the base moves when they take over
        nav_command = jnp.where(
            direct,
            robot.qvel[:3],  # the base's twist in the world frame
            jnp.concatenate([rotate(pose[2], command[:2]), command[2:]]),
        )

        # bookkeeping
        # a contact lasts until the base is a centimetre clear: a base held at a wall is not a new
        # collision each time it is pushed on
        overlap = self._overlap(ranges)
        hit_obstacle = blocked | (overlap > 0) | (s.touching[0] & (overlap > -CONTACT_RELEASE))
        body = footprint_distance(new_pose, users_xy)
        hit_user = jnp.any(present & (body < cfg.user_radius))
        res = _add(res, "collisions_obstacle", k, hit_obstacle & ~s.touching[0])
        res = _add(res, "collisions_user", k, hit_user & ~s.touching[1])
        res = _add(res, "travelled", k, jnp.linalg.norm(new_pose[:2] - pose[:2]))
        res = _add(res, "critical_time", k, CONTROL_DT * (closest < cfg.critical_distance))
        res = res | {"min_user_distance": res["min_user_distance"].at[k].min(closest)}
        play = jnp.clip(s.play + direction, 0, self.bank.max_steps - 1)

        t = s.t + 1
        given_up = requested & (t - request_t >= cfg.steps(cfg.serve_timeout))
        done = served | given_up | (t >= cfg.steps(cfg.episode_limit))
        res = _set(res, "served", k, 1.0, served)
        res = _set(res, "duration", k, t * CONTROL_DT, done)
        s = s.replace(
            robot=robot,
            t=t,
            mode=mode,
            mode_t=mode_t + 1,
            resume=resume,
            play=play,
            direction=direction,
            present=present,
            requested=requested,
            request_t=request_t,
            nav_command=nav_command,
            field=field,
            plan_goal=plan_goal,
            plan_t=plan_t,
            escape_goal=escape_goal,
            method=method_state,
            touching=jnp.stack([hit_obstacle, hit_user]),
            scan=ranges,
            key=key,
            results=res,
        )
        return jax.lax.cond(done, lambda: self._begin(s, schedule, k + 1), lambda: s)

    def _record(self, s: EvalState, schedule: Schedule) -> dict[str, jax.Array]:
        return {
            "episode": s.k,
            "mode": s.mode,
            "pose": robot_lib.pose(s.robot),
            "users": jax.vmap(self.bank.at)(
                schedule.users[jnp.minimum(s.k, schedule.num_episodes - 1)], s.play
            )["pose"],
            "present": s.present,
            "direction": s.direction,
            "touching": s.touching,  # obstacle, user contact
        }

    def _advance_impl(
        self, s: EvalState, schedule: Schedule, n: int, limit: jax.Array
    ) -> tuple[EvalState, dict]:
        """The first ``limit`` of ``n`` steps (none once every episode is done) and the records of
        all ``n``. ``run`` and ``trace`` both go through this one compiled function: XLA rounds the
        same step differently in differently built programs, and since SU episodes carry the base
        over, a difference in the last bit grows into another run within a few episodes."""

        def body(s, i):
            go = (s.k < schedule.num_episodes) & (i < limit)
            s = jax.lax.cond(go, lambda: self.step(s, schedule), lambda: s)
            return s, self._record(s, schedule)

        return jax.lax.scan(body, s, jnp.arange(n))

    def trace(
        self, schedule: Schedule, key: jax.Array, steps: int, chunk: int = 2500
    ) -> tuple[dict[str, np.ndarray], dict]:
        """The first ``steps`` steps, recorded: per step the episode, behaviour, robot pose, users'
        positions and presence, the playhead direction and the contacts (obstacle, user), for
        plots, animations and finding where collisions happen; plus the results so far. With the
        same ``chunk`` as :meth:`run` these are the steps of that run, bit for bit."""
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        s, records = self.init(schedule, key), []
        for start in range(0, steps, chunk):
            s, rec = self._advance(s, schedule, chunk, jnp.int32(min(chunk, steps - start)))
            records.append(jax.device_get(rec))
        rec = {k: np.concatenate([r[k] for r in records])[:steps] for k in records[0]}
        return rec, jax.device_get(s.results)

    def run(
        self,
        schedule: Schedule,
        key: jax.Array,
        chunk: int = 2500,
        progress: Callable[[int, int], None] | None = None,
    ) -> dict[str, np.ndarray]:
        """Every episode of ``schedule``; per-episode results as numpy arrays (see ``RESULT_FIELDS``)."""
        s = self.init(schedule, key)
        total = schedule.num_episodes
        while True:
            s, _ = self._advance(s, schedule, chunk, jnp.int32(chunk))
            done = int(s.k)
            if progress is not None:
                progress(done, total)
            if done >= total:
                break
        return {name: np.asarray(v) for name, v in jax.device_get(s.results).items()}


def _set(res: dict, name: str, k, value, cond) -> dict:
    return res | {name: res[name].at[k].set(jnp.where(cond, value, res[name][k]))}


def _add(res: dict, name: str, k, amount) -> dict:
    return res | {name: res[name].at[k].add(jnp.asarray(amount, jnp.float32))}


__all__ = [
    "ARM",
    "CHASE",
    "ESCAPE",
    "HAPTIC",
    "INFORM",
    "MODES",
    "RESULT_FIELDS",
    "Engine",
    "EngineConfig",
    "EvalState",
    "Schedule",
    "escape_point",
    "footprint_distance",
    "mu_schedule",
    "start_poses",
    "su_schedule",
]
