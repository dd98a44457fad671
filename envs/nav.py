"""The single-user (``su``, N = 1) and NavRL (``nav``, N users) environments of thesis §4.1-4.3.

One implementation for any number of users (a static config value). Brax's ``Env`` interface:
``reset(key) -> State`` and ``step(state, action) -> State`` on single environments (``jax.vmap``
for batches); the world lives in ``State.pipeline_state`` as a :class:`World` pytree whose ``key``
is split every step.

Observation (all in the robot frame; ``observation_layout`` names every slice):

==========================  =====  ==================================================================
``lidar``                   720    noisy ranges clamped to 3 m (N(0, 0.03), 0.5% dropout to 3 m)
``robot_velocity``          3      v_r: vx, vy (m/s), wz (rad/s)
``robot_acceleration``      3      q_r: over the last control period
``previous_action``         3      a_{t-1}
``previous_action_2``       3      a_{t-2}
``user<i>`` (per user)      8      p_u (2), v_u (vx, vy, wz), phi_u (bearing of the robot from the
                                   user's heading), theta_u (bearing of the user from the robot), d_u;
                                   users in a fixed order, or the goal's user first
                                   (``NavConfig.users_by_goal``)
``goal``                    5      p_g (2, dead zone 5 mm), d_g, theta_g (0 within 0.2 m), dyaw_g
                                   (dead zone 0.00436 rad)
``clearance`` (optional)    S      the footprint's clearance per sector of the scan
                                   (``NavConfig.clearance_sectors``, beyond the thesis; 0: absent)
==========================  =====  ==================================================================

720 + 25 values for one user, 720 + 33 for two. Angles are wrapped to [-pi, pi).

Action ``a`` in [-1, 1]^3 -> a~ = 0.5 a_t + 0.3 a_{t-1} + 0.2 a_{t-2} (4.18) -> scaled to
(3.0 m/s, 3.0 m/s, 2.0 rad/s) -> dead zone (5 mm/s, 0.00436 rad/s) -> the MJX base (which clips the
linear speed to 3.0 m/s and has finite acceleration).

Episode (§4.3.2): users replay random trajectories from their start; the robot starts at an exact
random free pose (see :meth:`NavEnv.reset`); the request fires when the first user's trajectory
reaches its request; after a 10 s cooldown the episode ends in success. Hitting an obstacle (any
range < b_r) or a user (d_u < 1.37 m) terminates with its penalty; the time limit truncates.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State
from flax import struct
from mujoco import mjx

from envs import rewards
from envs.goals import goal_from_weight
from envs.shield import ShieldConfig, safe_command
from methd_jax import floors, lidar, motion
from methd_jax import robot as robot_lib
from methd_jax.control import CONTROL_DT, CONTROL_HZ
from methd_jax.deploy.safety import SafetyConfig
from methd_jax.distances import USER_RADIUS
from methd_jax.evaluation import safety_layer
from methd_jax.floors import Floor, FloorConfig
from methd_jax.geometry import KAIROS, path_around_discs, rotate, to_local, wrap_angle
from methd_jax.motion.features import HipConfig, MotionBank

ENV_FLOORS = FloorConfig(room_size=(13.0, 16.0))
"""Procedural floors for the environments: large enough to hold the lab twin's user paths."""


@dataclasses.dataclass(frozen=True)
class NavConfig:
    """Static configuration of ``su`` / ``nav`` (hashable: it fixes shapes and compiled code)."""

    num_users: int = 1
    """N: users in the scene (1 for ``su``, 2 for ``nav``)."""
    motion: str = "default"
    """User trajectories: "default" (the 442-trajectory synthetic set), "sample" (the 4 in
    assets/), or a path to MCAP bags."""
    split: str = "train"
    """Which trajectories to replay: "train" (342), "test" (the last 100) or "all" (sets of at most
    100 trajectories, like the shipped sample, are used whole)."""
    lab: bool = False
    """Train on the lab twin instead of a fresh procedural floor per episode."""
    lab_fraction: float = 0.0
    """With ``lab=False``: the share of episodes on the lab twin, the rest on procedural floors."""
    floor: FloorConfig = ENV_FLOORS
    """Procedural floor parameters."""
    weights: rewards.RewardWeights = rewards.SU_WEIGHTS
    """Reward weights (Table 4.1 for ``su``, 4.3 for ``nav``)."""
    safety: rewards.SafetyConfig = dataclasses.field(default_factory=rewards.SafetyConfig)
    """Collision, critical and inflation distances; goal tolerances."""
    robot: robot_lib.RobotConfig = dataclasses.field(default_factory=robot_lib.RobotConfig)
    """Speed limits and control period of the base."""
    hip: HipConfig = dataclasses.field(default_factory=HipConfig)
    """Where the HIP lies relative to a user."""
    action_weights: tuple[float, float, float] = (0.5, 0.3, 0.2)
    """Interpolation weights of a_t, a_{t-1}, a_{t-2} (eq. 4.18)."""
    deadzone_linear: float = 0.005
    """Commanded linear velocities below this are zeroed, m/s (4.19-4.20)."""
    deadzone_angular: float = 0.00436
    """Commanded yaw rates below this are zeroed, rad/s (4.21)."""
    goal_tolerance: float = 0.2
    """Within this distance of the goal theta_g reads 0 (tolerance zone), m."""
    goal_deadzone: float = 0.005
    """Goal position components below this read 0, m."""
    goal_yaw_deadzone: float = 0.00436
    """Goal yaw errors below this read 0, rad."""
    cooldown: float = 10.0
    """Seconds between the request and the end of a successful episode."""
    time_limit: float = 90.0
    """Episodes are truncated after this many seconds."""
    num_rays: int = lidar.NUM_RAYS
    """LiDAR rays over 360 degrees."""
    lidar_range: float = lidar.STATE_RANGE
    """Ranges in the observation are clamped to this, m."""
    lidar_noise: float = lidar.NOISE_STD
    """Additive range noise in the observation, m."""
    lidar_dropout: float = lidar.DROPOUT
    """Per-ray dropout probability in the observation."""
    spawn_candidates: int = 256
    """Random candidate poses per reset for the exact free-space spawn sampler."""
    spawn_margin: float = 0.05
    """Extra clearance of the spawn disc (r = 0.77 m) from obstacles, and beyond d_crit from users, m."""
    spawn_near: tuple[float, float] = (0.0, 0.15)
    """(share, band): in ``share`` of the episodes the base starts with its spawn disc less than
    ``band`` m beyond ``spawn_margin`` from an obstacle or wall (where a free candidate is that
    close), so that training sees starts beside furniture, where the evaluation's Escape can park
    the base; uniform spawns put few there (the thesis: share 0)."""
    goal_switch_time: tuple[float, float] = (2.0, 6.0)
    """Scripted goal source (``nav`` without a GuideRL policy): seconds between new targets."""
    goal_rate: float = 0.02
    """Scripted goal source: largest change of u_w per step."""
    # -- beyond the thesis (all off by default) -------------------------------------------------
    goal_clearance: float = 0.0
    """Above 0: the goal is the HIP pushed out of obstacles until a disc of this radius around it
    is free and every user is beyond d_crit (:func:`methd_jax.floors.push_clear`), so a HIP inside
    furniture or a wall does not pull the robot into it (the thesis's goal is the raw HIP: 0), m."""
    distance_around: bool = False
    """r_d's distance is the way to the goal round each user's critical disc and each obstacle's
    covering discs (widened by half the base's width; :func:`methd_jax.floors.obstacle_discs`,
    :func:`methd_jax.geometry.path_around_discs`) instead of the straight line, so that a base
    behind a user or a piece of furniture is paid for going round it rather than for pressing
    toward the goal through it (the thesis: the straight distance)."""
    users_by_goal: bool = False
    """The observation lists the users nearest-first by the distance from the goal to each one's
    HIP (placed by ``hip`` from the user's present pose) instead of in a fixed order, so that the
    user the goal belongs to (once GuideRL has chosen) is always in the first slot: where a policy
    started from the SU policy saw its only user (the thesis: a fixed order)."""
    users_visible: bool = False
    """Users appear to the LiDAR as leg-height cylinders (the thesis's LiDAR could not see them)."""
    user_radius: float = USER_RADIUS
    """Radius of those cylinders, m."""
    randomize_dynamics: bool = False
    """Draw the base's mass and servo limits per episode."""
    mass_scale: tuple[float, float] = (0.8, 1.3)
    """Range of the mass (and inertia) multiplier when randomised."""
    force_scale: tuple[float, float] = (0.6, 1.0)
    """Range of the force/torque limit multiplier when randomised."""
    action_latency: int = 0
    """Commands reach the base this many control steps late."""
    request_jitter: float = 0.0
    """The request fires up to this many seconds before the trajectory's own request, s."""
    start_before_request: tuple[float, float] = (0.0, 0.0)
    """(lo, hi) with hi > 0: episodes begin a uniform lo-hi seconds before the first request (at the
    trajectories' beginning where they are shorter), so that training dwells on the approach to a
    user who is about to ask rather than on long walks; (0, 0): at the trajectories' beginning (the
    thesis)."""
    clearance_sectors: int = 0
    """Above 0: the observation ends with the footprint's clearance in this many equal sectors of
    the scan (:func:`sector_clearance`), so that the body sees how near each face and corner is
    without the LiDAR encoder's pooling; must divide ``num_rays`` (the thesis: 0, absent)."""
    contact_limit: int = 1
    """Obstacle contacts that end an episode. Above 1, each contact before the last stops the base
    at rest where it stood before the step (the evaluation stops a base at furniture rather than
    ending the episode there) and pays the collision penalty, and the episode goes on, so that
    training sees a base held at furniture with the goal beyond it (the thesis: 1)."""
    request_weight: float = 0.0
    """Above 0: at the step the request fires, r_d (towards the requester's HIP, which is the goal
    from that step on) is paid this many times more, reported as ``reward/request``. The
    evaluation hands the base to its navigator at the request, so where the base is then is what
    a policy is judged by; with a short ``cooldown`` the episode ends there (the thesis: 0)."""
    shield: ShieldConfig = dataclasses.field(default_factory=ShieldConfig)
    """The stopping rule of :meth:`NavEnv.shield_target` (used by PPO's ``ppo.shield_scale``)."""

    def __post_init__(self):
        for name in (
            "num_users",
            "num_rays",
            "spawn_candidates",
            "action_latency",
            "contact_limit",
            "clearance_sectors",
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        for name in ("lab", "users_visible", "users_by_goal", "distance_around", "randomize_dynamics"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type == "float" or f.type.startswith("tuple[float"):
                values = value if isinstance(value, tuple) else (value,)
                if not all(isinstance(x, int | float) and math.isfinite(x) for x in values):
                    raise ValueError(f"{f.name} must be finite numbers, got {value!r}")
        if not 0.0 <= self.lidar_dropout <= 1.0:
            raise ValueError(f"lidar_dropout must be in [0, 1], got {self.lidar_dropout}")
        for name in (
            "lidar_noise",
            "spawn_margin",
            "goal_tolerance",
            "goal_deadzone",
            "goal_yaw_deadzone",
            "goal_clearance",
            "request_weight",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("mass_scale", "force_scale", "goal_switch_time"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} must be an ordered positive range, got {(lo, hi)}")
        share, band = self.spawn_near
        if not (0.0 <= share <= 1.0 and band > 0):
            raise ValueError(f"spawn_near must be (share in [0, 1], band > 0), got {self.spawn_near!r}")
        window = self.start_before_request
        if not (len(window) == 2 and 0 <= window[0] <= window[1]):
            raise ValueError(f"start_before_request must be an ordered range of seconds >= 0, got {window!r}")
        if self.num_users < 1:
            raise ValueError(f"num_users must be at least 1, got {self.num_users}")
        if self.split not in ("train", "test", "all"):
            raise ValueError(f"split must be 'train', 'test' or 'all', got {self.split!r}")
        if self.action_latency < 0 or self.request_jitter < 0:
            raise ValueError("action_latency and request_jitter must be >= 0")
        if self.num_rays < 8 or self.spawn_candidates < 1:
            raise ValueError("num_rays must be >= 8 and spawn_candidates >= 1")
        if self.contact_limit < 1:
            raise ValueError(f"contact_limit must be at least 1, got {self.contact_limit}")
        if self.clearance_sectors < 0 or (self.clearance_sectors and self.num_rays % self.clearance_sectors):
            raise ValueError(
                f"clearance_sectors must be 0 or divide num_rays ({self.num_rays}), "
                f"got {self.clearance_sectors}"
            )
        if abs(sum(self.action_weights) - 1.0) > 1e-6:
            raise ValueError(f"action_weights must sum to 1, got {self.action_weights}")
        if not 0.0 <= self.lab_fraction <= 1.0:
            raise ValueError(f"lab_fraction must be in [0, 1], got {self.lab_fraction}")
        for name in ("cooldown", "time_limit", "lidar_range", "user_radius"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


def goal_user_order(user_pose: jax.Array, goal: jax.Array, hip: HipConfig) -> jax.Array:
    """Indices of the users (poses (N, 3): x, y, yaw) ordered by the distance from ``goal`` to each
    one's HIP as ``hip`` places it from that pose, nearest first; ties keep their order."""
    c, s = jnp.cos(user_pose[:, 2]), jnp.sin(user_pose[:, 2])
    hip_xy = user_pose[:, :2] + jnp.stack(hip.offset(c, s), 1)
    return jnp.argsort(jnp.linalg.norm(hip_xy - goal[:2], axis=1), stable=True)


def observation_layout(
    num_users: int, num_rays: int = lidar.NUM_RAYS, clearance_sectors: int = 0
) -> dict[str, slice]:
    """Name -> slice of the observation vector (see the module docstring)."""
    sizes = [("lidar", num_rays), ("robot_velocity", 3), ("robot_acceleration", 3)]
    sizes += [("previous_action", 3), ("previous_action_2", 3)]
    sizes += [(f"user{i}", 8) for i in range(num_users)] + [("goal", 5)]
    sizes += [("clearance", clearance_sectors)] if clearance_sectors else []
    out, start = {}, 0
    for name, n in sizes:
        out[name] = slice(start, start + n)
        start += n
    return out


CLEARANCE_RANGE = 1.5
"""The ``clearance`` observation reads clearances beyond this as this, m (the base stops from
3 m/s in 1.5 m)."""


def sector_clearance(ranges: jax.Array, boundary: jax.Array, sectors: int) -> jax.Array:
    """The footprint's clearance per sector ``(sectors,)``: over each sector's rays the least range
    beyond the footprint's boundary (``ranges`` and ``boundary`` (R,): b_r per ray), in [0,
    :data:`CLEARANCE_RANGE`]. Sector j holds the R / sectors rays about the ray at 2 pi j / sectors
    (sector 0 straight ahead; with an even count per sector, half a ray to its left)."""
    per = ranges.shape[-1] // sectors
    beyond = jnp.roll(ranges - boundary, per // 2)
    return jnp.clip(jnp.min(beyond.reshape(sectors, per), axis=1), 0.0, CLEARANCE_RANGE)


def load_bank(source: str, split: str, hip: HipConfig, *, require_split: bool = False) -> MotionBank:
    """The trajectories an environment replays, packed for the device (host side, once).

    A set of at most ``motion.dataset.TEST_SIZE`` trajectories has no train/test split and is
    replayed whole for either; ``require_split`` refuses that instead (:class:`MotionDataError`)."""
    if source == "default":
        trajs = motion.default_dataset()
    elif source == "sample":
        trajs = motion.sample()
    else:
        trajs = motion.load(source)
    if require_split and split != "all" and len(trajs) <= motion.dataset.TEST_SIZE:
        raise motion.MotionDataError(
            f"{source}: {len(trajs)} trajectories have no {split} split (it takes more than "
            f"{motion.dataset.TEST_SIZE}: the last {motion.dataset.TEST_SIZE} are the test ones)"
        )
    if split != "all" and len(trajs) > motion.dataset.TEST_SIZE:
        train, test = motion.split(trajs)
        trajs = train if split == "train" else test
    return MotionBank.from_trajectories(trajs, hip)


@struct.dataclass
class World:
    """Everything that changes in one environment (the Brax ``pipeline_state``)."""

    robot: mjx.Data  # the MJX base
    floor: Floor  # this episode's obstacles
    users: jax.Array  # (N,) int32 trajectory of each user
    t: jax.Array  # () int32 control step of the users' trajectories
    start: jax.Array  # () int32 t at reset (the time limit counts from it)
    request_step: jax.Array  # () int32 step at which the request fires
    requester: jax.Array  # () int32 the user who requests
    actions: jax.Array  # (2, 3) a_{t-1}, a_{t-2}
    velocity: jax.Array  # (3,) robot-frame velocity at the last step (for q_r)
    held: jax.Array  # () s the goal tolerance of r_g has been held
    goal: jax.Array  # (3,) goal pose x, y, yaw
    u_w: jax.Array  # () user weight (nav with 2 users)
    goal_target: jax.Array  # () scripted goal source: target u_w (2 users) or target user index
    guide_actions: jax.Array  # (2,) GuideRL's a_{t-1}, a_{t-2} (when a GuideRL policy drives the goal)
    pending: jax.Array  # (L, 3) commands on their way to the base (action latency)
    dynamics: jax.Array  # (2,) mass and force scale of the base
    contacts: jax.Array  # () int32 obstacle contacts so far in the episode
    key: jax.Array  # PRNG key, split every step


class NavEnv(Env):
    """``su`` / ``nav``: reach and hold the goal pose among users and obstacles."""

    def __init__(
        self,
        config: NavConfig = NavConfig(),
        *,
        bank: MotionBank | None = None,
        guide_policy: Callable[[jax.Array], jax.Array] | None = None,
    ):
        """``bank`` overrides ``config.motion``; ``guide_policy(obs) -> action`` (a trained GuideRL
        policy, deterministic; with the users' wrist heights when its manifest says so, see
        :func:`guide_takes_wrist`) drives the goal of ``nav`` with two users instead of the scripted
        source."""
        self.config = config
        if guide_policy is not None and config.num_users != 2:
            raise ValueError("a GuideRL goal source needs exactly 2 users")
        self.bank = bank if bank is not None else load_bank(config.motion, config.split, config.hip)
        self.guide_policy = guide_policy
        self._guide_wrist = guide_takes_wrist(guide_policy)
        self.robot = robot_lib.Robot(config.robot)
        self._lab = floors.lab() if config.lab else None
        # the lab twin padded to the procedural floors' capacity, so either fits one World
        mixed = config.lab_fraction > 0 and not config.lab
        self._lab_mixed = floors.lab().pad(*config.floor.capacity) if mixed else None
        self._boundary, self._inflation_scale = KAIROS.ray_geometry(config.num_rays)
        self._scale = jnp.array([config.robot.max_speed, config.robot.max_speed, config.robot.max_yaw_rate])
        self._cooldown_steps = round(config.cooldown * CONTROL_HZ)
        self._limit_steps = round(config.time_limit * CONTROL_HZ)
        self._layout = observation_layout(config.num_users, config.num_rays, config.clearance_sectors)

    # -- Brax Env interface -------------------------------------------------------------------

    @property
    def observation_size(self) -> int:
        return max(s.stop for s in self._layout.values())

    @property
    def action_size(self) -> int:
        return 3

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def observation_layout(self) -> dict[str, slice]:
        return self._layout

    def reset(self, rng: jax.Array) -> State:
        """A new episode: fresh floor, users at the start of random trajectories, robot at a free pose.

        Spawning is exact, not the thesis's adaptive occupancy grid: ``spawn_candidates`` uniform
        positions are tested with the floor's signed distance (disc of r = 0.77 m plus a margin,
        which covers the footprint at any yaw) and the distance to every user (beyond d_crit), and
        the first that passes is taken. A per-floor learned grid cannot work with a fresh floor
        every episode, and the exact test never spawns inside an obstacle. On 2000 default floors
        at least 26% of the area (41% on average) passes the obstacle test, so 256 candidates all
        failing has a probability below 1e-20 even after the users' discs are excluded; should it
        happen, candidate 0 is used and the episode ends at once in a collision. With
        ``spawn_near``, a share of the episodes takes the first passing candidate within the band
        of an obstacle instead (the uniform one where none is).
        """
        cfg = self.config
        keys = jax.random.split(rng, 12)  # one key per use: the world's own key is keys[8]
        if self._lab is not None:
            floor = self._lab
        else:
            floor = floors.generate(keys[0], cfg.floor)
            if self._lab_mixed is not None:
                on_lab = jax.random.bernoulli(keys[11], cfg.lab_fraction)
                floor = jax.tree.map(lambda a, b: jnp.where(on_lab, a, b), self._lab_mixed, floor)
        n_traj = self.bank.num_trajectories
        users = jax.random.choice(keys[1], n_traj, (cfg.num_users,), replace=n_traj < cfg.num_users)
        jitter = jax.random.uniform(keys[2], (cfg.num_users,), maxval=cfg.request_jitter * CONTROL_HZ)
        req = jnp.maximum(self.bank.request_step[users] - jnp.round(jitter).astype(jnp.int32), 1)
        start = jnp.int32(0)
        least, most = cfg.start_before_request
        if most > 0:
            lead = jax.random.uniform(jax.random.fold_in(keys[11], 1), minval=least, maxval=most)
            start = jnp.maximum(jnp.min(req) - jnp.round(lead * CONTROL_HZ).astype(jnp.int32), 0)
        user_xy = self.bank.pose[users, start, :2]

        lo, hi = floor.bounds[:2], floor.bounds[2:]
        cand = jax.random.uniform(keys[3], (cfg.spawn_candidates, 2), minval=lo, maxval=hi)
        radius = KAIROS.radius + cfg.spawn_margin
        clear = jax.vmap(lambda p: floors.is_free(floor, p, radius))(cand)
        far = jnp.all(
            jnp.linalg.norm(cand[:, None] - user_xy[None], axis=-1)
            >= cfg.safety.critical_distance + cfg.spawn_margin,
            axis=1,
        )
        ok = clear & far
        share, band = cfg.spawn_near
        if share > 0:
            gap = jax.vmap(lambda p: floors.clearance(floor, p))(cand) - radius
            close = ok & (gap < band)
            near = jax.random.bernoulli(jax.random.fold_in(keys[11], 2), share) & jnp.any(close)
            ok = jnp.where(near, close, ok)
        xy = cand[jnp.argmax(ok)]
        yaw = jax.random.uniform(keys[4], (), minval=-jnp.pi, maxval=jnp.pi)
        robot = self.robot.init(jnp.concatenate([xy, yaw[None]]))

        mass = jax.random.uniform(keys[5], (), minval=cfg.mass_scale[0], maxval=cfg.mass_scale[1])
        force = jax.random.uniform(keys[6], (), minval=cfg.force_scale[0], maxval=cfg.force_scale[1])
        dynamics = jnp.where(cfg.randomize_dynamics, jnp.stack([mass, force]), jnp.ones(2))
        target = jax.random.uniform(keys[7], (), minval=-1.0, maxval=1.0)
        world = World(
            robot=robot,
            floor=floor,
            users=users,
            t=start,
            start=start,
            request_step=jnp.min(req),
            requester=jnp.argmin(req).astype(jnp.int32),
            actions=jnp.zeros((2, 3)),
            velocity=jnp.zeros(3),
            held=jnp.float32(0.0),
            goal=jnp.zeros(3),
            u_w=jnp.float32(0.0),
            goal_target=target if cfg.num_users == 2 else jnp.floor((target + 1) / 2 * cfg.num_users),
            guide_actions=jnp.zeros(2),
            pending=jnp.zeros((cfg.action_latency, 3)),
            dynamics=dynamics,
            contacts=jnp.int32(0),
            key=keys[8],
        )
        world = self.update_goal(world, self._user_features(world), keys[9], scripted_step=False)
        obs, terms, metrics = self.observe(world, jnp.zeros(3), keys[10])
        _, weighted = rewards.total(terms, cfg.weights)
        weighted = self._with_request(weighted, terms, jnp.bool_(False))
        metrics = _step_metrics(metrics, weighted, terms, jnp.bool_(False), jnp.bool_(False))
        zero = jnp.float32(0.0)
        return State(
            pipeline_state=world,
            obs=obs,
            reward=zero,
            done=zero,
            metrics=jax.tree.map(jnp.zeros_like, metrics),  # same keys as step's: one compiled step
            info={"truncation": zero},
        )

    def step(self, state: State, action: jax.Array) -> State:
        cfg = self.config
        w: World = state.pipeline_state
        key, k_noise, k_goal = jax.random.split(w.key, 3)
        a = jnp.clip(action, -1.0, 1.0)
        cmd = self.command(a, w.actions)
        if cfg.action_latency:
            applied, pending = w.pending[0], jnp.concatenate([w.pending[1:], cmd[None]])
        else:
            applied, pending = cmd, w.pending
        model = self.robot.scaled_model(w.dynamics[0], w.dynamics[1]) if cfg.randomize_dynamics else None
        before = w.robot
        robot = self.robot.step(w.robot, applied, model)
        w = w.replace(robot=robot, t=w.t + 1, pending=pending, key=key)
        users = self._user_features(w)
        w = self.update_goal(w, users, k_goal, scripted_step=True)
        obs, terms, metrics = self.observe(w, a, k_noise, users)
        reward, weighted = rewards.total(terms, cfg.weights)
        weighted = self._with_request(weighted, terms, w.t == w.request_step)
        reward = reward + weighted.get("reward/request", 0.0)

        hit = terms["obstacle_collision"] > 0
        if cfg.contact_limit > 1:
            # the contact is paid where it happened; the base goes on from where it stood, at rest
            contacts = w.contacts + hit.astype(jnp.int32)
            hold = hit & (contacts < cfg.contact_limit)
            stopped = w.replace(robot=before.replace(qvel=jnp.zeros_like(before.qvel)))
            held_obs, _, held_metrics = self.observe(stopped, a, k_noise, users)
            pick = lambda x, y: jnp.where(hold, x, y)  # noqa: E731
            w = jax.tree.map(pick, stopped, w).replace(contacts=contacts)
            robot, obs, metrics = w.robot, pick(held_obs, obs), jax.tree.map(pick, held_metrics, metrics)
            hit = hit & ~hold
        collided = hit | (terms["user_collision"] > 0)
        success = w.t >= w.request_step + self._cooldown_steps
        timeout = w.t - w.start >= self._limit_steps
        done = collided | success | timeout
        w = w.replace(
            actions=jnp.stack([a, w.actions[0]]),
            velocity=robot_lib.velocity(robot),
            held=metrics["goal_held"],
        )
        # keep keys that wrappers (Brax's trainer adds "reward") put into the metrics
        metrics = {**state.metrics, **_step_metrics(metrics, weighted, terms, success, collided)}
        return state.replace(
            pipeline_state=w,
            obs=obs,
            reward=reward,
            done=done.astype(jnp.float32),
            metrics=metrics,
            info={**state.info, "truncation": (timeout & ~collided & ~success).astype(jnp.float32)},
        )

    # -- pieces ----------------------------------------------------------------------------------

    def command(self, action: jax.Array, previous: jax.Array) -> jax.Array:
        """The base's robot-frame velocity command for policy ``action`` in [-1, 1]^3 after the
        previous two actions ``previous`` (2, 3): interpolation (4.18), scaling, dead zone (4.19-4.21)."""
        cfg = self.config
        wa = cfg.action_weights
        blended = wa[0] * action + wa[1] * previous[0] + wa[2] * previous[1]
        cmd = blended * self._scale
        cmd = cmd.at[:2].set(jnp.where(jnp.abs(cmd[:2]) < cfg.deadzone_linear, 0.0, cmd[:2]))
        return cmd.at[2].set(jnp.where(jnp.abs(cmd[2]) < cfg.deadzone_angular, 0.0, cmd[2]))

    def shield_target(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(the action whose command is ``action``'s slowed by the stopping rule of
        :mod:`envs.shield`, whether the rule slowed it) for one raw observation ``obs``: its
        LiDAR ranges and the two previous actions it carries are all the rule needs. The target
        differs from ``action`` only in the components the rule changed and lies in [-1, 1]^3 (at
        -1 the base brakes as hard as a policy can make it when the previous actions still carry
        it on)."""
        cfg = self.config
        layout = self._layout
        previous = jnp.stack([obs[layout["previous_action"]], obs[layout["previous_action_2"]]])
        command = self.command(action, previous)
        safe, _ = safe_command(command, obs[layout["lidar"]], cfg.shield)
        wa = cfg.action_weights
        wanted = (safe / self._scale - wa[1] * previous[0] - wa[2] * previous[1]) / wa[0]
        changed = safe != command
        target = jnp.where(changed, jnp.clip(wanted, -1.0, 1.0), action)
        slowed = jnp.any(changed)
        return target, slowed

    def safety_target(
        self,
        world: World,
        action: jax.Array,
        scan: jax.Array,
        safety: SafetyConfig,
        users: dict | None = None,
        present: jax.Array | None = None,
    ) -> tuple[jax.Array, jax.Array]:
        """(the action whose command is ``action``'s after the deployment's safety layer, whether
        the layer changed it) in ``world``: :func:`methd_jax.evaluation.safety_layer.filter_command`
        with ``scan`` (a full-circle scan from the base, e.g. the evaluation's dense exact one), the
        users where they are and as they walk, and the base's velocity, as the evaluation's "DRL +
        safety" row applies it (``users``: their features as :meth:`MotionBank.at` gives them,
        default ``world``'s; ``present``: which of them are there, default all). Components the
        layer leaves alone keep ``action``'s value; the others lie in [-1, 1] (clipped where the
        blend with the previous actions cannot reach the layer's command in one step)."""
        command = self.command(action, world.actions)
        pose = robot_lib.pose(world.robot)
        users = self._user_features(world) if users is None else users
        present = jnp.ones(users["pose"].shape[0], bool) if present is None else present
        safe = safety_layer.filter_command(
            command,
            scan,
            to_local(pose, users["pose"][:, :2]),
            rotate(-pose[2], users["vel_world"][:, :2]),
            present,
            self.config.safety.collision_distance,
            safety,
            robot_lib.velocity(world.robot),
        )
        wa = self.config.action_weights
        wanted = (safe / self._scale - wa[1] * world.actions[0] - wa[2] * world.actions[1]) / wa[0]
        changed = safe != command
        return jnp.where(changed, jnp.clip(wanted, -1.0, 1.0), action), jnp.any(changed)

    def _with_request(self, weighted: dict, terms: dict, firing: jax.Array) -> dict:
        """``weighted`` with ``reward/request`` (the extra r_d at the request step) where it is paid."""
        cfg = self.config
        if cfg.request_weight <= 0:
            return weighted
        extra = jnp.where(firing, cfg.request_weight * cfg.weights.distance * terms["distance"], 0.0)
        return {**weighted, "reward/request": extra}

    def _user_features(self, w: World) -> dict[str, jax.Array]:
        return jax.vmap(self.bank.at, (0, None))(w.users, w.t)

    def update_goal(self, w: World, users: dict, key: jax.Array, scripted_step: bool) -> World:
        """The goal: the requester's HIP after the request (and always with one user); before it,
        u_w from a GuideRL policy or the scripted source (2 users), or a scripted target user (N != 2)."""
        cfg = self.config
        hips = users["hip"]  # (N, 3)
        requested = w.t >= w.request_step
        if cfg.num_users == 1:
            return w.replace(goal=self._reachable(w.floor, hips[0], users))
        u_w, target, guide_actions = w.u_w, w.goal_target, w.guide_actions
        if cfg.num_users == 2:
            if self.guide_policy is not None:
                u_next, guide_actions = self.guide_step(users, u_w, guide_actions)
            else:
                k1, k2 = jax.random.split(key)
                switch = scripted_step & (
                    jax.random.uniform(k1) < CONTROL_DT / (0.5 * sum(cfg.goal_switch_time))
                )
                target = jnp.where(switch, jax.random.uniform(k2, minval=-1.0, maxval=1.0), target)
                u_next = u_w + jnp.clip(target - u_w, -cfg.goal_rate, cfg.goal_rate)
            u_w = jnp.where(scripted_step, u_next, u_w)
            goal = goal_from_weight(u_w, hips[0], hips[1])
        else:
            k1, k2 = jax.random.split(key)
            switch = scripted_step & (jax.random.uniform(k1) < CONTROL_DT / (0.5 * sum(cfg.goal_switch_time)))
            target = jnp.where(
                switch, jax.random.randint(k2, (), 0, cfg.num_users).astype(jnp.float32), target
            )
            goal = hips[target.astype(jnp.int32)]
        goal = jnp.where(requested, hips[w.requester], goal)
        goal = self._reachable(w.floor, goal, users)
        return w.replace(goal=goal, u_w=u_w, goal_target=target, guide_actions=guide_actions)

    def guide_step(
        self, users: dict, u_w: jax.Array, guide_actions: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """One step of the GuideRL goal source: (u_w, GuideRL's last two actions) after it watched
        ``users`` (two users' features of :meth:`MotionBank.at`)."""
        wrist = users["wrist_height"] if self._guide_wrist else None
        obs = guide_observation(users["vel_local"], users["acc_local"], u_w, guide_actions, wrist)
        act = jnp.clip(jnp.reshape(self.guide_policy(obs), ()), -1.0, 1.0)
        return jnp.clip(u_w + GUIDE_MAX_DELTA * act, -1.0, 1.0), jnp.stack([act, guide_actions[0]])

    @property
    def action_scale(self) -> jax.Array:
        """(vx, vy, wz) of a policy action of 1 (eqs. 4.19-4.21)."""
        return self._scale

    def _reachable(self, floor: Floor, goal: jax.Array, users: dict) -> jax.Array:
        """``goal`` moved to the nearest clear point when ``goal_clearance`` is set (yaw kept)."""
        cfg = self.config
        if cfg.goal_clearance <= 0:
            return goal
        xy = floors.push_clear(
            floor,
            goal[:2],
            cfg.goal_clearance,
            avoid=users["pose"][:, :2],
            avoid_radius=cfg.safety.critical_distance,
        )
        return goal.at[:2].set(xy)

    def _path_length(self, floor: Floor, pose: jax.Array, goal: jax.Array, user_xy: jax.Array) -> jax.Array:
        """The way from the base to the goal round the users' critical discs and the obstacles."""
        discs, mask = floors.obstacle_discs(floor, 0.5 * KAIROS.width)
        users = jnp.concatenate(
            [user_xy, jnp.full((user_xy.shape[0], 1), self.config.safety.critical_distance)], 1
        )
        discs = jnp.concatenate([discs, users])
        mask = jnp.concatenate([mask, jnp.ones(user_xy.shape[0], bool)])
        return path_around_discs(pose[:2], goal[:2], discs, mask)

    def observe(self, w: World, action: jax.Array, key: jax.Array, users: dict | None = None):
        """The observation, the unweighted reward terms and the step's diagnostics.

        ``users`` (features of :meth:`MotionBank.at`, stacked per user) replaces the users that
        ``w.users`` and ``w.t`` index, for callers that replay users differently (evaluation)."""
        cfg = self.config
        pose = robot_lib.pose(w.robot)
        users = self._user_features(w) if users is None else users
        user_xy = users["pose"][:, :2]
        extra = None
        if cfg.users_visible:
            extra = jnp.concatenate([user_xy, jnp.full((cfg.num_users, 1), cfg.user_radius)], 1)
        ranges = lidar.scan(w.floor, pose, num_rays=cfg.num_rays, extra_circles=extra)
        noisy = lidar.corrupt(
            key, ranges, max_range=cfg.lidar_range, noise_std=cfg.lidar_noise, dropout=cfg.lidar_dropout
        )
        velocity = robot_lib.velocity(w.robot)
        accel = (velocity - w.velocity) / CONTROL_DT

        p_u = to_local(pose, user_xy)  # (N, 2)
        d_u = jnp.linalg.norm(p_u, axis=1)
        v_u = jnp.concatenate([rotate(-pose[2], users["vel_world"][:, :2]), users["vel_world"][:, 2:]], 1)
        theta_u = jnp.arctan2(p_u[:, 1], p_u[:, 0])
        to_robot = pose[:2] - user_xy
        phi_u = wrap_angle(jnp.arctan2(to_robot[:, 1], to_robot[:, 0]) - users["pose"][:, 2])
        s_u = jnp.concatenate([p_u, v_u, phi_u[:, None], theta_u[:, None], d_u[:, None]], 1)
        if cfg.users_by_goal:
            s_u = s_u[goal_user_order(users["pose"], w.goal, cfg.hip)]

        p_g = to_local(pose, w.goal[:2])
        d_g = jnp.linalg.norm(p_g)
        theta_g = jnp.where(d_g < cfg.goal_tolerance, 0.0, jnp.arctan2(p_g[1], p_g[0]))
        dyaw = wrap_angle(w.goal[2] - pose[2])
        p_g_obs = jnp.where(jnp.abs(p_g) < cfg.goal_deadzone, 0.0, p_g)
        dyaw_obs = jnp.where(jnp.abs(dyaw) < cfg.goal_yaw_deadzone, 0.0, dyaw)
        s_g = jnp.stack([p_g_obs[0], p_g_obs[1], d_g, theta_g, dyaw_obs])

        parts = [noisy, velocity, accel, action, w.actions[0], s_u.reshape(-1), s_g]
        if cfg.clearance_sectors:
            parts.append(sector_clearance(noisy, self._boundary, cfg.clearance_sectors))
        obs = jnp.concatenate(parts)
        within = (d_g < cfg.safety.goal_distance) & (jnp.abs(dyaw) < cfg.safety.goal_yaw)
        held = jnp.where(within, w.held + CONTROL_DT, 0.0)  # time the r_g tolerance has been held
        terms = rewards.terms(
            ranges=ranges,
            boundary=self._boundary,
            inflation_scale=self._inflation_scale,
            user_distances=d_u,
            d_goal=d_g,
            d_path=self._path_length(w.floor, pose, w.goal, user_xy) if cfg.distance_around else None,
            stopping=(
                rewards.stopping_overlap(ranges, velocity, KAIROS.half_extents, cfg.safety)
                if cfg.weights.stopping
                else None
            ),
            dyaw=dyaw,
            held=held,
            action=action,
            prev_action=w.actions[0],
            prev_prev_action=w.actions[1],
            velocity=velocity,
            acceleration=accel,
            safety=cfg.safety,
        )
        metrics = {
            "distance_to_goal": d_g,
            "yaw_error": dyaw,
            "closest_user": jnp.min(d_u),
            "closest_obstacle": jnp.min(ranges),
            "requested": (w.t >= w.request_step).astype(jnp.float32),
            "goal_held": held,
        }
        return obs, terms, metrics


def _step_metrics(metrics, weighted, terms, success, collided) -> dict[str, jax.Array]:
    return {
        **metrics,
        **weighted,
        "collision_obstacle": terms["obstacle_collision"],
        "collision_user": (terms["user_collision"] > 0).astype(jnp.float32),
        "success": (success & ~collided).astype(jnp.float32),
    }


GUIDE_MAX_DELTA = 0.05
"""GuideRL's largest change of u_w per step (eq. 4.25); a policy output of +-1 maps to +-0.05."""


def guide_observation(
    vel_local: jax.Array,
    acc_local: jax.Array,
    u_w: jax.Array,
    actions: jax.Array,
    wrist_height: jax.Array | None = None,
) -> jax.Array:
    """GuideRL's state: eq. 4.24's 15 values (v_u1, v_u2, q_u1, q_u2 in the users' frames, u_w,
    a_{t-1}, a_{t-2}), then, given ``wrist_height`` (2,), each user's wrist height above the head."""
    parts = [vel_local[0], vel_local[1], acc_local[0], acc_local[1], u_w[None], actions]
    return jnp.concatenate(parts if wrist_height is None else [*parts, wrist_height])


def guide_takes_wrist(policy) -> bool:
    """Whether an exported GuideRL ``policy`` (see :func:`train.export.load`) reads the users' wrist
    heights (``GuideConfig.wrist``); a bare callable is taken as eq. 4.24's 15 inputs."""
    manifest = getattr(policy, "manifest", None)
    return bool(manifest and "wrist" in manifest["observation_layout"])
