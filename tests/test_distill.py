"""The safety layer's labels and the DAgger distillation of :mod:`train.distill`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from methd_jax import motion
from methd_jax import robot as robot_lib
from methd_jax.deploy.safety import SafetyConfig
from methd_jax.evaluation import safety_layer
from methd_jax.geometry import KAIROS, ray_directions, rotate, to_local
from train import distill, export

RAYS = 720


def _wall_scan(distance: float) -> jnp.ndarray:
    """Ranges from the base's centre to the line x = distance (a wall ahead); nothing behind."""
    d = ray_directions(RAYS)
    with np.errstate(divide="ignore"):
        r = np.where(d[:, 0] > 1e-6, distance / np.maximum(d[:, 0], 1e-6), np.inf)
    return jnp.asarray(r, jnp.float32)


@pytest.fixture(scope="module")
def env_and_world():
    env = envs.make("su", bank=motion.MotionBank.from_trajectories(motion.sample()), num_rays=90)
    world = env.reset(jax.random.key(0)).pipeline_state
    users = jax.vmap(env.bank.at, (0, None))(world.users, world.t)
    # the base 8 m from its user, so that only the scan can make the layer act
    far = users["pose"][0, :2] + jnp.array([8.0, 0.0])
    world = world.replace(
        robot=env.robot.init(jnp.array([far[0], far[1], 0.3])),
        actions=jnp.array([[0.4, 0.1, 0.0], [0.3, 0.0, 0.2]]),
    )
    return env, world


def test_the_label_is_the_layers_command_before_a_wall(env_and_world):
    env, world = env_and_world
    scan = _wall_scan(KAIROS.half_extents[0] + 0.25)
    action = jnp.array([0.9, -0.2, 0.5])
    target, changed = env.safety_target(world, action, scan, SafetyConfig())
    assert bool(changed)
    command = env.command(action, world.actions)
    pose = robot_lib.pose(world.robot)
    users = jax.vmap(env.bank.at, (0, None))(world.users, world.t)
    want = safety_layer.filter_command(
        command,
        scan,
        to_local(pose, users["pose"][:, :2]),
        rotate(-pose[2], users["vel_world"][:, :2]),
        jnp.ones(1, bool),
        env.config.safety.collision_distance,
        SafetyConfig(),
        robot_lib.velocity(world.robot),
    )
    assert float(want[0]) < float(command[0])  # the layer slows the drive at the wall
    reachable = np.abs(np.asarray(target)) < 1.0  # a clipped label cannot reach it in one step
    assert reachable.any()
    np.testing.assert_allclose(
        np.asarray(env.command(target, world.actions))[reachable], np.asarray(want)[reachable], atol=1e-5
    )
    assert np.all(np.abs(np.asarray(target)) <= 1.0)


def test_the_label_is_the_action_where_the_layer_does_not_act(env_and_world):
    env, world = env_and_world
    action = jnp.array([0.9, -0.2, 0.5])
    open_floor = jnp.full(RAYS, jnp.inf)
    target, changed = env.safety_target(world, action, open_floor, SafetyConfig())
    assert not bool(changed)
    np.testing.assert_array_equal(target, action)
    backing = jnp.array([-0.8, 0.0, 0.0])  # away from the wall: left as it is
    target, changed = env.safety_target(
        world, backing, _wall_scan(KAIROS.half_extents[0] + 0.25), SafetyConfig()
    )
    assert not bool(changed)
    np.testing.assert_array_equal(target, backing)


def test_the_loss_is_one_sided_at_the_bounds():
    d = distill.Distiller.__new__(distill.Distiller)
    d.mean = lambda params, obs: params * obs  # a stand-in student
    obs = jnp.ones((4, 3))
    target = jnp.array([[1.0, -1.0, 0.5], [1.0, -1.0, 0.5], [0.0, 0.0, 0.0], [0.2, 0.2, 0.2]])
    weight = jnp.array([1.0, 1.0, 1.0, 4.0])
    params = jnp.array([1.5, -1.5, 0.5])  # past both bounds, at the free label
    row = lambda m, t: 0.5 * np.sum(np.where((t >= 1) & (m > 1) | (t <= -1) & (m < -1), 0.0, m - t) ** 2)  # noqa: E731
    m = np.asarray(params)
    w, t = np.asarray(weight), np.asarray(target)
    want = sum(float(w[i]) * row(m, t[i]) for i in range(4)) / float(w.sum())
    assert float(d.loss(params, obs, target, weight)) == pytest.approx(want, rel=1e-6)
    assert row(m, np.asarray(target[0])) == 0.0  # past a bound is as good as at it


def test_bad_options_and_sources_are_one_line_errors(tmp_path, capsys):
    (tmp_path / "file").write_text("kept")
    for argv, message in [
        (
            ["assets/pretrained/su", "--out", str(tmp_path / "o"), "--rounds", "0"],
            "rounds must be an integer >= 1",
        ),
        (["assets/pretrained/su", "--out", str(tmp_path / "o"), "--learning-rate", "-1"], "learning_rate"),
        (
            ["assets/pretrained/su", "--out", str(tmp_path / "o"), "--engine-steps", "-5"],
            "engine_steps must be",
        ),
        ([str(tmp_path / "none"), "--out", str(tmp_path / "o")], "holds no exported policy"),
        (["assets/pretrained/guide", "--out", str(tmp_path / "o")], "distillation takes su"),
        (["assets/pretrained/su", "--out", str(tmp_path / "file")], "is not an empty or earlier deployment"),
        (
            ["assets/pretrained/su", "--init", "assets/pretrained/nav", "--out", str(tmp_path / "o")],
            "takes su",
        ),
    ]:
        with pytest.raises(SystemExit) as exit_:
            distill.main(argv)
        assert exit_.value.code == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and message in err, err
    assert not (tmp_path / "o").exists() and (tmp_path / "file").read_text() == "kept"


@pytest.mark.slow
def test_a_small_distillation_exports_a_policy_that_loads(tmp_path):
    config = distill.DistillConfig(
        rounds=2, steps_per_round=64, num_envs=4, chunk=16, epochs=2, batch_size=32, engine_steps=300
    )
    lines = []
    out = distill.distill("assets/pretrained/su", tmp_path / "d", config, log=lines.append)
    assert len(lines) == 2 and lines[0].startswith("round 1/2")
    policy = export.load(out)
    source = export.load("assets/pretrained/su")
    rounds = policy.manifest["trained"]["distilled"]["rounds"]
    # each round adds its 64 environment steps and the engine's Chase steps
    chase = [r["engine_chase_steps"] for r in rounds]
    assert all(0 < c <= 300 for c in chase) and all(r["engine_contacts"] >= 0 for r in rounds)
    assert [r["steps"] for r in rounds] == [64 + chase[0], 128 + chase[0] + chase[1]]
    assert all(0.0 <= r["changed_share"] <= 1.0 and np.isfinite(r["own_error"]) for r in rounds)
    moved = jax.tree.map(lambda a, b: float(jnp.max(jnp.abs(a - b))), policy.params, source.params)
    assert max(jax.tree.leaves(moved)) > 0.0  # it was fitted
    obs = jnp.zeros(source.manifest["observation_size"])
    assert policy(obs).shape == (3,) and (out / "policy.onnx").is_file()
    assert policy.manifest["params_sha256"] != source.manifest["params_sha256"]
