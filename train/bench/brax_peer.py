"""Brax's PPO trainer (``brax.training.agents.ppo``) on our environments and network: the peer of
``train.bench``'s training section.

Brax trains any ``brax.envs.Env``; ours are. To compare the trainers rather than the networks,
Brax gets the thesis's network too (:func:`network_factory`: our Flax ``ActorCritic`` behind
Brax's ``FeedForwardNetwork`` interface). Brax keeps separate policy and value parameters, so it
runs the body twice per observation where ours shares it: that is Brax's design, and part of what
is measured. The batch shape is ours: ``num_envs`` environments x ``unroll_length`` (48) steps per
update, ``num_minibatches`` (8) x ``num_updates_per_batch`` (5) gradient steps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.training import distribution, types
from brax.training import networks as brax_networks
from brax.training.agents.ppo import networks as ppo_networks
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

import networks

BRAX_PMAP_AXIS = "i"
"""The axis name Brax's PPO gives its ``pmap`` (``_PMAP_AXIS_NAME`` in its ``train.py``)."""


def device_put_replicated(x, devices):
    """JAX's documented drop-in for the removed ``jax.device_put_replicated``.

    The mesh axis carries Brax's pmap axis name: jax 0.10's pmap shards its outputs over a mesh
    named after that axis, and an input laid out over a mesh of another name made Brax's first
    training epoch compile twice (once for the state put here, once for the epoch's own output).
    """
    sharding = NamedSharding(Mesh(np.array(devices), (BRAX_PMAP_AXIS,)), P(BRAX_PMAP_AXIS))
    return jax.tree.map(lambda y: jax.device_put(jnp.stack([y] * len(devices)), sharding), x)


def patch_jax_for_brax() -> None:
    """Brax 0.14's PPO still calls ``jax.device_put_replicated``, which jax 0.10 removed (google/brax
    issue 671, open): put the documented replacement back rather than pinning an old jax."""
    try:
        jax.device_put_replicated  # noqa: B018
    except AttributeError:
        jax.device_put_replicated = device_put_replicated


def network_factory(spec: dict):
    """A Brax ``network_factory`` building ``networks.from_spec(spec)`` for policy and value."""

    def make(
        observation_size,
        action_size,
        preprocess_observations_fn: types.PreprocessObservationFn = types.identity_observation_preprocessor,
        **_,
    ) -> ppo_networks.PPONetworks:
        module = networks.from_spec(spec)
        # Brax passes the observation's shape: an int, a shape tuple, or a dict of them by key
        size = observation_size["state"] if isinstance(observation_size, dict) else observation_size
        dummy = jnp.zeros((1, *np.atleast_1d(size).tolist()))

        def policy(processor_params, params, obs):
            mean, log_std, _ = module.apply(params, preprocess_observations_fn(obs, processor_params))
            return jnp.concatenate([mean, log_std], -1)

        def value(processor_params, params, obs):
            return module.apply(params, preprocess_observations_fn(obs, processor_params)).value

        init = lambda key: module.init(key, dummy)  # noqa: E731
        return ppo_networks.PPONetworks(
            policy_network=brax_networks.FeedForwardNetwork(init=init, apply=policy),
            value_network=brax_networks.FeedForwardNetwork(init=init, apply=value),
            parametric_action_distribution=distribution.NormalTanhDistribution(event_size=action_size),
        )

    return make
