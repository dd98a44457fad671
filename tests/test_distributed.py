"""Training over two processes with jax.distributed (gloo collectives on the CPU) gives the same
parameters as one process with two devices on the same global batch."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_RUN

ROOT = Path(__file__).resolve().parents[1]
ARGS = ["quick", *TINY_RUN, "timesteps=12", "checkpoint_every=2", "--quiet"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    return {**env, "JAX_PLATFORMS": "cpu", **extra}


def _two_processes(*args) -> list[subprocess.CompletedProcess]:
    cluster = ["--coordinator", f"localhost:{_free_port()}", "--num-processes", "2"]
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "train.run", *args, *cluster, "--process-id", str(i)],
            cwd=ROOT,
            env=_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    out = []
    try:
        for p in procs:
            stdout, stderr = p.communicate(timeout=300)
            out.append(subprocess.CompletedProcess(p.args, p.returncode, stdout, stderr))
    finally:
        for p in procs:
            p.kill()
    return out


@pytest.mark.slow
def test_two_processes_train_as_one_process_with_two_devices(tmp_path):
    # stopped after the first iteration, then resumed by both processes to the end
    for p in _two_processes(*ARGS, "--out", str(tmp_path / "two"), "--max-minutes", "1e-6"):
        assert p.returncode == 0, p.stderr[-2000:]
    for p in _two_processes("--resume", str(tmp_path / "two"), "--quiet"):
        assert p.returncode == 0, p.stderr[-2000:]
    one = subprocess.run(
        [sys.executable, "-m", "train.run", *ARGS, "--out", str(tmp_path / "one")],
        cwd=ROOT,
        env=_env(XLA_FLAGS="--xla_force_host_platform_device_count=2"),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert one.returncode == 0, one.stderr[-2000:]
    a, b = (np.load(tmp_path / run / "policy" / "params.npz") for run in ("one", "two"))
    assert sorted(a.files) == sorted(b.files)
    # measured: bit-identical (the same two shards reduced in the same order)
    for k in a.files:
        np.testing.assert_allclose(a[k], b[k], rtol=0, atol=1e-6, err_msg=k)
    meta = json.loads((tmp_path / "two" / "config.json").read_text())
    assert meta["device"].endswith("in 2 processes")
    assert sorted(p.name for p in (tmp_path / "two" / "checkpoints").iterdir()) == ["1", "2", "3"]
    rows = (tmp_path / "two" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(r)["iteration"] for r in rows] == [1, 2, 3]  # one writer, no duplicates


def test_cluster_flags_are_checked_before_anything_starts(tmp_path, capsys):
    from train.run import main

    out = ["--out", str(tmp_path / "x")]
    assert main(["quick", "--coordinator", "localhost:1"]) == 2  # no --out
    assert "needs --out" in capsys.readouterr().err
    assert main(["quick", *out, "--coordinator", "localhost:1", "--num-processes", "2"]) == 2
    assert "--coordinator, --num-processes and --process-id together" in capsys.readouterr().err
    args = ["quick", *out, "--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "2"]
    assert main(args) == 2
    assert "--process-id must be in [0, --num-processes)" in capsys.readouterr().err
    args = ["quick", *out, "--coordinator", "nohost", "--num-processes", "2", "--process-id", "0"]
    assert main(args) == 2
    assert "--coordinator must be host:port" in capsys.readouterr().err
    assert main(["quick", *out, "--distributed", "--process-id", "0"]) == 2
    assert "do not combine" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
