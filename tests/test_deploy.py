"""Exported policies and the deployment shim: ONNX / numpy parity with JAX, observations and
commands as in training, the safety layer, the watchdog, MCAP replay, and the CLIs."""

import dataclasses
import hashlib
import json
import math
import re
import shutil
import subprocess
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import export_random_policy, fuzz

import networks
from envs import sample_bag
from envs.nav import NavConfig, NavEnv
from methd_jax import deploy, floors, lidar, ros_messages
from methd_jax import robot as robot_lib
from methd_jax.deploy import mcap_replay, observation, ros_node
from methd_jax.deploy.controller import clamp_to_limits
from methd_jax.deploy.mcap_replay import read_inputs
from methd_jax.deploy.safety import CollisionMonitor, SafetyConfig, arc
from methd_jax.geometry import KAIROS
from methd_jax.jsonable import jsonable
from train import export

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = ROOT / "assets" / "deploy_sample.mcap"


@pytest.fixture(scope="module")
def su_env():
    return NavEnv(NavConfig(motion="sample", split="all", lab=True, lidar_noise=0.0, lidar_dropout=0.0))


@pytest.fixture(scope="module")
def su_deploy(tmp_path_factory, su_env):
    """A full-size SU network (720 rays, 3 x 512) exported to a deployment folder."""
    root = tmp_path_factory.mktemp("su")
    export_random_policy(root, su_env, "su", networks.ActorCritic(num_rays=720), seed=3)
    return export.export_deployment(root, log=lambda *a: None)


def test_deployment_folder_is_self_contained_and_described(su_deploy):
    files = sorted(p.name for p in su_deploy.iterdir())
    assert files == ["manifest.json", "params.npz", "policy.onnx"]
    m = json.loads((su_deploy / "manifest.json").read_text())
    d = m["deployment"]
    # every observation index is named once, with a unit per component
    covered = []
    for f in d["observation"]:
        covered += list(range(f["start"], f["stop"]))
        assert len(f["units"]) == len(f["components"])
    assert covered == list(range(m["observation_size"]))
    assert d["lidar"] == {
        "num_rays": 720,
        "angle_min": 0.0,
        "angle_increment": 2 * math.pi / 720,
        "direction": "counter-clockwise from the robot's +x axis",
        "max_range": 3.0,
    }
    assert d["action"]["interpolation_weights"] == [0.5, 0.3, 0.2]
    assert d["action"]["scale"] == [3.0, 3.0, 2.0]
    assert (d["action"]["deadzone_linear"], d["action"]["deadzone_angular"]) == (0.005, 0.00436)
    assert d["control_hz"] == 50 and d["collision_distance"] == 1.37
    assert m["params_sha256"] == export.params_sha256(su_deploy / "params.npz")
    assert m["onnx_sha256"] == hashlib.sha256((su_deploy / "policy.onnx").read_bytes()).hexdigest()
    assert m["versions"]["onnxruntime"] and m["versions"]["jax2onnx"] and m["versions"]["jax"]
    assert m["parameters"]["policy"] == 702_694
    # the exporter's patches of jax.numpy (jax2onnx) stay out of this process
    np.testing.assert_array_equal(jnp.cumsum(jnp.ones((2, 3)), 1)[1], [1.0, 2.0, 3.0])


def test_parity_jax_onnx_numpy_on_1000_observations(su_deploy):
    jax_policy = export.load(su_deploy)
    manifest = deploy.load_manifest(su_deploy)
    onnx_policy, numpy_policy = deploy.OnnxPolicy(manifest), deploy.NumpyPolicy(manifest)
    rng = np.random.default_rng(0)
    mean, std = np.asarray(jax_policy.obs_mean), np.asarray(jax_policy.obs_std)
    # up to 4 standard deviations out: the observation clip at 5 is exercised too
    obs = (mean + std * rng.normal(0, 2.0, (1000, mean.size))).astype(np.float32)
    a_jax = np.asarray(jax.jit(jax.vmap(jax_policy))(obs))
    a_onnx = onnx_policy(obs)
    a_np = numpy_policy(obs)
    assert a_onnx.shape == a_np.shape == (1000, 3)
    assert np.abs(a_jax).max() > 0.05  # a policy that does something
    np.testing.assert_allclose(a_onnx, a_jax, atol=1e-5, rtol=0)
    np.testing.assert_allclose(a_np, a_jax, atol=1e-5, rtol=0)
    # one observation at a time (the controller's call) gives the same
    np.testing.assert_allclose(onnx_policy(obs[0]), a_jax[0], atol=1e-5, rtol=0)


def test_guide_policy_exports_but_does_not_drive_the_base(tmp_path):
    from envs.guide import GuideConfig, GuideEnv

    env = GuideEnv(GuideConfig(motion="sample", split="all"))
    export_random_policy(tmp_path, env, "guide", networks.GuideActorCritic(), seed=1)
    out = export.export_deployment(tmp_path, log=lambda *a: None)
    manifest = deploy.load_manifest(out)
    obs = np.random.default_rng(1).normal(0, 1, (200, 15)).astype(np.float32)
    a_jax = np.asarray(jax.vmap(export.load(out))(obs))
    np.testing.assert_allclose(deploy.OnnxPolicy(manifest)(obs), a_jax, atol=1e-5, rtol=0)
    np.testing.assert_allclose(deploy.NumpyPolicy(manifest)(obs), a_jax, atol=1e-5, rtol=0)
    with pytest.raises(deploy.DeployError, match="'guide' policy does not drive the base"):
        deploy.Controller(out)


def _inputs(env, state) -> deploy.Inputs:
    w = state.pipeline_state
    pose = robot_lib.pose(w.robot)
    user = jax.vmap(env.bank.at, (0, None))(w.users, w.t)
    return deploy.Inputs(
        ranges=np.asarray(lidar.scan(w.floor, pose, num_rays=env.config.num_rays)),
        robot_pose=np.asarray(pose),
        velocity=np.asarray(robot_lib.velocity(w.robot)),
        users=np.concatenate([np.asarray(user["pose"]), np.asarray(user["vel_world"])], 1),
        goal=np.asarray(w.goal),
    )


def test_controller_matches_the_jax_policy_in_the_training_env(su_deploy, su_env):
    """50 Hz in lockstep: the controller rebuilds the env's observation from raw inputs (noise off)
    and its command equals the env's command for the JAX policy's action, within the base's limits."""
    policy = export.load(su_deploy)
    controller = deploy.Controller(su_deploy, safety=SafetyConfig(enabled=False))
    step = jax.jit(su_env.step)
    state = jax.jit(su_env.reset)(jax.random.key(5))
    for _ in range(40):
        w = state.pipeline_state
        action = policy(state.obs)
        # the base clips its speed to its limits in the simulator; the controller does so before sending
        expected_cmd = clamp_to_limits(np.asarray(su_env.command(action, w.actions)))
        out = controller.tick(_inputs(su_env, state))
        assert out.reason is None
        np.testing.assert_allclose(out.twist, expected_cmd, atol=1e-5, rtol=0)
        state = step(state, action)
        if state.done:
            break
    assert controller.ticks >= 20 and not controller.interventions


def test_a_policy_that_reads_sector_clearances_deploys_as_it_trained(tmp_path):
    """``NavConfig.clearance_sectors``: the deployment names the sectors, the controller rebuilds
    the clearances from the raw scan, and its command is the env's for the JAX policy's action."""
    cfg = NavConfig(motion="sample", split="all", lab=True, lidar_noise=0.0, lidar_dropout=0.0)
    env = NavEnv(dataclasses.replace(cfg, num_rays=90, clearance_sectors=18))
    assert env.observation_layout["clearance"] == slice(115, 133) and env.observation_size == 133
    export_random_policy(tmp_path, env, "su", networks.ActorCritic(num_rays=90, hidden=(32,)), seed=6)
    out = export.export_deployment(tmp_path, log=lambda *a: None)
    manifest = deploy.load_manifest(out)
    assert manifest["deployment"]["lidar"]["clearance_sectors"] == 18
    policy = export.load(out)
    controller = deploy.Controller(out, safety=SafetyConfig(enabled=False))
    step = jax.jit(env.step)
    state = jax.jit(env.reset)(jax.random.key(2))
    # the base in the corridor between the lab's round table and its north wall
    w = state.pipeline_state.replace(robot=env.robot.init(jnp.array([-3.0, 5.4, 0.3])))
    state = state.replace(pipeline_state=w, obs=env.observe(w, jnp.zeros(3), jax.random.key(0))[0])
    seen = []
    for _ in range(20):
        w = state.pipeline_state
        x = _inputs(env, state)
        action = np.asarray(policy(state.obs))
        # the clearances of the state's own observation (the rest is held to the env above)
        obs_np = _numpy_observation(manifest["deployment"], x, w, np.asarray(w.actions[0]), x.goal)
        np.testing.assert_allclose(obs_np[115:], np.asarray(state.obs)[115:], atol=2e-5)
        seen.append(np.asarray(state.obs)[115:])
        expected_cmd = clamp_to_limits(np.asarray(env.command(jnp.asarray(action), w.actions)))
        out_tick = controller.tick(x)
        assert out_tick.reason is None
        np.testing.assert_allclose(out_tick.twist, expected_cmd, atol=1e-5, rtol=0)
        state = step(state, jnp.asarray(action))
        if state.done:
            break
    seen = np.stack(seen)
    assert seen.min() < 0.5 and np.ptp(seen, axis=1).max() > 0.1  # furniture near some sectors, not all
    bad = json.loads((out / "manifest.json").read_text())
    bad["deployment"]["lidar"]["clearance_sectors"] = 9
    (out / "manifest.json").write_text(json.dumps(bad))
    with pytest.raises(deploy.DeployError, match="clearance_sectors 9 disagrees"):
        deploy.load_manifest(out)


def test_observation_and_command_match_the_env_term_by_term(su_env):
    state = jax.jit(su_env.reset)(jax.random.key(9))
    rng = np.random.default_rng(9)
    step = jax.jit(su_env.step)
    for _ in range(5):
        state = step(state, jnp.asarray(rng.uniform(-0.5, 0.5, 3), jnp.float32))
    w = state.pipeline_state
    x = _inputs(su_env, state)
    action = rng.uniform(-1, 1, 3)
    # env.observe(w, action) reads ``action`` as a_{t-1}, w.actions[0] as a_{t-2}, and the
    # acceleration from w.velocity
    obs_env, _, _ = su_env.observe(w, jnp.asarray(action, jnp.float32), jax.random.key(0))
    d = export.deployment_section(_manifest_of(su_env))
    obs_np = _numpy_observation(d, x, w, action, x.goal)
    np.testing.assert_allclose(obs_np, np.asarray(obs_env), atol=2e-5, rtol=1e-5)
    for _ in range(100):
        a, prev = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, (2, 3))
        if rng.uniform() < 0.3:  # into the dead zones
            a, prev = a * 1e-3, prev * 1e-3
        expected = np.asarray(su_env.command(jnp.asarray(a, jnp.float32), jnp.asarray(prev, jnp.float32)))
        np.testing.assert_allclose(observation.command(d, a, prev), expected, atol=1e-6)


def test_users_ordered_by_the_goal_match_the_env_and_put_the_goals_user_first():
    """``NavConfig.users_by_goal``: the user whose HIP the goal is at fills the first user slot,
    in the env and in the deployment's numpy observation alike."""
    cfg = NavConfig(num_users=2, motion="sample", split="all", lab=True, lidar_noise=0.0, lidar_dropout=0.0)
    fixed, ordered = NavEnv(cfg), NavEnv(dataclasses.replace(cfg, users_by_goal=True))
    state = jax.jit(fixed.reset)(jax.random.key(4))
    w = state.pipeline_state
    x = _inputs(fixed, state)
    user = fixed.observation_layout["user0"]
    slot = user.stop - user.start
    d = export.deployment_section(_manifest_of(ordered, "nav"))
    assert d["user_order"] == "goal" and d["hip"] == {"distance": 2.0, "lateral": -0.3}
    assert export.deployment_section(_manifest_of(fixed, "nav"))["user_order"] == "fixed"
    c, s = np.cos(x.users[:, 2]), np.sin(x.users[:, 2])
    hips = x.users[:, :2] + np.stack([2.0 * c + 0.3 * s, 2.0 * s - 0.3 * c], 1)
    action = np.array([0.2, -0.1, 0.3])
    for k in (0, 1):
        goal = np.array([*hips[k], 0.5])
        wk = w.replace(goal=jnp.asarray(goal, jnp.float32))
        key = jax.random.key(0)
        base = np.asarray(fixed.observe(wk, jnp.asarray(action, jnp.float32), key)[0])
        obs = np.asarray(ordered.observe(wk, jnp.asarray(action, jnp.float32), key)[0])
        users = base[user.start : user.start + 2 * slot].reshape(2, slot)
        np.testing.assert_array_equal(obs[user.start : user.start + slot], users[k])
        np.testing.assert_array_equal(obs[user.start + slot : user.start + 2 * slot], users[1 - k])
        rest = np.r_[0 : user.start, user.start + 2 * slot : len(obs)]
        np.testing.assert_array_equal(obs[rest], base[rest])  # nothing else moves
        np.testing.assert_allclose(_numpy_observation(d, x, w, action, goal), obs, atol=2e-5, rtol=1e-5)


def _numpy_observation(d: dict, x: deploy.Inputs, w, action: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """The deployment's observation of ``x`` as ``env.observe(w, action)`` builds it (``action`` as
    a_{t-1}, ``w.actions[0]`` as a_{t-2}, the acceleration from ``w.velocity``)."""
    return observation.observe(
        d,
        ranges=x.ranges,
        robot_pose=x.robot_pose,
        velocity=x.velocity,
        acceleration=(x.velocity - np.asarray(w.velocity)) * 50.0,
        actions=np.stack([action, np.asarray(w.actions[0])]),
        users=x.users,
        goal=goal,
    )


def _manifest_of(env, name: str = "su") -> dict:
    layout = {k: [s.start, s.stop] for k, s in env.observation_layout.items()}
    return {
        "env": name,
        "env_config": jsonable(env.config),
        "observation_layout": layout,
        "observation_clip": 5.0,
        "network": {"class": "ActorCritic", "hidden": [8], "num_rays": env.config.num_rays},
    }


# -- the safety layer ---------------------------------------------------------------------------


def _wall_ranges(x_wall: float, num_rays: int = 720) -> np.ndarray:
    """Ranges to an infinite wall x = x_wall (robot frame)."""
    ang = 2 * np.pi * np.arange(num_rays) / num_rays
    c = np.cos(ang)
    return np.where(c > 1e-9, x_wall / np.where(c > 1e-9, c, 1.0), np.inf)


def _monitor(**kw) -> CollisionMonitor:
    return CollisionMonitor(KAIROS.length, KAIROS.width, 720, 1.37, SafetyConfig(**kw))


def _newly_hits(command, ranges, horizon=1.0, dt=0.001) -> bool:
    """Ground truth at 10x the monitor's time resolution, footprint without margin."""
    ang = 2 * np.pi * np.arange(len(ranges)) / len(ranges)
    ok = np.isfinite(ranges)
    pts = np.stack([ranges[ok] * np.cos(ang[ok]), ranges[ok] * np.sin(ang[ok])], 1)
    half = np.array([KAIROS.length / 2, KAIROS.width / 2])
    poses = np.concatenate(
        [np.zeros((1, 3)), arc(np.asarray(command), np.arange(1, round(horizon / dt) + 1) * dt)]
    )
    c, s = np.cos(poses[:, 2:3]), np.sin(poses[:, 2:3])
    dx, dy = pts[None, :, 0] - poses[:, :1], pts[None, :, 1] - poses[:, 1:2]
    inside = (np.abs(c * dx + s * dy) <= half[0]) & (np.abs(-s * dx + c * dy) <= half[1])
    return bool(np.any(inside[1:] & ~inside[:1]))


def test_coast_is_the_simulated_base_with_the_default_limits():
    # the monitor's coasting model with its defaults against the MJX base's own servo model (which
    # tests/test_robot.py checks against MJX): a base moving and turning, driven and then braking
    from methd_jax.deploy.safety import coast

    rng = np.random.default_rng(4)
    commands = np.zeros((60, 3))
    commands[:20] = rng.uniform(-2, 2, 3)
    velocity = np.array([1.2, -0.7, 0.9])
    ours = coast(velocity, commands, SafetyConfig(), 0.02)
    base = robot_lib.Robot()
    theirs = np.asarray(
        jax.jit(robot_lib.predict, static_argnums=0)(
            base.servo(), jnp.asarray(velocity), jnp.asarray(commands)
        )
    )
    assert np.abs(ours[:, :2]).max() > 0.5
    np.testing.assert_allclose(ours, theirs, atol=2e-3)  # the MJCF's yaw servo: 9.998/s, 6.008 rad/s^2


def test_monitor_keeps_a_coasting_base_off_a_post():
    # the base slides right at 1.5 m/s with a post ahead on its right and the policy asks for
    # forward-left: the sweep of that command misses the post, the base's momentum would not
    from methd_jax import floors

    post = floors.Floor.from_primitives(
        [(0.85, -0.85, 0.1)], [], bounds=(-6, -6, 6, 6), max_circles=2, max_polygons=6
    )
    base, m = robot_lib.Robot(), _monitor()
    boundary, _ = KAIROS.ray_geometry(720)
    scan, step = jax.jit(lambda p: lidar.scan(post, p, num_rays=720)), jax.jit(base.step)
    command = np.array([0.8, 0.8, 0.0])

    def closest(told: bool) -> float:
        data, gaps = base.init(jnp.zeros(3)).replace(qvel=jnp.array([0.5, -1.5, 0.0])), []
        for _ in range(60):
            ranges = np.asarray(scan(robot_lib.pose(data)), np.float64)
            velocity = np.asarray(robot_lib.velocity(data), np.float64) if told else None
            out, _ = m(command, ranges, np.zeros((0, 2)), np.zeros((0, 2)), velocity=velocity)
            data = step(data, jnp.asarray(out, jnp.float32))
            gaps.append(float(np.min(np.asarray(scan(robot_lib.pose(data))) - boundary)))
        return min(gaps)

    assert closest(False) < -0.05  # taken to be at rest, the monitor lets it hit the post
    assert closest(True) > 0.02


def test_arc_integrates_the_twist_for_one_command_or_many():
    rng = np.random.default_rng(1)
    commands = np.vstack([rng.uniform(-2, 2, (5, 3)), [[1.0, -0.5, 0.0]]])  # the last drives straight
    t = np.linspace(0.1, 1.0, 10)
    many = arc(commands, t)
    assert many.shape == (6, 10, 3)
    n = 100_000  # midpoint rule on the world-frame velocity: error ~ 1e-10 m
    mid = (np.arange(n) + 0.5) / n
    at = np.round(t * n).astype(int) - 1
    for command, poses in zip(commands, many, strict=True):
        assert np.array_equal(arc(command, t), poses)
        th = command[2] * mid
        vx = command[0] * np.cos(th) - command[1] * np.sin(th)
        vy = command[0] * np.sin(th) + command[1] * np.cos(th)
        np.testing.assert_allclose(poses[:, 0], np.cumsum(vx)[at] / n, atol=1e-8)
        np.testing.assert_allclose(poses[:, 1], np.cumsum(vy)[at] / n, atol=1e-8)
        np.testing.assert_allclose(poses[:, 2], command[2] * t, atol=1e-12)


def test_obstacle_scales_of_many_commands_are_each_ones_own():
    m = _monitor()
    rng = np.random.default_rng(2)
    blocked = []
    for _ in range(20):
        ranges = np.where(rng.random(720) < 0.02, rng.uniform(0.8, 3.0, 720), np.inf)
        commands = rng.uniform(-1, 1, (10, 3)) * np.array([3.0, 3.0, 2.0]) * rng.random()
        points = m.points(ranges, np.array([3.0, 3.0, 2.0]))
        together = m.obstacle_scales(commands, points)
        assert together.tolist() == [m.obstacle_scale(c, points) for c in commands]
        blocked += list(together < 1.0)
    assert 0.2 < np.mean(blocked) < 0.8  # blocked and free ones, swept together


def test_safety_leaves_free_space_alone():
    m = _monitor()
    rng = np.random.default_rng(0)
    far = np.full(720, np.inf)
    far[::7] = 9.0  # a distant wall, out of the sweep's reach
    for _ in range(50):
        cmd = rng.uniform([-1.5, -1.5, -1.0], [1.5, 1.5, 1.0])
        out, reason = m(cmd, far, np.zeros((0, 2)), np.zeros((0, 2)))
        assert reason is None and np.array_equal(out, cmd)


def test_safety_wall_ahead_slows_then_stops_never_hits():
    m = _monitor()
    cmd = np.array([2.0, 0.0, 0.0])
    clearance = []
    for x_wall in (3.5, 2.0, 1.2, 0.8, 0.62):
        out, reason = m(cmd, _wall_ranges(x_wall), np.zeros((0, 2)), np.zeros((0, 2)))
        assert not _newly_hits(out, _wall_ranges(x_wall))
        clearance.append(np.linalg.norm(out))
        if x_wall == 3.5:  # 2 m/s for 1 s stays 0.3 m short of the wall: untouched
            assert reason is None and np.array_equal(out, cmd)
        else:
            assert reason == "obstacle"
    # slower the closer the wall; stopped when the margin is reached
    assert clearance == sorted(clearance, reverse=True) and clearance[-1] == 0.0
    assert clearance[1] > 1.0  # 2 m ahead: still driving briskly
    # driving away from the wall is never limited
    out, reason = m(np.array([-1.0, 0.3, 0.5]), _wall_ranges(0.64), np.zeros((0, 2)), np.zeros((0, 2)))
    assert reason is None


def _side_wall_ranges(y_wall: float, num_rays: int = 720) -> np.ndarray:
    """Ranges to an infinite wall y = y_wall > 0 (robot frame), the wall on the left."""
    ang = 2 * np.pi * np.arange(num_rays) / num_rays
    s = np.sin(ang)
    return np.where(s > 1e-9, y_wall / np.where(s > 1e-9, s, 1.0), np.inf)


@pytest.mark.parametrize("slide_angles", [(), (30.0, 60.0)])
def test_safety_random_scenes_never_lead_into_a_new_hit(slide_angles):
    m = _monitor(slide_angles=slide_angles)
    rng = np.random.default_rng(1)
    limited = turned = 0
    for _ in range(150):
        ranges = rng.uniform(0.6, 4.0, 720)
        ranges[rng.uniform(size=720) < 0.5] = np.inf
        cmd = rng.uniform([-3, -3, -2], [3, 3, 2])
        out, reason = m(cmd, ranges, np.zeros((0, 2)), np.zeros((0, 2)))
        limited += reason is not None
        assert not _newly_hits(out, ranges)
        # never faster, never turning faster
        assert np.linalg.norm(out[:2]) <= np.linalg.norm(cmd[:2]) + 1e-12 and abs(out[2]) <= abs(cmd[2])
        # never further from the command than stopping would be (in (vx, vy, r * wz))
        w = np.array([1.0, 1.0, m.reach_radius**2])
        assert np.sum(w * (out - cmd) ** 2) <= np.sum(w * cmd**2) + 1e-9
        if np.any(out[:2]):  # the linear velocity turned by no more than the largest slide angle
            cos = out[:2] @ cmd[:2] / (np.linalg.norm(out[:2]) * np.linalg.norm(cmd[:2]))
            assert cos >= np.cos(np.deg2rad(max(slide_angles, default=0.0))) - 1e-9
        turned += not np.allclose(np.cross(out, cmd), 0, atol=1e-9)
    assert limited > 50  # the scenes are cluttered: the test exercises the filter
    if slide_angles:
        assert turned > 20  # and the slides
    else:
        assert turned == 0  # without slide angles the filter only scales


def test_safety_slides_along_a_wall_instead_of_stopping():
    free = np.zeros((0, 2))
    wall = _side_wall_ranges(0.62)  # 0.62 m to the left: the margin's edge is 0.1 m from it
    cmd = np.array([1.2, 0.6, 0.0])  # forward and into the wall
    scaled, _ = _monitor(slide_angles=())(cmd, wall, free, free)
    out, reason = _monitor()(cmd, wall, free, free)
    assert reason == "obstacle" and not _newly_hits(out, wall)
    assert np.linalg.norm(scaled) < 0.3  # scaling alone nearly stops the base
    assert out[0] > 0.9 and out[1] < cmd[1]  # the slide keeps most of the forward speed
    # a turn that would swing a corner into the wall: scaling stops the base at once; the closest
    # clear neighbour keeps the whole turn and steers off the wall (cost 1.0 in (vx, vy, r * wz)
    # against 1.42 for driving straight on without the turn)
    wall, cmd = _side_wall_ranges(0.6), np.array([1.0, 0.0, 1.5])
    scaled, _ = _monitor(slide_angles=())(cmd, wall, free, free)
    out, reason = _monitor()(cmd, wall, free, free)
    assert np.abs(scaled).max() < 0.2 and reason == "obstacle" and not _newly_hits(out, wall)
    np.testing.assert_allclose(out, [0.5, -np.sqrt(0.75), 1.5], atol=1e-12)


def test_safety_user_stepping_in_front():
    m = _monitor()
    free = np.full(720, np.inf)
    cmd = np.array([1.5, 0.0, 0.0])
    # a user 2.5 m ahead, 1.2 m to the left, stepping into the path at 1.2 m/s
    user, vel = np.array([[2.5, 1.2]]), np.array([[0.0, -1.2]])
    out, reason = m(cmd, free, user, vel)
    assert reason == "user" and np.linalg.norm(out) < np.linalg.norm(cmd)
    t = np.linspace(0, 1.0, 1001)
    robot = arc(out, t)[:, :2]
    d = np.linalg.norm(user + t[:, None] * vel - robot, axis=1)
    assert d.min() >= 1.37
    # the same user walking away leaves the command alone
    out, reason = m(cmd, free, user, -vel)
    assert reason is None and np.array_equal(out, cmd)
    # already too close: moving away is allowed, moving closer is stopped
    close = np.array([[1.2, 0.0]])
    assert m(np.array([-1.0, 0.0, 0.0]), free, close, np.zeros((1, 2)))[1] is None
    out, reason = m(np.array([1.0, 0.0, 0.0]), free, close, np.zeros((1, 2)))
    assert reason == "user" and not np.any(out)


def test_controller_counts_safety_interventions(su_deploy):
    c = deploy.Controller(su_deploy, backend="numpy")
    x = deploy.Inputs(
        ranges=_wall_ranges(0.62),
        robot_pose=np.zeros(3),
        velocity=np.zeros(3),
        users=np.array([[-5.0, 0.0, 0.0, 0.0, 0.0, 0.0]]),
        goal=np.array([4.0, 0.0, 0.0]),
    )
    outs = [c.tick(x) for _ in range(20)]
    for o in outs:
        assert not _newly_hits(o.twist, x.ranges)
    limited = sum(o.reason == "safety:obstacle" for o in outs)
    assert c.interventions["safety:obstacle"] == limited
    assert sum(c.interventions.values()) == sum(o.reason is not None for o in outs)


@pytest.fixture(scope="module")
def coarse_deploy(tmp_path_factory):
    """A policy that samples 90 rays (4 degrees apart), as the CPU presets train."""
    env = NavEnv(NavConfig(motion="sample", split="all", num_rays=90))
    root = tmp_path_factory.mktemp("coarse")
    net = networks.ActorCritic(num_rays=90, hidden=(32, 32))
    export_random_policy(root, env, "su", net, seed=5)
    return export.export_deployment(root, log=lambda *a: None)


def _pole_scan(pose, pole, radius, beams=1440):
    """A LaserScan (angle_min -pi, ``beams`` beams, 0.05-30 m) of one pole seen from ``pose``."""
    ang = -np.pi + 2 * np.pi * np.arange(beams) / beams
    d = np.stack([np.cos(ang + pose[2]), np.sin(ang + pose[2])], 1)
    rel = np.asarray(pole) - pose[:2]
    along = d @ rel
    disc = along**2 - (rel @ rel - radius**2)
    hit = (disc >= 0) & (along > 0)
    ranges = np.where(hit, along - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    return ranges, (-np.pi, 2 * np.pi / beams, 0.05, 30.0)


def _pole_depth(pose, pole, radius) -> float:
    """How far the pole reaches into the footprint (<= 0: clear)."""
    q = observation.to_local(pose, np.asarray(pole)[None])[0]
    half = np.array([KAIROS.length / 2, KAIROS.width / 2])
    outside = np.maximum(np.abs(q) - half, 0.0)
    return (
        radius - float(np.linalg.norm(outside)) if outside.any() else radius + float(np.min(half - np.abs(q)))
    )


def _drive_at_pole(controller, pole, radius, full_scan, ticks=100):
    """Forces full-speed actions straight at the pole for ``ticks`` ticks, moving the base exactly
    as commanded; the deepest penetration and the closest the pole came."""
    pose = np.zeros(3)
    deepest = -np.inf
    controller.reset()
    for _ in range(ticks):
        ranges, geometry = _pole_scan(pose, pole, radius)
        rel = observation.to_local(pose, np.asarray(pole)[None])[0]
        controller.policy = lambda obs, rel=rel: np.r_[rel / np.abs(rel).max(), 0.0].astype(np.float32)
        x = deploy.Inputs(
            ranges=deploy.scan_to_rays(ranges, *geometry, controller.num_rays),
            scan_points=deploy.scan_points(ranges, *geometry) if full_scan else None,
            robot_pose=pose.copy(),
            velocity=np.zeros(3),
            users=np.array([[-20.0, 0.0, 0.0, 0.0, 0.0, 0.0]]),
            goal=np.r_[pole, 0.0],
        )
        twist = controller.tick(x).twist
        step = arc(twist, np.linspace(0, controller.dt, 11)[1:])  # the move, finely sampled
        for local in step:
            moved = np.r_[pose[:2] + observation.rotate(pose[2], local[:2]), pose[2] + local[2]]
            deepest = max(deepest, _pole_depth(moved, pole, radius))
        pose = moved
    return deepest, pose


def test_safety_stops_before_a_thin_pole_between_the_policys_rays(coarse_deploy):
    # 2 cm poles at 0.3-1.5 m beyond the bumper, each halfway between two of the policy's 90 rays
    # (which therefore miss it), with the policy forced to full speed straight at it
    c = deploy.Controller(coarse_deploy, backend="numpy")
    rng = np.random.default_rng(7)
    missed_by_rays, hits_without_full_scan = 0, 0
    for _ in range(12):
        bearing = np.deg2rad(4.0 * rng.integers(-5, 6) + 2.0)  # between two policy rays
        gap = rng.uniform(0.3, 1.5)
        boundary = float(KAIROS.boundary_distance(jnp.asarray(bearing)))
        pole = (boundary + gap + 0.01) * np.array([np.cos(bearing), np.sin(bearing)])
        ranges, geometry = _pole_scan(np.zeros(3), pole, 0.01)
        missed_by_rays += np.isinf(deploy.scan_to_rays(ranges, *geometry, 90)).all()
        deepest, pose = _drive_at_pole(c, pole, 0.01, full_scan=True)
        assert deepest <= 0.0, (bearing, gap, deepest)
        # it approached (slowing as the sweep's clear time shrinks), not stopped at the first sight
        assert _pole_depth(pose, pole, 0.01) > -(0.05 + 0.5 * gap)
        hits_without_full_scan += _drive_at_pole(c, pole, 0.01, full_scan=False)[0] > 0.0
    assert missed_by_rays == 12  # the policy's rays never saw a pole ...
    assert hits_without_full_scan >= 10  # ... so without the full scan the robot drives into it
    assert c.interventions["safety:obstacle"] > 0


def test_scan_points_are_the_beams_in_range():
    ranges = np.array([1.0, np.inf, 0.01, 2.0, np.nan, 50.0])
    pts = deploy.scan_points(ranges, 0.0, np.pi / 2, 0.05, 30.0)
    np.testing.assert_allclose(pts, [[1.0, 0.0], [0.0, -2.0]], atol=1e-12)  # beams 0 and 3 (270 deg)
    assert deploy.scan_points(np.array([]), 0.0, 0.1, 0.0, 1.0).shape == (0, 2)


# -- the watchdog -------------------------------------------------------------------------------


def _good(n_users: int = 1) -> deploy.Inputs:
    return deploy.Inputs(
        ranges=np.full(720, 2.5),
        robot_pose=np.array([0.0, 0.0, 0.3]),
        velocity=np.array([0.2, 0.0, 0.0]),
        users=np.tile([3.0, 1.0, 0.0, 0.1, 0.0, 0.0], (n_users, 1)),
        goal=np.array([1.0, 1.0, 0.0]),
        scan_stamp=10.0,
        odom_stamp=10.0,
        users_stamp=10.0,
    )


@pytest.mark.parametrize(
    "change, now, reason",
    [
        ({"scan_stamp": 9.5}, 10.0, "watchdog:stale_scan"),
        ({"odom_stamp": 9.0}, 10.0, "watchdog:stale_odom"),
        ({"users_stamp": float("nan")}, 10.0, "watchdog:stale_users"),
        ({"ranges": np.r_[np.full(719, 2.0), np.nan]}, 10.0, "watchdog:nan_ranges"),
        ({"ranges": np.full(700, 2.0)}, 10.0, "watchdog:shape_ranges"),
        ({"ranges": np.array([])}, 10.0, "watchdog:empty_ranges"),
        ({"ranges": None}, 10.0, "watchdog:missing_ranges"),
        ({"ranges": np.r_[np.full(719, 2.0), -0.1]}, 10.0, "watchdog:negative_ranges"),
        ({"ranges": "not a scan"}, 10.0, "watchdog:invalid_ranges"),
        ({"goal": np.array([np.nan, 0.0, 0.0])}, 10.0, "watchdog:nan_goal"),
        ({"users": np.zeros((2, 6))}, 10.0, "watchdog:shape_users"),
        ({"velocity": np.array([0.0, np.inf, 0.0])}, 10.0, "watchdog:nan_velocity"),
        ({"acceleration": np.zeros(2)}, 10.0, "watchdog:shape_acceleration"),
        ({"ranges": np.zeros(720)}, 10.0, "watchdog:zero_ranges"),
        ({"scan_stamp": 110.0}, 10.0, "watchdog:stale_scan"),  # from the future
        ({"odom_stamp": float("inf")}, 10.0, "watchdog:stale_odom"),
        ({"users_stamp": 15.0}, 10.0, "watchdog:stale_users"),  # a clock that jumped back 5 s
        ({"scan_points": np.zeros((4, 3))}, 10.0, "watchdog:shape_scan_points"),
        ({"scan_points": np.array([[1.0, np.nan]])}, 10.0, "watchdog:nan_scan_points"),
        ({"scan_points": [[1.0, "x"]]}, 10.0, "watchdog:invalid_scan_points"),
    ],
)
def test_watchdog_stops_on_bad_inputs(su_deploy, change, now, reason):
    c = deploy.Controller(su_deploy, backend="numpy")
    assert c.tick(_good(), now=10.05).reason in (None, "safety:obstacle", "safety:user")
    out = c.tick(dataclasses.replace(_good(), **change), now=now)
    assert out.reason == reason and not np.any(out.twist) and not np.any(out.policy)
    assert c.interventions[reason] == 1
    assert not np.any(c.actions) and c.last_velocity is None  # the next tick starts from the base's motion


def test_controller_resumes_from_the_bases_motion_after_a_pause(su_deploy):
    """A history from before a pause would be one tick's acceleration of the whole change since
    (here 62.5 m/s^2) and blend old actions into the command; the controller starts again from the
    base's velocity instead, with no acceleration, as after a watchdog stop."""
    c = deploy.Controller(su_deploy, backend="numpy", safety=SafetyConfig(enabled=False))
    seen = []
    c.policy = lambda obs: (seen.append(np.asarray(obs, np.float64)), np.array([0.1, 0.0, 0.0]))[1]
    layout = {k: slice(*v) for k, v in c.manifest["observation_layout"].items()}
    weights = np.asarray(c.deployment["action"]["interpolation_weights"])

    def tick(t, vx):
        x = dataclasses.replace(
            _good(), velocity=np.array([vx, 0.0, 0.0]), scan_stamp=t, odom_stamp=t, users_stamp=t
        )
        return c.tick(x, now=t)

    tick(10.0, 0.2)  # the first tick starts from the base's 0.2 m/s
    np.testing.assert_allclose(seen[-1][layout["robot_acceleration"]], 0.0)
    np.testing.assert_allclose(seen[-1][layout["previous_action"]], [0.2 / 3.0, 0.0, 0.0])
    tick(10.02, 0.25)  # 50 Hz: differenced, and the policy's own action is the history
    np.testing.assert_allclose(seen[-1][layout["robot_acceleration"]], [2.5, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(seen[-1][layout["previous_action"]], [0.1, 0.0, 0.0])
    out = tick(11.0, 1.5)  # ticks resume after ~1 s in which something else drove the base
    np.testing.assert_allclose(seen[-1][layout["robot_acceleration"]], 0.0)
    np.testing.assert_allclose(seen[-1][layout["previous_action"]], [0.5, 0.0, 0.0])
    expected = (weights[0] * 0.1 + (weights[1] + weights[2]) * 0.5) * 3.0
    assert out.policy[0] == pytest.approx(expected) and expected > 0.5 * 1.5
    tick(11.04, 1.6)  # one tick lost is not a pause: differenced over the two periods that passed
    np.testing.assert_allclose(seen[-1][layout["robot_acceleration"]], [2.5, 0.0, 0.0], atol=1e-9)
    tick(11.053, 1.65)  # a tick 3 ms early is still one period on
    np.testing.assert_allclose(seen[-1][layout["robot_acceleration"]], [2.5, 0.0, 0.0], atol=1e-9)


def test_the_evaluations_policy_resumes_as_the_controller_does(su_deploy, su_env):
    """The engine's Chase skips the policy while Escape, Inform or Haptic drive the base; on its
    next call it takes the history the deployed controller takes after a pause."""
    from envs.evaluation import Policy, PolicyState
    from methd_jax.evaluation.methods import Context

    method = Policy(su_env, policy=None)
    data = su_env.robot.init(jnp.array([1.0, 2.0, 0.4]))
    world_velocity = jnp.array([*jnp.asarray(observation.rotate(0.4, np.array([1.5, -4.0]))), 0.5])
    data = data.replace(qvel=data.qvel.at[:3].set(world_velocity.astype(data.qvel.dtype)))
    stale = PolicyState(jnp.full((3, 3), 0.7), jnp.ones(3), jnp.float32(0.0), jnp.zeros(2), jnp.int32(10))

    def context(step):
        return Context(data, None, None, None, None, None, jnp.int32(step), None, None)

    kept = method.resume(stale, context(11))
    np.testing.assert_array_equal(kept.actions, stale.actions)
    np.testing.assert_array_equal(kept.velocity, stale.velocity)
    resumed = method.resume(stale, context(60))
    c = deploy.Controller(su_deploy, backend="numpy")
    c.resume(np.asarray(robot_lib.velocity(data), np.float64))
    np.testing.assert_allclose(resumed.actions[:2], c.actions, atol=1e-6)
    np.testing.assert_allclose(resumed.actions[0], [0.5, -1.0, 0.25], atol=1e-6)  # -4 m/s clipped
    np.testing.assert_allclose(resumed.velocity, c.last_velocity, atol=1e-6)
    first = method.resume(method.init(), context(0))  # an episode's first call: from the base's motion
    np.testing.assert_allclose(first.actions, resumed.actions, atol=1e-6)


def test_the_evaluations_guide_keeps_watching_while_the_engine_drives():
    """GuideRL advances u_w on the engine's idle steps as it does in Chase (the deployed GuideRL node
    runs whatever drives the base); an SU policy has nothing to watch."""
    from envs.evaluation import Policy
    from methd_jax.evaluation.methods import Context

    config = NavConfig(num_users=2, motion="sample", split="all", lab=True)
    env = NavEnv(config, guide_policy=lambda obs: jnp.ones(1))
    method = Policy(env, policy=None)
    users = jax.vmap(env.bank.at, (0, None))(jnp.array([0, 1]), jnp.int32(50))
    ctx = Context(
        env.robot.init(jnp.zeros(3)),
        jnp.zeros(3),
        users,
        jnp.ones(2, bool),
        floors.lab(),
        None,
        jnp.int32(5),
        jax.random.key(0),
        None,
    )
    state = method.init()
    for _ in range(3):
        state = method.idle(state, ctx)
    assert float(state.u_w) == pytest.approx(0.15)  # three steps of GuideRL's largest turn
    np.testing.assert_array_equal(state.guide_actions, [1.0, 1.0])
    np.testing.assert_array_equal(state.actions, method.init().actions)  # the base's history is Chase's
    su = Policy(NavEnv(NavConfig(motion="sample", split="all", lab=True)), policy=None)
    start = su.init()
    assert su.idle(start, ctx) is start


def _tampered(src, tmp_path, edit=None, files=None):
    """A copy of the deployment folder ``src`` with ``edit(manifest)`` applied and ``files``
    (name -> bytes) overwritten."""
    out = tmp_path / "tampered"
    shutil.copytree(src, out)
    if edit is not None:
        m = json.loads((out / "manifest.json").read_text())
        edit(m)
        (out / "manifest.json").write_text(json.dumps(m))
    for name, data in (files or {}).items():
        if data is None:
            (out / name).unlink()
        else:
            (out / name).write_bytes(data)
    return out


def _set(path, value):
    def edit(m):
        *keys, last = path
        for k in keys:
            m = m[k]
        m[last] = value

    return edit


@pytest.mark.parametrize(
    "edit, files, message",
    [
        (_set(["params_sha256"], "0" * 64), None, "does not match the manifest's params_sha256"),
        (_set(["deployment", "lidar", "num_rays"], 360), None, "disagrees with the network"),
        (_set(["deployment", "footprint", "length"], 0.0), None, "is not the base's"),
        (_set(["deployment", "action", "scale"], [300, 300, 200]), None, "exceeds the base's limits"),
        (_set(["deployment", "control_hz"], 0), None, "control_hz must be positive"),
        (lambda m: m["deployment"].pop("footprint"), None, "missing or malformed field"),
        (_set(["deployment", "user_order"], "by_name"), None, "neither 'fixed' nor 'goal'"),
        (_set(["deployment", "user_order"], "goal"), None, "needs hip.distance and hip.lateral"),
        (None, {"manifest.json": b"{not json"}, "not valid JSON"),
        (None, {"params.npz": b"PK\x03\x04 truncated"}, "params.npz: unreadable"),
        (None, {"policy.onnx": b""}, "does not match the manifest's onnx_sha256"),
        (None, {"policy.onnx": bytes(range(256)) * 8}, "does not match the manifest's onnx_sha256"),
        (
            _set(["onnx_sha256"], hashlib.sha256(b"junk").hexdigest()),
            {"policy.onnx": b"junk"},
            "not a loadable ONNX",
        ),
        (None, {"policy.onnx": None}, "policy.onnx is missing"),
    ],
)
def test_a_folder_that_cannot_be_trusted_is_refused(su_deploy, tmp_path, edit, files, message):
    folder = _tampered(su_deploy, tmp_path, edit, files)
    with pytest.raises(deploy.DeployError, match=message):
        deploy.Controller(folder)


def test_params_of_another_run_are_refused(su_deploy, tmp_path, su_env):
    other = tmp_path / "other"
    export_random_policy(other, su_env, "su", networks.ActorCritic(num_rays=720), seed=4)
    folder = _tampered(
        su_deploy, tmp_path, files={"params.npz": (other / "policy" / "params.npz").read_bytes()}
    )
    with pytest.raises(deploy.DeployError, match="params_sha256"):
        deploy.Controller(folder, backend="numpy")


def test_no_command_beyond_the_robots_limits(su_deploy):
    from methd_jax.deploy.policy import ROBOT_FOOTPRINT, ROBOT_LIMITS

    # the deploy side's own constants are the simulator's robot
    assert ROBOT_LIMITS == (robot_lib.RobotConfig().max_speed, robot_lib.RobotConfig().max_yaw_rate)
    assert ROBOT_FOOTPRINT == (KAIROS.length, KAIROS.width)
    out = clamp_to_limits(np.array([224.0, -224.0, -50.0]))
    assert math.isclose(math.hypot(out[0], out[1]), 3.0) and out[0] == -out[1] and out[2] == -2.0
    np.testing.assert_array_equal(clamp_to_limits(np.array([1.0, 0.5, 0.3])), [1.0, 0.5, 0.3])
    c = deploy.Controller(su_deploy, backend="numpy", safety=SafetyConfig(enabled=False))
    c.policy = lambda obs: np.ones(3, np.float32)  # a policy gone wild: full speed in every axis
    for _ in range(5):
        twist = c.tick(_good()).twist
        assert math.hypot(twist[0], twist[1]) <= 3.0 + 1e-9 and abs(twist[2]) <= 2.0 + 1e-9


def test_watchdog_catches_a_failing_policy(su_deploy):
    c = deploy.Controller(su_deploy, backend="numpy")

    def broken(obs):
        raise MemoryError("out of memory")

    c.policy = broken
    out = c.tick(_good())
    assert out.reason == "error:MemoryError"
    assert not np.any(out.twist) and c.interventions[out.reason] == 1
    c.policy = lambda obs: np.full(3, np.nan)
    assert c.tick(_good()).reason == "watchdog:nan_action"


def test_controller_tick_latency_fits_the_50hz_budget(su_deploy):
    """The goal (p99 < 2 ms) is measured in docs/benchmarks.md; here, on a shared CI core, only the
    50 Hz budget itself is asserted, on the best of three measurements (timeit's minimum over
    repeats): another process on the shared cores can push a single measurement's p99 past it."""
    controller = deploy.Controller(su_deploy)
    runs = [deploy.latency(controller, ticks=300, seed=seed) for seed in range(3)]
    for stats in runs:
        assert stats["ticks"] == 300 and 0 < stats["median_ms"] <= stats["p99_ms"] <= stats["max_ms"]
    assert min(s["p99_ms"] for s in runs) < 20.0, runs


# -- replay ------------------------------------------------------------------------------------


def test_scan_to_rays_resamples_any_laserscan():
    # 1440 beams from -pi, 0.25 degree apart, each reading 1 m + its index / 1000
    ranges = 1.0 + np.arange(1440) / 1000
    rays = deploy.scan_to_rays(ranges, -math.pi, math.radians(0.25), 0.1, 10.0, 720)
    ours = 0.5 * np.arange(720)  # degrees: 0, 0.5, 1, ...
    beam = (np.rint((ours + 180.0) / 0.25).astype(int)) % 1440
    np.testing.assert_allclose(rays, ranges[beam])
    # a coarser scan (1 degree) gives each ray its nearest beam
    coarse = deploy.scan_to_rays(np.arange(360.0), 0.0, math.radians(1.0), 0.0, 1e3, 720)
    assert coarse[2] == 1.0 and coarse[4] == 2.0 and coarse[718] == 359.0
    # out of [range_min, range_max] -> no return; a partial scan leaves uncovered rays empty
    r = deploy.scan_to_rays(np.array([0.05, 2.0, 50.0]), 0.0, math.radians(0.5), 0.1, 10.0, 720)
    assert np.isinf(r[0]) and r[1] == 2.0 and np.isinf(r[2]) and np.isinf(r[3:]).all()
    assert np.isnan(deploy.scan_to_rays(np.array([np.nan] * 720), 0.0, 2 * np.pi / 720, 0.1, 10.0, 720)).all()


def _read(path, topic):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [
            (schema.name, m.log_time, msg)
            for schema, _, m, msg in reader.iter_decoded_messages(topics=[topic])
        ]


def test_replay_the_sample_bag(su_deploy, tmp_path):
    c = deploy.Controller(su_deploy)
    summary = deploy.replay(c, SAMPLE_BAG, tmp_path / "cmd.mcap")
    cmds = _read(tmp_path / "cmd.mcap", "/cmd_vel")
    raw = _read(tmp_path / "cmd.mcap", "/cmd_vel_policy")
    scans = _read(SAMPLE_BAG, "/scan")
    assert len(cmds) == len(raw) == summary["ticks"] == len(scans)
    assert {c[0] for c in cmds} == {"geometry_msgs/msg/Twist"}
    times = np.array([c[1] for c in cmds])
    assert np.all(np.diff(times) == 20_000_000)  # 50 Hz
    assert summary["moving_ticks"] > 0.9 * summary["ticks"]  # inputs are fresh and valid all along
    assert not any(k.startswith("watchdog") for k in summary["interventions"])
    # the replayed commands are the controller's: tick 0 by hand
    first = read_inputs(SAMPLE_BAG, 720, 1)
    twist = np.array([cmds[0][2].linear.x, cmds[0][2].linear.y, cmds[0][2].angular.z])
    c2 = deploy.Controller(su_deploy)
    odom = first["/odom"].values[0]
    rays, points = first["/scan"].values[0]
    assert len(points) == np.isfinite(rays).sum()  # the sample's LiDAR has the policy's 720 beams
    expected = c2.tick(
        deploy.Inputs(
            ranges=rays,
            scan_points=points,
            robot_pose=odom[0],
            velocity=odom[1],
            users=first["/user0/odom"].values[0][None],
            goal=first["/goal"].values[0],
        )
    )
    np.testing.assert_allclose(twist, expected.twist, atol=1e-9)


def test_replay_a_bag_with_a_scan_gap_reaches_the_watchdog(su_deploy, tmp_path):
    rows = {
        "ranges": np.full((100, 720), 2.0),
        "pose": np.zeros((100, 3)),
        "velocity": np.zeros((100, 3)),
        "user_pose": np.tile([4.0, 0.0, 0.0], (100, 1)),
        "user_twist": np.zeros((100, 3)),
        "goal": np.tile([1.0, 0.0, 0.0], (100, 1)),
    }
    bag = sample_bag.write(tmp_path / "in.mcap", rows, drop={"/scan": range(40, 70)})
    summary = deploy.replay(deploy.Controller(su_deploy), bag, tmp_path / "out.mcap")
    assert summary["ticks"] == 100
    # scans stop at tick 39 (t = 0.78 s); ticks more than 0.2 s later (50 to 69) are stale
    assert summary["interventions"]["watchdog:stale_scan"] == 20


def test_sample_bag_is_what_the_recorder_makes():
    """The shipped bag comes from `python -m envs.sample_bag` (its documented command)."""
    scans = _read(SAMPLE_BAG, "/scan")
    odom = _read(SAMPLE_BAG, "/odom")
    assert len(scans) == len(odom) >= 250 and scans[0][2].ranges.__len__() == 720
    pos = np.array([[o[2].pose.pose.position.x, o[2].pose.pose.position.y] for o in odom])
    assert np.linalg.norm(pos[-1] - pos[0]) > 0.5  # the base drives in it


# -- no JAX, ROS guard, CLIs --------------------------------------------------------------------


def test_the_controller_runs_without_jax(su_deploy):
    code = (
        "import sys, numpy as np\n"
        "sys.modules['jax'] = None  # any import of jax now fails\n"
        "from methd_jax.deploy import Controller, Inputs\n"
        f"c = Controller({str(su_deploy)!r})\n"
        "user = np.array([[4.0, 0, 0, 0, 0, 0]])\n"
        "x = Inputs(np.full(720, 2.0), np.zeros(3), np.zeros(3), user, np.ones(3))\n"
        "out = c.tick(x)\n"
        "assert out.reason in (None, 'safety:obstacle'), out.reason\n"
        "assert not [m for m in sys.modules if m.startswith(('jax.', 'flax', 'optax', 'mujoco'))]\n"
        "print('ok', out.twist)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.startswith("ok"), r.stderr


def test_ros_node_is_guarded(su_deploy):
    assert not ros_node.available()  # no ROS 2 on the test machine
    with pytest.raises(RuntimeError, match="rclpy is not importable"):
        ros_node.run(str(su_deploy))
    r = subprocess.run(
        [sys.executable, "-m", "methd_jax.deploy", "node", str(su_deploy)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 1 and r.stderr.strip().count("\n") == 0 and "source a ROS 2" in r.stderr


def _fake_ros(monkeypatch, bag_messages):
    """rclpy and the message packages as stand-ins: the node's wiring runs without ROS; ``spin``
    delivers ``bag_messages`` (topic, msg) to the subscriptions, firing the timer after each scan."""
    ns = types.SimpleNamespace

    class Twist:
        def __init__(self):
            self.linear, self.angular = ns(x=0.0, y=0.0, z=0.0), ns(x=0.0, y=0.0, z=0.0)

    published, nodes = [], []

    class Node:
        def __init__(self):
            self.subs, self.timers, self.clock_ns = {}, [], 0
            nodes.append(self)

        def create_subscription(self, kind, topic, callback, depth):
            self.subs[topic] = callback

        def create_publisher(self, kind, topic, depth):
            return ns(publish=lambda msg: published.append((topic, msg)))

        def create_timer(self, period, callback):
            self.timers.append(callback)

        def get_clock(self):
            return ns(now=lambda: ns(nanoseconds=self.clock_ns))

        def get_logger(self):
            return ns(info=lambda *a: None)

        def destroy_node(self):
            pass

    def spin(node):
        for topic, msg in bag_messages:
            node.subs[topic](msg)
            if topic == "/scan":
                node.clock_ns = ros_messages.stamp_ns(msg)
                node.timers[0]()

    rclpy = ns(init=lambda: None, create_node=lambda name: Node(), spin=spin, shutdown=lambda: None)
    modules = {
        "rclpy": rclpy,
        "geometry_msgs": ns(),
        "geometry_msgs.msg": ns(PoseStamped=object, Twist=Twist),
        "nav_msgs": ns(),
        "nav_msgs.msg": ns(Odometry=object),
        "sensor_msgs": ns(),
        "sensor_msgs.msg": ns(LaserScan=object),
    }
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    return published


def test_ros_node_wiring_with_stand_in_rclpy(su_deploy, monkeypatch):
    """The node's callbacks and timer, fed the sample bag's first second: it publishes the same
    /cmd_vel as the offline replay."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(SAMPLE_BAG, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        messages = [(c.topic, msg) for _, c, m, msg in reader.iter_decoded_messages(log_time_order=True)]
    # per tick the bag holds /scan first; deliver the other topics of a tick before its scan
    messages = messages[:200]
    order = {"/odom": 0, "/user0/odom": 1, "/goal": 2, "/scan": 3}
    ticks = [messages[i : i + 4] for i in range(0, len(messages), 4)]
    messages = [m for tick in ticks for m in sorted(tick, key=lambda tm: order[tm[0]])]
    published = _fake_ros(monkeypatch, messages)
    assert ros_node.available()
    ros_node.run(str(su_deploy))
    assert len(published) == 50 and {t for t, _ in published} == {"/cmd_vel"}
    got = np.array([[m.linear.x, m.linear.y, m.angular.z] for _, m in published])
    expected = []
    c = deploy.Controller(su_deploy)
    for tick in ticks:
        msgs = dict(tick)
        pose, twist = mcap_replay.odometry(msgs["/odom"])
        x = deploy.Inputs(
            ranges=deploy.scan_to_rays(
                msgs["/scan"].ranges,
                msgs["/scan"].angle_min,
                msgs["/scan"].angle_increment,
                msgs["/scan"].range_min,
                msgs["/scan"].range_max,
                720,
            ),
            robot_pose=pose,
            velocity=twist,
            users=mcap_replay.user_state(msgs["/user0/odom"])[None],
            goal=mcap_replay.goal_pose(msgs["/goal"]),
        )
        expected.append(c.tick(x).twist)
    np.testing.assert_allclose(got, np.array(expected), atol=1e-12)
    assert np.any(got)


def test_deploy_cli_replay_and_latency(su_deploy, tmp_path):
    from methd_jax.deploy.__main__ import main

    out = tmp_path / "cmd.mcap"
    assert main(["replay", str(SAMPLE_BAG), str(su_deploy), "--out", str(out), "--backend", "numpy"]) == 0
    assert len(_read(out, "/cmd_vel")) > 0
    assert main(["latency", str(su_deploy), "--ticks", "20"]) == 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["replay", "missing.mcap", "{policy}", "--out", "{tmp}/o.mcap"], "missing.mcap: no such file"),
        (["replay", "{bag}", "{tmp}", "--out", "{tmp}/o.mcap"], "holds no exported policy"),
        (["latency", "{policy}", "--ticks", "0"], "--ticks must be >= 1"),
        (["latency", "{policy}", "--backend", "tensorrt"], "invalid choice"),
    ],
)
def test_deploy_cli_errors_are_one_line(su_deploy, tmp_path, capsys, argv, message):
    from methd_jax.deploy.__main__ import main

    argv = [a.format(policy=su_deploy, tmp=tmp_path, bag=SAMPLE_BAG) for a in argv]
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code in (1, 2) and message in err and err.strip().count("\n") == 0


def test_export_cli(tmp_path, capsys, su_deploy):
    with pytest.raises(SystemExit) as e:
        export.main([str(tmp_path / "nothing")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "no such run or policy folder" in err and err.strip().count("\n") == 0
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        export.main([str(tmp_path / "empty")])
    assert "holds no exported policy" in capsys.readouterr().err
    # a training export without a deployment section is refused by the controller, with the fix
    with pytest.raises(deploy.DeployError, match=r"python -m train\.export"):
        deploy.Controller(su_deploy.parent / "policy")


def test_export_refuses_damaged_runs_and_leaves_no_half_folder(coarse_deploy, tmp_path, capsys):
    def run_copy(name):
        shutil.copytree(coarse_deploy.parent, tmp_path / name, ignore=shutil.ignore_patterns("deploy"))
        (tmp_path / name / "config.json").write_text("{}")
        return tmp_path / name

    cut = run_copy("cut")
    params = cut / "policy" / "params.npz"
    params.write_bytes(params.read_bytes()[:3000])
    bad_config = run_copy("config")
    (bad_config / "config.json").write_text("{bad")
    for run, message in ((cut, r"params\.npz: unreadable"), (bad_config, r"config\.json: unreadable")):
        with pytest.raises(SystemExit) as e:
            export.main([str(run)])
        err = capsys.readouterr().err
        assert e.value.code == 2 and re.search(message, err) and err.strip().count("\n") == 0, err
        assert sorted(p.name for p in run.iterdir()) == ["config.json", "policy"]  # nothing left behind
    # a folder of the user's is not overwritten; an earlier export is replaced whole
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    with pytest.raises(export.ExportError, match="not an earlier deployment folder"):
        export.export_deployment(coarse_deploy.parent, mine, log=lambda *a: None)
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    (coarse_deploy / "params.npz").write_bytes(b"stale")
    again = export.export_deployment(coarse_deploy.parent, log=lambda *a: None)
    assert again == coarse_deploy and deploy.Controller(again, backend="numpy").num_rays == 90


def test_replay_refuses_what_it_cannot_replay(su_deploy, tmp_path):
    controller = deploy.Controller(su_deploy, backend="numpy")
    copy = tmp_path / "in.mcap"
    copy.write_bytes(SAMPLE_BAG.read_bytes())
    with pytest.raises(deploy.DeployError, match="is the input bag"):
        deploy.replay(controller, copy, copy)
    assert copy.read_bytes() == SAMPLE_BAG.read_bytes()  # the recording is untouched
    for name, data in (("magic.mcap", b"\x89MCAP0\r\n"), ("cut.mcap", SAMPLE_BAG.read_bytes()[:9])):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(deploy.DeployError, match="unreadable MCAP file"):
            deploy.replay(controller, tmp_path / name, tmp_path / "out.mcap")
    # one /odom message stamped a day late: refused at once instead of 4.3M ticks
    series = mcap_replay.read_inputs(SAMPLE_BAG, controller.num_rays, controller.num_users)
    odom = series["/odom"]
    odom.stamps = odom.stamps.copy()
    odom.stamps[-1] += 86_400 * 10**9
    with pytest.raises(deploy.DeployError, match=r"/odom jumps 8\.64e\+04 s between two messages"):
        mcap_replay.check_stamps(series, "bag")


# -- fuzzing ------------------------------------------------------------------------------


def test_the_replay_refuses_corrupt_bags_cleanly(coarse_deploy, tmp_path):
    """Random bytes, cuts, bit flips and damaged spans of the sample bag (conftest.fuzz)."""
    controller = deploy.Controller(coarse_deploy, backend="numpy")
    original = (ROOT / "assets" / "deploy_sample.mcap").read_bytes()
    path, out = tmp_path / "fuzzed.mcap", tmp_path / "out.mcap"

    def target(data):
        path.write_bytes(data)
        try:
            summary = deploy.replay(controller, path, out)
        except deploy.DeployError as e:
            assert "\n" not in str(e)
            return "refused"
        assert summary["ticks"] >= 1 and out.exists()
        return "accepted"

    counts = fuzz(target, original, seed=1, cases=16)
    assert counts["refused"] >= 4 and counts["accepted"] >= 1, counts


def test_the_deploy_loader_refuses_corrupt_folders_cleanly(coarse_deploy, tmp_path):
    files = {
        name: (coarse_deploy / name).read_bytes() for name in ("manifest.json", "params.npz", "policy.onnx")
    }
    folder = tmp_path / "fuzzed"
    shutil.copytree(coarse_deploy, folder)
    good = deploy.Controller(coarse_deploy, backend="numpy")
    x = deploy.Inputs(
        ranges=np.full(90, 2.0),
        robot_pose=np.zeros(3),
        velocity=np.zeros(3),
        users=np.array([[4.0, 0.0, 0.0, 0.0, 0.0, 0.0]]),
        goal=np.array([1.0, 0.0, 0.0]),
    )
    expected = good.tick(x).twist
    for i, (name, original) in enumerate(files.items()):

        def target(data, name=name):
            (folder / name).write_bytes(data)
            try:
                c = deploy.Controller(folder, backend="onnx")
            except deploy.DeployError as e:
                assert "\n" not in str(e)
                return "refused"
            finally:
                (folder / name).write_bytes(files[name])
            # whatever loads drives exactly as the original (hashes cover the parameters and model)
            np.testing.assert_allclose(c.tick(x).twist, expected, atol=1e-5)
            return "accepted"

        counts = fuzz(target, original, seed=10 + i)
        assert counts["refused"] >= 10, (name, counts)


def test_guide_goal_twin_matches_the_training_goal():
    from envs.goals import SWITCH, goal_from_weight
    from methd_jax.deploy import guide

    assert guide.SWITCH == SWITCH
    rng = np.random.default_rng(0)
    weights = [-1.0, -SWITCH - 1e-3, -SWITCH, 0.0, SWITCH, SWITCH + 1e-3, 1.0, *rng.uniform(-1, 1, 20)]
    for u_w in weights:
        hips = rng.uniform([-5, -5, -np.pi], [5, 5, np.pi], (2, 3))
        want = np.asarray(goal_from_weight(jnp.float32(u_w), *jnp.asarray(hips, jnp.float32)))
        got = guide.goal_from_weight(u_w, *hips)
        np.testing.assert_allclose(got, want, atol=1e-5, err_msg=str(u_w))


def test_guide_goal_refuses_what_it_cannot_use(coarse_deploy):
    from methd_jax.deploy import guide

    with pytest.raises(deploy.DeployError, match="not a GuideRL"):
        guide.GuideGoal(coarse_deploy, backend="numpy")


def test_guide_goal_differences_over_the_periods_that_passed(tmp_path):
    """As the Controller: with ``now`` the users' velocities are differenced over the whole control
    periods since the last tick (a lost tick is two), and not across a pause."""
    from envs.guide import GuideConfig, GuideEnv
    from methd_jax.deploy import guide

    env = GuideEnv(GuideConfig(motion="sample", split="all"))
    export_random_policy(tmp_path / "g", env, "guide", networks.GuideActorCritic(), seed=4)
    goal = guide.GuideGoal(export.export_deployment(tmp_path / "g", log=lambda *a: None), backend="numpy")
    assert goal.dt == pytest.approx(0.02)

    def acceleration(t, vx):  # both users face +x, so their own frame is the world's
        users = np.array([[0.0, 0.0, 0.0, vx, 0.0, 0.0], [3.0, 0.0, 0.0, vx, 0.0, 0.0]])
        return goal.observation(users, now=t)[6:12].reshape(2, 3)

    np.testing.assert_allclose(acceleration(1.0, 0.5), 0.0)  # the first tick: none
    np.testing.assert_allclose(acceleration(1.02, 0.55)[:, 0], 2.5, atol=1e-6)
    np.testing.assert_allclose(acceleration(1.06, 0.65)[:, 0], 2.5, atol=1e-6)  # a tick lost
    np.testing.assert_allclose(acceleration(1.077, 0.7)[:, 0], 2.5, atol=1e-6)  # 3 ms early
    np.testing.assert_allclose(acceleration(2.0, 1.5), 0.0)  # after a pause: none
    goal.reset()
    np.testing.assert_allclose(acceleration(2.02, 1.0), 0.0)


def test_guide_goal_feeds_a_wrist_policy_the_wrists(tmp_path):
    """A GuideRL policy trained with the wrists (``GuideConfig.wrist``): GuideGoal appends the
    users' wrist heights to eq. 4.24's inputs as the training environment does, and refuses a tick
    without them (and wrists for a policy that does not read them)."""
    from envs.guide import GuideConfig, GuideEnv
    from envs.nav import guide_observation
    from methd_jax.deploy import guide

    env = GuideEnv(GuideConfig(motion="sample", split="all", wrist=True))
    export_random_policy(tmp_path / "w", env, "guide", networks.GuideActorCritic(), seed=4)
    folder = export.export_deployment(tmp_path / "w", log=lambda *a: None)
    policy = export.load(folder)
    rng = np.random.default_rng(2)
    goal = guide.GuideGoal(folder, backend="numpy")
    assert goal.wrist
    u_w, actions = 0.0, np.zeros(2)
    for _ in range(20):
        users = np.concatenate([rng.uniform(-3, 3, (2, 3)), rng.normal(0, 0.5, (2, 3))], 1)
        acc, wrist, hips = rng.normal(0, 1, (2, 3)), rng.uniform(-0.8, -0.3, 2), rng.uniform(-3, 3, (2, 3))
        c, s = np.cos(users[:, 2:3]), np.sin(users[:, 2:3])

        def own(v, c=c, s=s):  # world (vx, vy, wz) in the user's frame
            return np.concatenate([c * v[:, :1] + s * v[:, 1:2], -s * v[:, :1] + c * v[:, 1:2], v[:, 2:]], 1)

        obs = guide_observation(own(users[:, 3:]), own(acc), jnp.float32(u_w), actions, wrist)
        act = float(np.clip(np.asarray(policy(obs)).reshape(()), -1, 1))
        u_w, actions = float(np.clip(u_w + 0.05 * act, -1, 1)), np.array([act, actions[0]])
        goal.tick(users, hips, acceleration=acc, wrist=wrist)
        assert goal.u_w == pytest.approx(u_w, abs=1e-5)
    with pytest.raises(deploy.DeployError, match="pass wrist"):
        goal.tick(users, hips, acceleration=acc)
    plain = GuideEnv(GuideConfig(motion="sample", split="all"))
    export_random_policy(tmp_path / "p", plain, "guide", networks.GuideActorCritic(), seed=4)
    folder = export.export_deployment(tmp_path / "p", log=lambda *a: None)
    with pytest.raises(deploy.DeployError, match="does not read wrist"):
        guide.GuideGoal(folder, backend="numpy").tick(users, hips, acceleration=acc, wrist=wrist)
