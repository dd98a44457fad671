"""PPO as one jitted iteration: rollout (``lax.scan``), GAE, epochs x minibatches (``lax.scan``).

It follows skrl 1.4's PPO with the defaults Isaac Lab's skrl configs use, because those trained the
thesis's policies (Table 4.4 gives only rollouts, epochs, minibatches, gamma, lambda, lr, entropy):

- Gaussian policy with a state-independent log-std (clamped to [-20, 2]); actions are sampled
  unclipped (the environments clip them to [-1, 1]) and their log-probabilities are of that sample.
- Observations are standardised with running statistics (``RunningStats``, clipped to +-5); value
  targets too: the critic predicts standardised returns, which matters here because the rewards
  span -1000 (a user collision) to +50 per step.
- GAE with the advantages standardised over the batch; like skrl's default
  (``time_limit_bootstrap=False``) a truncated episode is treated as terminated.
- Loss: clipped surrogate (0.2), clipped value loss (0.2, scale 1) and an entropy bonus; one Adam
  for actor and critic with the gradient norm clipped to 1.
- skrl's ``KLAdaptiveLR`` after every epoch: the learning rate is divided by 1.5 when the epoch's
  mean KL exceeds 2 x 0.008 and multiplied by 1.5 below 0.008 / 2, within [1e-6, 1e-2].

One deliberate difference: the observation statistics are updated once per iteration from the
whole rollout, after the update, so that the update sees the observations exactly as the policy
that acted saw them (the first epoch's ratio is exactly 1); skrl updates them minibatch by
minibatch in the first epoch. Each epoch draws a fresh permutation of the whole batch, as skrl does.

``Trainer(env, network, config, num_envs)`` gives pure functions: ``init(key) -> TrainState``,
``update(state) -> (state, metrics)`` (one iteration) and ``train(key, iterations)``, which can be
``jax.vmap``-ped over seeds. Environments are sharded over all devices along the batch axis
(``jax.sharding``, one mesh axis ``"envs"``; with ``jax.distributed`` the devices of every process);
parameters are replicated, so the same code runs on one CPU, one GPU, several, or several hosts.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

import networks
from envs.wrappers import AutoReset
from methd_jax.normalise import normalise
from networks import LOG_STD_RANGE

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters: Table 4.4 where the thesis gives them, skrl / Isaac Lab otherwise."""

    rollouts: int = 48
    """Steps per environment per iteration."""
    epochs: int = 5
    """Passes over each batch."""
    minibatches: int = 8
    """Minibatches per epoch."""
    gamma: float = 0.99
    """Discount factor."""
    lam: float = 0.95
    """GAE lambda."""
    learning_rate: float = 5e-4
    """Initial Adam learning rate (then adapted to the KL)."""
    entropy_scale: float = 0.005
    """Weight of the entropy bonus."""
    ratio_clip: float = 0.2
    """PPO's epsilon."""
    value_clip: float = 0.2
    """Predicted (standardised) values move at most this far from the rollout's; 0 disables."""
    value_loss_scale: float = 1.0
    """Weight of the value loss."""
    grad_norm_clip: float = 1.0
    """Global gradient norm limit; 0 disables."""
    kl_threshold: float = 0.008
    """Target KL of the adaptive learning rate; 0 keeps the learning rate fixed."""
    kl_factor: float = 2.0
    """The learning rate changes when the KL leaves [threshold / factor, threshold * factor]."""
    lr_factor: float = 1.5
    """Factor by which the learning rate is divided or multiplied."""
    lr_range: tuple[float, float] = (1e-6, 1e-2)
    """Bounds of the adaptive learning rate."""
    obs_clip: float = 5.0
    """Standardised observations are clipped to +- this."""
    anchor_scale: float = 0.0
    """Weight of a penalty on the policy's mean leaving the start policy's (``init_from``) on the
    rollout's observations: half the squared distance in units of the current std, i.e. the KL
    from the start policy at the current std (:func:`anchor_penalty`); 0 disables."""
    shield_scale: float = 0.0
    """Weight of a pull of the policy's mean action, where the environment's stopping rule
    (``env.shield_target``, :mod:`envs.shield`) would slow it, toward the slowed action
    (:func:`shield_penalty`, averaged over the batch: zero where the rule lets the action be);
    0 disables."""

    def __post_init__(self):
        for name in ("rollouts", "epochs", "minibatches"):
            if getattr(self, name) < 1:
                raise ValueError(f"ppo.{name} must be at least 1, got {getattr(self, name)}")
        if not (0 < self.gamma <= 1 and 0 <= self.lam <= 1):
            raise ValueError(
                f"ppo.gamma must be in (0, 1] and ppo.lam in [0, 1], got {self.gamma}, {self.lam}"
            )
        if not self.learning_rate > 0:
            raise ValueError(f"ppo.learning_rate must be positive, got {self.learning_rate}")
        if min(self.ratio_clip, self.value_clip, self.grad_norm_clip, self.kl_threshold, self.obs_clip) < 0:
            raise ValueError("ppo clip values, kl_threshold and obs_clip must be >= 0")
        if not self.anchor_scale >= 0:
            raise ValueError(f"ppo.anchor_scale must be >= 0, got {self.anchor_scale}")
        if not self.shield_scale >= 0:
            raise ValueError(f"ppo.shield_scale must be >= 0, got {self.shield_scale}")
        if not 0 < self.lr_range[0] <= self.lr_range[1]:
            raise ValueError(f"ppo.lr_range must be an ordered positive range, got {self.lr_range}")


# -- running statistics -----------------------------------------------------------------------


@struct.dataclass
class RunningStats:
    """Mean and variance over everything seen so far (Chan et al.'s parallel update), float32."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def zeros(cls, shape=()) -> RunningStats:
        return cls(jnp.zeros(shape), jnp.ones(shape), jnp.float32(1e-4))

    def update(self, x: jax.Array) -> RunningStats:
        """Fold in a batch ``x`` of shape ``(..., *shape)``."""
        axes = tuple(range(x.ndim - self.mean.ndim))
        n = jnp.float32(np.prod([x.shape[a] for a in axes]))
        b_mean, b_var = jnp.mean(x, axes), jnp.var(x, axes)
        total = self.count + n
        delta = b_mean - self.mean
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + b_var * n + delta**2 * self.count * n / total
        return RunningStats(mean, m2 / total, total)

    @property
    def std(self) -> jax.Array:
        return jnp.sqrt(self.var + 1e-8)

    def normalize(self, x: jax.Array, clip: float = 0.0) -> jax.Array:
        return normalise(x, self.mean, self.std, clip)

    def denormalize(self, z: jax.Array) -> jax.Array:
        return z * self.std + self.mean


# -- the pieces that tests check against plain loops ---------------------------------------------


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, x: jax.Array) -> jax.Array:
    """Log-density of a diagonal Gaussian, summed over the last axis."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - _HALF_LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    return jnp.sum(log_std + 0.5 + _HALF_LOG_2PI, axis=-1)


def gae(rewards, values, dones, last_value, gamma: float, lam: float):
    """Generalised advantage estimates and returns for ``(T, ...)`` arrays.

    ``dones[t]`` marks that the episode ended at step t, so step t+1's value is not bootstrapped;
    ``last_value`` is the value of the state after the last step.
    """
    next_values = jnp.concatenate([values[1:], last_value[None]], 0)
    live = 1.0 - dones
    deltas = rewards + gamma * next_values * live - values

    def back(adv, xs):
        delta, alive = xs
        adv = delta + gamma * lam * alive * adv
        return adv, adv

    _, adv = jax.lax.scan(back, jnp.zeros_like(last_value), (deltas, live), reverse=True)
    return adv, adv + values


def anchor_penalty(mean: jax.Array, log_std: jax.Array, anchor_mean: jax.Array) -> jax.Array:
    """KL(N(anchor_mean, std) || N(mean, std)), summed over action dimensions and averaged over the
    batch: the pull of :attr:`PPOConfig.anchor_scale` toward the start policy's actions. Only the
    mean is held; the std stays PPO's to shape, so no gradient reaches it from here (through the
    std, widening the policy would be a way to shrink the penalty without coming back)."""
    z = (mean - anchor_mean) * jnp.exp(-jax.lax.stop_gradient(log_std))
    return jnp.mean(jnp.sum(0.5 * z**2, axis=-1))


def shield_penalty(mean: jax.Array, raw_obs: jax.Array, shield) -> tuple[jax.Array, jax.Array]:
    """(the penalty of :attr:`PPOConfig.shield_scale` before its weight, the share of the batch the
    rule slowed): half the squared distance of the mean action from ``shield(raw_obs, mean)``'s
    target where the rule slowed the mean, the target held fixed (the rule is a teacher, not a
    path for gradients). In action units, not the anchor's units of the std: as PPO narrows the
    std, a pull measured in it would grow without bound."""
    target, slowed = jax.vmap(shield)(raw_obs, jax.lax.stop_gradient(jnp.clip(mean, -1.0, 1.0)))
    per = jnp.where(slowed, jnp.sum(0.5 * (mean - jax.lax.stop_gradient(target)) ** 2, axis=-1), 0.0)
    return jnp.mean(per), jnp.mean(slowed.astype(jnp.float32))


def ppo_loss(params, apply_fn, batch, config: PPOConfig, shield=None):
    """skrl's PPO loss on one minibatch; returns ``(loss, parts)``.

    ``batch``: ``obs`` (standardised), ``action``, ``log_prob``, ``value`` and ``returns``
    (both standardised), ``advantage`` (standardised); with an anchor (``TrainState.anchor``),
    ``anchor_mean``, the start policy's mean action, adds :func:`anchor_penalty`; with
    ``config.shield_scale``, ``raw_obs`` (the observations as the environment gave them) and
    ``shield`` (the environment's ``shield_target``) add :func:`shield_penalty`.
    """
    mean, log_std, value = apply_fn(params, batch["obs"])
    log_std = jnp.clip(log_std, *LOG_STD_RANGE)
    log_prob = gaussian_log_prob(mean, log_std, batch["action"])
    log_ratio = log_prob - batch["log_prob"]
    ratio = jnp.exp(log_ratio)
    kl = jnp.mean((ratio - 1.0) - log_ratio)
    adv = batch["advantage"]
    clipped = jnp.clip(ratio, 1.0 - config.ratio_clip, 1.0 + config.ratio_clip)
    policy_loss = -jnp.mean(jnp.minimum(adv * ratio, adv * clipped))
    entropy = jnp.mean(gaussian_entropy(log_std))
    entropy_loss = -config.entropy_scale * entropy
    if config.value_clip > 0:
        value = batch["value"] + jnp.clip(value - batch["value"], -config.value_clip, config.value_clip)
    value_loss = config.value_loss_scale * jnp.mean((batch["returns"] - value) ** 2)
    loss = policy_loss + value_loss + entropy_loss
    anchor = {}
    if "anchor_mean" in batch:
        anchor_loss = config.anchor_scale * anchor_penalty(mean, log_std, batch["anchor_mean"])
        loss = loss + anchor_loss
        anchor = {"loss/anchor": anchor_loss}
    if config.shield_scale > 0:
        shield_loss, slowed = shield_penalty(mean, batch["raw_obs"], shield)
        loss = loss + config.shield_scale * shield_loss
        anchor |= {"loss/shield": config.shield_scale * shield_loss, "policy/shielded": slowed}
    parts = {
        "loss/policy": policy_loss,
        "loss/value": value_loss,
        "loss/entropy": entropy_loss,
        "policy/entropy": entropy,
        "policy/kl": kl,
        "policy/clip_fraction": jnp.mean(jnp.abs(ratio - 1.0) > config.ratio_clip),
        **anchor,
    }
    return loss, parts


def adapt_learning_rate(lr, kl, config: PPOConfig):
    """skrl's ``KLAdaptiveLR`` step."""
    if config.kl_threshold <= 0:
        return lr
    lo, hi = config.lr_range
    lr = jnp.where(kl > config.kl_threshold * config.kl_factor, jnp.maximum(lr / config.lr_factor, lo), lr)
    return jnp.where(kl < config.kl_threshold / config.kl_factor, jnp.minimum(lr * config.lr_factor, hi), lr)


# -- the trainer --------------------------------------------------------------------------------


@struct.dataclass
class TrainState:
    params: dict
    opt_state: optax.OptState
    obs_stats: RunningStats
    value_stats: RunningStats
    env_state: object
    key: jax.Array
    iteration: jax.Array
    learning_rate: jax.Array
    anchor: dict | None = None
    """The start policy (``{"params", "obs_stats"}``, frozen) whose mean actions
    :attr:`PPOConfig.anchor_scale` pulls toward; None: no anchor."""


def all_finite(tree) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))


def critic_mask(params) -> dict:
    """True at the parameters only the critic uses: the layers named ``value`` or ``critic*``
    (:class:`networks.ActorCritic`'s value head, :class:`networks.GuideActorCritic`'s critic)."""
    top = params["params"]
    if "value" not in top:
        raise ValueError(f"no critic layer named 'value' among {sorted(top)}")

    def every(tree, flag: bool):
        return jax.tree.map(lambda _: flag, tree)

    critic = {name: every(layer, name == "value" or name.startswith("critic")) for name, layer in top.items()}
    return {**{k: every(v, False) for k, v in params.items() if k != "params"}, "params": critic}


class Trainer:
    """PPO on ``num_envs`` copies of ``env`` with the Flax ``network`` (``obs -> (mean, log_std,
    value)``)."""

    def __init__(
        self,
        env,
        network: nn.Module,
        config: PPOConfig,
        num_envs: int,
        devices=None,
        ratios: Mapping | None = None,
    ):
        devices = list(devices if devices is not None else jax.devices())
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        if num_envs % len(devices):
            raise ValueError(f"num_envs ({num_envs}) must be a multiple of the device count ({len(devices)})")
        batch = num_envs * config.rollouts
        if batch % config.minibatches:
            raise ValueError(
                f"num_envs x rollouts ({batch}) must be divisible by minibatches ({config.minibatches})"
            )
        self.env = env if isinstance(env, AutoReset) else AutoReset(env)
        self.shield = getattr(self.env.env, "shield_target", None)
        if config.shield_scale > 0 and self.shield is None:
            name = type(self.env.env).__name__
            raise ValueError(f"ppo.shield_scale needs an environment with a shield_target; {name} has none")
        self.network = network
        self.config = config
        self.num_envs = num_envs
        self.ratios = dict(ratios or {})  # name -> envs.tasks.Ratio
        self.mesh = Mesh(np.array(devices), ("envs",))
        self._sharded = NamedSharding(self.mesh, P("envs"))
        self.optimizer = optax.chain(
            optax.clip_by_global_norm(config.grad_norm_clip)
            if config.grad_norm_clip > 0
            else optax.identity(),
            optax.inject_hyperparams(optax.adam)(learning_rate=config.learning_rate),
        )

    @property
    def transitions_per_iteration(self) -> int:
        return self.num_envs * self.config.rollouts

    def _shard_envs(self, tree):
        return jax.lax.with_sharding_constraint(tree, self._sharded)

    def init(self, key: jax.Array) -> TrainState:
        k_net, k_env, key = jax.random.split(key, 3)
        env_state = self._shard_envs(self.env.reset(jax.random.split(k_env, self.num_envs)))
        params = self.network.init(k_net, env_state.obs[:1])
        obs_stats = RunningStats.zeros(env_state.obs.shape[1:])
        return TrainState(
            params=params,
            opt_state=self.optimizer.init(params),
            obs_stats=obs_stats,
            value_stats=RunningStats.zeros(),
            env_state=env_state,
            key=key,
            iteration=jnp.int32(0),
            learning_rate=jnp.float32(self.config.learning_rate),
        )

    def policy(self, params, obs_stats: RunningStats, obs, key=None):
        """Actions for raw observations: the mean clipped to [-1, 1] if ``key`` is None, else a
        sample (``networks.make_inference_fn``)."""
        make_policy = networks.make_inference_fn(self.network, self.config.obs_clip)
        return make_policy(params, obs_stats.mean, obs_stats.std, deterministic=key is None)(obs, key)

    def _rollout(self, s: TrainState):
        cfg = self.config

        def step(carry, _):
            env_state, key = carry
            key, k_act = jax.random.split(key)
            obs = env_state.obs
            mean, log_std, value = self.network.apply(s.params, s.obs_stats.normalize(obs, cfg.obs_clip))
            log_std = jnp.clip(log_std, *LOG_STD_RANGE)
            action = mean + jnp.exp(log_std) * jax.random.normal(k_act, mean.shape)
            nxt = self._shard_envs(self.env.step(env_state, action))
            out = {
                "obs": obs,
                "action": action,
                "log_prob": gaussian_log_prob(mean, log_std, action),
                "value": s.value_stats.denormalize(value),
                "reward": nxt.reward,
                "done": nxt.done,
                "episode_done": nxt.info["episode_done"],
                "episode_return": nxt.info["completed_return"],
                "episode_length": nxt.info["completed_length"],
                "metrics": nxt.metrics,
            }
            return (nxt, key), out

        (env_state, key), traj = jax.lax.scan(step, (s.env_state, s.key), None, cfg.rollouts)
        _, _, last = self.network.apply(s.params, s.obs_stats.normalize(env_state.obs, cfg.obs_clip))
        return env_state, key, traj, s.value_stats.denormalize(last)

    def update(self, s: TrainState):
        """One PPO iteration; returns the new state and a dict of scalar metrics."""
        cfg = self.config
        env_state, key, traj, last_value = self._rollout(s)
        adv, returns = gae(traj["reward"], traj["value"], traj["done"], last_value, cfg.gamma, cfg.lam)
        adv = (adv - jnp.mean(adv)) / (jnp.std(adv) + 1e-8)
        value_stats = s.value_stats.update(returns)

        flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731
        data = {
            "obs": s.obs_stats.normalize(flat(traj["obs"]), cfg.obs_clip),
            "action": flat(traj["action"]),
            "log_prob": flat(traj["log_prob"]),
            "value": value_stats.normalize(flat(traj["value"])),
            "returns": value_stats.normalize(flat(returns)),
            "advantage": flat(adv),
        }
        if cfg.shield_scale > 0:
            data["raw_obs"] = flat(traj["obs"])
        if s.anchor is not None:  # the start policy's mean on the same observations, in one batch
            anchor_obs = s.anchor["obs_stats"].normalize(flat(traj["obs"]), cfg.obs_clip)
            data["anchor_mean"] = self.network.apply(s.anchor["params"], anchor_obs)[0]
        n = self.transitions_per_iteration
        grad_fn = jax.value_and_grad(ppo_loss, has_aux=True)

        def minibatch(carry, mb):
            params, opt_state = carry
            (_, parts), grads = grad_fn(params, self.network.apply, mb, cfg, self.shield)
            updates, opt_state = self.optimizer.update(grads, opt_state, params)
            parts["grad_norm"] = optax.tree.norm(grads)
            return (optax.apply_updates(params, updates), opt_state), parts

        def epoch(carry, k):
            params, opt_state, lr = carry
            inject = opt_state[1]
            opt_state = (
                opt_state[0],
                inject._replace(hyperparams={**inject.hyperparams, "learning_rate": lr}),
            )
            perm = jax.random.permutation(k, n).reshape(cfg.minibatches, -1)
            mbs = jax.tree.map(lambda x: x[perm], data)
            (params, opt_state), parts = jax.lax.scan(minibatch, (params, opt_state), mbs)
            parts = jax.tree.map(jnp.mean, parts)
            return (params, opt_state, adapt_learning_rate(lr, parts["policy/kl"], cfg)), parts

        key, k_epochs = jax.random.split(key)
        (params, opt_state, lr), parts = jax.lax.scan(
            epoch, (s.params, s.opt_state, s.learning_rate), jax.random.split(k_epochs, cfg.epochs)
        )
        state = TrainState(
            params=params,
            opt_state=opt_state,
            obs_stats=s.obs_stats.update(traj["obs"]),
            value_stats=value_stats,
            env_state=env_state,
            key=key,
            iteration=s.iteration + 1,
            learning_rate=lr,
            anchor=s.anchor,
        )
        return state, self._metrics(traj, parts, lr, params)

    def fit_critic(self, s: TrainState, iterations: int, learning_rate: float = 1e-3):
        """``iterations`` rollouts in which only the critic's own layers learn (those named
        ``value`` or ``critic*``, see :func:`critic_mask`), by Adam of their own on the squared
        error to the standardised returns; the actor, the PPO optimiser, the learning rate and the
        iteration count stay as they are (the statistics and environments move on).

        For a run started from an exported policy, which carries no critic: a random value head on
        the actor's shared body makes the first PPO update's advantages noise, and their gradient
        moves the policy far. Returns the state and the mean value loss of each iteration."""
        cfg = self.config
        mask = critic_mask(s.params)
        opt = optax.multi_transform({True: optax.adam(learning_rate), False: optax.set_to_zero()}, mask)
        flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731

        def loss(params, obs, target):
            return jnp.mean((self.network.apply(params, obs)[2] - target) ** 2)

        def one(carry, _):
            s, opt_state = carry
            env_state, key, traj, last_value = self._rollout(s)
            _, returns = gae(traj["reward"], traj["value"], traj["done"], last_value, cfg.gamma, cfg.lam)
            value_stats = s.value_stats.update(returns)
            obs = s.obs_stats.normalize(flat(traj["obs"]), cfg.obs_clip)
            target = value_stats.normalize(flat(returns))
            key, k_perm = jax.random.split(key)

            def epoch(carry, k):
                perm = jax.random.permutation(k, obs.shape[0]).reshape(cfg.minibatches, -1)

                def minibatch(carry, idx):
                    params, opt_state = carry
                    value, grads = jax.value_and_grad(loss)(params, obs[idx], target[idx])
                    updates, opt_state = opt.update(grads, opt_state, params)
                    return (optax.apply_updates(params, updates), opt_state), value

                return jax.lax.scan(minibatch, carry, perm)

            (params, opt_state), losses = jax.lax.scan(
                epoch, (s.params, opt_state), jax.random.split(k_perm, cfg.epochs)
            )
            s = s.replace(
                params=params,
                obs_stats=s.obs_stats.update(traj["obs"]),
                value_stats=value_stats,
                env_state=env_state,
                key=key,
            )
            return (s, opt_state), jnp.mean(losses)

        (s, _), losses = jax.lax.scan(one, (s, opt.init(s.params)), None, iterations)
        return s, losses

    def _metrics(self, traj, parts, lr, params) -> dict[str, jax.Array]:
        ended = traj["episode_done"]
        episodes = jnp.sum(ended)
        per_episode = lambda x: jnp.sum(x * ended) / jnp.maximum(episodes, 1.0)  # noqa: E731
        m = {k: jnp.mean(v) for k, v in traj["metrics"].items()}
        for name, ratio in self.ratios.items():  # shares of events (envs.tasks.Ratio)
            events = jnp.sum(traj["metrics"][ratio.denominator])
            m[name] = jnp.sum(traj["metrics"][ratio.numerator]) / jnp.maximum(events, 1.0)
            m[ratio.count] = events
        m.update({k: v[-1] for k, v in parts.items()})  # the last epoch's
        m.update(
            {
                "episode/return": per_episode(traj["episode_return"]),
                "episode/length": per_episode(traj["episode_length"]),
                "episode/count": episodes,
                "reward/step": jnp.mean(traj["reward"]),
                "learning_rate": lr,
                "finite": all_finite(params).astype(jnp.float32) * jnp.isfinite(parts["loss/value"][-1]),
            }
        )
        return m

    def run(self, state: TrainState, iterations: int):
        """``iterations`` updates under one ``lax.scan``; metrics stacked along the first axis."""
        return jax.lax.scan(lambda s, _: self.update(s), state, None, iterations)

    def run_upto(self, state: TrainState, count: jax.Array, size: int):
        """The first ``count`` (traced, at most ``size``) of ``size`` scanned steps update the state,
        the rest pass it through: any number of iterations up to ``size`` in one compiled call.
        Metrics are stacked along the first axis; rows from ``count`` on are zeros."""
        shapes = jax.eval_shape(self.update, state)[1]
        idle = {k: jnp.zeros(v.shape, v.dtype) for k, v in shapes.items()}

        def step(s, i):
            return jax.lax.cond(i < count, self.update, lambda s: (s, idle), s)

        return jax.lax.scan(step, state, jnp.arange(size))

    def train(self, key: jax.Array, iterations: int):
        """Pure: ``init`` then ``iterations`` updates. ``jax.vmap`` it over keys for several seeds."""
        return self.run(self.init(key), iterations)
