import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import guide as guide_lib
from envs.nav import NavConfig, observation_layout
from methd_jax import floors, motion
from methd_jax import robot as robot_lib
from methd_jax.floors import FloorConfig
from methd_jax.geometry import path_around_discs

EMPTY = FloorConfig(room_size=(13.0, 16.0), num_circles=(0, 0), num_polygons=(0, 0))
OPEN_ROOM = FloorConfig(room_size=(20.0, 20.0), num_circles=(0, 0), num_polygons=(0, 0))
"""An empty floor big enough that every HIP of the lab paths lies inside it."""


@pytest.fixture(scope="module")
def bank():
    return motion.MotionBank.from_trajectories(motion.sample())


def _rollout(env, n, steps, policy, key=0, copies=1):
    """``steps`` auto-reset steps of ``n`` copies in one jitted scan: final state and per-step data.
    ``copies`` > 1 repeats the same ``n / copies`` episodes that many times (to compare policies on
    equal episodes in one compiled program)."""
    wrapped = envs.AutoReset(env)

    @jax.jit
    def run(rng):
        k_reset, k_act = jax.random.split(rng)
        state = wrapped.reset(jnp.concatenate([jax.random.split(k_reset, n // copies)] * copies))

        def body(carry, k):
            state = carry
            action = policy(state.obs, k)
            state = wrapped.step(state, action)
            return state, (
                state.reward,
                state.done,
                state.metrics,
                state.info["episode_done"],
                state.info["completed_return"],
                jnp.all(jnp.isfinite(state.obs)),
            )

        return jax.lax.scan(body, state, jax.random.split(k_act, steps))

    return run(jax.random.key(key))


def _random(env):
    return lambda obs, k: jax.random.uniform(k, (obs.shape[0], env.action_size), minval=-1, maxval=1)


# nav runs the su code with a second user; its 2048-copy run is in the slow set to keep the default
# suite under 15 minutes on CI's 2 cores
# su and nav at 2,048 copies take minutes on 2 CPU cores: run with -m slow (guide stays as the check)
@pytest.mark.parametrize(
    "name",
    [pytest.param("su", marks=pytest.mark.slow), pytest.param("nav", marks=pytest.mark.slow), "guide"],
)
def test_2048_copies_step_500_times_finite(name, bank):
    env = envs.make(name, bank=bank)
    final, (reward, _, metrics, ep_done, _, finite) = _rollout(env, 2048, 500, _random(env))
    assert bool(finite.all()) and np.isfinite(np.asarray(reward)).all()
    assert final.obs.shape == (2048, env.observation_size)
    if name != "guide":  # random driving hits things, and episodes restart
        assert float(metrics["collision_obstacle"].sum()) > 0 and float(ep_done.sum()) > 0


def test_observation_layout_sizes():
    assert observation_layout(1)["goal"].stop == 720 + 25
    assert observation_layout(2)["goal"].stop == 720 + 33
    assert observation_layout(3)["goal"].stop == 720 + 41  # N is a config value, not hard-coded


def test_sector_clearance_is_each_sectors_least_range_beyond_the_footprint():
    """Against a per-sector loop over ray angles (the function rolls and reshapes instead)."""
    rng = np.random.default_rng(3)
    for rays, sectors in [(90, 18), (90, 9), (720, 16), (8, 8)]:
        angles = 2 * np.pi * np.arange(rays) / rays
        boundary = rng.uniform(0.45, 0.73, rays).astype(np.float32)
        ranges = (boundary + rng.uniform(-0.1, 2.0, rays)).astype(np.float32)
        got = np.asarray(envs.nav.sector_clearance(jnp.asarray(ranges), jnp.asarray(boundary), sectors))
        per, want = rays // sectors, []
        for j in range(sectors):
            # the ray at the sector's centre and per // 2 before it, the rest after it
            offset = (angles - 2 * np.pi * j / sectors + np.pi) % (2 * np.pi) - np.pi
            steps = np.round(offset / (2 * np.pi / rays)).astype(int)
            member = (steps >= -(per // 2)) & (steps < per - per // 2)
            assert member.sum() == per
            want.append(np.clip(np.min(ranges[member] - boundary[member]), 0.0, envs.nav.CLEARANCE_RANGE))
        np.testing.assert_allclose(got, want, atol=1e-6)
    with pytest.raises(ValueError, match="clearance_sectors must be 0 or divide num_rays"):
        NavConfig(num_rays=90, clearance_sectors=7)
    assert observation_layout(1, 90, 18)["clearance"] == slice(115, 133)
    assert "clearance" not in observation_layout(1, 90)


_OBSERVERS = {}


def _state_with_robot_at(env, key, pose):
    """The observation of a reset world with the robot moved to ``pose`` (one compiled function per env)."""
    if id(env) not in _OBSERVERS:

        @jax.jit
        def observe(key, pose):
            w = env.reset(key).pipeline_state
            w = w.replace(robot=env.robot.init(pose))
            return (w, *env.observe(w, jnp.zeros(3), key))

        _OBSERVERS[id(env)] = observe
    return _OBSERVERS[id(env)](key, jnp.asarray(pose, jnp.float32))


def test_observation_values_angles_and_tolerance_zone(bank):
    env = envs.make("su", bank=bank, floor=EMPTY, lidar_noise=0.0, lidar_dropout=0.0)
    lay = env.observation_layout
    w = env.reset(jax.random.key(3)).pipeline_state
    goal = np.asarray(w.goal)
    # robot 1 m behind the goal (in the goal's frame), facing along +x of the world
    pose = [goal[0] - 1.0, goal[1], 0.0]
    _, obs, _, _ = _state_with_robot_at(env, jax.random.key(3), pose)
    g = np.asarray(obs[lay["goal"]])
    assert g[0] == pytest.approx(1.0, abs=1e-5) and g[1] == pytest.approx(0.0, abs=1e-5)
    assert g[2] == pytest.approx(1.0, abs=1e-5) and g[3] == pytest.approx(0.0, abs=1e-5)
    assert g[4] == pytest.approx(math.remainder(goal[2], 2 * math.pi), abs=1e-5)
    # within 0.2 m theta_g reads 0 even though the goal lies to the side
    _, obs, _, _ = _state_with_robot_at(env, jax.random.key(3), [goal[0], goal[1] - 0.15, 0.0])
    g = np.asarray(obs[lay["goal"]])
    assert g[2] == pytest.approx(0.15, abs=1e-5) and g[3] == 0.0 and g[1] == pytest.approx(0.15, abs=1e-5)
    # just outside it theta_g is the bearing (+90 deg: the goal is to the robot's left)
    _, obs, _, _ = _state_with_robot_at(env, jax.random.key(3), [goal[0], goal[1] - 0.25, 0.0])
    assert float(obs[lay["goal"]][3]) == pytest.approx(math.pi / 2, abs=1e-4)
    # dead zones: 3 mm off and 0.002 rad off read exactly 0
    _, obs, _, _ = _state_with_robot_at(env, jax.random.key(3), [goal[0] - 0.003, goal[1], goal[2] - 0.002])
    g = np.asarray(obs[lay["goal"]])
    assert g[0] == 0.0 and g[4] == 0.0
    # all angles wrapped, ranges clamped to 3 m
    for yaw in np.linspace(-7, 7, 9):
        _, obs, _, _ = _state_with_robot_at(env, jax.random.key(3), [goal[0] - 2.0, goal[1] + 1.0, yaw])
        u = np.asarray(obs[lay["user0"]])
        assert (
            -math.pi <= u[5] < math.pi
            and -math.pi <= u[6] < math.pi
            and -math.pi <= obs[lay["goal"]][4] < math.pi
        )
        assert float(obs[lay["lidar"]].max()) <= 3.0
    # user state: distance and bearing consistent with the relative position
    assert u[7] == pytest.approx(np.hypot(u[0], u[1]), rel=1e-5)
    assert u[6] == pytest.approx(math.atan2(u[1], u[0]), abs=1e-5)


def test_spawn_is_clear_of_obstacles_and_users(bank):
    env = envs.make("nav", bank=bank)
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(5), 2048))
    w = states.pipeline_state
    pose = jax.vmap(robot_lib.pose)(w.robot)
    sd = jax.vmap(floors.signed_distance)(w.floor, pose[:, :2])
    assert float(sd.min()) >= 0.77 + 0.05 - 1e-4
    user_xy = bank.pose[w.users, 0, :2]  # (2048, 2, 2)
    d = np.linalg.norm(np.asarray(user_xy) - np.asarray(pose[:, None, :2]), axis=-1)
    assert d.min() >= 1.77
    assert float(states.metrics["closest_obstacle"].sum()) == 0.0  # reset metrics are zeros
    assert float(jnp.min(jax.vmap(lambda s: s)(states.obs)[:, :720])) > 0.7


def test_spawn_near_starts_a_share_of_episodes_beside_an_obstacle(bank):
    def gaps(**options):
        env = envs.make("su", bank=bank, **options)
        w = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(6), 512)).pipeline_state
        xy = jax.vmap(robot_lib.pose)(w.robot)[:, :2]
        return np.asarray(jax.vmap(floors.clearance)(w.floor, xy)) - (0.77 + 0.05)

    uniform, half = gaps(), gaps(spawn_near=(0.5, 0.15))
    assert uniform.min() >= -1e-4 and half.min() >= -1e-4  # both still spawn clear
    assert np.mean(uniform < 0.15) < 0.2
    # about half drawn within the band, plus the uniform draws that fall there anyway
    assert 0.45 < np.mean(half < 0.15) < 0.7
    with pytest.raises(ValueError, match="spawn_near must be"):
        NavConfig(spawn_near=(1.5, 0.15))
    with pytest.raises(ValueError, match="spawn_near must be"):
        NavConfig(spawn_near=(0.5, 0.0))


def _goal_seeker(env, gain=1.0, top_speed=1.0, keep_away=2.3):
    """Drives straight at the goal (velocity gain * (goal - robot), capped at ``top_speed`` m/s),
    backing away from a user closer than ``keep_away`` (the HIP itself lies 2.02 m from the user)."""
    lay = env.observation_layout

    def policy(obs, _):
        g = obs[:, lay["goal"]]
        u = obs[:, lay["user0"]]
        away = -u[:, :2] / jnp.maximum(u[:, 7:8], 1e-6) * 3.0 * jnp.maximum(keep_away - u[:, 7:8], 0.0)
        v = gain * g[:, :2] + away
        v = v * jnp.minimum(1.0, top_speed / jnp.maximum(jnp.linalg.norm(v, axis=1, keepdims=True), 1e-6))
        ang = jnp.clip(g[:, 4:5], -1, 1)
        return jnp.concatenate([v / 3.0, ang / 2.0 * 2.0], 1)

    return policy


@pytest.mark.slow  # 64 bases for 600 steps with their LiDAR: 121 s on a 2-core developer machine
def test_driving_at_the_hip_beats_standing_still(bank):
    env = envs.make("su", bank=bank, floor=OPEN_ROOM)
    seeker = _goal_seeker(env, gain=1.0, top_speed=1.5)
    # the same 32 episodes twice: seeking in the first block, standing still in the second
    both = lambda obs, k: jnp.concatenate([seeker(obs[:32], k), jnp.zeros((32, 3))])  # noqa: E731
    _, (r, *_) = _rollout(env, 64, 600, both, copies=2)
    seek, still = float(r[:, :32].sum(0).mean()), float(r[:, 32:].sum(0).mean())
    assert seek > still + 500, (seek, still)


def test_driving_into_a_wall_terminates_with_the_obstacle_penalty(bank):
    env = envs.make("su", bank=bank, floor=EMPTY)
    state = jax.jit(env.reset)(jax.random.key(7))
    w = state.pipeline_state
    b = np.asarray(w.floor.bounds)
    user = np.asarray(bank.pose[w.users[0], 0, :2])
    start_y = b[1] + 1.5 if user[1] > 0 else b[3] - 1.5  # the half of the room away from the user
    w = w.replace(
        robot=env.robot.init(jnp.array([b[2] - 4.0, start_y, 0.0]))
    )  # 4 m from the east wall, facing it
    state = state.replace(pipeline_state=w)
    step = jax.jit(env.step)
    for _ in range(200):
        state = step(state, jnp.array([1.0, 0.0, 0.0]))
        if float(state.done):
            break
    assert float(state.done) == 1.0 and float(state.info["truncation"]) == 0.0
    assert float(state.metrics["collision_obstacle"]) == 1.0
    assert float(state.metrics["reward/obstacle_collision"]) == -900.0 and float(state.reward) < -800


def test_contact_limit_holds_the_base_at_the_wall_and_pays_each_contact(bank):
    env = envs.make("su", bank=bank, floor=EMPTY, contact_limit=4)
    state = jax.jit(env.reset)(jax.random.key(7))
    w = state.pipeline_state
    b = np.asarray(w.floor.bounds)
    user = np.asarray(bank.pose[w.users[0], 0, :2])
    start_y = b[1] + 1.5 if user[1] > 0 else b[3] - 1.5
    robot = env.robot.init(jnp.array([b[2] - 4.0, start_y, 0.0]))  # 4 m from the east wall, facing it
    state = state.replace(pipeline_state=w.replace(robot=robot))
    step = jax.jit(env.step)
    contacts, held_at = [], None
    for _ in range(300):
        before = np.asarray(robot_lib.pose(state.pipeline_state.robot))
        state = step(state, jnp.array([1.0, 0.0, 0.0]))  # full speed at the east wall, throughout
        if float(state.metrics["collision_obstacle"]):
            contacts.append(float(state.metrics["reward/obstacle_collision"]))
            after = state.pipeline_state.robot
            if float(state.done):
                break
            # not the last contact: the base stands where it was before the step, at rest, and
            # sees the wall from there
            np.testing.assert_allclose(np.asarray(robot_lib.pose(after)), before, atol=1e-6)
            assert float(jnp.abs(after.qvel).max()) == 0.0
            assert float(state.metrics["closest_obstacle"]) > 0.0
            held_at = held_at if held_at is not None else before
        else:
            assert not contacts or float(state.done) == 0.0
    # pressing on ends the episode at the fourth contact, as a collision (not a truncation)
    assert contacts == [-900.0] * 4
    assert float(state.done) == 1.0 and float(state.info["truncation"]) == 0.0
    assert float(state.metrics["success"]) == 0.0
    assert int(state.pipeline_state.contacts) == 4
    assert held_at[0] > b[2] - 1.0  # held at the east wall, not somewhere on the way
    with pytest.raises(ValueError, match="contact_limit must be"):
        NavConfig(contact_limit=0)


def test_episode_succeeds_after_the_cooldown_and_auto_resets(bank):
    env = envs.make("su", bank=bank, floor=OPEN_ROOM, cooldown=1.0)
    wrapped = envs.AutoReset(env)
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.key(11), 4))
    w = state.pipeline_state
    # jump to just before the end of the cooldown: 45 of its 50 steps have passed
    state = state.replace(pipeline_state=w.replace(t=w.request_step + 45))
    step = jax.jit(wrapped.step)
    total = np.zeros(4)
    floor_before = np.asarray(w.floor.circles)
    for _ in range(5):
        state = step(state, jnp.zeros((4, 3)))
        total += np.asarray(state.reward)
    done = np.asarray(state.done) == 1.0
    safe = (np.asarray(state.metrics["collision_user"]) == 0) & (
        np.asarray(state.metrics["collision_obstacle"]) == 0
    )
    assert done.all() and np.all(np.asarray(state.metrics["success"])[safe] == 1.0) and safe.any()
    assert np.all(np.asarray(state.pipeline_state.t) == 0)  # fresh episodes ...
    assert not np.allclose(np.asarray(state.pipeline_state.floor.circles), floor_before)  # ... on new floors
    assert np.all(np.asarray(state.info["episode_done"]) == 1.0) and np.all(
        np.asarray(state.info["episode_length"]) == 0
    )
    np.testing.assert_allclose(np.asarray(state.info["completed_return"]), total, rtol=1e-5)


def test_truncation_at_the_time_limit(bank):
    env = envs.make("su", bank=bank, floor=EMPTY, time_limit=0.1)
    state = jax.jit(env.reset)(jax.random.key(2))
    step = jax.jit(env.step)
    for _ in range(5):
        state = step(state, jnp.zeros(3))
    assert float(state.done) == 1.0 and float(state.info["truncation"]) == 1.0


def test_episodes_can_start_shortly_before_the_request(bank):
    lead = (3.0, 5.0)
    env = envs.make(
        "nav", bank=bank, floor=EMPTY, num_users=2, num_rays=72, start_before_request=lead, time_limit=0.1
    )
    req = np.asarray(bank.request_step)
    reset = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(7), 64))
    w = reset.pipeline_state
    t, first = np.asarray(w.t), np.asarray(w.request_step)
    np.testing.assert_array_equal(first, req[np.asarray(w.users)].min(1))
    np.testing.assert_array_equal(t, np.asarray(w.start))
    early = first <= lead[0] * 50  # shorter than the window: from the beginning
    assert np.all(t[early] == 0)
    assert np.all((first - t)[~early] >= lead[0] * 50) and np.all((first - t)[~early] <= lead[1] * 50)
    assert len(np.unique(t)) > 16  # drawn per episode, not one offset
    # the users are where their trajectories are at the start, and the base spawned clear of them
    users = np.asarray(bank.pose)[np.asarray(w.users), t[:, None], :2]
    np.testing.assert_allclose(
        np.asarray(reset.obs[:, env.observation_layout["user0"]][:, 7]),
        np.linalg.norm(users[:, 0] - np.asarray(w.robot.qpos)[:, :2], axis=1),
        atol=1e-4,
    )
    base = np.asarray(w.robot.qpos)[:, None, :2]
    assert np.linalg.norm(users - base, axis=-1).min() >= env.config.safety.critical_distance
    # the time limit counts from the start, not from the trajectories' beginning
    step = jax.jit(jax.vmap(env.step))
    state = reset
    for _ in range(4):
        state = step(state, jnp.zeros((64, 3)))
    assert np.all(np.asarray(state.done) == 0.0)
    state = step(state, jnp.zeros((64, 3)))
    assert np.all(np.asarray(state.info["truncation"]) == 1.0)
    with pytest.raises(ValueError, match="start_before_request"):
        NavConfig(start_before_request=(5.0, 3.0))


def test_request_weight_pays_r_d_again_when_the_request_fires(bank):
    kw = dict(
        bank=bank, floor=EMPTY, num_users=2, num_rays=72, start_before_request=(0.2, 0.4), cooldown=0.02
    )
    plain, paid = envs.make("nav", **kw), envs.make("nav", request_weight=5.0, **kw)
    keys = jax.random.split(jax.random.key(3), 16)
    states = [jax.jit(jax.vmap(env.reset))(keys) for env in (plain, paid)]
    assert "reward/request" in states[1].metrics and "reward/request" not in states[0].metrics
    steps = [jax.jit(jax.vmap(env.step)) for env in (plain, paid)]
    fired = np.zeros(16, bool)
    for _ in range(25):  # 10-20 steps to the request, then one of cooldown
        before = np.asarray(states[1].pipeline_state.t) < np.asarray(states[1].pipeline_state.request_step)
        states = [step(s, jnp.zeros((16, 3))) for step, s in zip(steps, states, strict=True)]
        w = states[1].pipeline_state
        firing = before & (np.asarray(w.t) == np.asarray(w.request_step))
        extra = np.asarray(states[1].metrics["reward/request"])
        r_d = np.asarray(states[1].metrics["reward/distance"])
        np.testing.assert_allclose(extra, np.where(firing, 5.0 * r_d, 0.0), atol=1e-5)
        np.testing.assert_allclose(
            np.asarray(states[1].reward) - np.asarray(states[0].reward), extra, atol=1e-4
        )
        fired |= firing
        done = np.asarray(states[1].done) == 1.0
        assert np.all(np.asarray(states[1].metrics["success"])[done & ~fired] == 0.0)
    assert fired.sum() >= 12  # those that did not collide first
    with pytest.raises(ValueError, match="request_weight"):
        NavConfig(request_weight=-1.0)


def test_users_visible_option(bank):
    seen = envs.make("su", bank=bank, floor=EMPTY, users_visible=True, lidar_noise=0.0, lidar_dropout=0.0)
    blind = envs.make("su", bank=bank, floor=EMPTY, lidar_noise=0.0, lidar_dropout=0.0)
    key = jax.random.key(4)
    w = seen.reset(key).pipeline_state
    user = np.asarray(bank.pose[w.users[0], 0])
    pose = [user[0] - 2.0, user[1], 0.0]  # 2 m behind the user, facing them
    _, obs_seen, *_ = _state_with_robot_at(seen, key, pose)
    _, obs_blind, *_ = _state_with_robot_at(blind, key, pose)
    assert float(obs_seen[0]) == pytest.approx(2.0 - 0.25, abs=1e-4)  # ray 0 hits the user's legs
    assert float(obs_blind[0]) > 2.0


def test_distance_around_option_pays_r_d_for_the_way_round_the_user(bank):
    env = envs.make("su", bank=bank, floor=EMPTY, lidar_noise=0.0, lidar_dropout=0.0, distance_around=True)
    key = jax.random.key(4)
    w = env.reset(key).pipeline_state
    user, goal = np.asarray(bank.pose[w.users[0], 0, :2]), np.asarray(w.goal[:2])
    ahead = (goal - user) / np.linalg.norm(goal - user)
    side = np.array([-ahead[1], ahead[0]])
    side = side if np.dot(side, -goal) > 0 else -side  # toward the room's middle, away from walls
    # behind the user: round the critical disc, ~1.7 m longer than straight through
    pose = [*(user - 2.0 * ahead), 0.0]
    _, _, terms, m = _state_with_robot_at(env, key, pose)
    disc = jnp.array([[*user, 1.77]])
    way = float(path_around_discs(jnp.asarray(pose[:2]), jnp.asarray(goal), disc, jnp.array([True])))
    assert way > float(m["distance_to_goal"]) + 1.0
    assert float(terms["distance"]) == pytest.approx(3.0 - way, abs=1e-4)
    # beside the goal, nothing in the way: the straight distance, as in eq. 4.6
    _, _, terms, m = _state_with_robot_at(env, key, [*(goal + 1.5 * side), 0.0])
    assert float(m["distance_to_goal"]) == pytest.approx(1.5, abs=1e-4)
    assert float(terms["distance"]) == pytest.approx(1.5, abs=1e-4)


@pytest.mark.slow  # an option beyond the thesis, off by default
def test_randomized_dynamics_option(bank):
    env = envs.make("su", bank=bank, randomize_dynamics=True)
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    w = reset(jax.random.split(jax.random.key(0), 64)).pipeline_state
    dyn = np.asarray(w.dynamics)
    assert dyn[:, 0].min() >= 0.8 and dyn[:, 0].max() <= 1.3 and dyn[:, 0].std() > 0.05
    assert dyn[:, 1].min() >= 0.6 and dyn[:, 1].max() <= 1.0
    # a heavier, weaker base accelerates less under the same command
    state = reset(jax.random.split(jax.random.key(0), 64))
    dyn = jnp.tile(jnp.array([[1.0, 1.0], [1.3, 0.6]]), (32, 1))
    nxt = step(state.replace(pipeline_state=state.pipeline_state.replace(dynamics=dyn)), jnp.ones((64, 3)))
    v = np.asarray(jax.vmap(robot_lib.velocity)(nxt.pipeline_state.robot))
    assert v[1, 0] == pytest.approx(v[0, 0] * 0.6 / 1.3, rel=0.05)
    assert np.all(
        np.asarray(envs.make("su", bank=bank).reset(jax.random.key(0)).pipeline_state.dynamics) == 1.0
    )


@pytest.mark.slow  # an option beyond the thesis, off by default
def test_action_latency_option(bank):
    env = envs.make("su", bank=bank, floor=EMPTY, action_latency=3)
    state = jax.jit(env.reset)(jax.random.key(1))
    step = jax.jit(env.step)
    speeds = []
    for _ in range(5):
        state = step(state, jnp.array([1.0, 0.0, 0.0]))
        speeds.append(float(robot_lib.velocity(state.pipeline_state.robot)[0]))
    assert speeds[:3] == [0.0, 0.0, 0.0] and speeds[3] > 0


@pytest.mark.slow  # an option beyond the thesis, off by default
def test_request_jitter_option(bank):
    env = envs.make("su", bank=bank, request_jitter=3.0)
    w = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 256)).pipeline_state
    own = np.asarray(bank.request_step[w.users[:, 0]])
    early = own - np.asarray(w.request_step)
    assert early.min() >= 0 and early.max() <= 150 and early.mean() > 30


@pytest.mark.slow  # 1 min; test_run_cli trains nav with a GuideRL goal source in the default suite
def test_nav_goal_sources(bank):
    nav = envs.make("nav", bank=bank)
    assert nav.observation_size == 753
    state = jax.jit(nav.reset)(jax.random.key(0))
    step = jax.jit(nav.step)
    uw = []
    for _ in range(100):
        state = step(state, jnp.zeros(3))
        uw.append(float(state.pipeline_state.u_w))
    assert max(np.abs(np.diff(uw))) <= 0.02 + 1e-6 and np.ptp(uw) > 0  # scripted: moves, rate-limited
    # a GuideRL policy that always pushes toward user 2 drives the goal to user 2's HIP
    pushed = envs.make("nav", bank=bank, policies={"guide": lambda obs: jnp.ones(1)})
    state = jax.jit(pushed.reset)(jax.random.key(0))
    step = jax.jit(pushed.step)
    for _ in range(30):
        state = step(state, jnp.zeros(3))
    w = state.pipeline_state
    hip2 = np.asarray(bank.hip[w.users[1], w.t])
    assert float(w.u_w) == 1.0 and np.allclose(np.asarray(w.goal), hip2, atol=1e-5)
    with pytest.raises(ValueError, match="exactly 2 users"):
        envs.make("nav", bank=bank, num_users=1, policies={"guide": lambda obs: obs})
    with pytest.raises(ValueError, match="task 'su' takes no guide policy"):
        envs.make("su", bank=bank, policies={"guide": lambda obs: obs})
    three = envs.make("nav", bank=bank, num_users=3)  # N = 3: goal is one user's HIP, scripted
    s = jax.jit(lambda k: three.step(three.reset(k), jnp.zeros(3)))(jax.random.key(1))
    hips = np.asarray(jax.vmap(bank.at, (0, None))(s.pipeline_state.users, s.pipeline_state.t)["hip"])
    assert any(np.allclose(np.asarray(s.pipeline_state.goal), h, atol=1e-5) for h in hips)


def test_guide_rewards_and_accuracy(bank):
    env = envs.make("guide", bank=bank)
    assert (env.observation_size, env.action_size) == (15, 1)

    def oracle(state):  # knows the requester
        return jnp.where(state.pipeline_state.requester == 0, -1.0, 1.0)[None]

    def run(policy, key):
        state = jax.jit(env.reset)(key)
        step = jax.jit(env.step)
        acc = None
        for _ in range(4000):
            state = step(state, policy(state))
            if float(state.metrics["at_request"]):
                acc = float(state.metrics["correct_at_request"])
            if float(state.done):
                return acc, state
        raise AssertionError("guide episode did not end")

    acc_oracle, end = run(oracle, jax.random.key(3))
    acc_zero, _ = run(lambda s: jnp.zeros(1), jax.random.key(3))
    assert acc_oracle == 1.0 and acc_zero == 0.0  # u_w = 0 has no sign
    assert abs(float(end.pipeline_state.u_w)) == 1.0
    r = float(end.metrics["reward/correct"])
    assert r == pytest.approx(20.0)


def test_guide_request_weight_pays_the_choice_once_at_the_request(bank):
    from envs.guide import GuideWeights

    env = envs.make("guide", bank=bank, weights=GuideWeights(request=100.0))
    state = jax.jit(env.reset)(jax.random.key(3))
    sign = -1.0 if int(state.pipeline_state.requester) == 0 else 1.0
    step = jax.jit(env.step)
    paid = []
    while not float(state.done):  # toward the requester, then back a little from 0.3 s before
        late = int(state.pipeline_state.t) >= int(state.pipeline_state.request_step) - 15
        state = step(state, jnp.full(1, sign * (-0.2 if late else 1.0)))
        paid.append(
            (
                float(state.metrics["at_request"]),
                float(state.metrics["reward/request"]),
                float(state.pipeline_state.u_w),
            )
        )
    at, bonus, u_w = np.array(paid).T
    assert at.sum() == 1 and np.all(bonus[at == 0] == 0.0)
    assert (
        bonus[at == 1][0] == pytest.approx(100.0 * sign * u_w[at == 1][0])
        and 0.8 < bonus[at == 1][0] / 100 < 0.9
    )
    assert "reward/request" in envs.make("guide", bank=bank).reset(jax.random.key(0)).metrics


def test_guide_pays_the_midpoint_until_the_intent_shows_and_the_choice_after(bank):
    env = envs.make("guide", bank=bank)
    settled, request = guide_lib.settled_steps(bank), np.asarray(bank.request_step)
    speed = np.linalg.norm(np.asarray(bank.vel_world)[..., :2], axis=-1)
    for i in range(bank.num_trajectories):  # still from the final stop to the request, moving before
        assert 0 < settled[i] < request[i] and request[i] - settled[i] >= 25
        assert speed[i, settled[i] : request[i]].max() <= guide_lib.SETTLED_SPEED
        assert speed[i, settled[i] - 1] > guide_lib.SETTLED_SPEED

    state = jax.jit(env.reset)(jax.random.key(2))
    w = state.pipeline_state
    assert 0 <= int(w.t) <= max(int(w.request_step) - guide_lib.START_LEAD * 50, 0)
    step = jax.jit(env.step)
    rows = []
    while not float(state.done):  # one nudge, then u_w holds at 0.015
        state = step(state, jnp.full(1, 0.3 if not rows else 0.0))
        rows.append((int(state.pipeline_state.t), float(state.metrics["reward/midpoint"])))
    t, r_m = np.array(rows).T
    u_w = float(state.pipeline_state.u_w)
    intent = int(w.intent_step)
    assert intent == settled[int(w.users[int(w.requester)])]
    assert np.all(r_m[t >= intent] == 0.0) and np.all(r_m[t < intent] == pytest.approx(5 * (1 - 4 * 0.015)))
    sign = -1.0 if int(w.requester) == 0 else 1.0
    assert float(state.metrics["reward/correct"]) == pytest.approx(20.0 * sign * u_w)


def _still_user_np(vel0, vel1, u_w):
    """Turn toward a user standing still, else drift back to the midpoint (numpy)."""
    s0, s1 = np.linalg.norm(vel0[:2]), np.linalg.norm(vel1[:2])
    if min(s0, s1) < 0.05:
        return 1.0 if s1 < s0 else -1.0
    return float(np.clip(-u_w / 0.05, -1.0, 1.0))


def test_pair_accuracy_follows_u_w_from_the_trajectories_beginning_to_the_first_request(bank):
    """Against a plain numpy replay: both users from step 0, u_w += 0.05 a each step, scored by the
    sign of u_w at the first request."""
    pairs = guide_lib.held_out_pairs(bank)
    request = np.asarray(bank.request_step)
    assert len(pairs) == sum(
        request[i] != request[j] for i in range(len(request)) for j in range(len(request))
    )

    def policy(obs):
        s0, s1 = jnp.linalg.norm(obs[0:2]), jnp.linalg.norm(obs[3:5])
        drift = jnp.clip(-obs[12] / 0.05, -1.0, 1.0)
        return jnp.where(jnp.minimum(s0, s1) < 0.05, jnp.where(s1 < s0, 1.0, -1.0), drift)[None]

    got = guide_lib.pair_correct(policy, bank, pairs)
    early = guide_lib.pair_correct(policy, bank, pairs, lead=0.4)
    vel = np.asarray(bank.vel_local)
    want, want_early = [], []
    for a, b in pairs:
        first = min(request[a], request[b])
        u_w = [0.0]
        for t in range(first):
            step = 0.05 * _still_user_np(vel[a, t], vel[b, t], u_w[-1])
            u_w.append(float(np.clip(u_w[-1] + step, -1.0, 1.0)))
        sign = -1.0 if request[a] < request[b] else 1.0
        want.append(np.sign(u_w[-1]) == sign)
        want_early.append(first > 20 and np.sign(u_w[-21]) == sign)  # 0.4 s: 20 steps earlier
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(early, want_early)
    np.testing.assert_array_equal(
        guide_lib.pair_correct(policy, bank, pairs, lead=(0.0, 0.4)), [want, want_early]
    )
    assert early.sum() < got.sum()  # the still-user rule is right more often at the request
    always_second = guide_lib.pair_accuracy(lambda obs: jnp.ones(1), bank, pairs)
    assert always_second == (np.mean(request[pairs[:, 1]] < request[pairs[:, 0]]), len(pairs))
    assert guide_lib.pair_accuracy(lambda obs: jnp.zeros(1), bank, pairs)[0] == 0.0
    for bad, message in (
        (np.zeros((0, 2)), "non-empty"),
        (np.array([[0, bank.num_trajectories]]), "index trajectories"),
    ):
        with pytest.raises(ValueError, match=message):
            guide_lib.pair_correct(policy, bank, bad)
    with pytest.raises(ValueError, match="lead must be"):
        guide_lib.pair_correct(policy, bank, pairs, lead=-1.0)
    with pytest.raises(ValueError, match="lead must be"):
        guide_lib.pair_correct(policy, bank, pairs, lead=(0.0, float("nan")))
    with pytest.raises(ValueError, match="one lead"):
        guide_lib.pair_accuracy(policy, bank, pairs, lead=(0.0, 0.4))


def test_standing_pairs_are_those_whose_other_user_stands_at_the_request(bank):
    speed = np.linalg.norm(np.asarray(bank.vel_world)[..., :2], axis=-1)
    since = guide_lib.still_since(bank)
    for n in range(bank.num_trajectories):  # against a plain loop
        start = 0
        for t in range(speed.shape[1]):
            start = t + 1 if speed[n, t] > guide_lib.SETTLED_SPEED else start
            assert since[n, t] == start, (n, t)
    request = np.asarray(bank.request_step)
    want = {
        (i, j)
        for i in range(len(request))
        for j in range(len(request))
        if request[i] < request[j] and speed[j, request[i]] <= guide_lib.SETTLED_SPEED
    }
    got = {tuple(p) for p in guide_lib.standing_pairs(bank).tolist()}
    assert got == want and len(want) > 0


def test_guide_with_wrists_and_standing_pairs(bank):
    env = envs.make("guide", bank=bank, wrist=True, hard_fraction=1.0)
    assert env.observation_size == 17
    assert {k: (v.start, v.stop) for k, v in env.observation_layout.items()} == {
        "guide": (0, 15),
        "wrist": (15, 17),
    }
    states = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), 64))
    w = states.pipeline_state
    standing = {tuple(p) for p in guide_lib.standing_pairs(bank).tolist()}
    requester, other = np.asarray(w.requester), 1 - np.asarray(w.requester)
    users = np.asarray(w.users)
    rows = np.arange(64)
    assert all((a, b) in standing for a, b in zip(users[rows, requester], users[rows, other], strict=True))
    assert 0 < requester.mean() < 1  # either slot asks
    wrist = np.asarray(bank.wrist_height)[users, np.asarray(w.t)[:, None]]
    np.testing.assert_array_equal(np.asarray(states.obs)[:, 15:], wrist)
    plain = envs.make("guide", bank=bank)
    assert plain.observation_size == 15
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="hard_fraction"):
            envs.make("guide", bank=bank, hard_fraction=bad)


def test_make_rejects_bad_options(bank):
    with pytest.raises(ValueError, match="unknown task 'walk'; choose one of su, nav, guide"):
        envs.make("walk")
    with pytest.raises(ValueError, match=r"su: unknown option\(s\) \['speed'\]"):
        envs.make("su", bank=bank, speed=3)
    with pytest.raises(ValueError, match="num_users"):
        envs.make("nav", bank=bank, num_users=0)
    with pytest.raises(ValueError, match="task 'guide' takes no guide policy"):
        envs.make("guide", bank=bank, policies={"guide": lambda o: o})


def test_lab_floor_option(bank):
    env = envs.make("su", bank=bank, lab=True)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 8))
    lab = floors.lab()
    np.testing.assert_allclose(np.asarray(state.pipeline_state.floor.polygons[3]), np.asarray(lab.polygons))
    np.testing.assert_allclose(np.asarray(state.pipeline_state.floor.bounds[0]), [-5.5, -6.5, 5.5, 6.5])
    pose = jax.vmap(robot_lib.pose)(state.pipeline_state.robot)
    assert float(jax.vmap(floors.signed_distance, (None, 0))(lab, pose[:, :2]).min()) >= 0.82 - 1e-4


def test_goal_clearance_keeps_the_goal_off_obstacles_and_users(bank):
    # floors large enough to hold the sample users' paths, with furniture on them
    room = FloorConfig(room_size=(20.0, 20.0), num_circles=(4, 8), num_polygons=(4, 8))
    raw = envs.make("su", bank=bank, floor=room)
    clear = envs.make("su", bank=bank, floor=room, goal_clearance=0.9)

    @jax.jit
    def goals(key):
        w = jax.vmap(raw.reset)(jax.random.split(key, 64)).pipeline_state
        out = []
        for t in (0, 150, 300, 450, 600):
            wt = w.replace(t=jnp.full_like(w.t, t))
            users = jax.vmap(raw._user_features)(wt)
            hip = jax.vmap(lambda w, u: raw.update_goal(w, u, key, False).goal)(wt, users)
            goal = jax.vmap(lambda w, u: clear.update_goal(w, u, key, False).goal)(wt, users)
            room = jax.vmap(floors.clearance)
            out.append(
                (hip, goal, users["pose"][:, 0, :2], room(w.floor, hip[:, :2]), room(w.floor, goal[:, :2]))
            )
        return jax.tree.map(lambda *x: jnp.concatenate(x), *out)

    hip, goal, user, before, after = (np.asarray(x) for x in goals(jax.random.key(0)))
    blocked = before < 0.9
    assert blocked.sum() > 20 and (~blocked).sum() > 20  # both kinds of HIP occur
    np.testing.assert_array_equal(goal[~blocked], hip[~blocked])  # clear HIPs are the goal
    np.testing.assert_array_equal(goal[:, 2], hip[:, 2])  # the yaw is the HIP's
    assert np.mean(after[blocked] >= 0.9 - 1e-3) > 0.7
    assert np.mean(after[blocked] >= 0.77) > 0.85  # the footprint fits at nearly all
    assert np.all(np.linalg.norm(goal[:, :2] - user, axis=1) >= 1.77 - 1e-3)


def test_no_key_is_used_twice_between_reset_and_step(bank):
    # A standing robot sees the same true ranges at reset and after one zero-action step, so equal
    # noisy readings would mean the two observations drew their noise from the same key. (Rays past
    # 3 m read exactly 3 m either way, so only nearer rays say anything.)
    env = envs.make("su", bank=bank)
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(8), 16))
    nxt = jax.jit(jax.vmap(env.step))(states, jnp.zeros((16, 3)))
    lidar0, lidar1 = np.asarray(states.obs[:, :720]), np.asarray(nxt.obs[:, :720])
    near = (lidar0 < 2.9) & (lidar1 < 2.9)
    assert near.sum() > 500
    assert np.mean(lidar0[near] == lidar1[near]) < 0.01
    assert abs(np.mean(lidar0[near] - lidar1[near])) < 0.01  # same scene, independent noise


def test_lab_fraction_mixes_the_lab_twin_with_procedural_floors(bank):
    env = envs.make("su", bank=bank, lab_fraction=0.5)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), 64))
    bounds = np.asarray(state.pipeline_state.floor.bounds)
    on_lab = np.all(np.isclose(bounds, [-5.5, -6.5, 5.5, 6.5]), axis=1)
    assert 16 <= on_lab.sum() <= 48  # about half of 64 episodes, each floor whole
    lab = floors.lab().pad(*env.config.floor.capacity)
    i = int(np.argmax(on_lab))
    np.testing.assert_allclose(np.asarray(state.pipeline_state.floor.polygons[i]), np.asarray(lab.polygons))
    pose = jax.vmap(robot_lib.pose)(state.pipeline_state.robot)
    sdf = jax.vmap(floors.signed_distance)(state.pipeline_state.floor, pose[:, :2])
    assert float(sdf.min()) >= 0.82 - 1e-4  # spawned clear on either kind of floor
    with pytest.raises(ValueError, match="lab_fraction must be in"):
        envs.make("su", bank=bank, lab_fraction=1.5)


@pytest.mark.parametrize(
    ("option", "message"),
    [
        ({"lidar_dropout": 1.5}, "lidar_dropout must be in"),
        ({"lidar_noise": float("nan")}, "lidar_noise must be finite"),
        ({"lidar_noise": -0.03}, "lidar_noise must be >= 0"),
        ({"spawn_margin": float("nan")}, "spawn_margin must be finite"),
        ({"action_weights": (float("nan"), 0.5, 0.5)}, "action_weights must be finite"),
        ({"goal_tolerance": -0.2}, "goal_tolerance must be >= 0"),
        ({"mass_scale": (-1.0, 1.3)}, "mass_scale must be an ordered positive range"),
        ({"lab": "no"}, "lab must be true or false"),
        ({"distance_around": 1}, "distance_around must be true or false"),
        ({"num_rays": "90"}, "num_rays must be an integer"),
        ({"num_rays": 90.5}, "num_rays must be an integer"),
    ],
)
def test_invalid_options_are_refused_by_name(option, message):
    with pytest.raises(ValueError, match=message):
        NavConfig(**option)


def test_the_control_period_is_one_constant_not_a_setting():
    """The base, the motion data, the rewards and the evaluation share methd_jax.control's clock:
    no config carries a period of its own that could disagree with it."""
    from train.presets import ConfigError, apply_overrides, preset

    assert "control_dt" not in {f.name for f in dataclasses.fields(robot_lib.RobotConfig())}
    with pytest.raises(ConfigError, match="control_dt"):
        apply_overrides(preset("su"), ["env.robot.control_dt=0.015"])


def test_the_distances_around_users_have_one_home():
    """d_coll, d_crit and a user's radius come from methd_jax.distances in every config."""
    from methd_jax import distances
    from methd_jax.evaluation.engine import EngineConfig
    from methd_jax.geometry import KAIROS
    from methd_jax.viz import Rollout

    assert distances.COLLISION_DISTANCE == pytest.approx(KAIROS.radius + 0.6)  # the base's radius + 0.6 m
    safety = envs.rewards.SafetyConfig()
    assert (safety.collision_distance, safety.critical_distance) == (1.37, 1.77)
    assert safety.critical_distance == distances.CRITICAL_DISTANCE == EngineConfig().critical_distance
    assert NavConfig().user_radius == EngineConfig().user_radius == distances.USER_RADIUS
    rollout = {f.name: f.default for f in dataclasses.fields(Rollout)}
    assert rollout["collision_distance"] == distances.COLLISION_DISTANCE
    assert rollout["critical_distance"] == distances.CRITICAL_DISTANCE
