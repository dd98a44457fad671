"""The project's front door: lint, the README's commands, the benchmark CLI."""

import json
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import jax
import pytest

from train import bench
from train import run as run_lib

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


@pytest.mark.slow  # six minutes of timed repeats on two cores: a benchmark, run deliberately
def test_bench_quick_checks_ratios_against_the_peers(tmp_path):
    """``python -m train.bench --quick``: our caster and trainer beat their peers."""
    out = tmp_path / "bench.json"
    run = subprocess.run(
        [sys.executable, "-m", "train.bench", "--quick", "--json", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert "mjx.ray" in run.stdout and "Brax PPO" in run.stdout and "skrl PPO" in run.stdout
    res = json.loads(out.read_text())
    assert set(res) == {"machine", "lidar", "train", "peak_host_memory_mb", "peak_device_memory_mb"}
    (row,) = res["lidar"]
    assert row["floors"] == 64 and row["ratio"] >= 1.0 and row["rays_agreeing_1mm"] >= 0.999
    train = res["train"]
    assert (
        train["preset"] == "quick" and train["envs"] == 64 and train["transitions_per_iteration"] == 64 * 32
    )
    assert train["repeats"] == 5
    for peer in ("brax", "skrl"):
        assert train[f"ratio_{peer}"] == pytest.approx(
            train["ours_transitions_per_s"] / train[f"{peer}_transitions_per_s"]
        )
        assert train[f"ratio_{peer}"] >= 1.0 and train[f"{peer}_compile_s"] > 0
    assert train["skrl_updated_both_heads"]
    if jax.default_backend() == "cpu":  # XLA:CPU keeps no allocator statistics
        assert res["peak_device_memory_mb"] is None


def test_peak_device_memory_is_the_largest_allocator_peak():
    class Device:
        def __init__(self, stats):
            self.stats = stats

        def memory_stats(self):
            return self.stats

    gpus = [
        Device({"peak_bytes_in_use": 3 * 2**20, "bytes_in_use": 2**20}),
        Device({"peak_bytes_in_use": 5 * 2**20}),
    ]
    assert bench.peak_device_memory_mb(gpus) == 5.0
    assert bench.peak_device_memory_mb([Device(None), Device({})]) is None
    here = bench.peak_device_memory_mb()
    assert here is None if jax.default_backend() == "cpu" else here > 0


def test_bench_device_budget_runs_what_fits_and_skips_the_rest(tmp_path):
    out = tmp_path / "device.json"
    r = subprocess.run(
        [sys.executable, "-m", "train.bench", "--device-budget", "1", "--sizes", "8", "--json", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    results = json.loads(out.read_text())
    # the first section starts inside the budget and runs to its end; the rest do not start
    assert [row["floors"] for row in results["lidar"]] == [8] and results["lidar"][0]["ratio"] > 0
    assert sorted(results["skipped"]) == ["envs", "train", "train_quick"]
    rows = (tmp_path / "device.md").read_text()
    assert "| LiDAR, 8 floors x 720 rays, scans/s |" in rows and rows.count("skipped: budget spent") == 3
    argv = [sys.executable, "-m", "train.bench", "--device-budget", "0"]
    bad = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2 and "--device-budget must be positive" in bad.stderr


def test_bench_checks_fail_when_a_peer_is_faster():
    lidar = {"floors": 64, "ratio": 0.8, "rays_agreeing_1mm": 0.99}
    results = {"lidar": [lidar], "train": {"envs": 16, "ratio_brax": 0.9, "ratio_skrl": 0.5}}
    failures = bench.checks(results)
    assert len(failures) == 4
    assert "slower than mjx.ray" in failures[1] and "slower than Brax's" in failures[2]
    assert "slower than skrl's at 16 environments (0.50x)" in failures[3]
    results = {
        "lidar": [lidar | {"ratio": 3.0, "rays_agreeing_1mm": 1.0}],
        "train": {"envs": 16, "ratio_brax": 1.2, "ratio_skrl": 2.5},
    }
    assert bench.checks(results) == []


def test_without_skrl_the_benchmark_names_it_and_checks_brax(monkeypatch):
    import importlib.util

    from train.bench import skrl_peer

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "skrl" else real(name, *a)
    )
    assert not skrl_peer.available()
    train = {"preset": "quick", "envs": 16, "ours_transitions_per_s": 900.0, "brax_transitions_per_s": 1000.0}
    train |= {"ratio_brax": 0.9, "skrl_missing": skrl_peer.MISSING}
    assert bench.checks({"lidar": [], "train": train}) == [
        "our PPO is slower than Brax's at 16 environments (0.90x)"
    ]
    machine = {"device": "cpu", "jax": "0", "date": "today"}
    rows = bench.markdown_rows({"machine": machine, "train": train})
    assert "methd-jax[peers]" in rows and "Brax PPO 1,000" in rows


@pytest.mark.parametrize("args", [["--sizes", "0"], ["--repeats", "-1"], ["--bogus"]])
def test_bench_cli_rejects_bad_arguments(args):
    run = subprocess.run(
        [sys.executable, "-m", "train.bench", *args], cwd=ROOT, capture_output=True, text=True
    )
    assert run.returncode == 2 and "error:" in run.stderr and "Traceback" not in run.stderr


def test_scaling_plot_from_measurements(tmp_path):
    scaling = {
        "by_envs": [{"envs": n, "env_steps_per_s": 1000.0 * n**0.5} for n in (256, 1024, 4096)],
        "by_obstacles": [{"obstacles": k, "envs": 2048, "env_steps_per_s": 9000.0 / k} for k in (8, 16, 32)],
    }
    bench.plot_scaling(scaling, tmp_path / "scaling.png")
    assert (tmp_path / "scaling.png").stat().st_size > 5000


def test_floor_and_robot_sections_measure_rates():
    logged = []
    floors_row, robot_row = bench.bench_floors(8, 1, logged.append), bench.bench_robot(8, 1, logged.append)
    assert floors_row["floors"] == 8 and floors_row["floors_per_s"] > 0 and floors_row["compile_s"] > 0
    assert robot_row["robots"] == 8 and robot_row["robot_steps_per_s"] > 0 and robot_row["substeps"] >= 1
    assert "floors/s" in logged[0] and "robot-steps/s" in logged[1]


@pytest.mark.slow
def test_env_and_scaling_sections_measure_env_steps():
    rows = bench.bench_envs([4], 1, print)
    assert [(r["env"], r["rays"], r["envs"]) for r in rows] == [
        ("su", 720, 4),
        ("su", 8, 4),
        ("nav", 720, 4),
        ("nav", 8, 4),
    ]
    assert all(r["env_steps_per_s"] > 0 for r in rows)
    logged = []
    scaling = bench.bench_scaling([4, 8], [2, 6], 1, logged.append)
    assert [r["envs"] for r in scaling["by_envs"]] == [4, 8]
    assert [(r["obstacles"], r["envs"]) for r in scaling["by_obstacles"]] == [(2, 8), (6, 8)]
    assert all(r["env_steps_per_s"] > 0 for r in scaling["by_envs"] + scaling["by_obstacles"])
    assert len(logged) == 4


def test_a_wheel_runs_from_any_folder_with_its_assets(tmp_path):
    """A non-editable install (a wheel, in a fresh environment that borrows the installed
    dependencies) carries assets/ as methd_jax.assets: `python -m train.run --help` and the lab
    twin work from a folder outside the checkout."""
    import venv

    wheels = tmp_path / "wheels"
    build = [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(wheels)]
    done = subprocess.run(build, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    (wheel,) = wheels.glob("methd_jax-*.whl")
    env = tmp_path / "env"
    venv.create(env, system_site_packages=True)  # no pip of its own: this pip installs into it
    python = str(env / "bin" / "python")
    # the dependencies this test runs with, wherever they are installed (a virtual environment's are
    # not the base interpreter's system site): appended after the new environment's own
    # site-packages, so the wheel's methd_jax comes first and no editable install's hook is read
    inner = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    outer = dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib"))
    (Path(inner) / "borrowed_dependencies.pth").write_text("".join(f"{p}\n" for p in outer))
    done = subprocess.run(
        [sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", str(wheel)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    check = (
        "from methd_jax import floors; from train.presets import PRETRAINED; "
        "print(floors.ASSETS); print(floors.lab().bounds.tolist()); "
        "print(sorted(p.name for p in PRETRAINED.iterdir()))"
    )
    done = subprocess.run([python, "-c", check], cwd=elsewhere, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assets, bounds, shipped = done.stdout.strip().splitlines()[-3:]
    assert assets.startswith(str(env)) and "site-packages" in assets  # the wheel's copy, not the checkout
    assert bounds == "[-5.5, -6.5, 5.5, 6.5]" and "su" in shipped
    done = subprocess.run(
        [python, "-m", "train.run", "--help"], cwd=elsewhere, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0 and "quick" in done.stdout, done.stderr


def test_pyproject_lists_every_package_of_the_checkout():
    """The packages are listed by hand (assets/ is mapped to methd_jax.assets), so a new
    subpackage must be added there or a wheel would go without it."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {
        ".".join(p.parent.relative_to(ROOT).parts)
        for top in ("methd_jax", "envs", "networks", "train")
        for p in (ROOT / top).rglob("__init__.py")
    }
    assert listed == found | {"methd_jax.assets"}


def _imported_packages(path: Path) -> set[str]:
    import ast

    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize(
    "package, forbidden",
    [("methd_jax", {"envs", "networks", "train"}), ("networks", {"envs", "train"}), ("envs", {"train"})],
)
def test_imports_flow_one_way(package, forbidden):
    """methd_jax (core) -> envs -> networks -> train: no module imports from a package downstream
    of its own, at the top of the file or inside a function."""
    offenders = {
        str(path.relative_to(ROOT)): sorted(_imported_packages(path) & forbidden)
        for path in sorted((ROOT / package).rglob("*.py"))
    }
    assert {k: v for k, v in offenders.items() if v} == {}


@pytest.mark.slow
def test_loop_section_compares_the_two_call_shapes():
    logged = []
    row = bench.bench_loop(8, 1, logged.append)
    assert row["iterations_per_call"] == run_lib.CHUNK and row["envs"] == 8
    assert row["ratio"] == pytest.approx(
        row["chunked_donated_transitions_per_s"] / row["per_iteration_calls_transitions_per_s"]
    )
    assert min(row["chunked_donated_transitions_per_s"], row["per_iteration_calls_transitions_per_s"]) > 0
    assert "donated" in logged[0]
