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

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

ENCODER_CHANNELS = (64, 32, 32, 32)
ENCODER_KERNELS = (8, 5, 3, 3)
ENCODER_STRIDES = (4, 3, 1, 1)


class LidarEncoder(nn.Module):
    """Ranges ``(..., num_rays)`` -> latent ``(..., latent)``."""

    channels: Sequence[int] = ENCODER_CHANNELS
    kernels: Sequence[int] = ENCODER_KERNELS
    strides: Sequence[int] = ENCODER_STRIDES
    latent: int = 64

    @nn.compact
    def __call__(self, ranges: jax.Array) -> jax.Array:
        x = ranges[..., None]
        for i, (c, k, s) in enumerate(zip(self.channels, self.kernels, self.strides, strict=True)):
            x = nn.elu(nn.Conv(c, (k,), strides=(s,), padding="VALID", name=f"conv{i}")(x))
        x = x.reshape(*x.shape[:-2], -1)
        return nn.elu(nn.Dense(self.latent, name="project")(x))


class ActorCritic(nn.Module):
    """SU / NavRL network: ``obs (..., num_rays + state) -> (mean, log_std, value)``."""

    action_size: int = 3
    num_rays: int = 720
    hidden: Sequence[int] = (512, 512, 512)
    encoder: LidarEncoder = LidarEncoder()

    @nn.compact
    def __call__(self, obs: jax.Array):
        latent = self.encoder(obs[..., : self.num_rays])
        x = jnp.concatenate([latent, obs[..., self.num_rays :]], -1)
        for i, h in enumerate(self.hidden):
            x = nn.elu(nn.Dense(h, name=f"body{i}")(x))
        mean = nn.Dense(self.action_size, name="policy")(x)
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_size,))
        value = nn.Dense(1, name="value")(x)[..., 0]
        return mean, jnp.broadcast_to(log_std, mean.shape), value


class GuidePolicy(nn.Module):
    """GuideRL's policy: ``obs (..., 15) -> (mean, log_std)`` (the critic is a separate MLP)."""

    action_size: int = 1
    hidden: Sequence[int] = (128, 128)

    @nn.compact
    def __call__(self, obs: jax.Array):
        x = obs
        for i, h in enumerate(self.hidden):
            x = nn.elu(nn.Dense(h, name=f"hidden{i}")(x))
        mean = nn.Dense(self.action_size, name="policy")(x)
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_size,))
        return mean, jnp.broadcast_to(log_std, mean.shape)


def count(params) -> int:
    """Number of scalars in a parameter pytree."""
    return int(sum(np.prod(p.shape) for p in jax.tree.leaves(params)))


def policy_count(params) -> int:
    """Parameters of the policy path (everything but the value head), as the thesis counts them."""
    return count(params) - count(params["params"].get("value", {}))
