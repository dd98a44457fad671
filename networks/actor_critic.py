"""The thesis's networks as Flax modules (§4.1.1, §4.2.1, §4.2.2, Figs. 4.4, 4.6 and 4.7).

``ActorCritic`` (SU and NavRL): a conv1d encoder over the 720 LiDAR ranges (kernels 8, 5, 3, 3;
strides 4, 3, 1, 1; valid padding: 720 -> 179 -> 59 -> 57 -> 55), flattened and projected to a
64-d latent, concatenated with the non-LiDAR state, then an MLP of 3 x 512 ELU shared by actor and
critic, a policy head (mean of a Gaussian with a state-independent log-std) and a value head.

The thesis gives the parameter counts but not the channel widths. Its counts pin the shared body:
NavRL - SU = 706,770 - 702,674 = 4,096 = 8 extra inputs x 512, and they exclude the value head.
That leaves 129,740 parameters for the encoder; channels (64, 32, 32, 32) give 129,760, so the
policy has 702,694 (SU) and 706,790 (NavRL) parameters, 0.003% above the thesis's.

``GuidePolicy``: 15 -> 128 -> 128 -> 1 with ELU, plus a log-std: exactly 18,690 parameters.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from methd_jax.normalise import normalise

ENCODER_CHANNELS = (64, 32, 32, 32)
ENCODER_KERNELS = (8, 5, 3, 3)
ENCODER_STRIDES = (4, 3, 1, 1)


def _conv(x: jax.Array, w: jax.Array, stride: int) -> jax.Array:
    return jax.lax.conv_general_dilated(x, w, (stride,), "VALID", dimension_numbers=("NWC", "WIO", "NWC"))


def _conv_im2col(x: jax.Array, w: jax.Array, stride: int) -> jax.Array:
    # Patches from contiguous blocks of ``stride`` samples (reshapes, slices and one concatenation:
    # no strided slicing, whose gradients XLA:CPU runs slowly), then a single 2D matrix product.
    k, c = w.shape[0], x.shape[-1]
    n = (x.shape[-2] - k) // stride + 1
    blocks_per_patch = -(-k // stride)
    num_blocks = n + blocks_per_patch - 1
    length = num_blocks * stride
    if length > x.shape[-2]:  # the padding lies beyond the last patch's k samples: never used
        x = jnp.pad(x, ((0, 0), (0, length - x.shape[-2]), (0, 0)))
    blocks = x[:, :length].reshape(x.shape[0], num_blocks, stride, c)
    patches = jnp.concatenate([blocks[:, j : j + n] for j in range(blocks_per_patch)], axis=2)[:, :, :k]
    out = patches.reshape(-1, k * c) @ w.reshape(k * c, -1)
    return out.reshape(x.shape[0], n, -1)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv1d(x: jax.Array, w: jax.Array, stride: int) -> jax.Array:
    """Valid 1D convolution ``(B, L, Cin) x (k, Cin, Cout) -> (B, L', Cout)``.

    Forward is XLA's convolution; the gradient is that of the same convolution written as patches
    times a matrix. XLA:CPU computes strided-convolution gradients inside a while loop (as in
    PPO's scanned minibatches) on a slow path, 20-30x slower than outside one; the patch form
    runs at one speed everywhere (measured in the issue-5 note).
    """
    return _conv(x, w, stride)


def _conv1d_fwd(x, w, stride):
    return _conv(x, w, stride), (x, w)


def _conv1d_bwd(stride, residuals, g):
    x, w = residuals
    return jax.vjp(lambda x, w: _conv_im2col(x, w, stride), x, w)[1](g)


conv1d.defvjp(_conv1d_fwd, _conv1d_bwd)


class Outputs(NamedTuple):
    """What the actor-critics return, by name: PPO, export, the benchmark's peers and the tests read
    these fields rather than positions."""

    mean: jax.Array  # (..., A) the Gaussian's mean; the deterministic action is clip(mean, -1, 1)
    log_std: jax.Array  # (..., A) its log standard deviation
    value: jax.Array  # (...,) the critic's value estimate


LOG_STD_RANGE = (-20.0, 2.0)
"""The policy's log standard deviation is clipped to this range (skrl's defaults)."""


def make_inference_fn(network: nn.Module, obs_clip: float):
    """Brax-style policy factory for the actor-critics above: ``make_policy(params, obs_mean,
    obs_std, deterministic=True)`` returns ``policy(obs, key=None) -> action`` that normalises
    raw observations (:func:`methd_jax.normalise.normalise`, clipped to ``obs_clip``) and returns
    the Gaussian's mean clipped to [-1, 1], or with ``deterministic=False`` a sample (unclipped:
    the environments clip, PPO scores the sample). PPO's acting, exported policies and the tests
    go through it."""

    def make_policy(params, obs_mean, obs_std, deterministic: bool = True):
        def policy(obs: jax.Array, key: jax.Array | None = None) -> jax.Array:
            out = network.apply(params, normalise(obs, obs_mean, obs_std, obs_clip))
            if deterministic:
                return jnp.clip(out.mean, -1.0, 1.0)
            std = jnp.exp(jnp.clip(out.log_std, *LOG_STD_RANGE))
            return out.mean + std * jax.random.normal(key, out.mean.shape)

        return policy

    return make_policy


class Conv1D(nn.Module):
    """``nn.Conv`` with valid padding and the parameters of ``nn.Conv`` (``kernel (k, Cin, Cout)``,
    ``bias``), computed by :func:`conv1d`; any number of leading batch axes."""

    features: int
    kernel_size: int
    stride: int = 1

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        kernel = self.param(
            "kernel", nn.initializers.lecun_normal(), (self.kernel_size, x.shape[-1], self.features)
        )
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        lead = x.shape[:-2]
        y = conv1d(x.reshape(-1, *x.shape[-2:]), kernel, self.stride)
        return y.reshape(*lead, *y.shape[-2:]) + bias


class LidarEncoder(nn.Module):
    """Ranges ``(..., num_rays)`` -> latent ``(..., latent)``."""

    channels: Sequence[int] = ENCODER_CHANNELS
    kernels: Sequence[int] = ENCODER_KERNELS
    strides: Sequence[int] = ENCODER_STRIDES
    latent: int = 64

    @nn.compact
    def __call__(self, ranges: jax.Array) -> jax.Array:
        length = ranges.shape[-1]
        for k, s in zip(self.kernels, self.strides, strict=True):
            length = (length - k) // s + 1
        if length < 1:
            raise ValueError(f"{ranges.shape[-1]} rays are too few for the encoder's kernels and strides")
        x = ranges[..., None]
        for i, (c, k, s) in enumerate(zip(self.channels, self.kernels, self.strides, strict=True)):
            x = nn.elu(Conv1D(c, k, s, name=f"conv{i}")(x))
        x = x.reshape(*x.shape[:-2], -1)
        return nn.elu(nn.Dense(self.latent, name="project")(x))


class ActorCritic(nn.Module):
    """SU / NavRL network: ``obs (..., num_rays + state) -> (mean, log_std, value)``."""

    action_size: int = 3
    num_rays: int = 720
    hidden: Sequence[int] = (512, 512, 512)
    encoder: LidarEncoder = LidarEncoder()
    init_log_std: float = 0.0

    @nn.compact
    def __call__(self, obs: jax.Array):
        latent = self.encoder(obs[..., : self.num_rays])
        x = jnp.concatenate([latent, obs[..., self.num_rays :]], -1)
        for i, h in enumerate(self.hidden):
            x = nn.elu(nn.Dense(h, name=f"body{i}")(x))
        mean = nn.Dense(self.action_size, name="policy")(x)
        log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.action_size,))
        value = nn.Dense(1, name="value")(x)[..., 0]
        return Outputs(mean, jnp.broadcast_to(log_std, mean.shape), value)

    def policy_layers(self) -> dict:
        """The policy's forward pass as data, for runtimes outside JAX (``methd_jax.deploy``):
        parameter paths as ``train.export`` writes them to ``params.npz``; ELU after every layer
        but ``mean``."""
        return {
            "activation": "elu",
            "encoder": {
                "input": self.num_rays,
                "conv": [
                    {"params": f"params/encoder/conv{i}", "stride": s}
                    for i, s in enumerate(self.encoder.strides)
                ],
                "project": "params/encoder/project",
            },
            "body": [f"params/body{i}" for i in range(len(self.hidden))],
            "mean": "params/policy",
        }


def _check_fields(source_fields: dict, target_fields: dict) -> None:
    """The target observation must hold every source field with as many values."""
    missing = sorted(set(source_fields) - set(target_fields))
    if missing:
        raise ValueError(f"the target observation lacks the source's fields {missing}")
    for name, (a, b) in source_fields.items():
        if target_fields[name][1] - target_fields[name][0] != b - a:
            raise ValueError(f"field {name!r} has {b - a} values in the source, not in the target")


def transfer_inputs(
    source: dict, target: dict, num_rays: int, source_fields: dict, target_fields: dict
) -> dict:
    """:class:`ActorCritic` parameters ``source`` carried over to a network whose observation has
    other fields: ``target`` (the new network's initial parameters) with every array of ``source``,
    except that the first body layer's rows for the non-LiDAR inputs are rearranged by field name
    (``*_fields``: name -> (start, stop) in the observation, LiDAR first). A field only the target
    has gets zero rows, so the carried-over network starts out ignoring it. Every other array must
    have the same shape in both."""
    src, dst = source["params"], target["params"]
    _check_fields(source_fields, target_fields)
    out = jax.tree.map(lambda x: x, src)
    for path, leaf in jax.tree_util.tree_leaves_with_path(dst):
        theirs = functools.reduce(lambda d, k: d[k.key], path, src)
        if path[0].key != "body0" and theirs.shape != leaf.shape:
            name = "/".join(k.key for k in path)
            raise ValueError(f"{name}: shape {theirs.shape} in the source, {leaf.shape} in the target")
    kernel = src["body0"]["kernel"]
    latent = kernel.shape[0] - (max(b for _, b in source_fields.values()) - num_rays)
    rows = jnp.zeros((dst["body0"]["kernel"].shape[0], kernel.shape[1]), kernel.dtype)
    rows = rows.at[:latent].set(kernel[:latent])
    for name, (a, b) in source_fields.items():
        if a < num_rays:
            continue
        start = latent + target_fields[name][0] - num_rays
        rows = rows.at[start : start + b - a].set(kernel[latent + a - num_rays : latent + b - num_rays])
    if rows.shape[1] != dst["body0"]["kernel"].shape[1]:
        raise ValueError("body0: the source and target bodies have different widths")
    out["body0"] = {**src["body0"], "kernel": rows}
    return {"params": out}


def transfer_guide_inputs(source: dict, target: dict, source_fields: dict, target_fields: dict) -> dict:
    """:class:`GuideActorCritic` parameters ``source`` carried over to a network whose observation
    has more fields (``*_fields``: name -> (start, stop)): ``target``'s shapes with every array of
    ``source``, the rows of the two layers that read the observation (the actor's and the critic's
    first) rearranged by field name; a field only the target has gets zero rows, so the carried-over
    network starts out ignoring it."""
    src, dst = source["params"], target["params"]
    _check_fields(source_fields, target_fields)

    def rows(kernel, size):
        out = jnp.zeros((size, kernel.shape[1]), kernel.dtype)
        for name, (a, b) in source_fields.items():
            out = out.at[target_fields[name][0] : target_fields[name][0] + b - a].set(kernel[a:b])
        return out

    out = jax.tree.map(lambda x: x, src)
    first = (("actor", "hidden0"), ("critic0",))
    for path, leaf in jax.tree_util.tree_leaves_with_path(dst):
        keys = tuple(k.key for k in path)
        theirs = functools.reduce(lambda d, k: d[k], keys, src)
        if keys[:-1] in first and keys[-1] == "kernel":
            if theirs.shape[1] != leaf.shape[1]:
                raise ValueError(
                    f"{'/'.join(keys)}: width {theirs.shape[1]} in the source, {leaf.shape[1]} in the target"
                )
            functools.reduce(lambda d, k: d[k], keys[:-1], out)["kernel"] = rows(theirs, leaf.shape[0])
        elif theirs.shape != leaf.shape:
            raise ValueError(
                f"{'/'.join(keys)}: shape {theirs.shape} in the source, {leaf.shape} in the target"
            )
    return {"params": out}


class GuidePolicy(nn.Module):
    """GuideRL's policy: ``obs (..., 15) -> (mean, log_std)`` (the critic is a separate MLP)."""

    action_size: int = 1
    hidden: Sequence[int] = (128, 128)
    init_log_std: float = 0.0

    @nn.compact
    def __call__(self, obs: jax.Array):
        x = obs
        for i, h in enumerate(self.hidden):
            x = nn.elu(nn.Dense(h, name=f"hidden{i}")(x))
        mean = nn.Dense(self.action_size, name="policy")(x)
        log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.action_size,))
        return mean, jnp.broadcast_to(log_std, mean.shape)


class GuideActorCritic(nn.Module):
    """GuideRL for PPO: :class:`GuidePolicy` plus a critic of the same shape (15 -> 128 -> 128 -> 1,
    ELU) that shares nothing with it; ``obs -> (mean, log_std, value)``."""

    hidden: Sequence[int] = (128, 128)
    init_log_std: float = 0.0

    @nn.compact
    def __call__(self, obs: jax.Array):
        mean, log_std = GuidePolicy(hidden=self.hidden, init_log_std=self.init_log_std, name="actor")(obs)
        x = obs
        for i, h in enumerate(self.hidden):
            x = nn.elu(nn.Dense(h, name=f"critic{i}")(x))
        return Outputs(mean, log_std, nn.Dense(1, name="value")(x)[..., 0])

    def policy_layers(self) -> dict:
        """The policy's forward pass as data (see :meth:`ActorCritic.policy_layers`)."""
        return {
            "activation": "elu",
            "body": [f"params/actor/hidden{i}" for i in range(len(self.hidden))],
            "mean": "params/actor/policy",
        }


def count(params) -> int:
    """Number of scalars in a parameter pytree."""
    return int(sum(np.prod(p.shape) for p in jax.tree.leaves(params)))


def policy_count(params) -> int:
    """Parameters of the policy path (everything but the value head or critic), as the thesis counts them."""
    critic = [v for k, v in params["params"].items() if k == "value" or k.startswith("critic")]
    return count(params) - count(critic)
