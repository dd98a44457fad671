"""Auto-reset and episode bookkeeping for batches of our environments.

Brax's own ``AutoResetWrapper`` restarts an episode from its *first* state, which would replay the
same floor, users and spawn forever; ours draws a fresh episode from ``reset`` with a key derived
from the world's own key. And it resets only the environments that finished: under ``vmap`` a
``where(done, reset(...), next)`` computes a full reset (floor, spawn search, LiDAR scan) for every
environment on every step, which measured 12x slower than stepping alone at 2048 environments. So
this wrapper works on whole batches: it gathers the finished environments in chunks, resets those,
and scatters them back, inside one ``lax.while_loop``.

Episode return and length are kept in ``info`` and published when an episode ends
(``info["episode_done"]`` marks those steps), so logging can average completed episodes on device.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State

_OURS = (
    "terminal_obs",
    "episode_return",
    "episode_length",
    "episode_done",
    "completed_return",
    "completed_length",
)


class AutoReset:
    """Batched ``reset(keys) -> State`` and ``step(states, actions) -> State`` with auto-reset.

    On ``done``, the next state is a fresh episode: ``reward``, ``done`` and ``metrics`` stay the
    finished step's (for learning), ``obs`` and ``pipeline_state`` are the new episode's, and
    ``info["terminal_obs"]`` keeps the finished step's observation for bootstrapping truncated
    episodes (``info["truncation"]`` is the inner environment's).
    """

    def __init__(self, env: Env, resets_per_pass: int | None = None):
        """``resets_per_pass``: environments reset per loop pass (default: 1/128 of the batch)."""
        self.env = env
        self.resets_per_pass = resets_per_pass

    @property
    def observation_size(self):
        return self.env.observation_size

    @property
    def action_size(self):
        return self.env.action_size

    def reset(self, keys: jax.Array) -> State:
        state = jax.vmap(self.env.reset)(keys)
        zero = jnp.zeros(keys.shape[0])
        info = {
            **state.info,
            "terminal_obs": state.obs,
            "episode_return": zero,
            "episode_length": zero,
            "episode_done": zero,
            "completed_return": zero,
            "completed_length": zero,
        }
        return state.replace(info=info)

    def step(self, state: State, action: jax.Array) -> State:
        inner_info = {k: v for k, v in state.info.items() if k not in _OURS}
        nxt = jax.vmap(self.env.step)(state.replace(info=inner_info), action)
        done = nxt.done > 0
        n = done.shape[0]
        chunk = self.resets_per_pass or max(1, n // 128)
        keys = jax.vmap(lambda k: jax.random.fold_in(k, 0x5EED))(nxt.pipeline_state.key)

        def reset_some(carry):
            world, obs, todo = carry
            idx = jnp.nonzero(todo, size=chunk, fill_value=n)[0]  # n: out of range, dropped below
            fresh = jax.vmap(self.env.reset)(keys[jnp.minimum(idx, n - 1)])
            world = jax.tree.map(
                lambda old, new: old.at[idx].set(new, mode="drop"), world, fresh.pipeline_state
            )
            obs = obs.at[idx].set(fresh.obs, mode="drop")
            return world, obs, todo.at[idx].set(False, mode="drop")

        world, obs, _ = jax.lax.while_loop(
            lambda c: jnp.any(c[2]), reset_some, (nxt.pipeline_state, nxt.obs, done)
        )
        ret = state.info["episode_return"] + nxt.reward
        length = state.info["episode_length"] + 1.0
        info = {
            **nxt.info,
            "terminal_obs": nxt.obs,
            "episode_return": jnp.where(done, 0.0, ret),
            "episode_length": jnp.where(done, 0.0, length),
            "episode_done": done.astype(jnp.float32),
            "completed_return": jnp.where(done, ret, state.info["completed_return"]),
            "completed_length": jnp.where(done, length, state.info["completed_length"]),
        }
        return nxt.replace(pipeline_state=world, obs=obs, info=info)
