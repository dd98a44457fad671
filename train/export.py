"""Exported policies: what a trained run hands to evaluation and deployment.

A policy folder holds ``params.npz`` (every network parameter under its Flax path, e.g.
``params/body0/kernel``, plus ``obs_mean`` and ``obs_std``, all float32, readable with numpy alone)
and ``manifest.json``: the environment and its options, the observation layout (name -> [start,
stop)), the action's meaning and scale, the network (class and fields, parameter counts), the
observation clip, and where and when it was trained. :func:`load` gives a deterministic JAX policy.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

import networks

FORMAT = "methd-jax-policy/1"

ACTIONS = {
    "su": {"names": ["vx", "vy", "wz"], "units": ["m/s", "m/s", "rad/s"], "frame": "robot"},
    "nav": {"names": ["vx", "vy", "wz"], "units": ["m/s", "m/s", "rad/s"], "frame": "robot"},
    "guide": {"names": ["delta_u_w"], "units": ["1"], "frame": "none"},
}


def jsonable(value):
    """Dataclasses as dicts and tuples as lists, recursively (for JSON)."""
    if dataclasses.is_dataclass(value):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [jsonable(v) for v in value]
    return value


def from_jsonable(default, data: dict):
    """The inverse of :func:`jsonable` for a dataclass: ``default`` with the fields in ``data``
    (nested dataclasses and tuples rebuilt from dicts and lists)."""

    def as_tuple(v):
        return tuple(as_tuple(x) for x in v) if isinstance(v, list) else v

    changes = {}
    for f in dataclasses.fields(default):
        if f.name not in data:
            continue
        current, value = getattr(default, f.name), data[f.name]
        if dataclasses.is_dataclass(current):
            value = from_jsonable(current, value)
        elif isinstance(current, tuple):
            value = as_tuple(value)
        changes[f.name] = value
    return dataclasses.replace(default, **changes)


def export(path: str | Path, *, env_name, env, network_spec, params, obs_stats, obs_clip, trained) -> Path:
    """Write ``params.npz`` and ``manifest.json`` into the folder ``path``; returns it."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    flat = traverse_util.flatten_dict(jax.device_get(params), sep="/")
    arrays = {k: np.asarray(v, np.float32) for k, v in flat.items()}
    arrays["obs_mean"] = np.asarray(obs_stats.mean, np.float32)
    arrays["obs_std"] = np.asarray(obs_stats.std, np.float32)
    np.savez(path / "params.npz", **arrays)
    if env_name == "guide":
        layout, scale = {"guide": [0, env.observation_size]}, [0.05]
    else:
        layout = {k: [s.start, s.stop] for k, s in env.observation_layout.items()}
        robot = env.config.robot
        scale = [robot.max_speed, robot.max_speed, robot.max_yaw_rate]
    manifest = {
        "format": FORMAT,
        "env": env_name,
        "env_config": jsonable(env.config),
        "observation_size": env.observation_size,
        "observation_layout": layout,
        "observation_clip": obs_clip,
        "action": {**ACTIONS[env_name], "size": env.action_size, "scale": scale, "range": [-1.0, 1.0]},
        "network": dict(network_spec),
        "parameters": {"total": networks.count(params), "policy": networks.policy_count(params)},
        "trained": trained,
    }
    (path / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return path


@dataclasses.dataclass(frozen=True)
class Policy:
    """A loaded policy: ``policy(obs) -> action`` in [-1, 1] (the Gaussian's mean), jit- and vmap-able."""

    manifest: dict
    params: dict
    obs_mean: jax.Array
    obs_std: jax.Array

    @property
    def network(self):
        return networks.from_spec(self.manifest["network"])

    def __call__(self, obs: jax.Array) -> jax.Array:
        clip = self.manifest["observation_clip"]
        z = (obs - self.obs_mean) / self.obs_std
        z = jnp.clip(z, -clip, clip) if clip > 0 else z
        mean, _, _ = self.network.apply(self.params, z)
        return jnp.clip(mean, -1.0, 1.0)


def load(path: str | Path) -> Policy:
    """The policy exported to ``path`` (a policy folder, or a run folder containing ``policy/``)."""
    path = Path(path)
    if (path / "policy" / "manifest.json").exists():
        path = path / "policy"
    if not (path / "manifest.json").exists():
        raise FileNotFoundError(f"{path} holds no exported policy (manifest.json is missing)")
    manifest = json.loads((path / "manifest.json").read_text())
    if manifest.get("format") != FORMAT:
        raise ValueError(f"{path}: unknown policy format {manifest.get('format')!r}, expected {FORMAT!r}")
    with np.load(path / "params.npz") as data:
        arrays = {k: data[k] for k in data.files}
    mean, std = arrays.pop("obs_mean"), arrays.pop("obs_std")
    params = traverse_util.unflatten_dict({tuple(k.split("/")): jnp.asarray(v) for k, v in arrays.items()})
    return Policy(manifest, params, jnp.asarray(mean), jnp.asarray(std))
