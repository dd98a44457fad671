"""Environments of the thesis as pure JAX functions behind Brax's ``Env`` interface.

``envs.make(name, **overrides)`` with ``name`` one of:

- ``"su"``: single-user chase (N = 1, Table 4.1 weights), :class:`envs.nav.NavEnv`;
- ``"nav"``: NavRL (N = 2 by default, Table 4.3 weights; goal from a GuideRL policy passed as
  ``guide_policy=`` or from the scripted source), :class:`envs.nav.NavEnv`;
- ``"guide"``: GuideRL, :class:`envs.guide.GuideEnv`.

Overrides are fields of :class:`envs.nav.NavConfig` / :class:`envs.guide.GuideConfig` (for example
``envs.make("su", lab=True, users_visible=True)``), plus ``bank=`` (a ``MotionBank``) and, for
``nav``, ``guide_policy=``. Wrap with :class:`envs.wrappers.AutoReset` for training loops.
``envs.record(env, key, steps, policy)`` records one episode for pictures
(:class:`methd_jax.viz.Rollout`).
"""

from __future__ import annotations

import dataclasses

from envs import rewards
from envs.episode import record, zero_policy
from envs.guide import GuideConfig, GuideEnv
from envs.nav import NavConfig, NavEnv, observation_layout
from envs.wrappers import AutoReset

PRESETS = {
    "su": NavConfig(num_users=1, weights=rewards.SU_WEIGHTS),
    "nav": NavConfig(num_users=2, weights=rewards.NAV_WEIGHTS),
    "guide": GuideConfig(),
}


def make(name: str, **overrides):
    """A fresh environment ``name`` ("su", "nav", "guide") with config fields overridden."""
    if name not in PRESETS:
        raise ValueError(f"unknown environment {name!r}; choose one of {sorted(PRESETS)}")
    extra = {k: overrides.pop(k) for k in ("bank", "guide_policy") if k in overrides}
    config = PRESETS[name]
    fields = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {unknown}; valid: {sorted(fields)}")
    config = dataclasses.replace(config, **overrides)
    if name == "guide":
        if "guide_policy" in extra:
            raise ValueError("guide_policy applies to 'nav' only")
        return GuideEnv(config, **extra)
    return NavEnv(config, **extra)


__all__ = [
    "AutoReset",
    "GuideConfig",
    "GuideEnv",
    "NavConfig",
    "NavEnv",
    "make",
    "observation_layout",
    "record",
    "zero_policy",
]
