"""The project's front door: lint, the README's commands, the benchmark CLI."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_ruff_lint_and_format_are_clean():
    lint = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "."], cwd=ROOT, capture_output=True, text=True
    )
    assert lint.returncode == 0, lint.stdout + lint.stderr
    fmt = subprocess.run(
        [sys.executable, "-m", "ruff", "format", "--check", "."], cwd=ROOT, capture_output=True, text=True
    )
    assert fmt.returncode == 0, fmt.stdout + fmt.stderr


def test_readme_has_exactly_two_setup_commands_and_ci_runs_the_test_one():
    readme = (ROOT / "README.md").read_text()
    setup = readme.split("## Set up", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"```bash\n(.*?)\n```", setup, re.S)
    assert commands == [
        "python -m pip install -e . && python -m train.run",
        "python -m pip install -e '.[test]' && python -m pytest",
    ]
    ci = subprocess.run(
        ["bash", "-c", (ROOT / ".ci/run").read_text().split("cmd=", 1)[1].split("\n", 1)[0][2:-1]],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert ci.stdout.strip() == commands[1]


def test_bench_cli_smoke(tmp_path):
    out = tmp_path / "bench.json"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "train.bench",
            "--sizes",
            "8",
            "--robots",
            "8",
            "--env-sizes",
            "4",
            "--train-envs",
            "8",
            "--repeats",
            "1",
            "--json",
            str(out),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "mjx.ray" in run.stdout and "robot-steps/s" in run.stdout
    res = json.loads(out.read_text())
    (row,) = res["lidar"]
    assert row["floors"] == 8 and row["ours_scans_per_s"] > 0 and row["mjx_ray_scans_per_s"] > 0
    assert row["rays_agreeing_1mm"] >= 0.999
    assert res["robot"]["robots"] == 8 and res["robot"]["robot_steps_per_s"] > 0
    assert [(r["env"], r["envs"]) for r in res["envs"]] == [("su", 4), ("nav", 4)]
    assert all(r["env_steps_per_s"] > 0 for r in res["envs"])
    train = res["train"]
    assert train["envs"] == 8 and train["transitions_per_iteration"] == 8 * 48
    assert train["transitions_per_s"] == pytest.approx(8 * 48 / train["iteration_s"])


@pytest.mark.parametrize("args", [["--sizes", "0"], ["--repeats", "-1"], ["--bogus"]])
def test_bench_cli_rejects_bad_arguments(args):
    run = subprocess.run(
        [sys.executable, "-m", "train.bench", *args], cwd=ROOT, capture_output=True, text=True
    )
    assert run.returncode == 2 and "error:" in run.stderr and "Traceback" not in run.stderr
