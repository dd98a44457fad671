"""The benchmark's peers (``train.bench.brax_peer``, ``train.bench.skrl_peer``) are set up the way their own
outputs will look, so each compiles its pieces once: a second compile would be charged to the
peer's compile time in ``train.bench`` and lengthen ``--quick``."""

import logging
import re

import jax
import jax.numpy as jnp
from brax.training.agents.ppo import train as brax_ppo

from train.bench import brax_peer, skrl_peer
from train.ppo import PPOConfig
from train.presets import apply_overrides, preset
from train.run import build


def _compiles(caplog, name: str) -> int:
    pattern = re.compile(rf"Compiling (?:jit\()?{re.escape(name)}\b")
    return sum(bool(pattern.search(r.getMessage())) for r in caplog.records)


def test_replicated_state_feeds_brax_pmap_without_a_recompile(caplog):
    assert brax_peer.BRAX_PMAP_AXIS == brax_ppo._PMAP_AXIS_NAME

    def epoch(state):  # stands in for Brax's training epoch: state in, state out
        return jax.tree.map(lambda x: x + 1, state)

    step = jax.pmap(epoch, axis_name=brax_ppo._PMAP_AXIS_NAME, donate_argnums=0)
    state = brax_peer.device_put_replicated({"w": jnp.zeros(3), "n": jnp.int32(0)}, jax.local_devices()[:1])
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        for _ in range(3):
            state = step(state)
    assert int(state["n"][0]) == 3
    assert _compiles(caplog, "_fun") == 1  # jax 0.10's pmap is a jit of a shard_map named _fun


def test_skrl_compiles_its_step_and_models_once(caplog):
    config = apply_overrides(preset("guide"), ["env.motion=sample", "env.split=all", "num_envs=8"])
    setup = build(config)
    ppo = PPOConfig(rollouts=4, epochs=1, minibatches=2)
    run = skrl_peer.make(setup.env, setup.network_spec, ppo, 8, episode_length=50)
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        run.iteration()
        first = {name: _compiles(caplog, name) for name in ("step", "apply")}
        caplog.clear()
        run.iteration()
        second = {name: _compiles(caplog, name) for name in ("step", "apply")}
    assert first["step"] == 1 and first["apply"] >= 2  # the environment, the policy and the value
    assert second == {"step": 0, "apply": 0}
