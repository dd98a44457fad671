"""Shared helpers: MuJoCo's own ray casting as the independent reference; a compilation cache; a
bounded fuzzer of file readers."""

# ruff: noqa: E402  (the test environment is set up before JAX is imported)
import atexit
import os
import shutil
import subprocess
import sys
import tempfile
import types
from pathlib import Path

TEST_XLA_FLAGS = "--xla_cpu_use_fusion_emitters=false"
"""Most of the suite's time is XLA compiling for the CPU. Without XLA's CPU fusion emitters the
evaluation engines compile in half the time (and run ~13% slower), a good trade for tests that run
each program briefly; small MLPs over thousands of rows run up to 4x slower."""


def _set_up_test_environment() -> str:
    """Once per session, in the first process that loads this file (pytest's controller, before
    xdist starts its workers): a persistent XLA cache, so that the many tests compiling the same
    programs (the tiny training configuration, the engines, the envs) compile each once, and
    TEST_XLA_FLAGS where this XLA knows them. Both pass on through the environment: to the workers,
    to subprocesses (``python -m ...``) and to the notebooks' kernels. Returns the cache folder."""
    cache = os.environ.get("METHD_JAX_TEST_XLA_CACHE", "")
    if cache:
        return cache
    cache = tempfile.mkdtemp(prefix="methd-jax-test-xla-")
    atexit.register(shutil.rmtree, cache, ignore_errors=True)
    os.environ["METHD_JAX_TEST_XLA_CACHE"] = cache
    flags = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()
    # XLA aborts the process on a flag it does not know (a newer jaxlib may drop this one)
    probe = "import jax.numpy as jnp; jnp.zeros(2).block_until_ready()"
    env = {**os.environ, "XLA_FLAGS": flags}
    known = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, timeout=120)
    if known.returncode == 0:
        os.environ["XLA_FLAGS"] = flags
    return cache


_XLA_CACHE = _set_up_test_environment()
os.environ.update(
    JAX_COMPILATION_CACHE_DIR=_XLA_CACHE,
    JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
    JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
)

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from methd_jax import floors
from train import export

jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

TINY_RUN = (
    "env.num_rays=72",  # the fewest the encoder takes
    "env.motion=sample",
    "hidden=32,32",
    "num_envs=8",
    "ppo.rollouts=4",
    "ppo.minibatches=2",
    "ppo.epochs=2",
)
"""Overrides of the quick preset for a seconds-scale training run (tests of the machinery)."""

RAY_HEIGHT = 0.5  # to_mjcf's default obstacles are 1 m tall; scan at mid-height


def mujoco_scan(floor, pose, num_rays: int = 720) -> np.ndarray:
    """Ranges from MuJoCo's C ray caster (float64) on the floor's MJCF export; inf on a miss."""
    m = mujoco.MjModel.from_xml_string(floors.to_mjcf(floor, height=2 * RAY_HEIGHT))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return mujoco_scan_model(m, d, pose, num_rays)


def mujoco_scan_model(m, d, pose, num_rays: int = 720) -> np.ndarray:
    pose = np.asarray(pose, np.float64)
    ang = pose[2] + 2 * np.pi * np.arange(num_rays) / num_rays
    vec = np.stack([np.cos(ang), np.sin(ang), np.zeros(num_rays)], 1).ravel()
    dist = np.zeros(num_rays)
    gid = np.zeros(num_rays, np.int32)
    group = np.array([1, 1, 1, 0, 1, 1], np.uint8)  # group 3 is the ground plane
    pnt = np.array([pose[0], pose[1], RAY_HEIGHT])
    mujoco.mj_multiRay(m, d, pnt, vec, group, 1, -1, gid, dist, None, num_rays, 1e9)
    return np.where(dist < 0, np.inf, dist)


@pytest.fixture(scope="session")
def mujoco_reference():
    return mujoco_scan


def export_random_policy(folder: Path, env, env_name: str, net, seed: int) -> Path:
    """A policy folder for ``net`` at random init, with a non-trivial observation normaliser."""
    params = net.init(jax.random.key(seed), jnp.zeros((1, env.observation_size)))
    rng = np.random.default_rng(seed)
    stats = types.SimpleNamespace(
        mean=rng.normal(0, 0.5, env.observation_size).astype(np.float32),
        std=rng.uniform(0.5, 2.0, env.observation_size).astype(np.float32),
    )
    spec = {"class": type(net).__name__, "hidden": list(net.hidden), "init_log_std": 0.0}
    if env_name != "guide":
        spec["num_rays"] = net.num_rays
    return export.export(
        folder / "policy",
        env_name=env_name,
        env=env,
        network_spec=spec,
        params=params,
        obs_stats=stats,
        obs_clip=5.0,
        trained={"run": "test", "iteration": 0, "transitions": 0},
    )


# -- fuzzing (a fixed number of seeded cases: the same corruptions on every machine and load) ---


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One random corruption of ``data``: random bytes, a cut, bit flips, a span overwritten with
    noise or zeros, or a span deleted."""
    n = len(data)
    kind = rng.integers(6)
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 4096)))
    if kind == 1:
        return data[: int(rng.integers(0, n))]
    buf = bytearray(data)
    if kind == 2:
        for i in rng.integers(0, n, int(rng.integers(1, 17))):
            buf[i] ^= 1 << int(rng.integers(8))
        return bytes(buf)
    start = int(rng.integers(0, n))
    stop = min(n, start + int(rng.integers(1, 257)))
    if kind == 3:
        buf[start:stop] = rng.bytes(stop - start)
    elif kind == 4:
        buf[start:stop] = bytes(stop - start)
    else:
        del buf[start:stop]
    return bytes(buf)


def fuzz(target, original: bytes, seed: int, cases: int = 40) -> dict:
    """Runs ``target`` on ``cases`` corruptions of ``original`` drawn from ``seed``; counts the
    outcomes it returns ("refused" / "accepted")."""
    rng = np.random.default_rng(seed)
    counts = {"refused": 0, "accepted": 0}
    print(target.__qualname__, end=": ")
    for _ in range(cases):
        counts[target(mutate(original, rng))] += 1
    print(counts)
    return counts
