"""Datasets: the default synthetic set (made once into a cache folder), the shipped sample, splits."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from methd_jax.floors import ASSETS
from methd_jax.motion import bags
from methd_jax.motion.synth import SynthConfig, synthesize
from methd_jax.motion.trajectory import Trajectory

SAMPLE_DIR = ASSETS / "motion_sample"
"""A few synthetic trajectories shipped as MCAP files, for tests and quick runs."""
CACHE_ENV = "METHD_JAX_CACHE"
"""Environment variable that overrides the cache folder (default ``~/.cache/methd-jax``)."""
DEFAULT_SIZE = 442
"""Trajectories in the thesis dataset."""
TEST_SIZE = 100
"""Consecutive held-out trajectories in the thesis's test set."""
FORMAT = 2
"""Bump when the cached layout or the generator's output changes."""


def cache_dir() -> Path:
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "methd-jax")


def progress_bar(desc: str, enabled: bool = True):
    """A ``progress(done, total)`` callback drawing a tqdm bar (or doing nothing)."""
    if not enabled:
        return None
    from tqdm import tqdm

    state = {}

    def progress(done: int, total: int):
        if "bar" not in state:
            state["bar"] = tqdm(total=total, desc=desc, unit="traj", leave=False)
        state["bar"].update(done - state["bar"].n)
        if done >= total:
            state["bar"].close()

    return progress


def _key(n: int, seed: int, config: SynthConfig) -> str:
    digest = hashlib.sha256(repr((FORMAT, dataclasses.astuple(config))).encode()).hexdigest()[:10]
    return f"synthetic-n{n}-seed{seed}-{digest}"


def _write_npz(path: Path, trajectories: Sequence[Trajectory]):
    lengths = np.array([len(t.time) for t in trajectories])
    np.savez(
        path,
        names=np.array([t.name for t in trajectories]),
        lengths=lengths,
        head=np.concatenate([t.head for t in trajectories]),
        wrist=np.concatenate([t.wrist for t in trajectories]),
        time=np.concatenate([t.time for t in trajectories]),
        request_time=np.array([t.request_time for t in trajectories]),
        start_ns=np.array([t.start_ns for t in trajectories], np.int64),
    )


def _read_npz(path: Path) -> list[Trajectory]:
    with np.load(path) as npz:
        z = {k: npz[k] for k in npz.files}  # each npz[k] access reads the array from disk again
    ends = np.cumsum(z["lengths"])
    starts = ends - z["lengths"]
    return [
        Trajectory(
            name=str(z["names"][i]),
            time=z["time"][a:b],
            head=z["head"][a:b],
            wrist=z["wrist"][a:b],
            request_time=float(z["request_time"][i]),
            start_ns=int(z["start_ns"][i]),
        )
        for i, (a, b) in enumerate(zip(starts, ends, strict=True))
    ]


def default_dataset(
    n: int = DEFAULT_SIZE,
    seed: int = 0,
    *,
    config: SynthConfig | None = None,
    cache: str | Path | None = None,
    progress: bool = True,
) -> list[Trajectory]:
    """The synthetic dataset, made on first use into ``<cache>/motion/<key>/`` and read after.

    The folder holds one MCAP bag per trajectory (open them in Foxglove) and ``trajectories.npz``,
    a fast copy that later calls read. The key encodes ``n``, ``seed`` and the generator config
    (default :class:`SynthConfig`).
    """
    config = config or SynthConfig()
    folder = Path(cache or cache_dir()) / "motion" / _key(n, seed, config)
    npz = folder / "trajectories.npz"
    if npz.is_file():
        return _read_npz(npz)
    trajectories = synthesize(n, seed, config=config, progress=progress_bar("synthesising", progress))
    # a folder of this process's own: two runs started together each make the dataset, and the
    # first to finish places it (the key fixes the data, so the other's copy is the same)
    tmp = folder.with_name(f"{folder.name}.partial-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    bags.save(tmp, trajectories, progress=progress_bar("writing MCAP", progress))
    _write_npz(tmp / "trajectories.npz", trajectories)
    if not npz.is_file():
        shutil.rmtree(folder, ignore_errors=True)  # an incomplete folder of another version
    try:
        tmp.rename(folder)  # all or nothing: a crash leaves only the .partial folder
    except OSError:
        if not npz.is_file():
            raise
    shutil.rmtree(tmp, ignore_errors=True)
    return trajectories


def sample() -> list[Trajectory]:
    """The few trajectories shipped in ``assets/motion_sample``."""
    return bags.load(SAMPLE_DIR)


def split(trajectories: Sequence[Trajectory], n_test: int = TEST_SIZE) -> tuple[list, list]:
    """(train, test): the test set is the last ``n_test`` consecutive trajectories, never trained on."""
    if not 0 < n_test < len(trajectories):
        raise ValueError(f"cannot hold out {n_test} of {len(trajectories)} trajectories")
    return list(trajectories[:-n_test]), list(trajectories[-n_test:])
