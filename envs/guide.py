"""GuideRL (``guide``, thesis §4.2.2): predict which of two users will request haptics next.

State (15, eq. 4.24): both users' velocities and accelerations in their own frames (3 + 3 + 3 + 3),
the user weight u_w, and the two previous actions. Action: one value in [-1, 1], scaled to a change
of u_w of at most 0.05 (eq. 4.25); u_w <- clip(u_w + delta, -1, 1). Kinematics only: no robot.

Rewards (Table 4.2): r_m = max(1 - 4 |u_w|, 0) (weight 5) and p_a (eq. 4.14, weight -0.05) every
step, and r_c = -u_w if user 1 requested, +u_w if user 2 (weight 20). The request fires when the
first of the two trajectories reaches its own request; a 5 s cooldown follows and the episode ends.

Interpretation (see the issue note): the thesis calls r_c terminal, yet with r_m paid every step
a single r_c of 20 is worth less than the r_m forgone while moving u_w from 0 to +-1 (20 steps at
0.05), so a return-maximising policy would never commit, contrary to the 99% accuracy reported.
We pay r_c at every step of the cooldown after the request, which makes committing early
worthwhile. ``accuracy`` (the sign of u_w at the request matches the requester) is reported at the
request step.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State
from flax import struct

from envs.nav import GUIDE_MAX_DELTA, guide_observation, load_bank
from methd_jax.motion.features import CONTROL_HZ, HipConfig, MotionBank


@dataclasses.dataclass(frozen=True)
class GuideWeights:
    """Table 4.2."""

    correct: float = 20.0
    midpoint: float = 5.0
    action_smoothness: float = -0.05


@dataclasses.dataclass(frozen=True)
class GuideConfig:
    """Static configuration of ``guide``."""

    motion: str = "default"
    """User trajectories: "default", "sample", or a path to MCAP bags (see NavConfig)."""
    split: str = "train"
    """"train", "test" or "all"."""
    weights: GuideWeights = GuideWeights()
    """Reward weights."""
    cooldown: float = 5.0
    """Seconds after the request until the episode ends (r_c is paid throughout)."""
    time_limit: float = 120.0
    """Episodes are truncated after this many seconds."""

    def __post_init__(self):
        if self.split not in ("train", "test", "all"):
            raise ValueError(f"split must be 'train', 'test' or 'all', got {self.split!r}")
        if not (self.cooldown > 0 and self.time_limit > 0):
            raise ValueError("cooldown and time_limit must be positive")


@struct.dataclass
class GuideWorld:
    users: jax.Array  # (2,) int32 trajectories
    t: jax.Array  # () int32 control steps since reset
    request_step: jax.Array  # () int32 the first user's request
    requester: jax.Array  # () int32 0 or 1
    u_w: jax.Array  # () user weight in [-1, 1]
    actions: jax.Array  # (2,) a_{t-1}, a_{t-2}
    key: jax.Array


class GuideEnv(Env):
    """``guide``: move the user weight toward whoever will request next."""

    def __init__(self, config: GuideConfig = GuideConfig(), *, bank: MotionBank | None = None):
        self.config = config
        self.bank = bank if bank is not None else load_bank(config.motion, config.split, HipConfig())
        if self.bank.num_trajectories < 2:
            raise ValueError("guide needs at least two trajectories")
        self._cooldown_steps = round(config.cooldown * CONTROL_HZ)
        self._limit_steps = round(config.time_limit * CONTROL_HZ)

    @property
    def observation_size(self) -> int:
        return 15

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "kinematic"

    def _observe(self, w: GuideWorld) -> jax.Array:
        feats = jax.vmap(self.bank.at, (0, None))(w.users, w.t)
        return guide_observation(feats["vel_local"], feats["acc_local"], w.u_w, w.actions)

    def reset(self, rng: jax.Array) -> State:
        k_users, key = jax.random.split(rng)
        users = jax.random.choice(k_users, self.bank.num_trajectories, (2,), replace=False)
        req = self.bank.request_step[users]
        w = GuideWorld(
            users=users,
            t=jnp.int32(0),
            request_step=jnp.min(req),
            requester=jnp.argmin(req).astype(jnp.int32),
            u_w=jnp.float32(0.0),
            actions=jnp.zeros(2),
            key=key,
        )
        zero = jnp.float32(0.0)
        metrics = {k: zero for k in self._metric_names()}
        return State(
            pipeline_state=w,
            obs=self._observe(w),
            reward=zero,
            done=zero,
            metrics=metrics,
            info={"truncation": zero},
        )

    @staticmethod
    def _metric_names():
        return (
            "reward/correct",
            "reward/midpoint",
            "reward/action_smoothness",
            "u_w",
            "at_request",
            "correct_at_request",
            "requested",
        )

    def step(self, state: State, action: jax.Array) -> State:
        cfg = self.config
        w: GuideWorld = state.pipeline_state
        a = jnp.clip(jnp.reshape(action, ()), -1.0, 1.0)
        u_w = jnp.clip(w.u_w + GUIDE_MAX_DELTA * a, -1.0, 1.0)
        t = w.t + 1
        requested = t >= w.request_step
        sign = jnp.where(w.requester == 0, -1.0, 1.0)  # eq. 4.26: -u_w for user 1, +u_w for user 2
        r_c = jnp.where(requested, sign * u_w, 0.0)
        r_m = jnp.maximum(1.0 - 4.0 * jnp.abs(u_w), 0.0)  # eq. 4.27
        p_a = (a - w.actions[0]) ** 2 + (a - 2 * w.actions[0] + w.actions[1]) ** 2
        weighted = {
            "reward/correct": cfg.weights.correct * r_c,
            "reward/midpoint": cfg.weights.midpoint * r_m,
            "reward/action_smoothness": cfg.weights.action_smoothness * p_a,
        }
        at_request = t == w.request_step
        success = t >= w.request_step + self._cooldown_steps
        timeout = t >= self._limit_steps
        w = w.replace(t=t, u_w=u_w, actions=jnp.stack([a, w.actions[0]]))
        metrics = {
            **state.metrics,  # keep keys that wrappers put there (Brax's trainer adds "reward")
            **weighted,
            "u_w": u_w,
            "at_request": at_request.astype(jnp.float32),
            "correct_at_request": (at_request & (jnp.sign(u_w) == sign)).astype(jnp.float32),
            "requested": requested.astype(jnp.float32),
        }
        return state.replace(
            pipeline_state=w,
            obs=self._observe(w),
            reward=sum(weighted.values()),
            done=(success | timeout).astype(jnp.float32),
            metrics=metrics,
            info={**state.info, "truncation": (timeout & ~success).astype(jnp.float32)},
        )
