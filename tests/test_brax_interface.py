"""The environments run unchanged under Brax's own PPO trainer (a smoke test of the interface)."""

import functools

import jax
import numpy as np
import pytest
from brax.training.agents.ppo import networks as ppo_networks
from brax.training.agents.ppo import train as ppo

import envs
from methd_jax import motion
from train.bench import brax_peer


@pytest.fixture
def brax_on_new_jax(monkeypatch):
    """Brax 0.14 on jax 0.10: ``jax.device_put_replicated`` put back for this test only."""
    monkeypatch.setattr(jax, "device_put_replicated", brax_peer.device_put_replicated, raising=False)


# su under Brax's trainer takes ~1.5 min of CI's 15; guide checks the same interface in CI and
# su runs with -m slow.
@pytest.mark.parametrize("name", [pytest.param("su", marks=pytest.mark.slow), "guide"])
def test_brax_ppo_runs_a_few_iterations(name, brax_on_new_jax):
    bank = motion.MotionBank.from_trajectories(motion.sample())
    env = envs.make(name, bank=bank)
    progress = []
    make_inference, params, _ = ppo.train(
        environment=env,
        num_timesteps=2 * 8 * 8 * 5,
        episode_length=100,
        num_envs=8,
        batch_size=8,
        num_minibatches=2,
        unroll_length=5,
        num_updates_per_batch=2,
        num_evals=2,
        num_eval_envs=4,
        network_factory=functools.partial(
            ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=(32,), value_hidden_layer_sizes=(32,)
        ),
        seed=0,
        progress_fn=lambda step, m: progress.append((step, m)),
    )
    assert progress and progress[-1][0] > 0
    assert np.isfinite(float(progress[-1][1]["eval/episode_reward"]))
    policy = make_inference(params, deterministic=True)
    state = env.reset(jax.random.key(0))
    action, _ = jax.jit(policy)(state.obs, jax.random.key(1))
    assert action.shape == (env.action_size,) and np.all(np.abs(np.asarray(action)) <= 1.0)
