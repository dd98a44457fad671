"""skrl's JAX PPO (``skrl.agents.jax.ppo``, the trainer library of the thesis) on our environments
and network: the second peer of ``train.bench``'s training section.

skrl steps any batched JAX environment through its MuJoCo Playground wrapper (a jitted
``reset(keys)`` / ``step(state, action)`` returning Brax-style states); ours are Brax environments,
so they are vectorised, time-limited and auto-reset by Brax's own training wrapper, exactly as
Brax's PPO does it. skrl's design is what is measured: a Python loop over time steps that calls
jitted pieces (policy, value, environment step) one at a time, a Python loop over epochs and
minibatches, and separate policy and value models (so the thesis's network body runs twice per
observation, as in Brax; ours shares it).

Everything else is ours: the network (``networks.from_spec``), the batch shape (N environments x
48 steps, 5 epochs x 8 minibatches), observation and value standardisation with running
statistics (skrl's ``RunningStandardScaler``, clipped to +-5 as ours), the KL-adaptive learning
rate (skrl's ``KLAdaptiveLR``, which ours reproduces) and every PPO coefficient of the preset.
"""

from __future__ import annotations

import importlib.util
import logging
import time
import warnings
from dataclasses import dataclass

import flax.linen as nn
import jax
from brax.envs.wrappers import training as brax_training

import networks
from train.ppo import PPOConfig

MISSING = "skrl is not installed (pip install 'methd-jax[peers]', or '.[peers]' in a checkout)"
"""What the benchmark says in place of skrl's column when the optional peer is missing."""


def available() -> bool:
    """Whether skrl, an optional dependency (the ``peers`` extra), can be imported."""
    return importlib.util.find_spec("skrl") is not None


class _Batched:
    """What skrl's Playground wrapper reads: ``num_envs`` and a batched, auto-resetting env."""

    def __init__(self, env, num_envs: int, episode_length: int):
        self.env = brax_training.wrap(env, episode_length=episode_length)
        self.num_envs = num_envs
        self.observation_size = env.observation_size
        self.action_size = env.action_size

    def reset(self, keys):
        return self.env.reset(keys)

    def step(self, state, action):
        return self.env.step(state, action)


def _models(spec: dict, observation_space, action_space, device):
    """skrl policy and value models around ``networks.from_spec(spec)`` (unclipped Gaussian
    actions, as ours: the environments clip them)."""
    from skrl.models.jax import DeterministicMixin, GaussianMixin, Model

    class Policy(GaussianMixin, Model):
        def __init__(self, **kwargs):
            Model.__init__(self, **kwargs)
            GaussianMixin.__init__(self, clip_actions=False)

        @nn.compact
        def __call__(self, inputs, role):
            out = networks.from_spec(spec)(inputs["observations"])
            return out.mean, {"log_std": out.log_std}

    class Value(DeterministicMixin, Model):
        def __init__(self, **kwargs):
            Model.__init__(self, **kwargs)
            DeterministicMixin.__init__(self, clip_actions=False)

        @nn.compact
        def __call__(self, inputs, role):
            return networks.from_spec(spec)(inputs["observations"]).value[..., None], {}

    kw = {"observation_space": observation_space, "action_space": action_space}
    models = {"policy": Policy(**kw), "value": Value(**kw)}
    for role, model in models.items():
        model.init_state_dict(role=role)
        # the initialiser leaves constant-initialised parameters (biases, log-std) uncommitted and
        # skrl's first update commits them: committed from the start, each model compiles once
        model.state_dict = model.state_dict.replace(params=jax.device_put(model.state_dict.params, device))
    return models


@dataclass
class SkrlRun:
    """skrl's agent and trainer on one environment; :meth:`iteration` runs one PPO iteration."""

    trainer: object
    agent: object
    transitions_per_iteration: int

    def head(self, role: str) -> jax.Array:
        """The output layer's kernel of the ``"policy"`` (mean) or ``"value"`` model."""
        model = getattr(self.agent, role)
        return model.state_dict.params["params"]["ActorCritic_0"][role]["kernel"]

    def iteration(self) -> float:
        """One iteration (rollouts steps, then the update skrl runs after the last); seconds."""
        t0 = time.perf_counter()
        self.trainer.train()
        jax.block_until_ready(self.agent.policy.state_dict.params)
        return time.perf_counter() - t0


def make(env, spec: dict, ppo: PPOConfig, num_envs: int, episode_length: int, seed: int = 0) -> SkrlRun:
    """skrl's PPO configured as ``ppo`` on ``num_envs`` copies of ``env`` with the network ``spec``."""
    from skrl import config as skrl_config
    from skrl.agents.jax.ppo import PPO, PPO_CFG
    from skrl.envs.wrappers.jax import wrap_env
    from skrl.memories.jax import RandomMemory
    from skrl.resources.preprocessors.jax import RunningStandardScaler
    from skrl.resources.schedulers.jax import KLAdaptiveLR
    from skrl.trainers.jax import SequentialTrainer

    logging.getLogger("skrl").setLevel(logging.WARNING)  # its INFO lines at exit say nothing timed
    # skrl's memory writes float flags into int8 tensors: JAX warns on every write, to no purpose here
    warnings.filterwarnings("ignore", "scatter inputs have incompatible types", FutureWarning)
    skrl_config.jax.device = jax.devices()[0]  # its default names "cuda:0" and warns on a CPU
    # skrl makes its key under `jax.default_device` (uncommitted) but puts actions on the device
    # (committed): the environment's state would switch from the one to the other after the first
    # step, and its step compile twice. The same key, committed from the start, compiles once.
    skrl_config.jax.key = jax.device_put(jax.random.PRNGKey(seed), skrl_config.jax.device)
    wrapped = wrap_env(_Batched(env, num_envs, episode_length), wrapper="playground", verbose=False)
    models = _models(spec, wrapped.observation_space, wrapped.action_space, skrl_config.jax.device)
    cfg = PPO_CFG(
        rollouts=ppo.rollouts,
        learning_epochs=ppo.epochs,
        mini_batches=ppo.minibatches,
        discount_factor=ppo.gamma,
        gae_lambda=ppo.lam,
        learning_rate=ppo.learning_rate,
        learning_rate_scheduler=KLAdaptiveLR if ppo.kl_threshold > 0 else None,
        learning_rate_scheduler_kwargs={
            "kl_threshold": ppo.kl_threshold,
            "kl_factor": ppo.kl_factor,
            "lr_factor": ppo.lr_factor,
            "min_lr": ppo.lr_range[0],
            "max_lr": ppo.lr_range[1],
        }
        if ppo.kl_threshold > 0
        else {},
        observation_preprocessor=RunningStandardScaler,
        observation_preprocessor_kwargs={"size": wrapped.observation_space, "clip_threshold": ppo.obs_clip},
        value_preprocessor=RunningStandardScaler,
        value_preprocessor_kwargs={"size": 1},
        grad_norm_clip=ppo.grad_norm_clip,
        ratio_clip=ppo.ratio_clip,
        value_clip=ppo.value_clip,
        entropy_loss_scale=ppo.entropy_scale,
        value_loss_scale=ppo.value_loss_scale,
    )
    # no TensorBoard files or checkpoints: skrl's writers are not what is timed
    cfg.experiment.write_interval = 0
    cfg.experiment.checkpoint_interval = 0
    agent = PPO(
        models=models,
        memory=RandomMemory(memory_size=ppo.rollouts, num_envs=num_envs),
        observation_space=wrapped.observation_space,
        action_space=wrapped.action_space,
        cfg=cfg,
    )
    trainer = SequentialTrainer(
        env=wrapped,
        agents=agent,
        cfg={"timesteps": ppo.rollouts, "headless": True, "disable_progressbar": True},
    )
    return SkrlRun(trainer, agent, ppo.rollouts * num_envs)
