"""Each reward term of eqs. 4.6-4.17 against hand-computed values in constructed situations."""

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest

from envs import rewards
from envs.rewards import NAV_WEIGHTS, SU_WEIGHTS, SafetyConfig
from methd_jax import lidar
from methd_jax import robot as robot_lib
from methd_jax.floors import Floor
from methd_jax.geometry import KAIROS, ray_angles

SAFE = SafetyConfig()
ANGLES = jnp.asarray(ray_angles(), jnp.float32)
BOUNDARY, SCALE = KAIROS.ray_geometry()
HALF_L, HALF_W = 1.13 / 2, 0.91 / 2


def _terms(
    ranges,
    user_distances=(10.0,),
    d_goal=2.0,
    dyaw=0.5,
    held=0.0,
    a=(0, 0, 0),
    a1=(0, 0, 0),
    a2=(0, 0, 0),
    v=(0, 0, 0),
    q=(0, 0, 0),
    safety=SAFE,
    d_path=None,
):
    f = jnp.asarray
    return rewards.terms(
        ranges=f(ranges, jnp.float32),
        boundary=BOUNDARY,
        inflation_scale=SCALE,
        user_distances=f(user_distances),
        d_goal=f(d_goal),
        dyaw=f(dyaw),
        held=f(held),
        action=f(a, jnp.float32),
        prev_action=f(a1, jnp.float32),
        prev_prev_action=f(a2, jnp.float32),
        velocity=f(v, jnp.float32),
        acceleration=f(q, jnp.float32),
        safety=safety,
        d_path=None if d_path is None else f(d_path),
    )


OPEN = np.full(720, 30.0)  # nothing within the inflation layer


def test_robot_at_goal_and_held():
    t = _terms(OPEN, d_goal=0.005, dyaw=0.001, held=0.1)
    assert float(t["distance"]) == pytest.approx(2.995)  # 3 - d_g
    assert float(t["goal"]) == 1.0
    assert float(t["yaw"]) == pytest.approx(math.exp(-0.003) * 0.995, rel=1e-5)
    # not yet held for 0.1 s, or slightly off: no r_g
    assert float(_terms(OPEN, d_goal=0.005, dyaw=0.001, held=0.08)["goal"]) == 0.0
    assert float(_terms(OPEN, d_goal=0.02, dyaw=0.001, held=0.5)["goal"]) == 0.0
    assert float(_terms(OPEN, d_goal=0.005, dyaw=0.01, held=0.5)["goal"]) == 0.0
    total, weighted = rewards.total(t, SU_WEIGHTS)
    assert float(weighted["reward/goal"]) == 50.0 and float(weighted["reward/yaw"]) == pytest.approx(
        8 * 0.992, rel=1e-3
    )
    assert float(total) == pytest.approx(2.995 + 50 + 8 * math.exp(-0.003) * 0.995, rel=1e-5)


def test_yaw_radius_widens_r_omega():
    # the thesis's r_omega ends 1 m from the goal; with a 3 m radius it falls linearly to 0 there
    assert float(_terms(OPEN, d_goal=2.0, dyaw=0.5)["yaw"]) == 0.0
    wide = dataclasses.replace(SAFE, yaw_radius=3.0)
    assert float(_terms(OPEN, d_goal=2.0, dyaw=0.5, safety=wide)["yaw"]) == pytest.approx(
        math.exp(-1.5) / 3, rel=1e-5
    )
    assert float(_terms(OPEN, d_goal=3.5, dyaw=0.0, safety=wide)["yaw"]) == 0.0
    with pytest.raises(ValueError, match="yaw_radius"):
        rewards.SafetyConfig(yaw_radius=0.0)


def test_robot_in_the_critical_zone_loses_positive_rewards():
    t = _terms(OPEN, user_distances=(1.5, 4.0), d_goal=0.5, dyaw=0.0, held=1.0)
    assert float(t["critical_zone"]) == 1.0 and float(t["user_collision"]) == 0.0
    assert float(t["distance"]) == 0.0 and float(t["yaw"]) == 0.0 and float(t["goal"]) == 0.0
    far = _terms(OPEN, user_distances=(1.5,), d_goal=4.0)  # negative r_d is never withheld
    assert float(far["distance"]) == pytest.approx(-1.0)
    both = _terms(OPEN, user_distances=(1.2, 1.7))
    assert float(both["critical_zone"]) == 2.0 and float(both["user_collision"]) == 1.0
    _, w = rewards.total(both, SU_WEIGHTS)
    assert float(w["reward/user_collision"]) == -1000.0 and float(w["reward/critical_zone"]) == -40.0


def _wall_ranges(side: str, gap: float) -> np.ndarray:
    """True ranges with a long wall ``gap`` metres beyond the footprint's front or left side."""
    if side == "front":
        x = HALF_L + gap
        f = Floor.from_primitives(polygons=[[(x, -20), (x + 0.2, -20), (x + 0.2, 20), (x, 20)]])
    else:
        y = HALF_W + gap
        f = Floor.from_primitives(polygons=[[(-20, y), (20, y), (20, y + 0.2), (-20, y + 0.2)]])
    return np.asarray(lidar.scan(f, jnp.zeros(3)))


@pytest.mark.parametrize("side", ["front", "side"])
def test_touching_a_wall_collides_and_the_inflation_layer_counts_rays(side):
    touching = _terms(_wall_ranges(side, -0.01))  # 1 cm inside the footprint
    assert float(touching["obstacle_collision"]) == 1.0
    clear = _terms(_wall_ranges(side, 0.02))
    assert float(clear["obstacle_collision"]) == 0.0
    # with a collision margin the same 2 cm gap already counts, a 4 cm one does not
    margin = SafetyConfig(collision_margin=0.03)
    assert float(_terms(_wall_ranges(side, 0.02), safety=margin)["obstacle_collision"]) == 1.0
    assert float(_terms(_wall_ranges(side, 0.04), safety=margin)["obstacle_collision"]) == 0.0
    # p_i by hand: rays that hit the wall, with f(l) of eq. 4.13 from the same ranges
    r = _wall_ranges(side, 0.2)
    f = np.asarray(KAIROS.inflation_distance(jnp.asarray(r), ANGLES))
    expected = np.sum(np.maximum((0.5 - f) / 0.5, 0.0))
    got = float(_terms(r)["inflation"])
    assert got == pytest.approx(expected, rel=1e-5) and got > 1.0
    # straight at the wall (ray 0 for the front, ray 180 for the left side) f(l) is exactly the gap
    ray = 0 if side == "front" else 180
    assert f[ray] == pytest.approx(0.2, abs=1e-5)
    # inside the layer the state is unsafe: positive rewards are withheld
    assert float(_terms(r, d_goal=0.5, dyaw=0.0)["distance"]) == 0.0
    assert float(_terms(_wall_ranges(side, 0.8), d_goal=0.5, dyaw=0.0)["distance"]) == pytest.approx(2.5)
    assert float(_terms(_wall_ranges(side, 0.8))["inflation"]) == 0.0


def test_a_jerk_in_actions():
    a2, a1, a = np.array([0.0, 0, 0]), np.array([0.2, 0, 0]), np.array([-0.6, 0.3, 0])
    t = _terms(OPEN, a=a, a1=a1, a2=a2)
    expected = np.sum((a - a1) ** 2) + np.sum((a - 2 * a1 + a2) ** 2)  # 0.64+0.09 + 1.0+0.09
    assert float(t["action_smoothness"]) == pytest.approx(expected) == pytest.approx(1.82)
    assert float(_terms(OPEN, a=a1, a1=a1, a2=a1)["action_smoothness"]) == 0.0  # constant action


def test_velocity_and_acceleration_penalties_and_weights():
    t = _terms(OPEN, v=(1.0, -0.5, 0.2), q=(3.0, 0.0, -4.0))
    assert float(t["velocity"]) == pytest.approx(1.29) and float(t["acceleration"]) == pytest.approx(25.0)
    _, su = rewards.total(t, SU_WEIGHTS)
    _, nav = rewards.total(t, NAV_WEIGHTS)
    assert float(su["reward/velocity"]) == pytest.approx(-2.58)
    assert float(su["reward/acceleration"]) == pytest.approx(-0.0375)
    assert float(nav["reward/acceleration"]) == pytest.approx(-25 * 7.5e-6)


def test_weights_are_the_thesis_tables():
    assert SU_WEIGHTS == rewards.RewardWeights(
        1.0, 50.0, 8.0, -900.0, -1000.0, -20.0, -0.5, -0.25, -2.0, -0.0015
    )
    assert NAV_WEIGHTS.acceleration == -0.0000075 and NAV_WEIGHTS.goal == 50.0
    assert (SAFE.collision_distance, SAFE.critical_distance, SAFE.inflation_distance) == (1.37, 1.77, 0.5)


def test_the_way_round_replaces_the_straight_distance_in_r_d_only():
    straight = _terms(OPEN, d_goal=0.005, dyaw=0.001, held=0.1)
    around = _terms(OPEN, d_goal=0.005, dyaw=0.001, held=0.1, d_path=4.2)
    assert float(around["distance"]) == pytest.approx(3.0 - 4.2)  # negative: paid even while unsafe
    for name in straight:
        if name != "distance":
            assert float(around[name]) == float(straight[name]), name


@pytest.mark.parametrize(
    "v", [(2.0, 0.0, 0.0), (1.0, -1.5, 0.0), (2.0, 0.5, 2.0), (0.0, 0.0, 2.0), (3.0, 0.0, -1.0)]
)
def test_the_stopping_path_ends_where_the_base_servos_stop_it(v):
    servo = robot_lib.Robot().servo()
    path = np.asarray(rewards.stopping_path(jnp.asarray(v), SAFE.deceleration, SAFE.yaw_deceleration))
    rest = np.asarray(robot_lib.predict(servo, jnp.asarray(v), jnp.zeros((60, 3))))[-1]
    assert path.shape == (rewards.STOP_SAMPLES, 3)
    np.testing.assert_allclose(path[-1, :2], rest[:2], atol=0.05)
    assert abs(path[-1, 2] - rest[2]) < 0.03
    # monotone along the way: every sample is farther along than the one before
    travelled = np.linalg.norm(path[:, :2], axis=1)
    assert np.all(np.diff(travelled) >= -1e-6)


def test_a_base_at_rest_stops_where_it_is():
    assert np.all(np.asarray(rewards.stopping_path(jnp.zeros(3), 3.0, 6.0)) == 0.0)


def _stopping(ranges, v):
    half = jnp.asarray([HALF_L, HALF_W], jnp.float32)
    return float(rewards.stopping_overlap(jnp.asarray(ranges), jnp.asarray(v, jnp.float32), half, SAFE))


def _brute_overlap(ranges, v):
    """The same shortfall from the base's own servo model, sampled every 10 ms, in numpy."""
    servo = robot_lib.Robot().servo()
    poses = np.concatenate(
        [np.zeros((1, 3)), np.asarray(robot_lib.predict(servo, jnp.asarray(v), jnp.zeros((60, 3))))]
    )
    a = np.asarray(ANGLES, np.float64)
    ok = np.isfinite(ranges)
    pts = np.stack([ranges[ok] * np.cos(a[ok]), ranges[ok] * np.sin(a[ok])], -1)
    best = np.inf
    for x, y, th in poses:
        c, s = np.cos(th), np.sin(th)
        d = pts - (x, y)
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
        q = np.abs(local) - (HALF_L, HALF_W)
        sd = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
        best = min(best, sd.min())
    return max(SAFE.stopping_margin - best, 0.0)


def test_p_s_is_the_braking_shortfall_toward_a_wall():
    wall = _wall_ranges("front", 1.0)  # a wall 1 m ahead of the front face
    assert _stopping(wall, (0, 0, 0)) == 0.0
    assert _stopping(wall, (1.0, 0, 0)) == 0.0  # stops in 0.17 m
    assert _stopping(wall, (-3.0, 0, 0)) == 0.0  # driving away
    # needs 1.5 m: it would stop 0.5 m into the wall, whose points then lie 0.455 m inside the
    # nearest face (a side): that depth plus the 5 cm margin
    assert _stopping(wall, (3.0, 0, 0)) == pytest.approx(0.455 + 0.05, abs=0.01)
    assert _stopping(wall, (2.5, 0, 0)) == pytest.approx(2.5**2 / 6 - 1.0 + 0.05, abs=0.01)
    for v in [(3.0, 0, 0), (2.5, 1.0, 1.5), (2.0, -0.5, -2.0), (0.5, 0.0, 2.0)]:
        assert _stopping(wall, v) == pytest.approx(_brute_overlap(wall, v), abs=0.04), v
    near = _wall_ranges("side", 0.02)  # 2 cm from the left side, at rest: the margin's shortfall
    assert _stopping(near, (0, 0, 0)) == pytest.approx(0.03, abs=2e-3)
    assert _stopping(near, (0.0, 0.0, 2.0)) > _stopping(near, (0, 0, 0))  # turning swings a corner in
