"""The shield's stopping rule against brute force, and its pull in PPO's loss."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs.shield import ShieldConfig, free_distance, safe_command, stopping_speed, sweep_scale
from methd_jax import motion
from methd_jax.geometry import KAIROS, ray_directions
from train import ppo

BODY = np.asarray(KAIROS.half_extents)


def _marched(points, direction, body, step=5e-4, far=8.0):
    """free_distance by moving the box in small steps (numpy)."""
    inside = np.all(np.abs(points) < body, -1)
    if np.any(inside & (points @ direction > 0)):
        return 0.0
    t = np.arange(0.0, far, step)
    moved = points[None] - t[:, None, None] * direction
    met = np.all(np.abs(moved) <= body, -1) & ~inside
    hit = np.any(met, 1)
    return float(t[np.argmax(hit)]) if hit.any() else np.inf


def test_free_distance_matches_marching_the_footprint():
    rng = np.random.default_rng(0)
    for trial in range(60):
        points = rng.uniform(-3.0, 3.0, (24, 2)).astype(np.float32)
        angle = rng.uniform(-np.pi, np.pi) if trial % 6 else np.pi / 2 * (trial // 6 % 4)
        u = np.array([np.cos(angle), np.sin(angle)], np.float32)
        got = float(free_distance(jnp.asarray(points), jnp.asarray(u), jnp.asarray(BODY)))
        want = _marched(points, u, BODY)
        if np.isinf(want):
            assert got > 8.0 - 1e-3, trial  # nothing within the marched 8 m
        else:
            assert got == pytest.approx(want, abs=1e-3), trial


def test_free_distance_lets_the_base_slide_along_and_back_off_a_wall():
    wall = jnp.asarray([[x, BODY[1] + 0.02] for x in np.linspace(-3, 3, 61)], jnp.float32)
    assert np.isinf(free_distance(wall, jnp.array([1.0, 0.0]), jnp.asarray(BODY)))
    into = float(free_distance(wall, jnp.array([0.0, 1.0]), jnp.asarray(BODY)))
    assert into == pytest.approx(0.02, abs=1e-5)
    touching = jnp.asarray([[0.0, BODY[1] - 0.01]], jnp.float32)  # already inside the footprint
    assert float(free_distance(touching, jnp.array([0.0, 1.0]), jnp.asarray(BODY))) == 0.0
    assert np.isinf(free_distance(touching, jnp.array([0.0, -1.0]), jnp.asarray(BODY)))


def test_stopping_speed_stops_within_the_distance():
    for d in (0.0, 0.05, 0.3, 2.0):
        v = float(stopping_speed(jnp.float32(d), 2.0, 0.12))
        assert v * 0.12 + v * v / 4.0 == pytest.approx(d, abs=1e-5)
    assert float(stopping_speed(jnp.float32(-1.0), 2.0, 0.12)) == 0.0


def _wall_scan(distance: float, num_rays: int = 90) -> jnp.ndarray:
    """Ranges from the base's centre to the line x = distance (a wall ahead); inf behind."""
    d = ray_directions(num_rays)
    with np.errstate(divide="ignore"):
        r = np.where(d[:, 0] > 1e-6, distance / np.maximum(d[:, 0], 1e-6), np.inf)
    return jnp.asarray(np.minimum(r, 3.0), jnp.float32)


def test_safe_command_slows_only_what_drives_at_an_obstacle():
    cfg = ShieldConfig(horizon=0.0)  # the stopping rule alone
    scan = _wall_scan(BODY[0] + 0.5)  # the front face 0.5 m from the wall
    ahead = jnp.array([1.2, 0.0, 0.7])
    safe, scale = safe_command(ahead, scan, cfg)
    v = float(stopping_speed(jnp.float32(0.5 - cfg.margin), cfg.deceleration, cfg.reaction))
    assert float(safe[0]) == pytest.approx(v, rel=1e-4) and float(scale) < 1.0
    assert safe[2] == ahead[2]  # the stopping rule leaves the turn rate alone
    for clear in (jnp.array([-1.2, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]), jnp.array([0.3, 0.0, 0.0])):
        for c in (cfg, ShieldConfig()):
            safe, scale = safe_command(clear, scan, c)  # away, along, or slow enough already
            np.testing.assert_array_equal(safe, clear)
            assert float(scale) == 1.0
    with pytest.raises(ValueError, match="margin"):
        ShieldConfig(margin=-0.1)
    with pytest.raises(ValueError, match="samples"):
        ShieldConfig(samples=0)


def _swept(command, points, body, margin, horizon, samples):
    """sweep_scale in numpy: the footprint at each pose of the arc, point by point."""
    vx, vy, w = command
    inside = np.all(np.abs(points) <= body, -1)
    ring = np.all(np.abs(points) <= body + margin, -1) & ~inside
    for k in range(1, samples + 1):
        t = horizon * k / samples
        th = w * t
        if abs(w) > 1e-6:
            x = (vx * np.sin(th) + vy * (np.cos(th) - 1)) / w
            y = (vx * (1 - np.cos(th)) + vy * np.sin(th)) / w
        else:
            x, y = vx * t, vy * t
        c, s = np.cos(th), np.sin(th)
        d = points - [x, y]
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
        size = np.where(ring[:, None], body, body + margin)
        if np.any(np.all(np.abs(local) <= size, -1) & ~inside):
            return (k - 1) / samples
    return 1.0


def test_the_sweep_sees_a_corner_turning_into_a_wall():
    cfg = ShieldConfig()
    body = jnp.asarray(BODY)

    def wall(off):  # a wall along the base's left side, ``off`` metres from it
        return jnp.asarray([[x, BODY[1] + off] for x in np.linspace(-3, 3, 121)], jnp.float32)

    turn, along = jnp.array([0.0, 0.0, 1.5]), jnp.array([0.8, 0.0, 0.0])
    assert float(sweep_scale(turn, wall(0.1), body, cfg)) < 0.5  # a corner swings into it
    assert float(sweep_scale(along, wall(0.1), body, cfg)) == 1.0
    assert np.isinf(free_distance(wall(0.1), jnp.array([1.0, 0.0]), body))  # the stopping rule sees none
    # within the margin, as the safety layer: the wall ahead of the front corner counts
    assert float(sweep_scale(along, wall(0.045), body, cfg)) == 0.0
    rng = np.random.default_rng(5)
    for trial in range(40):
        points = rng.uniform(-2.0, 2.0, (30, 2)).astype(np.float32)
        command = rng.uniform([-1.2, -1.2, -2.0], [1.2, 1.2, 2.0]).astype(np.float32)
        got = float(sweep_scale(jnp.asarray(command), jnp.asarray(points), jnp.asarray(BODY), cfg))
        want = _swept(command, points, BODY, cfg.sweep_margin, cfg.horizon, cfg.samples)
        assert got == pytest.approx(want, abs=1e-6), trial


def test_shield_target_gives_the_slowed_command():
    env = envs.make("su", bank=motion.MotionBank.from_trajectories(motion.sample()), num_rays=90)
    lay = env.observation_layout
    obs = jnp.zeros(env.observation_size)
    obs = obs.at[lay["lidar"]].set(_wall_scan(BODY[0] + 0.6))
    previous = jnp.array([[0.4, 0.1, 0.0], [0.3, 0.0, 0.2]])
    obs = obs.at[lay["previous_action"]].set(previous[0]).at[lay["previous_action_2"]].set(previous[1])
    action = jnp.array([0.9, -0.2, 0.5])
    target, slowed = env.shield_target(obs, action)
    assert bool(slowed)
    want, _ = safe_command(env.command(action, previous), obs[lay["lidar"]], env.config.shield)
    np.testing.assert_allclose(env.command(target, previous), want, atol=1e-5)
    calm = jnp.array([-0.5, 0.0, 0.1])  # backing away: left as it is
    target, slowed = env.shield_target(obs, calm)
    assert not bool(slowed)
    np.testing.assert_array_equal(target, calm)


def test_shield_penalty_pulls_only_slowed_actions_toward_their_targets():
    B, A = 6, 3
    rng = np.random.default_rng(4)
    mean = jnp.asarray(rng.uniform(-1, 1, (B, A)), jnp.float32)
    raw = jnp.asarray(rng.normal(size=(B, 5)), jnp.float32)
    slowed = jnp.arange(B) % 2 == 0

    def shield(obs, action):  # a stand-in rule: halve the action where obs[0] says so
        i = jnp.argmin(jnp.abs(raw[:, 0] - obs[0]))
        return jnp.where(slowed[i], 0.5 * action, action), slowed[i]

    loss, share = ppo.shield_penalty(mean, raw, shield)
    want = np.mean(np.where(slowed, 0.5 * np.sum((0.5 * np.asarray(mean)) ** 2, -1), 0.0))
    assert float(loss) == pytest.approx(want, rel=1e-5) and float(share) == pytest.approx(0.5)
    grad = jax.grad(lambda m: ppo.shield_penalty(m, raw, shield)[0])(mean)
    np.testing.assert_allclose(grad[~np.asarray(slowed)], 0.0)
    # the target is held fixed: the gradient is (mean - target) / B, not through the target
    np.testing.assert_allclose(grad[np.asarray(slowed)], 0.5 * mean[np.asarray(slowed)] / B, rtol=1e-5)
    with pytest.raises(ValueError, match="shield_scale must be >= 0"):
        ppo.PPOConfig(shield_scale=-1.0)


def test_a_shield_needs_an_environment_that_has_one():
    from networks.actor_critic import GuideActorCritic

    env = envs.make("guide")
    with pytest.raises(ValueError, match="shield_target"):
        ppo.Trainer(env, GuideActorCritic(hidden=(8,)), ppo.PPOConfig(shield_scale=1.0), 8)


@pytest.mark.slow
def test_a_run_with_the_shield_reports_its_share_and_loss():
    from conftest import TINY_RUN

    from train.presets import apply_overrides, preset
    from train.run import build

    config = apply_overrides(preset("quick"), [*TINY_RUN, "ppo.shield_scale=5", "env.floor.num_circles=6,8"])
    trainer = build(config).trainer
    state = jax.jit(trainer.init)(jax.random.key(0))
    state, metrics = jax.jit(trainer.update)(state)
    assert 0.0 <= float(metrics["policy/shielded"]) <= 1.0 and float(metrics["loss/shield"]) >= 0.0
    plain = build(apply_overrides(preset("quick"), list(TINY_RUN))).trainer
    _, without = jax.jit(plain.update)(jax.jit(plain.init)(jax.random.key(0)))
    assert "loss/shield" not in without
