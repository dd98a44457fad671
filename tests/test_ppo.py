"""PPO's pieces against plain loops, and the trainer's guarantees (purity, resume, devices, NaN)."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TINY_RUN

from train import ppo
from train.presets import ConfigError, apply_overrides, preset
from train.run import NonFiniteError, build, train

TINY = (*TINY_RUN, "checkpoint_every=2")


# The trainer's guarantees do not depend on the environment: the default suite checks them on
# GuideRL (kinematic, compiles in a third of the time), the slow set on SU's MJX and LiDAR as well.
TINY_GUIDE = tuple(o for o in TINY_RUN if not o.startswith("env.num_rays"))  # GuideRL has no LiDAR
ENVS = [
    pytest.param("guide", TINY_GUIDE, ("actor", "hidden0"), id="guide"),
    pytest.param("quick", TINY, ("body0",), id="su", marks=pytest.mark.slow),
]


def _kernel(state, layer):
    p = state.params["params"]
    for name in layer:
        p = p[name]
    return p["kernel"]


def test_gae_matches_a_python_loop():
    rng = np.random.default_rng(0)
    T, N, gamma, lam = 9, 4, 0.97, 0.9
    rewards, values = rng.normal(size=(T, N)), rng.normal(size=(T, N))
    dones = (rng.random((T, N)) < 0.25).astype(float)
    last = rng.normal(size=N)
    want_adv = np.zeros((T, N))
    for n in range(N):
        running = 0.0
        for t in reversed(range(T)):
            next_value = last[n] if t == T - 1 else values[t + 1, n]
            live = 1.0 - dones[t, n]
            delta = rewards[t, n] + gamma * next_value * live - values[t, n]
            running = delta + gamma * lam * live * running
            want_adv[t, n] = running
    adv, ret = ppo.gae(*(jnp.asarray(x) for x in (rewards, values, dones, last)), gamma, lam)
    np.testing.assert_allclose(adv, want_adv, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(ret, want_adv + values, rtol=1e-5, atol=1e-5)


def test_ppo_loss_matches_a_python_loop():
    rng = np.random.default_rng(1)
    B, A, D = 12, 2, 3
    W = rng.normal(size=(D, A)) * 0.5
    v = rng.normal(size=D)
    log_std = np.array([-0.3, 0.2])
    params = {"W": jnp.asarray(W), "v": jnp.asarray(v), "log_std": jnp.asarray(log_std)}

    def apply_fn(p, obs):
        return obs @ p["W"], jnp.broadcast_to(p["log_std"], (obs.shape[0], A)), obs @ p["v"]

    batch = {k: rng.normal(size=s) for k, s in [("obs", (B, D)), ("action", (B, A))]}
    batch.update({k: rng.normal(size=B) for k in ("log_prob", "value", "returns", "advantage")})
    batch["log_prob"] = batch["log_prob"] - 2.0
    cfg = ppo.PPOConfig(ratio_clip=0.2, value_clip=0.3, entropy_scale=0.01, value_loss_scale=2.0)
    loss, parts = ppo.ppo_loss(params, apply_fn, {k: jnp.asarray(x) for k, x in batch.items()}, cfg)

    pol, val, ent, kl = [], [], [], []
    for i in range(B):
        mean = batch["obs"][i] @ W
        logp = sum(
            -0.5 * ((batch["action"][i, j] - mean[j]) / np.exp(log_std[j])) ** 2
            - log_std[j]
            - 0.5 * np.log(2 * np.pi)
            for j in range(A)
        )
        r = np.exp(logp - batch["log_prob"][i])
        a = batch["advantage"][i]
        pol.append(-min(r * a, np.clip(r, 0.8, 1.2) * a))
        pred = batch["obs"][i] @ v
        pred = batch["value"][i] + np.clip(pred - batch["value"][i], -0.3, 0.3)
        val.append((batch["returns"][i] - pred) ** 2)
        ent.append(sum(log_std[j] + 0.5 + 0.5 * np.log(2 * np.pi) for j in range(A)))
        kl.append((r - 1) - np.log(r))
    want = np.mean(pol) + 2.0 * np.mean(val) - 0.01 * np.mean(ent)
    np.testing.assert_allclose(loss, want, rtol=1e-5)
    np.testing.assert_allclose(parts["loss/policy"], np.mean(pol), rtol=1e-5)
    np.testing.assert_allclose(parts["policy/kl"], np.mean(kl), rtol=1e-4)


def test_the_anchor_penalty_is_the_kl_from_the_start_policy():
    rng = np.random.default_rng(4)
    B, A = 9, 2
    mean, anchor = rng.normal(size=(B, A)), rng.normal(size=(B, A))
    log_std = rng.normal(size=(B, A)) * 0.3
    s = np.exp(log_std)
    # KL(N(m1, s1) || N(m2, s2)) per dimension, the general formula at s1 = s2
    kl = np.log(s / s) + (s**2 + (anchor - mean) ** 2) / (2 * s**2) - 0.5
    np.testing.assert_allclose(ppo.anchor_penalty(mean, log_std, anchor), kl.sum(-1).mean(), rtol=1e-5)
    # it pulls the mean back (the gradient of the KL at s1 = s2) and leaves the std alone: through
    # the std, widening the policy would shrink the penalty
    d_mean, d_log_std = jax.grad(ppo.anchor_penalty, argnums=(0, 1))(
        jnp.asarray(mean), jnp.asarray(log_std), jnp.asarray(anchor)
    )
    np.testing.assert_allclose(d_mean, (mean - anchor) / s**2 / B, rtol=1e-4, atol=1e-7)
    np.testing.assert_array_equal(d_log_std, 0.0)

    params = {"W": jnp.asarray(rng.normal(size=(3, A)))}

    def apply_fn(p, obs):
        return obs @ p["W"], jnp.zeros((obs.shape[0], A)), obs[:, 0]

    batch = {"obs": rng.normal(size=(B, 3)), "action": rng.normal(size=(B, A))}
    batch.update({k: rng.normal(size=B) for k in ("log_prob", "value", "returns", "advantage")})
    batch = {k: jnp.asarray(v) for k, v in batch.items()}
    cfg = ppo.PPOConfig(anchor_scale=3.0)
    plain, parts = ppo.ppo_loss(params, apply_fn, batch, cfg)
    assert "loss/anchor" not in parts  # no anchor in the batch: PPO's loss alone
    at = {**batch, "anchor_mean": jnp.asarray(anchor)}
    loss, parts = ppo.ppo_loss(params, apply_fn, at, cfg)
    want = 3.0 * 0.5 * np.mean(np.sum((np.asarray(batch["obs"] @ params["W"]) - anchor) ** 2, -1))
    np.testing.assert_allclose(parts["loss/anchor"], want, rtol=1e-5)
    np.testing.assert_allclose(loss - plain, want, rtol=1e-5)
    with pytest.raises(ValueError, match="anchor_scale must be >= 0"):
        ppo.PPOConfig(anchor_scale=-1.0)


def test_running_stats_equal_the_statistics_of_everything_seen():
    rng = np.random.default_rng(2)
    batches = [rng.normal(3.0, 2.0, size=(n, 4, 5)) for n in (7, 1, 30)]
    stats = ppo.RunningStats.zeros((5,))
    for b in batches:
        stats = stats.update(jnp.asarray(b))
    everything = np.concatenate([b.reshape(-1, 5) for b in batches])
    np.testing.assert_allclose(stats.mean, everything.mean(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(stats.var, everything.var(0), rtol=1e-3)
    np.testing.assert_allclose(stats.denormalize(stats.normalize(everything[:3])), everything[:3], rtol=1e-4)


def test_fit_critic_moves_only_the_critic_and_lowers_its_error():
    trainer = build(apply_overrides(preset("guide"), list(TINY_GUIDE))).trainer
    start = jax.jit(trainer.init)(jax.random.key(1))
    fitted, losses = jax.jit(trainer.fit_critic, static_argnums=1)(start, 12)
    losses = np.asarray(losses)
    assert losses.shape == (12,) and losses[-3:].mean() < 0.5 * losses[0]
    mask = ppo.critic_mask(start.params)
    moved = jax.tree.map(lambda a, b: not np.array_equal(a, b), start.params, fitted.params)
    assert jax.tree.leaves(moved) == jax.tree.leaves(mask)  # the critic's layers and only they
    assert mask["params"]["value"]["kernel"] and not mask["params"]["actor"]["policy"]["kernel"]
    for a, b in zip(jax.tree.leaves(start.opt_state), jax.tree.leaves(fitted.opt_state), strict=True):
        np.testing.assert_array_equal(a, b)  # PPO's optimiser, rate and count untouched
    assert float(fitted.learning_rate) == float(start.learning_rate) and int(fitted.iteration) == 0
    assert float(fitted.obs_stats.count) > float(start.obs_stats.count)  # the statistics move on
    with pytest.raises(ValueError, match="no critic layer"):
        ppo.critic_mask({"params": {"actor": {}}})


def test_kl_adaptive_learning_rate_follows_skrl():
    cfg = ppo.PPOConfig(kl_threshold=0.01, kl_factor=2.0, lr_factor=1.5, lr_range=(1e-4, 1e-3))
    assert float(ppo.adapt_learning_rate(6e-4, 0.03, cfg)) == pytest.approx(4e-4)  # KL > 0.02: slower
    assert float(ppo.adapt_learning_rate(6e-4, 0.001, cfg)) == pytest.approx(9e-4)  # KL < 0.005: faster
    assert float(ppo.adapt_learning_rate(6e-4, 0.01, cfg)) == pytest.approx(6e-4)
    assert float(ppo.adapt_learning_rate(9e-4, 0.0, cfg)) == pytest.approx(1e-3)  # capped
    assert float(ppo.adapt_learning_rate(1.2e-4, 1.0, cfg)) == pytest.approx(1e-4)  # floored


@pytest.mark.parametrize("name, overrides, layer", ENVS)
def test_train_is_pure_and_vmaps_over_seeds(name, overrides, layer):
    trainer = build(apply_overrides(preset(name), list(overrides))).trainer
    keys = jax.random.split(jax.random.key(3), 2)
    batched, metrics = jax.jit(jax.vmap(lambda k: trainer.train(k, 2)))(keys)
    single = jax.jit(lambda k: trainer.train(k, 2))
    one, _ = single(keys[1])
    again, _ = single(keys[1])
    leaf = lambda s: _kernel(s, layer)  # noqa: E731
    np.testing.assert_array_equal(leaf(one), leaf(again))
    np.testing.assert_allclose(leaf(batched)[1], leaf(one), rtol=1e-4, atol=1e-5)
    assert not np.allclose(leaf(batched)[0], leaf(batched)[1])
    assert metrics["loss/value"].shape == (2, 2)


@pytest.mark.parametrize("name, overrides, layer", ENVS)
def test_resume_after_a_kill_is_bit_identical(tmp_path, name, overrides, layer):
    config = apply_overrides(preset(name), [*overrides, "checkpoint_every=2", "timesteps=24"])  # 6 iterations
    whole = train(config, tmp_path / "whole", preset_name=name, progress=False)
    # the process ends after iteration 3: the newest checkpoint is the one at 2
    train(config, tmp_path / "cut", preset_name=name, progress=False, stop_after=3)
    resumed = train(config, tmp_path / "cut", preset_name=name, progress=False, resume=True)
    assert int(resumed["state"].iteration) == 6
    for a, b in zip(
        jax.tree.leaves(whole["state"].params), jax.tree.leaves(resumed["state"].params), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    rows = [json.loads(line) for line in (tmp_path / "cut" / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3, 4, 5, 6]
    np.testing.assert_array_equal([r["loss/value"] for r in rows], [r["loss/value"] for r in whole["rows"]])


@pytest.mark.parametrize("name, overrides, layer", ENVS)
def test_a_diverging_update_stops_the_run(tmp_path, name, overrides, layer):
    bad = apply_overrides(preset(name), [*overrides, "timesteps=8", "ppo.learning_rate=1e30"])  # NaN at once
    with pytest.raises(NonFiniteError, match=r"at iteration 1; stopped. Last good checkpoint: none"):
        train(bad, tmp_path, preset_name=name, progress=False)


@pytest.mark.parametrize("name, overrides, layer", ENVS)
def test_a_non_finite_update_keeps_the_last_good_checkpoint(tmp_path, monkeypatch, name, overrides, layer):
    real_update = ppo.Trainer.update

    def poisoned(self, state):  # parameters turn to NaN in the third iteration
        new, metrics = real_update(self, state)
        scale = jnp.where(state.iteration >= 2, jnp.nan, 1.0)
        new = new.replace(params=jax.tree.map(lambda p: p * scale, new.params))
        return new, {**metrics, "finite": ppo.all_finite(new.params).astype(jnp.float32)}

    monkeypatch.setattr(ppo.Trainer, "update", poisoned)
    config = apply_overrides(preset(name), [*overrides, "checkpoint_every=2", "timesteps=16"])
    with pytest.raises(NonFiniteError, match=r"at iteration 3; stopped. Last good checkpoint: iteration 2"):
        train(config, tmp_path, preset_name=name, progress=False)
    from train.checkpoint import Checkpoints

    assert Checkpoints(tmp_path / "checkpoints").latest() == 2
    assert not (tmp_path / "policy").exists()  # nothing is exported from a broken run


@pytest.mark.parametrize("name, overrides, layer", ENVS)
def test_sharding_over_two_devices_matches_one(name, overrides, layer):
    script = textwrap.dedent(
        f"""
        import jax, numpy as np
        from train.presets import ConfigError, apply_overrides, preset
        from train.run import build
        assert len(jax.devices()) == 2, jax.devices()
        config = apply_overrides(preset({name!r}), {list(overrides)!r})
        out = []
        for devices in (jax.devices()[:1], jax.devices()):
            trainer = build(config, devices=devices).trainer
            state, m = jax.jit(lambda k: trainer.train(k, 2))(jax.random.key(0))
            kernel = state.params["params"]{"".join(f"[{n!r}]" for n in layer)}["kernel"]
            out.append(np.asarray(kernel))
            if len(devices) == 2:
                assert len(state.env_state.obs.sharding.device_set) == 2, state.env_state.obs.sharding
        err = np.max(np.abs(out[0] - out[1]))
        print("max difference", err)
        assert err < 1e-4, err
        """
    )
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    assert "max difference" in done.stdout


def test_an_anchored_run_stays_near_its_start_and_resumes_bit_identical(tmp_path):
    source = tmp_path / "source"
    train(
        apply_overrides(preset("guide"), [*TINY_GUIDE, "timesteps=8"]),
        source,
        preset_name="guide",
        progress=False,
    )
    # a fixed, large learning rate so that the policy moves far in a few updates unless held
    fast = [
        *TINY_GUIDE,
        f"init_from={source / 'policy'}",
        "ppo.kl_threshold=0",
        "ppo.learning_rate=1e-2",
        "timesteps=24",
    ]

    def run(folder, scale, **kw):
        config = apply_overrides(preset("guide"), [*fast, f"ppo.anchor_scale={scale}", "checkpoint_every=2"])
        return train(config, folder, preset_name="guide", progress=False, **kw)

    free, held = run(tmp_path / "free", 0), run(tmp_path / "held", 300)
    trainer = build(apply_overrides(preset("guide"), fast)).trainer
    start = held["state"].anchor
    obs = trainer.env.reset(jax.random.split(jax.random.key(5), 64)).obs

    def mean(state):
        return trainer.network.apply(state["params"], state["obs_stats"].normalize(obs, 5.0))[0]

    def moved(result):
        s = result["state"]
        return float(jnp.mean(jnp.abs(mean({"params": s.params, "obs_stats": s.obs_stats}) - mean(start))))

    assert free["state"].anchor is None
    assert moved(held) < 0.5 * moved(free), (moved(held), moved(free))
    assert held["rows"][-1]["loss/anchor"] > 0
    # the anchor lives in the checkpoint: a run cut after iteration 3 resumes to the same parameters
    run(tmp_path / "cut", 300, stop_after=3)
    resumed = run(tmp_path / "cut", 300, resume=True)
    learned = lambda s: (s.params, s.obs_stats, s.anchor)  # noqa: E731
    for a, b in zip(
        jax.tree.leaves(learned(held["state"])), jax.tree.leaves(learned(resumed["state"])), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ConfigError, match="anchor_scale needs init_from"):
        apply_overrides(preset("guide"), [*TINY_GUIDE, "ppo.anchor_scale=1"])
