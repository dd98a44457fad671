"""Fuzzing, bounded in time: random bytes, truncations and bit flips thrown at the motion bag reader,
the deployment replay and the deployment folder loader. Each must answer with its own one-line
error class (or a correct result); no other exception, no hang."""

import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import export_random_policy

import networks
from envs.nav import NavConfig, NavEnv
from methd_jax import deploy
from methd_jax.motion import bags
from methd_jax.motion.trajectory import MotionDataError, Trajectory
from train import export

ROOT = Path(__file__).resolve().parents[1]
BUDGET = 8.0
"""Seconds of fuzzing per target (each also stops after ``CASES`` cases)."""
CASES = 40


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


def fuzz(target, original: bytes, seed: int) -> dict:
    """Runs ``target(corrupted_bytes)`` until the budget or the case count runs out; counts outcomes."""
    rng = np.random.default_rng(seed)
    counts = {"refused": 0, "accepted": 0}
    print(target.__qualname__, end=": ")
    end = time.monotonic() + BUDGET
    while time.monotonic() < end and sum(counts.values()) < CASES:
        counts[target(mutate(original, rng))] += 1
    print(counts)
    return counts


def test_the_motion_bag_reader_refuses_corrupt_files_cleanly(tmp_path):
    source = ROOT / "assets" / "motion_sample" / "traj_0003.mcap"
    path = tmp_path / "fuzzed.mcap"

    def target(data):
        path.write_bytes(data)
        try:
            traj = bags.read_bag(path)
        except MotionDataError as e:
            assert str(path) in str(e) and "\n" not in str(e)
            return "refused"
        assert isinstance(traj, Trajectory) and np.isfinite(traj.head).all() and np.isfinite(traj.wrist).all()
        return "accepted"

    counts = fuzz(target, source.read_bytes(), seed=0)
    assert counts["refused"] >= 10 and sum(counts.values()) >= 20, counts


@pytest.fixture(scope="module")
def small_deploy(tmp_path_factory):
    env = NavEnv(NavConfig(motion="sample", split="all", num_rays=90))
    root = tmp_path_factory.mktemp("small")
    export_random_policy(root, env, "su", networks.ActorCritic(num_rays=90, hidden=(16, 16)), seed=2)
    return export.export_deployment(root, log=lambda *a: None)


def test_the_replay_refuses_corrupt_bags_cleanly(small_deploy, tmp_path):
    controller = deploy.Controller(small_deploy, backend="numpy")
    original = (ROOT / "assets" / "deploy_sample.mcap").read_bytes()
    path, out = tmp_path / "fuzzed.mcap", tmp_path / "out.mcap"

    def target(data):
        path.write_bytes(data)
        try:
            summary = deploy.replay(controller, path, out)
        except deploy.DeployError as e:
            assert "\n" not in str(e)
            return "refused"
        assert summary["ticks"] >= 1 and out.exists()
        return "accepted"

    counts = fuzz(target, original, seed=1)
    assert counts["refused"] >= 3 and sum(counts.values()) >= 6, counts


def test_the_deploy_loader_refuses_corrupt_folders_cleanly(small_deploy, tmp_path):
    files = {
        name: (small_deploy / name).read_bytes() for name in ("manifest.json", "params.npz", "policy.onnx")
    }
    folder = tmp_path / "fuzzed"
    shutil.copytree(small_deploy, folder)
    good = deploy.Controller(small_deploy, backend="numpy")
    x = deploy.Inputs(
        ranges=np.full(90, 2.0),
        robot_pose=np.zeros(3),
        velocity=np.zeros(3),
        users=np.array([[4.0, 0.0, 0.0, 0.0, 0.0, 0.0]]),
        goal=np.array([1.0, 0.0, 0.0]),
    )
    expected = good.tick(x).twist
    for i, (name, original) in enumerate(files.items()):

        def target(data, name=name):
            (folder / name).write_bytes(data)
            try:
                c = deploy.Controller(folder, backend="onnx")
            except deploy.DeployError as e:
                assert "\n" not in str(e)
                return "refused"
            finally:
                (folder / name).write_bytes(files[name])
            # whatever loads drives exactly as the original (hashes cover the parameters and model)
            np.testing.assert_allclose(c.tick(x).twist, expected, atol=1e-5)
            return "accepted"

        counts = fuzz(target, original, seed=10 + i)
        assert counts["refused"] >= 10, (name, counts)
