"""``python -m train.rollout [RUN] [--env NAME] [key=value ...]``: watch one episode.

Records one episode of a trained policy (a run folder or an exported policy folder; its environment
and configuration come from the policy's manifest) or, without ``RUN``, of ``--env`` with the robot
standing still, and writes into ``--out``:

- ``frame.png``: top-down picture at the request (or the last step);
- ``rollout.gif``: the episode until it ends (every ``--stride``-th control step, real time);
- ``scan.png``: the LiDAR scan at the same step in polar form (``su`` / ``nav``);
- ``u_w.png``: the user weight over time against the requester (``guide``, two-user ``nav``);
- ``rollout.mcap``: everything as Foxglove scene, LaserScan and pose channels.

A task the pictures cannot draw (``envs.tasks.Task.pictures``) gets ``episode.npz`` instead
(observations, actions, rewards, done flags). ``key=value`` options change the environment (fields
of the task's configuration, for example ``lab=true`` or ``motion=sample``). A NavRL policy drives
its goal with the GuideRL policy it was trained with (``--guide`` names another).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

import envs
from envs import tasks
from methd_jax import viz
from methd_jax.cli import OneLineParser
from train import export
from train.presets import ConfigError, override
from train.run import load_dependencies


def build(
    run: str | None, env_name: str | None, overrides: list[str], policies: dict[str, str] | None = None
):
    """(task, environment, policy or None) for ``run`` or ``env_name``, with ``overrides`` applied; the
    policies ``run`` was trained with (GuideRL for NavRL) from ``policies`` (task name -> folder)
    or where its manifest records them."""
    if run is None:
        name = env_name or "su"
        if name not in tasks.TASKS:
            raise ConfigError(f"--env must be one of {', '.join(tasks.TASKS)}, got {name!r}")
        task = tasks.get(name)
        return task, task.build(override(task.config, overrides)), None
    try:
        policy = export.load(run)
        folders = export.dependencies(run, policies)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(str(err)) from None
    name = policy.manifest["env"]
    if env_name is not None and env_name != name:
        raise ConfigError(f"{run} holds a {name!r} policy; drop --env or pass --env {name}")
    task = tasks.get(name)
    config = override(task.config_from(policy.manifest["env_config"]), overrides)
    return task, task.build(config, policies=load_dependencies(folders, run)), policy


def trimmed(rollout: viz.Rollout, tail: int = 25) -> viz.Rollout:
    """The rollout up to ``tail`` steps after the episode ended (the world is frozen beyond)."""
    if not rollout.done.any():
        return rollout
    end = min(int(np.argmax(rollout.done)) + tail + 1, rollout.num_steps)
    arrays = {k: v[:end] for k, v in vars(rollout).items() if isinstance(v, np.ndarray)}
    return dataclasses.replace(rollout, **arrays)


def key_step(rollout: viz.Rollout) -> int:
    """The step a still picture shows: the request, or the last step when none fired."""
    return int(np.argmax(rollout.requested)) if rollout.requested.any() else rollout.num_steps - 1


def write_all(rollout: viz.Rollout, out: Path, stride: int, log=print) -> dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    i = key_step(rollout)
    files = {"frame": out / "frame.png"}
    viz.frame(rollout, i, files["frame"])
    if rollout.ranges is not None:
        files["scan"] = out / "scan.png"
        viz.polar_scan(rollout.ranges[i], max_range=rollout.lidar_range, path=files["scan"])
    if rollout.u_w is not None:
        files["u_w"] = out / "u_w.png"
        viz.user_weight(rollout, path=files["u_w"])
    files["mcap"] = viz.to_mcap(rollout, out / "rollout.mcap")
    log(f"writing the animation ({rollout.num_steps} steps, every {stride}th) ...")
    files["gif"] = viz.animate(rollout, out / "rollout.gif", stride=stride, progress=True)
    return files


def summary(rollout: viz.Rollout) -> str:
    parts = [f"{rollout.env}: {rollout.num_steps} steps recorded"]
    if rollout.requested.any():
        parts.append(f"user {rollout.requester + 1} requested at {rollout.t[key_step(rollout)]:.1f} s")
    if rollout.done.any():
        parts.append(f"episode ended at {rollout.t[np.argmax(rollout.done)]:.1f} s: {rollout.outcome}")
    if rollout.robot is not None:
        d_goal = np.linalg.norm(rollout.robot[-1, :2] - rollout.goal[-1, :2])
        d_user = np.linalg.norm(rollout.robot[:, None, :2] - rollout.users[..., :2], axis=-1).min()
        parts.append(f"final distance to goal {d_goal:.2f} m, closest user {d_user:.2f} m")
    return "; ".join(parts)


def trace_summary(name: str, arrays: dict) -> str:
    done = arrays["done"]
    steps = int(np.argmax(done)) + 1 if done.any() else len(done)
    ended = (
        f"episode ended after {steps} steps" if done.any() else f"episode still running after {steps} steps"
    )
    return f"{name}: {ended}, return {float(arrays['reward'][:steps].sum()):.2f}"


def main(argv=None) -> int:
    ap = OneLineParser(
        prog="python -m train.rollout",
        description="Record one episode and write a frame, a GIF, a polar scan and a Foxglove MCAP.",
    )
    ap.add_argument(
        "run", nargs="?", help="run folder or exported policy folder (omit to watch --env standing still)"
    )
    ap.add_argument("overrides", nargs="*", metavar="key=value", help="environment options, e.g. lab=true")
    ap.add_argument("--env", choices=list(tasks.TASKS), help="environment without a policy (default su)")
    ap.add_argument(
        "--guide", help="GuideRL policy folder for a NavRL policy (default: the one it was trained with)"
    )
    ap.add_argument(
        "--steps", type=int, default=1500, help="control steps to record, at 50 Hz (default 1500)"
    )
    ap.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    ap.add_argument("--stride", type=int, default=5, help="animation frame every N control steps (default 5)")
    ap.add_argument("--out", type=Path, help="output folder (default RUN/rollout, or rollout-ENV)")
    args = ap.parse_args(argv)
    # a lone key=value lands in `run`: argparse fills positionals left to right
    if args.run is not None and "=" in args.run and not Path(args.run).exists():
        args.overrides, args.run = [args.run, *args.overrides], None
    if args.steps < 1 or args.stride < 1:
        ap.error("--steps and --stride must be at least 1")
    try:
        task, env, policy = build(
            args.run, args.env, args.overrides, {"guide": args.guide} if args.guide else None
        )
    except (ConfigError, ValueError) as err:
        ap.error(str(err))
    out = args.out or (Path(args.run) / "rollout" if args.run else Path(f"rollout-{args.env or 'su'}"))
    print(
        f"recording {args.steps} steps of {'the policy in ' + args.run if args.run else args.env or 'su'} ..."
    )
    key = jax.random.key(args.seed)
    if not task.pictures:
        arrays = envs.trace(env, key, args.steps, policy)
        out.mkdir(parents=True, exist_ok=True)
        np.savez(out / "episode.npz", **arrays)
        print(trace_summary(task.name, arrays))
        print(f"  arrays {out / 'episode.npz'} (obs, action, reward, done)")
        return 0
    rollout = trimmed(envs.record(env, key, args.steps, policy))
    print(summary(rollout))
    files = write_all(rollout, out, args.stride)
    for kind, path in files.items():
        print(f"  {kind:5s} {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
