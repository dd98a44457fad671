"""Environments of the thesis as pure JAX functions behind Brax's ``Env`` interface.

Every task is a row of the task table, :mod:`envs.tasks` (``envs.tasks.TASKS``):

- ``"su"``: single-user chase (N = 1, Table 4.1 weights), :class:`envs.nav.NavEnv`;
- ``"nav"``: NavRL (N = 2 by default, Table 4.3 weights; goal from a GuideRL policy handed in as
  ``policies={"guide": policy}`` or from the scripted source), :class:`envs.nav.NavEnv`;
- ``"guide"``: GuideRL, :class:`envs.guide.GuideEnv`.

``envs.make(name, **overrides)`` builds one; overrides are fields of the task's configuration
(:class:`envs.nav.NavConfig` / :class:`envs.guide.GuideConfig`, for example
``envs.make("su", lab=True, users_visible=True)``), plus ``bank=`` (a ``MotionBank``) and
``policies=``. Wrap with :class:`envs.wrappers.AutoReset` for training loops.
``envs.record(env, key, steps, policy)`` records one episode for pictures
(:class:`methd_jax.viz.Rollout`; the thesis's tasks), ``envs.trace`` one episode of any task as
arrays.
"""

from __future__ import annotations

import dataclasses

from envs import rewards, tasks
from envs.episode import record, trace, zero_policy
from envs.guide import GuideConfig, GuideEnv
from envs.nav import NavConfig, NavEnv, observation_layout
from envs.wrappers import AutoReset


def make(name: str, **overrides):
    """A fresh environment of task ``name`` with configuration fields overridden."""
    task = tasks.get(name)
    extra = {k: overrides.pop(k) for k in ("bank", "policies") if k in overrides}
    fields = {f.name for f in dataclasses.fields(task.config)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {unknown}; valid: {sorted(fields)}")
    return task.build(dataclasses.replace(task.config, **overrides), **extra)


__all__ = [
    "AutoReset",
    "GuideConfig",
    "GuideEnv",
    "NavConfig",
    "NavEnv",
    "make",
    "observation_layout",
    "record",
    "rewards",
    "tasks",
    "trace",
    "zero_policy",
]
