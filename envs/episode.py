"""One episode of an environment, recorded step by step as a :class:`methd_jax.viz.Rollout`.

``record(env, key, steps, policy)`` runs a single episode under ``jit`` (one ``lax.scan``; the
world freezes once the episode ends, so every array has ``steps + 1`` rows). It reads the
environment's world, so it lives here beside the environments; the pictures drawn from it live in
:mod:`methd_jax.viz`, which needs no environment.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from envs.guide import GuideEnv
from envs.nav import NavEnv
from methd_jax import floors
from methd_jax import robot as robot_lib
from methd_jax.control import CONTROL_DT
from methd_jax.viz.episode import Rollout


def zero_policy(action_size: int) -> Callable[[jax.Array], jax.Array]:
    """The robot stands still (GuideRL keeps u_w): the default when no trained policy is given."""
    return lambda obs: jnp.zeros(action_size)


def _episode(env, key: jax.Array, steps: int, policy, snapshot) -> tuple[dict, object]:
    """``snapshot(state, action)`` of the reset state (action 0) and after each of ``steps`` steps
    under ``policy``, in one jitted ``lax.scan`` (the state freezes once the episode ends), as
    numpy arrays with ``steps + 1`` rows; and the final state."""
    if steps < 1:
        raise ValueError(f"steps must be at least 1, got {steps}")
    policy = policy or zero_policy(env.action_size)

    def body(state, _):
        action = policy(state.obs)
        nxt = env.step(state, action)
        state = jax.tree.map(lambda old, new: jnp.where(state.done > 0, old, new), state, nxt)
        return state, snapshot(state, action)

    @jax.jit
    def run(key):
        state = env.reset(key)
        first = snapshot(state, jnp.zeros(env.action_size))
        state, rest = jax.lax.scan(body, state, None, length=steps)
        return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, rest), state

    rows, state = run(key)
    return {k: np.asarray(v) for k, v in rows.items()}, state


def trace(env, key: jax.Array, steps: int, policy: Callable[[jax.Array], jax.Array] | None = None) -> dict:
    """``steps`` control steps of one episode of any environment of the task table, as numpy arrays
    ``obs (steps + 1, D)``, ``action (steps, A)``, ``reward (steps,)``, ``done (steps,)`` (the state
    freezes once the episode ends, so rows after the first ``done`` repeat it)."""

    def snapshot(state, action):
        return {"obs": state.obs, "action": action, "reward": state.reward, "done": state.done > 0}

    rows, _ = _episode(env, key, steps, policy, snapshot)
    return {"obs": rows["obs"], **{k: rows[k][1:] for k in ("action", "reward", "done")}}


def record(
    env: NavEnv | GuideEnv,
    key: jax.Array,
    steps: int,
    policy: Callable[[jax.Array], jax.Array] | None = None,
) -> Rollout:
    """``steps`` control steps of one episode of ``env`` (from ``envs.make``) driven by
    ``policy(obs) -> action`` (deterministic, e.g. ``train.export.load(run)``; default
    :func:`zero_policy`)."""
    if not isinstance(env, NavEnv | GuideEnv):
        raise TypeError(f"record needs an environment from envs.make, got {type(env).__name__}")
    is_nav = isinstance(env, NavEnv)

    def snapshot(state) -> dict:
        w = state.pipeline_state
        feats = jax.vmap(env.bank.at, (0, None))(w.users, w.t)
        out = {
            "t": w.t,
            "users": feats["pose"],
            "hips": feats["hip"],
            "requested": w.t >= w.request_step,
            "done": state.done > 0,
            "u_w": w.u_w,
            "success": state.metrics.get("success", jnp.float32(0.0)) > 0,
            "obstacle": state.metrics.get("collision_obstacle", jnp.float32(0.0)) > 0,
            "user": state.metrics.get("collision_user", jnp.float32(0.0)) > 0,
        }
        if is_nav:
            out |= {
                "robot": robot_lib.pose(w.robot),
                "goal": w.goal,
                "ranges": state.obs[env.observation_layout["lidar"]],
            }
        return out

    rows, state = _episode(env, key, steps, policy, lambda state, action: snapshot(state))
    requester, floor = state.pipeline_state.requester, state.pipeline_state.floor if is_nav else None
    outcome = "running"
    if rows["done"].any():
        end = int(np.argmax(rows["done"]))
        flags = [rows["obstacle"][end], rows["user"][end]]
        outcome = "obstacle collision" if flags[0] else "user collision" if flags[1] else "time limit"
        # GuideRL reports no success flag: an episode it ends before the limit is a success
        if rows["success"][end] or (not is_nav and rows["requested"][end]):
            outcome = "success"
    if is_nav:
        cfg = env.config
        extra = {
            "robot": rows["robot"],
            "goal": rows["goal"],
            "ranges": rows["ranges"],
            "lidar_range": float(cfg.lidar_range),
            "collision_distance": cfg.safety.collision_distance,
            "critical_distance": cfg.safety.critical_distance,
            "u_w": rows["u_w"] if cfg.num_users == 2 else None,
        }
        name = "su" if cfg.num_users == 1 else "nav"
        floor = jax.tree.map(np.asarray, floor)
    else:  # GuideRL has no floor; its users walk in the lab twin, where the motion data lives
        floor = jax.tree.map(np.asarray, floors.lab())
        extra = {"u_w": rows["u_w"]}
        name = "guide"
    return Rollout(
        env=name,
        floor=floor,
        t=rows["t"] * CONTROL_DT,
        users=rows["users"],
        hips=rows["hips"],
        requested=rows["requested"],
        done=rows["done"],
        requester=int(requester),
        outcome=outcome,
        **extra,
    )
