"""What a training run is: :class:`RunConfig`, the named presets, and ``key=value`` overrides.

Presets (Table 4.4 for ``su``, ``nav`` and ``guide``):

=========  =====================================================================================
``quick``  SU on floors without obstacles (walls only), 90 LiDAR rays, a 3 x 128 body, 256
           environments x 32 rollouts, 4.1M transitions, and a tenth of Table 4.1's velocity
           penalty: with the full penalty a policy spends its first million or so transitions
           learning to stand still, so a CPU-sized run would show nothing else. About 7 minutes
           on a 2-core CPU; the robot learns to reach and hold the HIP (on 256 evaluation
           episodes of the sample users, 15 s in: median 0.16 m from it, 76% within 0.3 m,
           91% of episodes without a collision). The default.
``su_cpu`` SU for a 2-core CPU: procedural floors with 0-8 cylinders and 0-8 boxes/triangles
           and the lab twin in 30% of episodes, the 342 training trajectories, 90 rays (the
           inflation weight x 8 so that p_i, a sum over rays, weighs what 720 rays did), a
           3 x 256 body, a tenth of the velocity penalty, 256 environments x 32 rollouts; the
           goal pushed 0.9 m clear of obstacles (``env.goal_clearance``: a HIP inside furniture
           or a wall otherwise pulls the robot into it), a 3 cm collision margin on the 90 rays
           (``env.safety.collision_margin``: without it corners graze furniture between two
           rays, which the evaluation's 720 rays count), no entropy bonus and an initial log-std
           of -0.5 (with skrl's 0.005 and 0 the std grew to ~1.3 and stayed there). The
           shipped policy (``assets/pretrained/su``) is seven stages of it: 2,200 iterations with
           ``env.safety.collision_margin=0``, then 1,119 from that checkpoint (``init_from=``),
           then 408 with a 10 cm margin and the lab twin in half the episodes (fewer grazed
           corners on the lab's furniture, which the evaluation counts), then 2,616 more from
           that policy with p_s, the penalty on the base's stopping path
           (``env.weights.stopping=-100``: Table 4.1's obstacle terms see only where the base is,
           and its contacts come at speed), the critic fitted first and a learning rate of 5e-5,
           then 1,716 more from that policy, its settings and the critical-zone penalty at -60 per step
           (Table 4.1: -20; the fourth stage kept off furniture by letting walking users close in,
           behind the safety layer 712 s within d_crit on the lab's 100 test trajectories, the
           fifth 51 s), then 1,864 more with the obstacles' inflation layer at 0.25 m
           (``env.safety.inflation_distance=0.25``: the fifth stopped short of HIPs near furniture,
           outside the 0.5 m layer), then 1,400 more from that run with p_s at -300 and seed 1,
           exported as the average of its checkpoints 1,000, 1,200 and 1,400 (chosen on fresh
           validation trajectories; with seed 2 the same stage ended further from the HIP); 93M
           transitions, 257 min as measured on three or four machines. The first four run end
           to end on one machine took 99 min and gave a policy that keeps its distance (T_pos
           3.2 s): the recipe's outcome varies from run to run. Commands, figures and what did
           not work: ``docs/results.md`` and the card.
``nav_cpu`` NavRL for a 2-core CPU: ``su_cpu``'s floors, rays, body and departures with two
           users (Table 4.3's weights, ``su_cpu``'s scaling), the goal from the shipped GuideRL
           policy (``assets/pretrained/guide``; the shipped NavRL policy's first two stages
           trained with the previous, 15-input one of commit ebffd4d), started from the shipped SU policy
           (``assets/pretrained/su``; the shipped NavRL policy started from its third stage, as
           shipped at commit a0e9d93; the second user's inputs start at zero weight; its critic,
           which an exported policy lacks, fitted alone for 20 iterations first), users visible
           to the LiDAR as leg-height cylinders (the thesis's simulated LiDAR did not see them; a
           real one does: 2.5x fewer user collisions in the first 130 iterations), the users
           listed nearest the goal first (``env.users_by_goal``: the goal's user where the SU
           policy saw its only one), the critical-zone penalty at -5 instead of -20 per user and
           step (at -20 PPO trades the start's approach for distance from walking users), a
           learning rate of 5e-5 (the start is a trained policy), 79,360 timesteps (20.3M
           transitions, ~40 min). The shipped NavRL policy is this preset and a second stage
           from it with p_s (``env.weights.stopping=-100``, a 10 cm collision margin, the lab
           twin in half the episodes, 35 min) and a third with the same settings and the shipped
           wrist-reading GuideRL as the goal source (35 min; 110 min in all), averaged over
           that stage's last three checkpoints (``python -m train.export RUN --iteration 1200
           1400 1600``); commands, figures and what did not work: ``docs/results.md`` and the card.
``su``     single-user policy: 2,048 environments, 960,000 timesteps (Table 4.4).
``guide``  GuideRL: 4,096 environments, 240,000 timesteps.
``guide_cpu`` GuideRL for a 2-core CPU: ``guide`` with 1,024 environments for 48,000 timesteps
           (49M transitions, ~16 min). The shipped GuideRL policy (``assets/pretrained/guide``) is
           this and a second stage of 900 iterations (~13 min) from it (``init_from=``) that adds
           each user's wrist height to the state (``env.wrist=true``, 17 inputs: eq. 4.24's cannot
           tell who asks when both users stand still, the raised arm can; the wrists start at zero
           weight), restarts the action noise (``noise_restart=true``), draws half its episodes
           from the pairs in which both users stand at the request (``env.hard_fraction=0.5``) and
           pays the choice once more at the request (``env.weights.request=3000``: the arm rises
           in the last second and u_w turns at most 0.05 a step, so the policy must turn at once):
           99.1% of the held-out pairs at the request, the first stage 95.6%. Commands: the card.
``nav``    NavRL with two users: 2,048 environments, 960,000 timesteps; the goal comes from the
           GuideRL policy of ``guide_run=RUN_DIR`` or, without one, from the scripted source.
=========  =====================================================================================

"Timesteps" are skrl's: steps of each environment (so ``su`` is 960,000 x 2,048 transitions).
Overrides are dotted paths into :class:`RunConfig`: ``num_envs=512``, ``ppo.learning_rate=3e-4``,
``env.lab=true``, ``env.floor.num_circles=0,4``.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import functools
import inspect
import itertools
import math
import textwrap
from typing import Any

import envs
from envs import tasks
from methd_jax.floors import ASSETS, FloorConfig
from train.ppo import PPOConfig

PRETRAINED = ASSETS / "pretrained"
"""The shipped policies: ``su/``, ``guide/``, ``nav/``, each an exported policy folder."""


class ConfigError(ValueError):
    """A preset name or override that cannot be applied; the message is one line."""


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run."""

    env_name: str = "su"
    """The task (a row of ``envs.tasks.TASKS``: "su", "nav", "guide", ...)."""
    env: Any = tasks.get("su").config
    """The task's environment options, its configuration class (``env.<field>=value``)."""
    num_envs: int = 2048
    """Parallel environments."""
    timesteps: int = 960_000
    """Steps per environment (skrl's timesteps); iterations = ceil(timesteps / ppo.rollouts)."""
    ppo: PPOConfig = dataclasses.field(default_factory=PPOConfig)
    """PPO hyperparameters (``ppo.<field>=value``)."""
    hidden: tuple[int, ...] = (512, 512, 512)
    """Hidden layers of the shared body (SU, NavRL) or of the actor and critic MLPs (GuideRL)."""
    init_log_std: float = 0.0
    """Initial log standard deviation of the Gaussian policy (skrl's ``initial_log_std``)."""
    seed: int = 0
    """Seed of everything random in the run."""
    guide_run: str = ""
    """A ``guide`` run or policy folder whose policy drives the goal, for the tasks that take one
    (``nav``; empty: scripted)."""
    checkpoint_every: int = 50
    """Iterations between checkpoints (one is always written at the end)."""
    checkpoint_keep: int = 3
    """Checkpoints kept, the newest (0: every one, to choose between them afterwards:
    ``python -m train.export RUN --iteration N``, or ``N1 N2 ...`` for their average)."""
    init_from: str = ""
    """Start from a run folder's newest checkpoint (parameters, optimiser, observation and value
    statistics; same network, observation size and num_envs; floors, rewards and PPO settings may
    differ) or from an exported policy folder (parameters and observation statistics, the latter at
    the weight of the transitions they came from; the run may see more observation fields, e.g. a
    second user, which start at zero weight)."""
    noise_restart: bool = False
    """With ``init_from``: the policy's action noise (its log standard deviation) restarts at
    ``init_log_std`` instead of the source's, so that PPO explores again (e.g. what inputs the
    source did not see allow)."""
    critic_warmup: int = 0
    """With ``init_from``: iterations in which only the critic learns before PPO starts
    (:meth:`train.ppo.Trainer.fit_critic`; an exported policy carries no critic, and PPO on a
    random one moves the policy far in its first update); not logged as iterations."""

    def __post_init__(self):
        if self.env_name not in tasks.TASKS:
            raise ConfigError(f"env_name must be one of {', '.join(tasks.TASKS)}, got {self.env_name!r}")
        task = tasks.get(self.env_name)
        expected = type(task.config)
        if not isinstance(self.env, expected):
            raise ConfigError(f"env must be a {expected.__name__} for {self.env_name!r}")
        for name in ("num_envs", "timesteps", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.checkpoint_keep < 0:
            raise ConfigError(f"checkpoint_keep must be >= 0 (0: every one), got {self.checkpoint_keep}")
        if self.ppo.anchor_scale and not self.init_from:
            raise ConfigError("ppo.anchor_scale needs init_from (the policy it anchors to)")
        if self.noise_restart and not self.init_from:
            raise ConfigError("noise_restart needs init_from (the policy whose noise restarts)")
        if self.critic_warmup < 0 or (self.critic_warmup and not self.init_from):
            raise ConfigError(f"critic_warmup must be >= 0 and needs init_from, got {self.critic_warmup}")
        if not self.hidden or min(self.hidden) < 1:
            raise ConfigError(f"hidden must list positive layer widths, got {self.hidden}")
        if self.guide_run and "guide_run" not in task.depends.values():
            takers = [t.name for t in tasks.TASKS.values() if "guide_run" in t.depends.values()]
            raise ConfigError(f"guide_run applies to env_name={' or '.join(takers)} only")
        if (self.num_envs * self.ppo.rollouts) % self.ppo.minibatches:
            raise ConfigError(
                f"num_envs x ppo.rollouts ({self.num_envs * self.ppo.rollouts}) must be divisible by "
                f"ppo.minibatches ({self.ppo.minibatches})"
            )

    @property
    def iterations(self) -> int:
        return math.ceil(self.timesteps / self.ppo.rollouts)

    @property
    def transitions(self) -> int:
        return self.iterations * self.ppo.rollouts * self.num_envs


_OPEN_FLOOR = FloorConfig(room_size=(13.0, 16.0), num_circles=(0, 0), num_polygons=(0, 0))
_CPU_RAYS = 90
# Up to 8 cylinders and 8 boxes/triangles: from an empty walled room to a cluttered one, each floor
# drawn afresh; the capacity (8, 12, 4) holds the lab twin too, so both batch together.
_CLUTTERED_FLOOR = FloorConfig(room_size=(13.0, 16.0), num_circles=(0, 8), num_polygons=(0, 8))

_QUICK = RunConfig(
    env_name="su",
    env=dataclasses.replace(
        tasks.get("su").config,
        floor=_OPEN_FLOOR,
        motion="sample",
        num_rays=_CPU_RAYS,
        weights=dataclasses.replace(envs.rewards.SU_WEIGHTS, velocity=-0.2),
    ),
    num_envs=256,
    timesteps=16_000,
    ppo=PPOConfig(rollouts=32, minibatches=4),
    hidden=(128, 128, 128),
    checkpoint_every=100,
)

_SU_CPU = dataclasses.replace(
    _QUICK,
    env=dataclasses.replace(
        _QUICK.env,
        floor=_CLUTTERED_FLOOR,
        lab_fraction=0.3,
        motion="default",
        goal_clearance=0.9,
        safety=dataclasses.replace(envs.rewards.SafetyConfig(), collision_margin=0.03),
        # p_i sums over rays: scaled so that 90 rays weigh what the thesis's 720 did
        weights=dataclasses.replace(
            _QUICK.env.weights, inflation=envs.rewards.SU_WEIGHTS.inflation * 720 / _CPU_RAYS
        ),
    ),
    timesteps=168_000,
    ppo=dataclasses.replace(_QUICK.ppo, entropy_scale=0.0),
    init_log_std=-0.5,
    hidden=(256, 256, 256),
    checkpoint_every=200,
)

_NAV_CPU = dataclasses.replace(
    _SU_CPU,
    env_name="nav",
    env=dataclasses.replace(
        _SU_CPU.env,
        num_users=2,
        # started from the SU policy, the second user's inputs carry no weight: a LiDAR that sees
        # the users' legs shows where they are through the encoder the SU policy already has
        users_visible=True,
        # the goal's user in the slot where the SU policy saw its only one
        users_by_goal=True,
        weights=dataclasses.replace(
            _SU_CPU.env.weights,
            acceleration=envs.rewards.NAV_WEIGHTS.acceleration,
            # at Table 4.3's -20 per user and step, PPO learns to hang back from walking users
            # (whose HIP is 0.23 m outside d_crit) rather than reach the goal
            critical_zone=-5.0,
        ),
    ),
    timesteps=79_360,
    ppo=dataclasses.replace(_SU_CPU.ppo, learning_rate=5e-5),
    guide_run=str(PRETRAINED / "guide"),
    init_from=str(PRETRAINED / "su"),
    critic_warmup=20,
)

_GUIDE = RunConfig(
    env_name="guide",
    env=tasks.get("guide").config,
    num_envs=4096,
    timesteps=240_000,
    hidden=(128, 128),
    # with the small GuideRL networks the KL stays low and the adaptive rate climbs to skrl's
    # 1e-2 cap, where the critic (one Adam with the actor) diverged after 112 iterations of a
    # 512-env run (value statistics to 4e13, then NaN); 3e-3 ran 200 iterations cleanly
    ppo=PPOConfig(lr_range=(1e-6, 3e-3)),
)
_GUIDE_CPU = dataclasses.replace(_GUIDE, num_envs=1024, timesteps=48_000, checkpoint_every=25)

PRESETS: dict[str, tuple[str, RunConfig]] = {
    "quick": (
        "SU on walled floors without obstacles, 90 rays, a 3 x 128 body, a tenth of the velocity "
        "penalty: ~7 min on a 2-core CPU, the robot learns to reach and hold the HIP (default)",
        _QUICK,
    ),
    "su_cpu": (
        "SU for the 2-core CPU: procedural floors with obstacles and the lab twin (30%), the 342 "
        "training trajectories, 90 rays, a 3 x 256 body, the goal kept clear of obstacles; the "
        "shipped policy's recipe (seven stages, the last four with env.weights.stopping: docs/results.md)",
        _SU_CPU,
    ),
    "guide_cpu": (
        "GuideRL for the 2-core CPU: the guide preset with 1,024 environments, 49M transitions "
        "(~16 min); the shipped GuideRL policy's first stage (the second adds the users' wrists: "
        "docs/results.md)",
        _GUIDE_CPU,
    ),
    "nav_cpu": (
        "NavRL for the 2-core CPU: su_cpu's floors and departures with two users, the goal from the "
        "shipped GuideRL policy, started from the shipped SU policy; the shipped policy's recipe (three "
        "stages, the last two with env.weights.stopping: docs/results.md)",
        _NAV_CPU,
    ),
    "su": ("single-user policy, Table 4.4 (2,048 envs, 960k timesteps)", RunConfig()),
    "guide": (
        "GuideRL, Table 4.4 (4,096 envs, 240k timesteps)",
        _GUIDE,
    ),
    "nav": (
        "NavRL with two users, Table 4.3/4.4 (2,048 envs, 960k timesteps); goal from guide_run= or scripted",
        RunConfig(env_name="nav", env=tasks.get("nav").config),
    ),
}


def preset(name: str) -> RunConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name][1]


def _parse(text: str, like, path: str, variable_length: bool = False):
    """``text`` as a value of the type of ``like`` (the current value); tuples keep their length
    unless ``variable_length``."""
    if isinstance(like, bool):
        low = text.strip().lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ConfigError(f"{path} expects true or false, got {text!r}")
    if isinstance(like, tuple):
        parts = [p for p in text.split(",") if p.strip()]
        if not variable_length and len(parts) != len(like):
            raise ConfigError(f"{path} expects {len(like)} comma-separated values, got {text!r}")
        kind = type(like[0]) if like else float
        return tuple(_parse(p, kind(0), path) for p in parts)
    for kind, name in ((int, "an integer"), (float, "a number")):
        if isinstance(like, kind):
            try:
                value = kind(text)
            except ValueError:
                raise ConfigError(f"{path} expects {name}, got {text!r}") from None
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"{path} must be finite, got {text!r}")
            return value
    if isinstance(like, str):
        return text
    raise ConfigError(f"{path} cannot be set from the command line")


def _set(obj, keys: list[str], text: str, path: str):
    """``obj`` with the field at ``keys`` (a suffix of the dotted ``path``) set from ``text``."""
    prefix = path.split(".")[: len(path.split(".")) - len(keys)]
    fields = sorted(f.name for f in dataclasses.fields(obj))
    key = keys[0]
    if key not in fields:
        near = difflib.get_close_matches(key, fields, n=1)
        hint = f"; did you mean {'.'.join([*prefix, near[0]])!r}?" if near else ""
        raise ConfigError(f"unknown option {path!r}{hint} (python -m train.run --help lists them)")
    current = getattr(obj, key)
    if dataclasses.is_dataclass(current):
        if len(keys) == 1:
            first = sorted(f.name for f in dataclasses.fields(current))[0]
            raise ConfigError(f"{path!r} is a group; set one of its fields, e.g. {path}.{first}=...")
        value = _set(current, keys[1:], text, path)
    elif len(keys) > 1:
        raise ConfigError(f"unknown option {path!r}: {'.'.join([*prefix, key])} has no fields")
    else:
        annotation = str(next(f.type for f in dataclasses.fields(obj) if f.name == key))
        value = _parse(text, current, path, variable_length="..." in annotation)
    try:
        return dataclasses.replace(obj, **{key: value})
    except ConfigError:
        raise
    except (ValueError, TypeError) as err:
        raise ConfigError(f"{path}={text}: {err}") from None


def override(obj, overrides: list[str]):
    """``obj`` (any configuration dataclass) with each dotted ``key=value`` applied in order;
    :class:`ConfigError` on any bad one."""
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {item!r} is not key=value")
        key = key.strip()
        obj = _set(obj, key.split("."), text.strip(), key)
    return obj


def apply_overrides(config: RunConfig, overrides: list[str]) -> RunConfig:
    """``config`` with each ``key=value`` applied in order; :class:`ConfigError` on any bad one."""
    if any(item.partition("=")[0].strip() == "env_name" for item in overrides):
        raise ConfigError("env_name is fixed by the preset; pick another preset instead")
    return override(config, overrides)


def options(config: RunConfig, prefix: str = "") -> list[tuple[str, object, str]]:
    """Every settable option: ``(dotted name, current value, docstring)``."""
    out = []
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            out.extend(options(value, f"{prefix}{f.name}."))
        else:
            out.append((f"{prefix}{f.name}", value, _doc(type(config), f.name)))
    return out


def _doc(cls, field: str) -> str:
    return _field_docs(cls).get(field, "")


@functools.cache
def _field_docs(cls) -> dict[str, str]:
    """The attribute docstrings in ``cls``'s source (the convention of our configs), by field."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    docs = {}
    for node, nxt in itertools.pairwise(tree.body[0].body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
        ):
            docs[node.target.id] = " ".join(str(nxt.value.value).split())
    return docs
