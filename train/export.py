"""Exported policies: what a trained run hands to evaluation and deployment.

Every run writes ``policy/``; ``python -m train.export RUN`` turns it into a self-contained
deployment folder (``RUN/deploy`` by default) that :class:`methd_jax.deploy.Controller` loads
without JAX: ``policy.onnx`` (the deterministic policy with the observation normaliser folded in,
exported by jax2onnx), ``params.npz`` and a ``manifest.json`` extended with a ``deployment``
section (observation fields with units, action scaling, interpolation weights, dead zones, LiDAR
clamp, control rate, footprint and distances), the run's configuration, the library versions and
a SHA-256 of the parameters.

A policy folder holds ``params.npz`` (every network parameter under its Flax path, e.g.
``params/body0/kernel``, plus ``obs_mean`` and ``obs_std``, all float32, readable with numpy alone)
and ``manifest.json``: the environment and its options, the observation layout (name -> [start,
stop)), the action's meaning and scale, the network (class and fields, parameter counts), the
observation clip, and where and when it was trained. :func:`load` gives a deterministic JAX policy.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import json
import logging
import math
import shutil
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

import networks
from envs import tasks
from envs.nav import CLEARANCE_RANGE
from methd_jax.cli import OneLineParser
from methd_jax.control import CONTROL_HZ
from methd_jax.deploy.policy import params_sha256
from methd_jax.geometry import KAIROS
from methd_jax.jsonable import jsonable
from train.presets import ConfigError

FORMAT = "methd-jax-policy/1"


def export(
    path: str | Path, *, env_name, env, network_spec, params, obs_stats, obs_clip, trained, policies=None
) -> Path:
    """Write ``params.npz`` and ``manifest.json`` into the folder ``path``; returns it. ``policies``
    (task name -> folder) records the policies the environment was trained with (GuideRL for
    NavRL), as given: :func:`dependencies` finds them again."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    flat = traverse_util.flatten_dict(jax.device_get(params), sep="/")
    arrays = {k: np.asarray(v, np.float32) for k, v in flat.items()}
    arrays["obs_mean"] = np.asarray(obs_stats.mean, np.float32)
    arrays["obs_std"] = np.asarray(obs_stats.std, np.float32)
    np.savez(path / "params.npz", **arrays)
    task = tasks.get(env_name)
    layout = {k: [s.start, s.stop] for k, s in env.observation_layout.items()}
    action = {k: list(v) if isinstance(v, tuple) else v for k, v in task.action.items()}
    manifest = {
        "format": FORMAT,
        "env": env_name,
        "env_config": jsonable(env.config),
        "observation_size": env.observation_size,
        "observation_layout": layout,
        "observation_clip": obs_clip,
        "action": {
            **action,
            "size": env.action_size,
            "scale": task.action_scale(env.config),
            "range": [-1.0, 1.0],
        },
        "network": dict(network_spec),
        "parameters": {"total": networks.count(params), "policy": networks.policy_count(params)},
        "trained": trained,
        "policies": {name: str(folder) for name, folder in (policies or {}).items()},
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
        make_policy = networks.make_inference_fn(self.network, self.manifest["observation_clip"])
        return make_policy(self.params, self.obs_mean, self.obs_std)(obs)


def load(path: str | Path) -> Policy:
    """The policy exported to ``path`` (a policy folder, or a run folder containing ``policy/``)."""
    path = Path(path)
    if (path / "policy" / "manifest.json").exists():
        path = path / "policy"
    if not (path / "manifest.json").exists():
        raise FileNotFoundError(f"{path} holds no exported policy (manifest.json is missing)")
    try:
        manifest = json.loads((path / "manifest.json").read_text())
    except (ValueError, OSError) as e:
        raise ValueError(f"{path / 'manifest.json'}: unreadable ({type(e).__name__}: {e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        got = manifest.get("format") if isinstance(manifest, dict) else manifest
        raise ValueError(f"{path}: unknown policy format {got!r}, expected {FORMAT!r}")
    try:
        with np.load(path / "params.npz") as data:
            arrays = {k: data[k] for k in data.files}
        mean, std = arrays.pop("obs_mean"), arrays.pop("obs_std")
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path / 'params.npz'}: unreadable ({type(e).__name__}: {e})") from None
    params = traverse_util.unflatten_dict({tuple(k.split("/")): jnp.asarray(v) for k, v in arrays.items()})
    return Policy(manifest, params, jnp.asarray(mean), jnp.asarray(std))


# ----------------------------------------------------------------------------------------------
# Deployment folders


def dependencies(path: str | Path, given: dict[str, str] | None = None) -> dict[str, str]:
    """Task name -> folder of each policy the exported policy at ``path`` was trained with: from
    ``given`` where named there, else as its manifest records them (a relative folder is taken from
    the policy folder; manifests without a ``policies`` entry record them in ``run_config``)."""
    path = Path(path)
    folder = path / "policy" if (path / "policy" / "manifest.json").exists() else path
    manifest = load(folder).manifest
    task = tasks.get(manifest["env"])
    given = dict(given or {})
    unknown = sorted(set(given) - set(task.depends))
    if unknown:
        raise ValueError(f"a {task.name!r} policy takes no {', '.join(unknown)} policy")
    recorded = manifest.get("policies")
    if recorded is None:  # exported before manifests listed them
        run = (manifest.get("run_config") or {}).get("config") or {}
        recorded = {name: run[field] for name, field in task.depends.items() if run.get(field)}
    out = {}
    for name, where in recorded.items():
        if name in given:
            continue
        candidate = Path(where) if Path(where).is_absolute() else folder / where
        if (
            not (candidate / "manifest.json").exists()
            and not (candidate / "policy" / "manifest.json").exists()
        ):
            raise ValueError(
                f"{path} was trained with the {name} policy in {where}, which is not there; name one"
                f" (--{name} FOLDER)"
            )
        out[name] = str(candidate)
    return {**out, **given}


class ExportError(ValueError):
    """A run or policy folder that cannot be exported (the message says why)."""


def observation_fields(manifest: dict) -> list[dict]:
    """Every slice of the observation with its components' names and units, in order."""
    task = tasks.get(manifest["env"])
    out = []
    for name, (start, stop) in manifest["observation_layout"].items():
        try:
            names, units = (list(x) for x in task.field(name))
        except KeyError as err:
            raise ExportError(str(err.args[0])) from None
        if len(names) != 1 and len(names) != stop - start:
            raise ExportError(f"observation field {name!r} has {stop - start} values, expected {len(names)}")
        out.append({"name": name, "start": start, "stop": stop, "components": names, "units": units})
    return out


def deployment_section(manifest: dict) -> dict:
    """What a controller outside JAX needs to build observations and commands as training did."""
    env = manifest["env_config"]
    section = {
        "control_hz": CONTROL_HZ,
        "policy_layers": networks.from_spec(manifest["network"]).policy_layers(),
        "observation": observation_fields(manifest),
        "observation_normaliser": "folded into policy.onnx; obs_mean/obs_std in params.npz",
        "observation_clip": manifest["observation_clip"],
    }
    if not tasks.get(manifest["env"]).drives_base:
        return section
    robot, safety = env["robot"], env["safety"]
    num_rays = env["num_rays"]
    return {
        **section,
        "num_users": env["num_users"],
        "lidar": {
            "num_rays": num_rays,
            "angle_min": 0.0,
            "angle_increment": 2 * math.pi / num_rays,
            "direction": "counter-clockwise from the robot's +x axis",
            "max_range": env["lidar_range"],
            **_clearance(env),
        },
        "action": {
            "scale": [robot["max_speed"], robot["max_speed"], robot["max_yaw_rate"]],
            "interpolation_weights": list(env["action_weights"]),
            "deadzone_linear": env["deadzone_linear"],
            "deadzone_angular": env["deadzone_angular"],
            "frame": "robot",
        },
        "goal": {
            "tolerance": env["goal_tolerance"],
            "deadzone": env["goal_deadzone"],
            "yaw_deadzone": env["goal_yaw_deadzone"],
        },
        "footprint": {"length": KAIROS.length, "width": KAIROS.width, "radius": KAIROS.radius},
        "collision_distance": safety["collision_distance"],
        "critical_distance": safety["critical_distance"],
        **_user_order(env),
    }


def _clearance(env: dict) -> dict:
    """The footprint's clearance per sector of the scan, at the observation's end
    (``NavConfig.clearance_sectors``); nothing where the observation has none."""
    sectors = env.get("clearance_sectors", 0)
    return {"clearance_sectors": sectors, "clearance_range": CLEARANCE_RANGE} if sectors else {}


def _user_order(env: dict) -> dict:
    """How the observation orders the users: as given, or (``NavConfig.users_by_goal``) by the
    distance from the goal to each user's HIP, placed this far ahead of and beside the user."""
    if not env.get("users_by_goal", False):
        return {"user_order": "fixed"}
    hip = env["hip"]
    return {"user_order": "goal", "hip": {"distance": hip["distance"], "lateral": hip["lateral"]}}


def versions() -> dict:
    out = {"python": sys.version.split()[0]}
    for dist in ("methd-jax", "jax", "flax", "numpy", "jax2onnx", "onnx", "onnxruntime"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[dist] = None
    return out


def _convert(policy_dir: str, path: str) -> None:
    """The conversion itself (run in a child process by :func:`to_onnx`)."""
    import onnx
    from jax2onnx import to_onnx as convert  # heavy import: only when exporting

    policy = load(policy_dir)
    # onnx_ir warns about untyped shape constants of broadcasts; the model checks and runs fine
    logging.getLogger("onnx_ir").setLevel(logging.ERROR)
    model = convert(
        policy,
        [("B", policy.manifest["observation_size"])],
        model_name=f"methd_jax_{policy.manifest['env']}_policy",
        input_names=["observation"],
        output_names=["action"],
    )
    onnx.checker.check_model(model)
    Path(path).write_bytes(model.SerializeToString())


def to_onnx(policy_dir: str | Path, path: str | Path) -> Path:
    """Writes the deterministic policy of ``policy_dir`` (normalise, clip, network mean, clip to
    [-1, 1]) as ONNX with a dynamic batch axis: input ``observation`` (B, D) float32, output
    ``action`` (B, A).

    The conversion runs in a child process: jax2onnx (0.17.1) leaves its patches of ``jax.numpy``
    in place after converting (``jnp.cumsum`` stays replaced by a wrapper that rejects an axis
    argument), which would break JAX code run afterwards in the same process.
    """
    path = Path(path)
    code = "import sys; from train.export import _convert; _convert(sys.argv[1], sys.argv[2])"
    root = Path(__file__).resolve().parents[1]
    r = subprocess.run(
        [sys.executable, "-c", code, str(Path(policy_dir).resolve()), str(path.resolve())],
        capture_output=True,
        text=True,
        cwd=root,
    )
    if r.returncode != 0 or not path.exists():
        lines = [x for x in r.stderr.strip().splitlines() if x.strip()]
        raise ExportError(f"ONNX conversion failed: {lines[-1] if lines else f'exit status {r.returncode}'}")
    return path


def export_deployment(
    source: str | Path,
    out: str | Path | None = None,
    *,
    iteration: int | Sequence[int] | None = None,
    log=print,
) -> Path:
    """The deployment folder for the run or policy folder ``source`` (default ``<run>/deploy``); with
    ``iteration``, for that checkpoint of the run folder ``source`` (default ``<run>/deploy-<N>``),
    or for the average of several (default ``<run>/deploy-avg-<N1>-<N2>...``; see
    :func:`train.run.export_checkpoint`)."""
    source = Path(source)
    if not source.exists():
        raise ExportError(f"{source}: no such run or policy folder")
    if iteration is None:
        return _deploy(source, out, log)
    if not (source / "config.json").is_file():
        raise ExportError(f"--iteration takes a run folder; {source} has no config.json")
    from train import run as run_lib  # train.run imports this module

    iterations = [iteration] if isinstance(iteration, int) else list(iteration)
    with tempfile.TemporaryDirectory(prefix=".checkpoint-", dir=source) as tmp:
        try:
            run_lib.export_checkpoint(source, iterations, Path(tmp) / "policy")
        except (ConfigError, FileNotFoundError) as e:
            raise ExportError(str(e)) from None
        shutil.copyfile(source / "config.json", Path(tmp) / "config.json")
        if len(iterations) == 1:
            name, what = f"deploy-{iterations[0]}", f"checkpoint {iterations[0]} of {source}"
        else:
            its = sorted(iterations)
            name = "deploy-avg-" + "-".join(map(str, its))
            what = f"the average of checkpoints {', '.join(map(str, its))} of {source}"
        out = out if out is not None else source / name
        return _deploy(Path(tmp), out, log, what)


def _deploy(source: Path, out: str | Path | None, log, what: str | None = None) -> Path:
    policy_dir = source / "policy" if (source / "policy" / "manifest.json").exists() else source
    try:
        policy = load(policy_dir)
    except (FileNotFoundError, ValueError) as e:
        raise ExportError(str(e)) from None
    run_dir = policy_dir.parent if policy_dir.name == "policy" else None
    out = Path(out) if out is not None else (run_dir or policy_dir) / "deploy"
    if out.resolve() == policy_dir.resolve():
        raise ExportError(f"--out {out} is the policy folder itself; choose another folder")
    if out.exists() and not _replaceable(out):
        raise ExportError(
            f"--out {out} exists and is not an earlier deployment folder; choose a new or empty folder"
        )
    run_config = None
    if run_dir is not None and (run_dir / "config.json").exists():
        try:
            run_config = json.loads((run_dir / "config.json").read_text())
        except (ValueError, OSError) as e:
            raise ExportError(f"{run_dir / 'config.json'}: unreadable ({type(e).__name__}: {e})") from None
    out.parent.mkdir(parents=True, exist_ok=True)
    # built beside ``out`` and moved into place whole: a failed export leaves no half folder
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    tmp.chmod(0o755)  # mkdtemp's 0700 would make the deployment folder private
    try:
        shutil.copyfile(policy_dir / "params.npz", tmp / "params.npz")
        log(f"exporting {policy.manifest['env']} policy from {what or policy_dir} to ONNX ...")
        to_onnx(policy_dir, tmp / "policy.onnx")
        manifest = dict(policy.manifest)
        manifest.update(
            deployment=deployment_section(policy.manifest),
            onnx={"file": "policy.onnx", "input": "observation", "output": "action", "batch": "dynamic"},
            run_config=run_config,
            versions=versions(),
            params_sha256=params_sha256(tmp / "params.npz"),
            onnx_sha256=hashlib.sha256((tmp / "policy.onnx").read_bytes()).hexdigest(),
        )
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log(
        f"wrote {out} (policy.onnx, params.npz, manifest.json; "
        f"params sha256 {manifest['params_sha256'][:12]})"
    )
    return out


def _replaceable(folder: Path) -> bool:
    """An empty folder, or one that holds only what an earlier export writes."""
    return folder.is_dir() and {p.name for p in folder.iterdir()} <= {
        "manifest.json",
        "params.npz",
        "policy.onnx",
    }


def main(argv=None) -> int:
    parser = OneLineParser(
        prog="python -m train.export",
        description="Export a trained policy to a self-contained deployment folder (ONNX + manifest) "
        "that methd_jax.deploy.Controller loads with numpy and onnxruntime only.",
    )
    parser.add_argument("source", help="a run folder (runs/<name>) or its policy/ folder")
    parser.add_argument(
        "--out",
        help="deployment folder to write (default: <run>/deploy; with --iteration <run>/deploy-<N>, "
        "or <run>/deploy-avg-<N1>-<N2>... for several)",
    )
    parser.add_argument(
        "--iteration",
        type=int,
        nargs="+",
        metavar="N",
        help="export the run's checkpoint at iteration N instead of its final policy; several: "
        "the uniform average of their weights and observation statistics",
    )
    args = parser.parse_args(argv)
    try:
        export_deployment(args.source, args.out, iteration=args.iteration)
    except ExportError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
