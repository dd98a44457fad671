"""``python -m train.run [PRESET] [key=value ...]``: train a policy and write a run folder.

The run folder (``runs/<preset>-<time>`` unless ``--out``) holds ``config.json`` (preset, overrides,
the resolved configuration), ``metrics.jsonl`` (one line of scalars per iteration), TensorBoard event
files under ``tb/`` (every reward term, loss and rate), ``reward_curve.png`` (mean episode return on a
symlog axis, as in the thesis's figures), orbax checkpoints under ``checkpoints/``, the exported
policy under ``policy/`` and a ``README.md`` that says what was trained and how to use it.
``--resume RUN_DIR`` continues from the newest checkpoint exactly where the run stopped;
``--resume RUN_DIR timesteps=N`` carries a run on past its configured length.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import networks
from envs import tasks
from methd_jax.cli import OneLineParser
from methd_jax.jsonable import from_jsonable, jsonable
from methd_jax.motion import MotionDataError
from train import distributed, export
from train.checkpoint import CheckpointError, Checkpoints
from train.ppo import Trainer
from train.presets import PRESETS, ConfigError, RunConfig, apply_overrides, options, preset

CHUNK = 8
"""Iterations per compiled call of the run loop (fewer where a checkpoint or the end comes first)."""


class NonFiniteError(RuntimeError):
    """The loss or the parameters stopped being finite."""


@dataclasses.dataclass
class Setup:
    config: RunConfig
    env: object
    network_spec: dict
    trainer: Trainer


def network_spec(config: RunConfig) -> dict:
    """The network of ``config``'s task, as ``networks.from_spec`` takes it."""
    return tasks.get(config.env_name).network(config.env, config.hidden, config.init_log_std)


def dependencies(config: RunConfig) -> dict[str, str]:
    """Task name -> folder of each policy the run's environment takes (``guide_run=`` ...)."""
    task = tasks.get(config.env_name)
    return {name: getattr(config, field) for name, field in task.depends.items() if getattr(config, field)}


def absolute_folders(config: RunConfig) -> RunConfig:
    """``config`` with its folders (``init_from``, the policies its environment takes) made absolute.

    They are read relative to the working directory, but the run folder's ``config.json`` and the
    manifest of every policy it exports (which records the policies it was trained with) are read
    from anywhere, and a relative folder there would name a different place or none."""
    fields = ["init_from", *tasks.get(config.env_name).depends.values()]
    changes = {f: str(Path(getattr(config, f)).resolve()) for f in fields if getattr(config, f)}
    return dataclasses.replace(config, **changes)


def load_dependencies(folders: dict[str, str], what: str) -> dict:
    """The policies in ``folders`` (task name -> folder), each checked to be of that task."""
    policies = {}
    for name, folder in folders.items():
        try:
            policy = export.load(folder)
        except (FileNotFoundError, ValueError) as err:
            raise ConfigError(f"the {name} policy of {what}: {err}") from None
        if policy.manifest["env"] != name:
            kind = policy.manifest["env"]
            raise ConfigError(f"{folder} holds a {kind!r} policy, not a {name} policy ({what})")
        policies[name] = policy
    return policies


def build(config: RunConfig, devices=None) -> Setup:
    """The environment, network and trainer of ``config`` (kept in the setup with its folders
    absolute: :func:`absolute_folders`)."""
    config = absolute_folders(config)
    task = tasks.get(config.env_name)
    env = task.build(config.env, policies=load_dependencies(dependencies(config), "this run"))
    spec = network_spec(config)
    trainer = Trainer(
        env, networks.from_spec(spec), config.ppo, config.num_envs, devices=devices, ratios=task.ratios
    )
    return Setup(config, env, spec, trainer)


def _warm_start(state, source: Path, setup: Setup):
    """``state`` with the learned parts of ``source``: of a run folder, the newest checkpoint's
    parameters, optimiser, statistics and learning rate; of an exported policy folder, its
    parameters and observation statistics (see :func:`_from_policy`). Environments, key and
    iteration stay fresh."""
    state = _learned(state, source, setup)
    if setup.config.noise_restart:
        state = state.replace(params=_restart_noise(state.params, setup.config.init_log_std))
    return state


def _restart_noise(params, log_std: float):
    """``params`` with every ``log_std`` (the policy's action noise) set to ``log_std``."""

    def restart(path, leaf):
        return jnp.full_like(leaf, log_std) if path[-1].key == "log_std" else leaf

    return jax.tree_util.tree_map_with_path(restart, params)


def _learned(state, source: Path, setup: Setup):
    if (source / "manifest.json").is_file():
        return _from_policy(state, source, setup)
    if not (source / "checkpoints").is_dir():
        raise ConfigError(f"init_from={source}: neither a run folder with checkpoints nor a policy folder")
    ckpts = Checkpoints(source / "checkpoints")
    try:
        if ckpts.latest() is None:
            raise ConfigError(f"init_from={source}: no checkpoint there")
        learned = ckpts.restore_fields(
            state, ("params", "opt_state", "obs_stats", "value_stats", "learning_rate")
        )
    except (ValueError, KeyError, TypeError) as err:
        raise ConfigError(f"init_from={source}: its checkpoint does not fit this run ({err})") from None
    finally:
        ckpts.close()
    return state.replace(**learned)


def _from_policy(state, folder: Path, setup: Setup):
    """``state`` started from the exported policy in ``folder``, which may see fewer observation
    fields than this run (a single-user policy for two users): the parameters through
    :func:`networks.transfer_inputs` (a new field starts at zero weight), each field's
    normaliser statistics from the same field, or for a new field from its namesake up to the
    index (``user1`` from ``user0``), or for a field without either at mean 0 and variance 1
    (its inputs reach the body unscaled). The statistics keep the weight of the transitions they
    were estimated on (the manifest's ``trained.transitions``), as a resumed run's do, so that the
    policy keeps seeing the inputs it was trained on; with any borrowed field they weigh one
    iteration of data, so that the borrowed ones adapt. The optimiser, value statistics and
    learning rate stay fresh."""
    try:
        policy = export.load(folder)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(f"init_from={folder}: {err}") from None
    spec, theirs = setup.network_spec, policy.manifest["network"]
    same = {k: v for k, v in spec.items() if k != "init_log_std"}
    if {k: theirs.get(k) for k in same} != same:
        raise ConfigError(f"init_from={folder}: its network {theirs} is not this run's {spec}")
    source = {k: tuple(v) for k, v in policy.manifest["observation_layout"].items()}
    layout = getattr(setup.env, "observation_layout", None)
    size = state.obs_stats.mean.shape[0]
    target = {k: (v.start, v.stop) for k, v in layout.items()} if layout else {"obs": (0, size)}
    if spec["class"] not in ("ActorCritic", "GuideActorCritic") and source != target:
        raise ConfigError(f"init_from={folder}: its observation differs from this run's")
    try:
        if spec["class"] == "ActorCritic":
            params = networks.transfer_inputs(policy.params, state.params, spec["num_rays"], source, target)
        elif source != target:
            params = networks.transfer_guide_inputs(policy.params, state.params, source, target)
        else:
            params = policy.params
            if _shapes(params) != _shapes(state.params):
                raise ValueError(f"{_shapes(params)} against {_shapes(state.params)}")
    except (ValueError, KeyError) as err:
        raise ConfigError(f"init_from={folder}: its parameters do not fit this run ({err})") from None
    mean, var = np.zeros(size, np.float32), np.ones(size, np.float32)
    borrowed = False
    for name, (a, b) in target.items():
        origin = source.get(name) or source.get(name.rstrip("0123456789") + "0")
        if origin is not None and origin[1] - origin[0] == b - a:
            mean[a:b] = policy.obs_mean[origin[0] : origin[1]]
            var[a:b] = np.asarray(policy.obs_std[origin[0] : origin[1]]) ** 2
            borrowed = borrowed or name not in source
    iteration = setup.trainer.transitions_per_iteration
    trained = int(policy.manifest.get("trained", {}).get("transitions") or 0)
    count = iteration if borrowed else max(iteration, trained)
    stats = state.obs_stats.replace(mean=mean, var=var, count=np.float32(count))
    # onto the devices (and shardings) of the fresh state's arrays
    place = functools.partial(jax.tree.map, lambda new, old: jax.device_put(new, old.sharding))
    return state.replace(params=place(params, state.params), obs_stats=place(stats, state.obs_stats))


def _anchored(state):
    """``state`` anchored (``ppo.anchor_scale``) to its own policy: a copy, since each compiled
    chunk donates the state's buffers and one buffer cannot be donated twice."""
    return state.replace(
        anchor=jax.tree.map(jnp.copy, {"params": state.params, "obs_stats": state.obs_stats})
    )


def _shapes(tree) -> list:
    return [(jax.tree_util.keystr(k), v.shape) for k, v in jax.tree_util.tree_leaves_with_path(tree)]


def _symlog_curve(rows: list[dict], path: Path, title: str, ratios: dict) -> None:
    """Mean episode return and mean reward per step against transitions (symlog, as the thesis plots
    rewards), and the task's ratios (``envs.tasks.Ratio``, e.g. GuideRL's accuracy at the request)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ended = [r for r in rows if r["episode/count"] > 0]
    panels = [
        ("mean episode return", [(r["transitions"], r["episode/return"]) for r in ended]),
        ("mean reward per step", [(r["transitions"], r["reward/step"]) for r in rows]),
    ]
    for name, ratio in ratios.items():
        pts = [(r["transitions"], 100 * r[name]) for r in rows if r.get(ratio.count, 0) > 0]
        if pts:
            panels.append((f"{ratio.label} (%)", pts))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4), squeeze=False)
    for ax, (label, pts) in zip(axes[0], panels, strict=True):
        if pts:
            x, y = np.array(pts).T
            ax.plot(x, y, lw=0.8, alpha=0.45, label="per iteration")
            k = max(1, len(y) // 20)
            if len(y) > 2 * k > 1:
                ax.plot(x[k - 1 :], np.convolve(y, np.ones(k) / k, mode="valid"), lw=2, label=f"mean of {k}")
            ax.legend(loc="lower right")
        if not label.endswith("(%)"):
            ax.set_yscale("symlog")
        ax.set(xlabel="environment transitions", ylabel=label)
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _read_rows(path: Path) -> list[dict]:
    """The rows of a run's ``metrics.jsonl``; a torn last line (a kill while appending) is dropped,
    anything else that is not one of our rows is refused (:class:`ConfigError`)."""
    if not path.exists():
        return []
    try:
        lines = [line for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: unreadable ({type(e).__name__})") from None
    rows = []
    for i, line in enumerate(lines):
        try:
            row = json.loads(line)
        except ValueError:
            if i == len(lines) - 1:
                break
            raise ConfigError(f"{path}: line {i + 1} is not JSON; not this run's metrics") from None
        if not (isinstance(row, dict) and isinstance(row.get("iteration"), int)):
            raise ConfigError(f"{path}: line {i + 1} is not a metrics row of a run; not this run's metrics")
        rows.append(row)
    return rows


def _write_readme(run_dir: Path, setup: Setup, meta: dict, rows: list[dict]) -> None:
    c = setup.config
    last = [r for r in rows if r.get("episode/count", 0) > 0][-10:]
    final_return = np.mean([r["episode/return"] for r in last]) if last else float("nan")
    lines = [
        f"# Training run `{run_dir.name}`",
        "",
        f"Preset `{meta['preset']}`"
        + (f" with overrides `{' '.join(meta['overrides'])}`" if meta["overrides"] else ""),
        f"({PRESETS[meta['preset']][0] if meta['preset'] in PRESETS else 'configured in Python'}).",
        "",
        "| | |",
        "|---|---|",
        f"| environment | `{c.env_name}` ({c.num_envs} parallel) |",
        f"| iterations | {meta['iteration']} of {c.iterations} ({c.ppo.rollouts} x {c.num_envs} steps) |",
        f"| transitions | {meta['iteration'] * c.ppo.rollouts * c.num_envs:,} |",
        f"| network | {setup.network_spec['class']} {tuple(c.hidden)}: {meta['policy_parameters']:,} policy "
        f"parameters ({meta['parameters']:,} with the critic) |",
        f"| wall clock | {meta['wall_s'] / 60:.1f} min on {meta['device']} |",
        f"| throughput | {meta['transitions_per_s']:,.0f} transitions/s (with updates, after compiling) |",
        f"| mean episode return (last 10 iterations with episodes) | {final_return:.1f} |",
    ]
    task = tasks.get(c.env_name)
    for name, ratio in task.ratios.items():
        seen = [r[name] for r in rows if r.get(ratio.count, 0) > 0][-10:]
        shown = f"{100 * np.mean(seen):.1f}%" if seen else "none yet"
        lines.append(f"| {ratio.label} (last 10 iterations) | {shown} |")
    lines += [
        "",
        "Files: `config.json` (the resolved configuration), `metrics.jsonl` (scalars per iteration),",
        "`tb/` (TensorBoard: `tensorboard --logdir " + str(run_dir / "tb") + "`), `reward_curve.png`,",
        "`checkpoints/` (orbax), `policy/` (the exported policy: `params.npz` + `manifest.json`).",
        "",
        "Continue this run: `python -m train.run --resume " + str(run_dir) + "`",
        "",
        "Use the policy (deterministic, observations as the environment produces them):",
        "",
        "```python",
        "import jax",
        "from train import export, run",
        f"policy = export.load({str(run_dir)!r})",
        f"env = run.build(run.load_config({str(run_dir)!r})[2]).env",
        "state = env.reset(jax.random.key(0))",
        "state = env.step(state, policy(state.obs))",
        "```",
    ]
    if task.readme is not None:
        lines += ["", *task.readme(str(run_dir))]
    (run_dir / "README.md").write_text("\n".join(lines) + "\n")


def train(
    config: RunConfig,
    run_dir: str | Path,
    *,
    preset_name: str = "custom",
    overrides: tuple[str, ...] = (),
    resume: bool = False,
    progress: bool = True,
    stop_after: int | None = None,
    max_minutes: float | None = None,
    devices=None,
) -> dict:
    """Train ``config`` into ``run_dir`` (resuming from its newest checkpoint if ``resume``).

    ``stop_after``: leave after this many iterations in total (for tests of interrupted runs); the
    checkpoint schedule is unchanged. ``max_minutes``: end early, with a checkpoint and the export,
    after the first call (:data:`CHUNK` iterations or fewer) that finishes past this much wall time
    (``--resume`` continues).
    Returns the run's summary. Raises :class:`NonFiniteError`.
    """
    from tensorboardX import SummaryWriter
    from tqdm import tqdm

    run_dir = Path(run_dir)
    primary = distributed.is_primary()  # the process that writes the run folder
    progress = progress and primary
    earlier_rows = _read_rows(run_dir / "metrics.jsonl") if resume else []  # checked before any write
    distributed.barrier("run folder checked")
    setup = build(config, devices)
    config, trainer = setup.config, setup.trainer
    processes = f" in {jax.process_count()} processes" if jax.process_count() > 1 else ""
    meta = {
        "preset": preset_name,
        "overrides": list(overrides),
        "config": jsonable(config),
        "device": f"{trainer.mesh.devices.size} x {jax.devices()[0].device_kind} "
        f"({jax.default_backend()}){processes}",
    }

    log = (lambda *a: tqdm.write(" ".join(map(str, a)), file=sys.stderr)) if progress else (lambda *a: None)
    init = jax.jit(trainer.init)
    # CHUNK iterations per compiled call, the state's buffers donated to the next: one dispatch and
    # one host round trip per chunk instead of per iteration
    run_chunk = jax.jit(trainer.run_upto, static_argnums=2, donate_argnums=0)
    state = init(jax.random.key(config.seed))
    start = 0
    # a start that fails here (a warm start that does not fit) leaves no run folder behind
    if config.init_from and not resume:
        state = _warm_start(state, Path(config.init_from), setup)
        source = Path(config.init_from)
        what = "the exported policy" if (source / "manifest.json").is_file() else "the newest checkpoint of"
        log(f"started from {what} {source}")
        if config.ppo.anchor_scale:
            state = _anchored(state)
        if config.critic_warmup:
            began = time.perf_counter()
            fit = jax.jit(trainer.fit_critic, static_argnums=1, donate_argnums=0)
            state, losses = fit(state, config.critic_warmup)
            losses = np.asarray(losses)
            log(
                f"fitted the critic alone for {config.critic_warmup} iterations "
                f"({config.critic_warmup * trainer.transitions_per_iteration:,} transitions, "
                f"{time.perf_counter() - began:.0f} s): value loss {losses[0]:.3g} -> {losses[-1]:.3g}"
            )
    run_dir.mkdir(parents=True, exist_ok=True)
    if primary:
        (run_dir / "config.json").write_text(json.dumps(meta, indent=2) + "\n")
    ckpts = Checkpoints(run_dir / "checkpoints", keep=config.checkpoint_keep or None)
    if resume:
        if config.ppo.anchor_scale:  # the checkpoint holds the anchor; this gives it its shape
            state = _anchored(state)
        state, _ = ckpts.restore_intact(state, log)
        start = int(state.iteration)
        log(f"resumed {run_dir} at iteration {start}")
    rows = [r for r in earlier_rows if r["iteration"] <= start]
    if primary:
        (run_dir / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))

    params = state.params
    meta["parameters"], meta["policy_parameters"] = networks.count(params), networks.policy_count(params)
    thesis = tasks.get(config.env_name).thesis_parameters
    log(
        f"{setup.network_spec['class']}: {meta['policy_parameters']:,} policy params"
        + (f" (thesis {thesis:,}), " if thesis else ", ")
        + f"{meta['parameters']:,} with the critic; {config.num_envs} envs on {meta['device']}; "
        f"{config.iterations} iterations of {trainer.transitions_per_iteration:,} transitions"
    )

    per = trainer.transitions_per_iteration
    end = config.iterations if stop_after is None else min(config.iterations, stop_after)
    writer = SummaryWriter(str(run_dir / "tb")) if primary else _NoWriter()
    bar = tqdm(
        total=config.iterations * per,
        initial=start * per,
        unit="steps",
        unit_scale=True,
        disable=not progress,
        dynamic_ncols=True,
        mininterval=2.0,
        file=sys.stderr,
    )
    t_begin, timed, timed_s = time.perf_counter(), 0, 0.0
    post = {"return": "-", "len": "-"}
    last_saved = ckpts.latest()
    try:
        it = start
        while it < end:
            # a chunk never crosses a checkpoint, so the schedule is the same whatever CHUNK is
            count = min(CHUNK, end - it, config.checkpoint_every - it % config.checkpoint_every)
            t0 = time.perf_counter()
            state, stacked = run_chunk(state, jnp.int32(count), CHUNK)
            stacked = jax.device_get(stacked)
            dt = (time.perf_counter() - t0) / count
            for j in range(count):
                m = {k: float(v[j]) for k, v in stacked.items()}
                if not m.pop("finite"):
                    where = f"iteration {last_saved} in {ckpts.directory}" if last_saved else "none yet"
                    raise NonFiniteError(
                        f"non-finite loss or parameters at iteration {it + j + 1}; stopped. "
                        f"Last good checkpoint: {where}"
                    )
                row = {"iteration": it + j + 1, "transitions": (it + j + 1) * per, "seconds": dt, **m}
                _record(row, m, rows, writer, run_dir if primary else None, per)
                post = _postfix(m, post, trainer.ratios)
            if it > start:  # the first call of a process includes compilation
                timed, timed_s = timed + count, timed_s + dt * count
            it += count
            bar.set_postfix(post, refresh=False)
            bar.update(per * count)
            out_of_time = max_minutes is not None and time.perf_counter() - t_begin >= 60 * max_minutes
            out_of_time = distributed.agree(out_of_time)  # every process saves the same checkpoints
            if it % config.checkpoint_every == 0 or it == config.iterations or out_of_time:
                ckpts.save(it, state)
                last_saved = it
                if primary:
                    _symlog_curve(
                        rows, run_dir / "reward_curve.png", f"{preset_name}: {run_dir.name}", trainer.ratios
                    )
            if out_of_time:
                log(f"stopping after iteration {it}: the {max_minutes:g}-minute budget is spent")
                break
    finally:
        bar.close()
        writer.close()
        ckpts.close()

    meta["iteration"] = int(state.iteration)
    meta["wall_s"] = time.perf_counter() - t_begin
    # with no chunk past the first (compilation included), the rate over the whole wall time
    done = meta["iteration"] - start
    meta["transitions_per_s"] = timed * per / timed_s if timed else per * max(1, done) / meta["wall_s"]
    if primary:
        _export(setup, run_dir / "policy", state.params, state.obs_stats, run_dir, meta["iteration"])
        _symlog_curve(rows, run_dir / "reward_curve.png", f"{preset_name}: {run_dir.name}", trainer.ratios)
        _write_readme(run_dir, setup, meta, rows)
    distributed.barrier("run folder written")
    log(f"wrote {run_dir} ({meta['transitions_per_s']:,.0f} transitions/s)")
    return {**meta, "rows": rows, "state": state}


def _record(row: dict, m: dict, rows: list, writer, run_dir: Path | None, per: int) -> None:
    """One iteration's metrics into ``metrics.jsonl`` (when ``run_dir``), ``rows`` and TensorBoard."""
    if run_dir is not None:
        with (run_dir / "metrics.jsonl").open("a") as f:
            f.write(json.dumps(row) + "\n")
    rows.append(row)
    for k, v in m.items():
        if k.startswith("episode/") and m["episode/count"] == 0:
            continue
        writer.add_scalar(k, v, row["transitions"])
    writer.add_scalar("perf/transitions_per_s", per / row["seconds"], row["transitions"])


def _postfix(m: dict, last: dict, ratios: dict) -> dict:
    """The progress bar's text: the newest episode return and length, the task's ratios."""
    post = dict(last)
    if m["episode/count"] > 0:
        post |= {"return": f"{m['episode/return']:.1f}", "len": f"{m['episode/length'] / 50:.1f}s"}
    for name, ratio in ratios.items():
        if m.get(ratio.count, 0) > 0:
            post[ratio.short] = f"{100 * m[name]:.0f}%"
    return post


class _NoWriter:
    """TensorBoard's writer on the processes that do not write the run folder."""

    def add_scalar(self, *args):
        pass

    def close(self):
        pass


def _help_epilog() -> str:
    lines = ["presets:"]
    lines += [f"  {name:<7} {text}" for name, (text, _) in PRESETS.items()]
    lines += ["", "options (key=value; defaults of the su preset; tuples comma-separated):"]
    for name, value, doc in options(preset("su")):
        shown = ",".join(map(str, value)) if isinstance(value, tuple) else value
        lines.append(f"  {name}={shown}" + (f"  -- {doc}" if doc else ""))
    lines += ["", "example: python -m train.run su num_envs=1024 ppo.learning_rate=3e-4 env.lab=true"]
    return "\n".join(lines)


def export_checkpoint(run_dir: str | Path, iteration: int | Sequence[int], out: str | Path) -> Path:
    """The policy of the checkpoint at ``iteration`` of the run in ``run_dir`` exported to the
    policy folder ``out``, as the run exports its last one to ``policy/``; with several iterations,
    the uniform average of their parameters and observation statistics (a weight average of one
    run's late checkpoints, as in stochastic weight averaging, Izmailov et al. 2018).
    :class:`ConfigError` names the iterations there when one of ``iteration`` is not."""
    run_dir = Path(run_dir)
    iterations = [iteration] if isinstance(iteration, int) else list(iteration)
    if not iterations or len(set(iterations)) != len(iterations):
        raise ConfigError(f"iterations to export must be distinct and at least one, got {iterations}")
    _, _, config = load_config(run_dir)
    if not (run_dir / "checkpoints").is_dir():
        raise ConfigError(f"{run_dir} has no checkpoints folder")
    ckpts = Checkpoints(run_dir / "checkpoints")
    try:
        steps = ckpts.steps()
        missing = [i for i in iterations if i not in steps]
        if missing:
            have = ", ".join(map(str, steps)) or "none"
            raise ConfigError(
                f"{run_dir} has no checkpoint at iteration {', '.join(map(str, missing))} (it has: "
                f"{have}; a run keeps every one with checkpoint_keep=0)"
            )
        setup = build(config)
        state = jax.jit(setup.trainer.init)(jax.random.key(config.seed))
        learned = []
        for it in iterations:
            try:
                learned.append(ckpts.restore_fields(state, ("params", "obs_stats"), it))
            except (ValueError, KeyError, TypeError) as err:
                raise ConfigError(f"{run_dir}: checkpoint {it} does not restore ({err})") from None
    finally:
        ckpts.close()
    if len(learned) == 1:
        params, obs_stats = learned[0]["params"], learned[0]["obs_stats"]
    else:
        # in float64: the average does not depend on the order the checkpoints are named in
        # beyond float32's rounding; the normaliser's variance is averaged like a weight
        def mean(*xs):
            return np.mean(np.stack([np.asarray(x, np.float64) for x in xs]), 0).astype(np.float32)

        params = jax.tree.map(mean, *[d["params"] for d in learned])
        obs_stats = jax.tree.map(mean, *[d["obs_stats"] for d in learned])
    trained_at = max(iterations)
    averaged = sorted(iterations) if len(iterations) > 1 else None
    return _export(setup, out, params, obs_stats, run_dir, trained_at, averaged)


def _export(
    setup: Setup,
    out: Path,
    params,
    obs_stats,
    run_dir: Path,
    iteration: int,
    averaged: list[int] | None = None,
) -> Path:
    """The policy ``params`` + ``obs_stats`` of ``run_dir`` at ``iteration`` as the policy folder
    ``out``; ``averaged`` names the checkpoints whose average they are."""
    config = setup.config
    trained = {
        "run": str(run_dir),
        "iteration": iteration,
        "transitions": iteration * setup.trainer.transitions_per_iteration,
    }
    if averaged:
        trained["averaged_iterations"] = averaged
    return export.export(
        out,
        env_name=config.env_name,
        env=setup.env,
        network_spec=setup.network_spec,
        params=params,
        obs_stats=obs_stats,
        obs_clip=config.ppo.obs_clip,
        policies=dependencies(config),
        trained=trained,
    )


def load_config(run_dir: str | Path) -> tuple[str, list[str], RunConfig]:
    """The preset, overrides and configuration of the run in ``run_dir``: the resolved configuration
    ``config.json`` stored when the run started, so that a run started from Python resumes and a
    preset changed since does not change the run (a folder from before the resolved configuration
    was stored is rebuilt from its preset and overrides)."""
    meta_path = Path(run_dir) / "config.json"
    if not meta_path.exists():
        raise ConfigError(f"{run_dir} is not a run folder (no config.json)")
    try:
        meta = json.loads(meta_path.read_text())
        name, overrides = meta["preset"], meta["overrides"]
        stored = meta.get("config")
    except (ValueError, KeyError, TypeError) as err:
        raise ConfigError(f"{meta_path}: unreadable ({type(err).__name__}: {err})") from None
    if stored is None:
        return name, overrides, apply_overrides(preset(name), overrides)
    try:
        kind = stored["env_name"]
        default = RunConfig(env_name=kind, env=tasks.get(kind).config)
        return name, overrides, from_jsonable(default, stored)
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(
            f"{meta_path}: its configuration does not load ({type(err).__name__}: {err})"
        ) from None


def _extended(config: RunConfig, overrides: list[str]) -> RunConfig:
    """``config`` with a longer ``timesteps`` if ``overrides`` asks for one, the only option a
    resumed run may change: more iterations of the same run continue its optimiser, its critic and
    its normalisers, where a new run from its export would refit and restart them."""
    if not overrides:
        return config
    if [o.partition("=")[0].strip() for o in overrides] != ["timesteps"]:
        raise ConfigError(
            "--resume continues a run as configured (timesteps=N alone may extend it); "
            "start a new run to change options"
        )
    longer = apply_overrides(config, overrides)
    if longer.timesteps < config.timesteps:
        raise ConfigError(
            f"--resume can extend a run, not shorten it: {overrides[0]} is below the run's "
            f"timesteps={config.timesteps}"
        )
    return longer


def main(argv=None) -> int:
    parser = OneLineParser(
        prog="python -m train.run",
        description="Train the thesis's policies with PPO and write a run folder.",
        epilog=_help_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("preset", nargs="?", help="one of: " + ", ".join(PRESETS) + " (default quick)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="options to change (listed below)")
    parser.add_argument("--out", type=Path, help="run folder (default: runs/<preset>-<date>-<time>)")
    parser.add_argument(
        "--resume",
        type=Path,
        metavar="RUN_DIR",
        help="continue the run in RUN_DIR (with timesteps=N: to a new, larger length)",
    )
    parser.add_argument(
        "--max-minutes",
        type=float,
        metavar="M",
        help="end early (checkpoint and export) after the iteration that passes M minutes of wall time",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    cluster = parser.add_argument_group(
        "several processes or hosts (jax.distributed; every process runs the same command)"
    )
    cluster.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0's coordinator")
    cluster.add_argument("--num-processes", type=int, metavar="N", help="processes in the job")
    cluster.add_argument("--process-id", type=int, metavar="I", help="this process's index, 0 to N-1")
    cluster.add_argument(
        "--distributed",
        action="store_true",
        help="join the job JAX detects (SLURM, Open MPI, ...) instead of the three flags above",
    )
    args = parser.parse_args(argv)
    overrides = list(args.overrides)
    if args.preset is not None and "=" in args.preset:  # `python -m train.run num_envs=8`: no preset
        overrides.insert(0, args.preset)
        args.preset = None
    try:
        cluster_flags = (args.coordinator, args.num_processes, args.process_id)
        if args.distributed or any(x is not None for x in cluster_flags):
            if args.out is None and args.resume is None:
                raise ConfigError("multi-process training needs --out (or --resume): one folder for all")
            distributed.initialize(*cluster_flags, auto=args.distributed)
        if args.max_minutes is not None and not args.max_minutes > 0:
            raise ConfigError(f"--max-minutes must be positive, got {args.max_minutes}")
        if args.resume is not None:
            if args.out is not None:
                raise ConfigError("--resume continues a run in its own folder; --out starts a new one")
            if args.preset is not None:
                raise ConfigError(f"--resume continues the run's own preset; leave out {args.preset!r}")
            name, stored, config = load_config(args.resume)
            config = _extended(config, overrides)
            overrides = [*stored, *overrides]
            run_dir = args.resume
        else:
            name = args.preset or "quick"
            config = apply_overrides(preset(name), overrides)
            run_dir = args.out or Path("runs") / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"
            if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
                what = "holds checkpoints" if (run_dir / "checkpoints").is_dir() else "is not an empty folder"
                raise ConfigError(f"{run_dir} {what}; use --resume {run_dir} or another --out")
        train(
            config,
            run_dir,
            preset_name=name,
            overrides=tuple(overrides),
            resume=args.resume is not None,
            progress=not args.quiet,
            max_minutes=args.max_minutes,
        )
    except (ConfigError, CheckpointError, FileNotFoundError, MotionDataError) as err:
        print(f"python -m train.run: error: {err}", file=sys.stderr)
        return 2
    except NonFiniteError as err:
        print(f"train.run: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("train.run: interrupted; resume with --resume from the last checkpoint", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
