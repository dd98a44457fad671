"""``python -m train.distill``: the deployment's safety layer distilled into a single-user policy.

The evaluation's "DRL + safety" row puts the robot's safety layer between the policy and the base;
this trains the policy network to act as that pair does, so that the policy alone keeps off
furniture where the layer would have stopped it. It is DAgger (Ross, Gordon and Bagnell 2011):
the teacher is the source policy with the layer after it, the student starts as the source policy.
Each round the student drives ``num_envs`` environments of the source's own ``su`` configuration
(its floors, lab share and training trajectories) for ``steps_per_round`` steps, and, with
``engine_steps``, the evaluation's behaviour engine on the lab twin (where it takes the base over
from the engine's Escape and Inform, which training never does); every step is
labelled with the action whose command is the teacher's after the layer
(:meth:`envs.nav.NavEnv.safety_target`, on the evaluation's dense exact scan), the round's steps
join those of the rounds before, and the student's Gaussian mean is fitted to the labels by
regression (steps the layer changed weigh ``changed_weight`` times the others). Where the layer
leaves the source's action alone, the label is that action: the student is held to the source
there, with no reward or critic to drift on. The result is an exported policy folder (ONNX,
parameters, manifest) that every loader of trained policies takes.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import tempfile
import time
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from envs import tasks
from envs.evaluation import Policy, PolicyState
from envs.wrappers import AutoReset
from methd_jax import floors, lidar
from methd_jax import robot as robot_lib
from methd_jax.cli import OneLineParser
from methd_jax.deploy.safety import SafetyConfig
from methd_jax.evaluation import engine as engine_lib
from methd_jax.geometry import KAIROS
from methd_jax.normalise import normalise
from train import export


@dataclasses.dataclass(frozen=True)
class DistillConfig:
    """How much the student sees and how it is fitted."""

    rounds: int = 6
    """Rounds of collecting with the current student and fitting on everything collected."""
    steps_per_round: int = 131_072
    """Environment steps collected per round (rounded up to whole collections of
    ``num_envs`` x ``chunk``)."""
    num_envs: int = 128
    chunk: int = 256
    """Steps per environment in one compiled collection."""
    epochs: int = 3
    """Passes over the collected steps per round."""
    batch_size: int = 1024
    learning_rate: float = 1e-4
    changed_weight: float = 4.0
    """Weight of a step whose command the layer changed (the others weigh 1)."""
    engine_steps: int = 0
    """Steps per round, besides the environments', in the evaluation's behaviour engine on the lab
    twin with the training trajectories in a shuffled sequence: the states a policy meets there
    and never in training (taking over from the engine's Escape and Inform with the base moving,
    the base carried from one user's episode to the next). 0: none."""
    seed: int = 7
    """Key of the environments and the engine (the fit's shuffles use the round number)."""

    def __post_init__(self):
        for name in (
            "rounds",
            "steps_per_round",
            "num_envs",
            "chunk",
            "epochs",
            "batch_size",
            "engine_steps",
        ):
            value = getattr(self, name)
            least = 0 if name == "engine_steps" else 1
            if not isinstance(value, int) or isinstance(value, bool) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        if not (self.learning_rate > 0 and math.isfinite(self.learning_rate)):
            raise ValueError(f"learning_rate must be a positive number, got {self.learning_rate}")
        if not (self.changed_weight > 0 and math.isfinite(self.changed_weight)):
            raise ValueError(f"changed_weight must be a positive number, got {self.changed_weight}")

    @property
    def collections(self) -> int:
        return -(-self.steps_per_round // (self.num_envs * self.chunk))


class DistillError(ValueError):
    """A source or option that cannot be distilled; the message is one line."""


def _load_su(path: str | Path, what: str) -> export.Policy:
    try:
        policy = export.load(path)
    except (FileNotFoundError, ValueError) as e:
        raise DistillError(f"{what}: {e}") from None
    if policy.manifest.get("env") != "su":
        raise DistillError(f"{what} {path} is a {policy.manifest.get('env')!r} policy; distillation takes su")
    return policy


@struct.dataclass
class _Seen:
    policy: PolicyState
    obs: jax.Array  # the policy's raw observation at the last Chase step
    target: jax.Array  # the teacher's label there
    changed: jax.Array  # whether the layer changed the teacher's command
    acted: jax.Array  # whether the policy drove at this step (Chase)
    student: dict  # the student's parameters: data, so that one compiled engine serves every round


class _Recorder(Policy):
    """The student in the engine's Chase, keeping what it saw and the teacher's label for it."""

    def __init__(self, distiller: Distiller):
        super().__init__(distiller.env, policy=None, name="student")
        self.distiller = distiller
        self.student = distiller.teacher.params
        """The parameters a run starts with (:meth:`_RecordingEngine._begin` carries them on)."""

    def init(self):
        size = self.env.observation_size
        false = jnp.bool_(False)
        return _Seen(super().init(), jnp.zeros(size), jnp.zeros(3), false, false, self.student)

    def idle(self, state, ctx):
        return state.replace(policy=super().idle(state.policy, ctx), acted=jnp.bool_(False))

    def chase(self, state, ctx):
        d = self.distiller
        policy, world, obs = self.observe(state.policy, ctx)
        teacher = jnp.clip(d.mean(d.teacher.params, obs), -1.0, 1.0)
        labelled = world.replace(actions=policy.actions[:2])  # the two actions the command blends in
        target, changed = self.env.safety_target(
            labelled, teacher, ctx.scan, d.safety, ctx.users, ctx.present
        )
        policy, order = self.act(policy, ctx, world, jnp.clip(d.mean(state.student, obs), -1.0, 1.0))
        return _Seen(policy, obs, target, changed, jnp.bool_(True), state.student), order


class _RecordingEngine(engine_lib.Engine):
    def _begin(self, s, schedule, k):
        # a new episode resets the method's state, but not the student it runs
        new = super()._begin(s, schedule, k)
        return new.replace(method=new.method.replace(student=s.method.student))

    def _record(self, s, schedule):
        m = s.method
        return {
            "obs": m.obs,
            "target": m.target,
            "changed": m.changed,
            "acted": m.acted,
            "touch": s.touching[0],
        }


class Distiller:
    """The teacher, the student's network and the environments of one distillation."""

    def __init__(
        self, source: str | Path, config: DistillConfig = DistillConfig(), safety: SafetyConfig | None = None
    ):
        self.source = str(source)
        self.config = config
        self.teacher = _load_su(source, "source")
        task = tasks.get("su")
        self.env = task.build(task.config_from(self.teacher.manifest["env_config"]))
        self.envs = AutoReset(self.env)
        self.safety = safety or SafetyConfig()
        self.network = self.teacher.network
        self.obs_clip = self.teacher.manifest["observation_clip"]
        rays = engine_lib.EngineConfig().collision_rays
        self._rays = rays
        self._boundary = jnp.asarray(KAIROS.ray_geometry(rays)[0])
        self._optimizer = optax.adam(config.learning_rate)
        self.collect = jax.jit(self._collect)
        self.fit_step = jax.jit(self._fit_step)
        self._engine = None  # built on the first engine round, compiled once

    def mean(self, params, obs: jax.Array) -> jax.Array:
        """The Gaussian's mean (unclipped) for raw observations ``obs`` (..., O), normalised with
        the source's statistics, which the student keeps."""
        t = self.teacher
        return self.network.apply(params, normalise(obs, t.obs_mean, t.obs_std, self.obs_clip)).mean

    def label(self, world, action):
        """(the layer's action for the teacher's ``action``, whether the layer changed it, whether
        the footprint overlaps an obstacle on the dense scan: the evaluation's contact)."""
        scan = lidar.scan(world.floor, robot_lib.pose(world.robot), num_rays=self._rays)
        target, changed = self.env.safety_target(world, action, scan, self.safety)
        return target, changed, jnp.max(self._boundary - scan) > 0.0

    def _collect(self, student, state):
        def body(state, _):
            obs = state.obs
            teacher = jnp.clip(self.mean(self.teacher.params, obs), -1.0, 1.0)
            # one state at a time: vmapped, the layer's early-exit loops run every state as long as
            # the longest (22x slower on a 2-core CPU)
            target, changed, touch = jax.lax.map(lambda x: self.label(*x), (state.pipeline_state, teacher))
            nxt = self.envs.step(state, jnp.clip(self.mean(student, obs), -1.0, 1.0))
            record = {
                "obs": obs,
                "target": target,
                "changed": changed,
                "touch": touch,
                "done": nxt.info["episode_done"],
                "obstacle": nxt.metrics["collision_obstacle"],
            }
            return nxt, record

        return jax.lax.scan(body, state, None, self.config.chunk)

    def collect_engine(self, student, round_: int) -> dict[str, np.ndarray]:
        """``config.engine_steps`` steps of the student in the behaviour engine on the lab twin,
        the training trajectories in a sequence shuffled by ``round_``: the Chase steps' records
        and, per step, whether the base was in contact."""
        cfg = self.config
        if self._engine is None:
            self._engine = _RecordingEngine(_Recorder(self), self.env.bank, floors.lab())
        engine = self._engine
        engine.method.student = student
        order = np.random.default_rng([cfg.seed, round_]).permutation(self.env.bank.num_trajectories)
        starts = engine_lib.start_poses(engine.floor, engine.grid)
        schedule = engine_lib.su_schedule(self.env.bank, starts, order)
        key = jax.random.fold_in(jax.random.key(cfg.seed), round_)
        rec, _ = engine.trace(schedule, key, cfg.engine_steps)
        acted = rec["acted"]
        return {
            "obs": rec["obs"][acted],
            "target": rec["target"][acted],
            "changed": rec["changed"][acted],
            "touch": rec["touch"],
        }

    def loss(self, params, obs, target, weight):
        """Weighted half squared error of the student's mean from the labels; at a bound of
        [-1, 1] a label is one-sided (a mean past it acts as the bound does)."""
        m = self.mean(params, obs)
        past = ((target >= 1.0) & (m > 1.0)) | ((target <= -1.0) & (m < -1.0))
        err = jnp.where(past, 0.0, m - target)
        return jnp.sum(weight * 0.5 * jnp.sum(err**2, -1)) / jnp.sum(weight)

    def _fit_step(self, params, opt_state, obs, target, weight):
        loss, grads = jax.value_and_grad(self.loss)(params, obs, target, weight)
        updates, opt_state = self._optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    def run(self, student=None, log=print, progress=None) -> tuple[dict, list[dict]]:
        """The distilled parameters (from ``student``, default the source's) and one log entry per
        round; ``progress(done, total)`` is called after each collection."""
        cfg = self.config
        params = self.teacher.params if student is None else student
        opt_state = self._optimizer.init(params)
        state = jax.jit(self.envs.reset)(jax.random.split(jax.random.key(cfg.seed), cfg.num_envs))
        data = {"obs": [], "target": [], "changed": []}
        entries, start = [], time.time()
        total = cfg.rounds * cfg.collections
        for r in range(cfg.rounds):
            counts = dict.fromkeys(("done", "obstacle", "touch", "changed"), 0)
            for c in range(cfg.collections):
                state, rec = self.collect(params, state)
                rec = {k: np.asarray(v) for k, v in jax.device_get(rec).items()}
                for k in data:
                    data[k].append(rec[k].reshape((-1, *rec[k].shape[2:])))
                for k in counts:
                    counts[k] += int(rec[k].sum())
                if progress:
                    progress(r * cfg.collections + c + 1, total)
            steps = cfg.collections * cfg.num_envs * cfg.chunk
            if cfg.engine_steps:
                seen = self.collect_engine(params, r)
                for k in data:
                    data[k].append(seen[k])
                counts["engine_chase_steps"] = len(seen["obs"])
                counts["engine_changed"] = int(seen["changed"].sum())
                # contacts as the evaluation counts them: a contact begins where one was not
                touch = seen["touch"]
                counts["engine_contacts"] = int(np.sum(touch[1:] & ~touch[:-1]) + touch[0])
                steps += len(seen["obs"])
            obs, target = np.concatenate(data["obs"]), np.concatenate(data["target"])
            weight = np.where(np.concatenate(data["changed"]), cfg.changed_weight, 1.0).astype(np.float32)
            # the first batches of a round are the student's error on its own new steps
            new = slice(len(obs) - steps, len(obs))
            own = float(
                self.loss(
                    params,
                    obs[new][: cfg.batch_size],
                    target[new][: cfg.batch_size],
                    weight[new][: cfg.batch_size],
                )
            )
            rng = np.random.default_rng(r)
            losses = []
            for _ in range(cfg.epochs):
                order = rng.permutation(len(obs))
                for i in range(0, len(obs) - cfg.batch_size + 1, cfg.batch_size):
                    idx = order[i : i + cfg.batch_size]
                    params, opt_state, loss = self.fit_step(
                        params, opt_state, obs[idx], target[idx], weight[idx]
                    )
                    losses.append(float(loss))
            entry = {
                "round": r,
                "steps": len(obs),
                "episodes_ended": counts["done"],
                "episodes_ended_at_obstacles": counts["obstacle"],
                "contact_steps": counts["touch"],
                "changed_share": counts["changed"] / (cfg.collections * cfg.num_envs * cfg.chunk),
                **{k: v for k, v in counts.items() if k.startswith("engine_")},
                "own_error": own,
                "fit_loss_last": float(np.mean(losses[-20:])),
                "minutes": (time.time() - start) / 60,
            }
            entries.append(entry)
            log(
                f"round {r + 1}/{cfg.rounds}: layer changed {100 * entry['changed_share']:.1f}% of the "
                f"student's steps, contact steps {counts['touch']}"
                + (f", engine contacts {counts['engine_contacts']}" if cfg.engine_steps else "")
                + f", error on its own steps {own:.4f}, fit {entry['fit_loss_last']:.4f} "
                f"({entry['minutes']:.1f} min)"
            )
        return params, entries

    def export(self, params, out: str | Path, entries: list[dict], init: str | None = None) -> Path:
        """``params`` as a deployment folder ``out`` (ONNX, parameters, manifest)."""
        trained = dict(self.teacher.manifest.get("trained", {}))
        trained["distilled"] = {
            "source": self.source,
            "source_params_sha256": self.teacher.manifest.get("params_sha256"),
            "init": init,
            "config": dataclasses.asdict(self.config),
            "safety": dataclasses.asdict(self.safety),
            "rounds": entries,
        }
        stats = types.SimpleNamespace(mean=self.teacher.obs_mean, std=self.teacher.obs_std)
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f".{out.name}-", dir=out.parent) as tmp:
            export.export(
                tmp,
                env_name="su",
                env=self.env,
                network_spec=self.teacher.manifest["network"],
                params=params,
                obs_stats=stats,
                obs_clip=self.obs_clip,
                trained=trained,
                policies=self.teacher.manifest.get("policies"),
            )
            try:
                return export.export_deployment(tmp, out, log=lambda _: None)
            except export.ExportError as e:
                raise DistillError(str(e)) from None


def start_params(distiller: Distiller, init: str | Path | None):
    """The student's first parameters: ``init``'s (an SU policy of the source's network), or None
    (the source's)."""
    if init is None:
        return None
    start = _load_su(init, "init")
    if start.manifest["network"] != distiller.teacher.manifest["network"]:
        raise DistillError(f"init {init} has another network than the source {distiller.source}")
    return start.params


def distill(
    source: str | Path,
    out: str | Path,
    config: DistillConfig = DistillConfig(),
    *,
    init: str | Path | None = None,
    log=print,
    progress=None,
) -> Path:
    """:class:`Distiller` from ``source`` (an exported SU policy or a run folder with one), the
    student starting from ``init`` (default the source), exported to ``out``."""
    distiller = Distiller(source, config)
    params, entries = distiller.run(start_params(distiller, init), log=log, progress=progress)
    return distiller.export(params, out, entries, None if init is None else str(init))


def main(argv=None) -> int:
    parser = OneLineParser(
        prog="python -m train.distill",
        description="Distil the deployment's safety layer into a single-user policy (DAgger): the "
        "policy learns to act as it does with the layer after it.",
    )
    parser.add_argument("source", help="an exported SU policy folder (or a run folder with one): the teacher")
    parser.add_argument("--out", required=True, type=Path, help="deployment folder to write")
    parser.add_argument("--init", help="an SU policy to start the student from (default: the source)")
    defaults = DistillConfig()
    helps = {
        "rounds": "rounds of collecting with the student and fitting it",
        "steps_per_round": "environment steps collected per round",
        "num_envs": "environments driven together",
        "chunk": "steps per environment in one compiled collection",
        "epochs": "passes over all collected steps per round",
        "batch_size": "steps per gradient step",
        "learning_rate": "Adam's learning rate",
        "changed_weight": "weight of the steps whose command the layer changed (the others: 1)",
        "engine_steps": "steps per round in the behaviour engine on the lab twin (0: none)",
        "seed": "key of the environments and the engine",
    }
    for f in dataclasses.fields(DistillConfig):
        value = getattr(defaults, f.name)
        parser.add_argument(
            "--" + f.name.replace("_", "-"),
            type=type(value),
            default=value,
            help=f"{helps[f.name]} (default {value})",
        )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        config = DistillConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(DistillConfig)})
    except ValueError as e:
        parser.error(str(e))
    if args.out.exists() and not (
        args.out.is_dir() and (not any(args.out.iterdir()) or export._replaceable(args.out))
    ):
        parser.error(f"--out {args.out} exists and is not an empty or earlier deployment folder")
    try:
        distiller = Distiller(args.source, config)
        student = start_params(distiller, args.init)
    except DistillError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=config.rounds * config.collections, desc="distilling", unit="collection")
    try:
        params, entries = distiller.run(
            student,
            log=bar.write if bar else print,
            progress=(lambda done, _: bar.update(done - bar.n)) if bar else None,
        )
    finally:
        if bar:
            bar.close()
    try:
        out = distiller.export(params, args.out, entries, args.init)
    except DistillError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    print(
        f"wrote {out} (params sha256 {json.loads((out / 'manifest.json').read_text())['params_sha256'][:12]})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
