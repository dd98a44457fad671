import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from methd_jax import robot
from methd_jax.robot import Robot, RobotConfig


@pytest.fixture(scope="module")
def base():
    return Robot()


_ROLLOUTS = {}
MAX_TICKS = 256


def _run(base, data, command, ticks):
    """``ticks`` control steps under a constant command: (final data, poses (T, 3), velocities (T, 3))."""
    assert ticks <= MAX_TICKS
    if id(base) not in _ROLLOUTS:  # one compiled rollout per base, of every length up to MAX_TICKS

        def rollout(data, command, ticks):
            def tick(d, t):
                d = jax.lax.cond(t < ticks, lambda: base.step(d, command), lambda: d)
                return d, (robot.pose(d), robot.velocity(d))

            return jax.lax.scan(tick, data, jnp.arange(MAX_TICKS))

        _ROLLOUTS[id(base)] = jax.jit(rollout)
    final, (poses, vels) = _ROLLOUTS[id(base)](data, jnp.asarray(command, jnp.float32), ticks)
    return final, np.asarray(poses)[:ticks], np.asarray(vels)[:ticks]


def test_model_matches_the_spec(base):
    assert base.mj_model.body_mass[1] == pytest.approx(130.0)
    assert base.substeps * base.mj_model.opt.timestep == pytest.approx(0.02)


def test_step_response_reaches_95_percent_in_half_a_second_without_overshoot(base):
    _, _, v = _run(base, base.init(jnp.zeros(3)), [1.0, 0.0, 0.0], 50)  # 1 s at 50 Hz
    vx = v[:, 0]
    t95 = 0.02 * (1 + np.argmax(vx >= 0.95))
    assert vx.max() >= 0.95 and t95 <= 0.5
    assert vx.max() <= 1.10
    assert vx[0] > 0 and vx[0] < 0.2  # finite acceleration: no teleporting to the target


def test_commands_beyond_the_limits_saturate(base):
    _, _, v = _run(base, base.init(jnp.zeros(3)), [10.0, 0.0, 0.0], 150)
    assert v[-1, 0] == pytest.approx(3.0, rel=0.01)
    _, _, v = _run(base, base.init(jnp.zeros(3)), [5.0, 5.0, 0.0], 150)
    assert np.linalg.norm(v[-1, :2]) == pytest.approx(3.0, rel=0.01)
    assert v[-1, 0] == pytest.approx(v[-1, 1], rel=1e-3)  # direction kept
    _, _, v = _run(base, base.init(jnp.zeros(3)), [0.0, 0.0, -9.0], 150)
    assert v[-1, 2] == pytest.approx(-2.0, rel=0.01)
    np.testing.assert_allclose(base.saturate(jnp.array([0.3, -0.2, 0.1])), [0.3, -0.2, 0.1], rtol=1e-6)


def test_non_finite_command_stops_the_base(base):
    moving, _, v = _run(base, base.init(jnp.zeros(3)), [1.0, 0.0, 0.0], 50)
    assert v[-1, 0] > 0.9
    _, _, v = _run(base, moving, [float("nan"), 0.0, 0.0], 50)
    assert np.all(np.abs(v[-1]) < 1e-3)


def test_robot_frame_command_after_a_quarter_turn(base):
    # Turn on the spot until the base faces +y, then drive "forward" and "left".
    _, poses, _ = _run(base, base.init(jnp.zeros(3)), [0.0, 0.0, 0.5], 250)  # 5 s: 2.4 rad
    first = int(np.argmax(poses[:, 2] >= math.pi / 2 - 0.05))
    assert first > 0
    turned, _, _ = _run(base, base.init(jnp.zeros(3)), [0.0, 0.0, 0.5], first + 1)
    data, poses, _ = _run(base, turned, [0.0, 0.0, 0.0], 30)  # settle
    assert abs(poses[-1, 2] - math.pi / 2) < 0.1
    start = poses[-1, :2]
    _, fwd, _ = _run(base, data, [1.0, 0.0, 0.0], 50)
    moved = fwd[-1, :2] - start
    assert moved[1] > 0.6 and abs(moved[0]) < 0.05 * moved[1]  # forward is world +y
    _, left, _ = _run(base, data, [0.0, 1.0, 0.0], 50)
    moved = left[-1, :2] - start
    assert moved[0] < -0.6 and abs(moved[1]) < 0.05 * abs(moved[0])  # left is world -x


def test_holonomic_velocity_is_kept_in_the_robot_frame_while_turning(base):
    _, poses, v = _run(base, base.init(jnp.zeros(3)), [1.0, 0.0, 1.0], 100)
    assert v[-1, 0] == pytest.approx(1.0, abs=0.05) and abs(v[-1, 1]) < 0.1
    assert v[-1, 2] == pytest.approx(1.0, abs=0.05)
    # the path curves: after ~1.7 rad of turning the base is no longer on the x axis
    assert poses[-1, 1] > 0.5


def test_thousands_of_robots_step_in_one_jitted_call(base):
    n = 4096
    poses = jax.random.uniform(jax.random.key(0), (n, 3), minval=-3, maxval=3)
    cmds = jax.random.uniform(jax.random.key(1), (n, 3), minval=-2, maxval=2)
    data = jax.vmap(base.init)(poses)
    step = jax.jit(jax.vmap(base.step))
    for _ in range(3):
        data = step(data, cmds)
    p = np.asarray(jax.vmap(robot.pose)(data))
    assert p.shape == (n, 3) and np.isfinite(p).all()
    assert np.all(np.linalg.norm(p[:, :2] - np.asarray(poses[:, :2]), axis=1) > 0)
    a = np.asarray(jax.vmap(robot.acceleration)(data))
    # force limit / mass, per robot axis, at any heading; qacc is rotated by the yaw at the end of the
    # last 10 ms substep while the force acted at its start (up to 0.02 rad apart): 3% slack
    assert np.abs(a[:, :2]).max() <= 3.0 * 1.03
    assert np.abs(a[:, :2]).max() >= 2.9  # and the limit is reached by these big commands


def test_predict_follows_the_mjx_base(base):
    # the servo model outside MJX against MJX itself: a base already moving and turning, driven by
    # sustained commands and then braking, in the frame it started from
    step = jax.jit(base.step)
    data = base.init(jnp.array([1.0, -2.0, 0.7]))
    for _ in range(40):
        data = step(data, jnp.array([1.6, -0.8, 1.2]))
    start, velocity = np.asarray(robot.pose(data)), robot.velocity(data)
    commands = np.zeros((100, 3), np.float32)
    commands[:50] = [-0.5, 2.0, -1.5]
    commands[50:65] = [2.5, 0.0, 0.0]
    poses = []
    for c in commands:
        data = step(data, jnp.asarray(c))
        poses.append(np.asarray(robot.pose(data)))
    poses = np.array(poses)
    from methd_jax.geometry import to_local, wrap_angle

    want = np.concatenate(
        [
            np.asarray(to_local(jnp.asarray(start), jnp.asarray(poses[:, :2]))),
            np.asarray(wrap_angle(poses[:, 2:] - start[2])),
        ],
        1,
    )
    got = np.asarray(jax.jit(robot.predict, static_argnums=0)(base.servo(), velocity, jnp.asarray(commands)))
    assert np.abs(want[:, :2]).max() > 0.5 and np.abs(want[:, 2]).max() > 1.0  # it went somewhere
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert base.servo().limit[:2] == pytest.approx((3.0, 3.0))  # 390 N on 130 kg, as the MJCF says


def test_bad_config_is_rejected(tmp_path):
    coarse = tmp_path / "coarse.xml"  # 0.02 s is not a whole number of 0.003 s timesteps
    coarse.write_text(Path(RobotConfig().mjcf).read_text().replace('timestep="0.01"', 'timestep="0.003"'))
    with pytest.raises(ValueError, match="not a whole number of its timesteps"):
        Robot(RobotConfig(mjcf=str(coarse)))
    with pytest.raises(ValueError, match="max_speed"):
        RobotConfig(max_speed=0)
    with pytest.raises(FileNotFoundError, match="robot MJCF not found"):
        Robot(RobotConfig(mjcf=str(tmp_path / "none.xml")))
