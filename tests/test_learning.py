"""PPO learns on CPU within CI's budget: SU reaches and holds the HIP, GuideRL picks the requesting user.

Both runs are scaled down from the thesis's (Table 4.4: 960k timesteps x 2,048 environments, ~2,000M
transitions, for SU; 240k x 4,096, ~980M, for GuideRL; these see 0.6M and 2M) and say so in their
configuration.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.wrappers import AutoReset
from methd_jax import motion
from train.presets import apply_overrides, preset
from train.run import build, train


def _evaluate(setup, policies: dict, key, steps, n=64):
    """Per policy ``policy(obs, key)``: mean reward per step and per-step metrics on ``n`` fresh
    episodes. All policies run side by side in one compiled scan (a block of ``n`` episodes each):
    the environment is compiled once, not once per policy."""
    env = AutoReset(setup.env)
    names = list(policies)

    @jax.jit
    def roll(key):
        state = env.reset(jax.random.split(key, n * len(names)))

        def body(s, k):
            obs = s.obs.reshape(len(names), n, -1)
            action = jnp.concatenate([policies[name](obs[i], k) for i, name in enumerate(names)])
            s = env.step(s, action)
            return s, (s.reward, s.metrics)

        _, (rewards, metrics) = jax.lax.scan(body, state, jax.random.split(jax.random.fold_in(key, 1), steps))
        return rewards, metrics

    rewards, metrics = jax.device_get(roll(key))
    block = lambda x, i: x[:, i * n : (i + 1) * n]  # noqa: E731
    return {
        name: (float(np.mean(block(rewards, i))), {k: block(v, i) for k, v in metrics.items()})
        for i, name in enumerate(names)
    }


def _policies(setup, state, action_size):
    return {
        "trained": lambda obs, k: setup.trainer.policy(state.params, state.obs_stats, obs),
        "random": lambda obs, k: jax.random.uniform(k, (obs.shape[0], action_size), minval=-1, maxval=1),
    }


@pytest.mark.slow  # 4 min; the default suite checks the shipped SU policy (test_pretrained.py) and
# that a run learns (the toy task of test_tasks.py)
def test_su_policy_learns_to_reach_and_hold_the_hip(tmp_path):
    """614k transitions (the thesis trained on ~2,000M) on an open floor: after the request, while
    the user stands and reaches out, the trained robot holds the HIP where random acting stays
    metres away.

    Floating-point results differ between CPUs, and so does what one seed learns in this budget.
    Measured, seed 0 unless named: Intel Xeon (2 cores) median distance 0.47 / 0.36 / 0.68 m
    (seeds 0 / 1 / 2), 88% / 87% / 83% of those steps within 1 m; AMD EPYC (2 cores) 0.73 / 0.84 /
    0.56 m and 61% / 71% / 58% (seeds 0 / 1 / 2) on one machine, 1.33 m and 31% (seed 0) on
    another; random acting 6.1 m and 0% everywhere. The
    thresholds (median < 2 m, > 20% within 1 m) hold the worst of these with a 1.5x margin and
    still lie far from random acting."""
    # An open floor (walls only), 72 rays and a tenth of Table 4.1's velocity penalty: with the full
    # penalty the policy first spends ~1M transitions learning to stand still. A 3 x 128 body
    # trains as fast as a 2 x 64 one here (the environment dominates) and learns much faster.
    config = apply_overrides(
        preset("quick"),
        [
            "env.num_rays=72",
            "env.motion=sample",
            "env.weights.velocity=-0.2",
            "hidden=128,128,128",
            "num_envs=256",
            "ppo.rollouts=32",
            "ppo.minibatches=4",
            "timesteps=2400",
        ],
    )
    out = train(config, tmp_path, progress=False)
    setup = build(config)
    # 30 s: three of the four sample users request a touch (at 10.8, 17.3 and 18.7 s) and an
    # episode succeeds 10 s after its request
    results = _evaluate(setup, _policies(setup, out["state"], 3), jax.random.key(9), steps=1500)
    (trained, m_trained), (random, m_random) = results["trained"], results["random"]

    def holding(m):  # distances to the HIP on the steps after the request
        return m["distance_to_goal"][m["requested"] > 0]

    d_trained, d_random = holding(m_trained), holding(m_random)
    print(
        f"reward/step trained {trained:.2f} random {random:.2f}; after the request: median HIP "
        f"distance {np.median(d_trained):.2f} m vs {np.median(d_random):.2f} m, within 0.5 / 1 m "
        f"{np.mean(d_trained < 0.5):.0%} / {np.mean(d_trained < 1):.0%} vs {np.mean(d_random < 0.5):.0%} / "
        f"{np.mean(d_random < 1):.0%} of {d_trained.size} / {d_random.size} steps"
    )
    assert trained > random + 0.3 * abs(random)
    assert d_trained.size > 10_000  # most of the 64 episodes reach their request
    assert np.median(d_trained) < 2.0 and np.mean(d_trained < 1.0) > 0.2
    assert np.median(d_random) > 2.0 and np.mean(d_random < 1.0) < 0.1


@pytest.mark.slow  # 2.5 min; the default suite checks the shipped GuideRL policy's accuracy instead
def test_guide_policy_learns_to_pick_the_requesting_user(tmp_path):
    """GuideRL in CI's budget (2M transitions; the thesis trained on ~980M) picks the requesting
    user at >= 90% of requests and beats random acting; a scripted rule (turn toward the user
    standing still) shows what the data allows."""
    motion.save(tmp_path / "bags", motion.synthesize(40, seed=3))
    config = apply_overrides(
        preset("guide"),
        [f"env.motion={tmp_path / 'bags'}", "env.split=all", "num_envs=1024", "timesteps=1920"],
    )
    out = train(config, tmp_path / "run", progress=False)
    setup = build(config)

    def still_user(obs, k):
        speed = jnp.linalg.norm(obs[:, 0:2], axis=1), jnp.linalg.norm(obs[:, 3:5], axis=1)
        toward = jnp.where(speed[1] < speed[0], 1.0, -1.0)
        back = jnp.clip(-obs[:, 12] / 0.05, -1.0, 1.0)  # drift u_w back to the midpoint
        return jnp.where(jnp.minimum(*speed) < 0.05, toward, back)[:, None]

    policies = {**_policies(setup, out["state"], 1), "still_user": still_user}
    results = _evaluate(setup, policies, jax.random.key(4), steps=1500)
    accuracy = {
        name: m["correct_at_request"].sum() / max(m["at_request"].sum(), 1)
        for name, (_, m) in results.items()
    }
    print({name: (round(r, 2), round(float(accuracy[name]), 3)) for name, (r, _) in results.items()})
    assert results["trained"][0] > results["random"][0] + 1.0
    assert results["still_user"][1]["at_request"].sum() >= 64
    assert accuracy["still_user"] >= 0.9
    assert accuracy["trained"] >= 0.9 and accuracy["random"] < 0.7
