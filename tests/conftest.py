"""Shared helpers: MuJoCo's own ray casting as the independent reference; a compilation cache."""

import atexit
import shutil
import tempfile

import jax
import mujoco
import numpy as np
import pytest

from methd_jax import floors

# Many tests train the same tiny configuration from scratch; XLA's persistent cache (fresh for each
# session) compiles each distinct program once instead of once per test.
_XLA_CACHE = tempfile.mkdtemp(prefix="methd-jax-test-xla-")
atexit.register(shutil.rmtree, _XLA_CACHE, ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
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
