"""The task table: one row per task, everything the rest of the project needs to know about it.

A task is an environment plus the facts that training, export, rollout, evaluation and the robot
side read: its configuration class and default, how to build the environment (and which trained
policies it needs handed in), the network that fits it, what each observation field and action
component means, and the thesis's parameter count. ``train.run``, ``train.export``,
``train.rollout``, ``train.evaluate`` and the presets look tasks up here and nowhere else; the
robot side (``methd_jax.deploy``) reads the same facts from the manifest that export writes.

Adding a task is one environment module and one :func:`register` call::

    envs.tasks.register(envs.tasks.Task(name="three_users", config=..., make_env=..., ...))
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Mapping
from typing import Any

from envs import rewards
from envs.guide import GuideConfig, GuideEnv
from envs.nav import GUIDE_MAX_DELTA, NavConfig, NavEnv
from methd_jax.jsonable import from_jsonable

Fields = Mapping[str, tuple[tuple[str, ...], tuple[str, ...]]]


@dataclasses.dataclass(frozen=True)
class Ratio:
    """A training metric reported per iteration as sum(numerator) / sum(denominator) of two step
    metrics of the environment (a share of events, not a mean over steps)."""

    numerator: str
    denominator: str
    count: str
    """The metric that reports the denominator's sum (0: the ratio is undefined that iteration)."""
    label: str
    """What the ratio means, for plots and READMEs (shown as a percentage)."""
    short: str
    """Its name on the progress bar."""


@dataclasses.dataclass(frozen=True)
class Task:
    """One row of the table."""

    name: str
    """What presets, manifests (``env``) and ``--env`` options call the task."""
    summary: str
    """One line for ``--help`` and docs."""
    config: Any
    """The default configuration (a frozen dataclass); its class is the task's configuration class."""
    make_env: Callable[..., Any]
    """``make_env(config, *, bank=None, policies={})`` -> a Brax ``Env`` with ``observation_layout``
    (name -> slice). ``policies`` maps a task name to a loaded policy this task depends on."""
    network: Callable[[Any, tuple[int, ...], float], dict]
    """``network(config, hidden, init_log_std)`` -> the spec ``networks.from_spec`` builds."""
    fields: Fields
    """Observation field -> (component names, units); a field ``user1`` reads the row ``user``, and a
    single component stands for every element of its field (the LiDAR's range per ray)."""
    action: Mapping[str, Any]
    """The action's ``names``, ``units`` and ``frame`` ("robot": a base velocity command)."""
    action_scale: Callable[[Any], list[float]]
    """``action_scale(config)``: what an action of 1 means, per component, in ``action``'s units."""
    thesis_parameters: int | None = None
    """The thesis's policy parameter count (Table 4.4), when the thesis has the task."""
    depends: Mapping[str, str] = dataclasses.field(default_factory=dict)
    """Task name of a policy this task can take -> the run-config field that names its folder."""
    ratios: Mapping[str, Ratio] = dataclasses.field(default_factory=dict)
    """Training metrics (by name) that are shares of events: see :class:`Ratio`."""
    pictures: bool = False
    """Whether ``envs.record`` can draw the task (its world has the users, floor and robot of
    :class:`envs.nav.NavEnv` or :class:`envs.guide.GuideEnv`); ``train.rollout`` writes the arrays
    of ``envs.trace`` otherwise."""
    readme: Callable[[str], list[str]] | None = None
    """Extra lines for a run folder's README (given the run folder), e.g. what the policy feeds."""

    @property
    def drives_base(self) -> bool:
        """Whether the policy's action is a velocity command for the base."""
        return self.action.get("frame") == "robot"

    def field(self, name: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """Component names and units of observation field ``name`` (``user1`` -> row ``user``)."""
        if name in self.fields:
            return self.fields[name]
        stem = re.sub(r"\d+$", "", name)
        if stem in self.fields:
            return self.fields[stem]
        raise KeyError(f"task {self.name!r} has no observation field {name!r}")

    def config_from(self, stored: dict):
        """The configuration stored by ``methd_jax.jsonable.jsonable`` (a manifest's ``env_config``)."""
        return from_jsonable(self.config, stored)

    def build(self, config=None, *, bank=None, policies: Mapping[str, Any] | None = None):
        """The environment for ``config`` (default: the task's), with dependency policies handed in."""
        policies = dict(policies or {})
        unknown = sorted(set(policies) - set(self.depends))
        if unknown:
            raise ValueError(f"task {self.name!r} takes no {', '.join(unknown)} policy")
        config = self.config if config is None else config
        if not isinstance(config, type(self.config)):
            raise TypeError(
                f"task {self.name!r} needs a {type(self.config).__name__}, got {type(config).__name__}"
            )
        return self.make_env(config, bank=bank, policies=policies)


TASKS: dict[str, Task] = {}
"""Every registered task by name, in registration order."""


def register(task: Task, *, replace: bool = False) -> Task:
    """Add ``task`` to the table (``replace=True`` to overwrite a row of the same name)."""
    if not re.fullmatch(r"[a-z][a-z0-9_]*", task.name):
        raise ValueError(f"task names are lower-case identifiers, got {task.name!r}")
    if task.name in TASKS and not replace:
        raise ValueError(f"task {task.name!r} is already registered")
    TASKS[task.name] = task
    return task


def unregister(name: str) -> None:
    """Remove a row (for tests that register toy tasks)."""
    TASKS.pop(name, None)


def get(name: str) -> Task:
    """The row of ``name``; a clear error naming the known tasks otherwise."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; choose one of {', '.join(TASKS)}")
    return TASKS[name]


# -- the thesis's tasks ---------------------------------------------------------------------------

_BASE_ACTION = {"names": ("vx", "vy", "wz"), "units": ("m/s", "m/s", "rad/s"), "frame": "robot"}

_NAV_FIELDS: Fields = {
    "lidar": (("range",), ("m",)),
    "robot_velocity": (("vx", "vy", "wz"), ("m/s", "m/s", "rad/s")),
    "robot_acceleration": (("ax", "ay", "alpha_z"), ("m/s^2", "m/s^2", "rad/s^2")),
    "previous_action": (("a_vx", "a_vy", "a_wz"), ("1", "1", "1")),
    "previous_action_2": (("a_vx", "a_vy", "a_wz"), ("1", "1", "1")),
    "user": (
        ("p_x", "p_y", "v_x", "v_y", "w_z", "phi", "theta", "d"),
        ("m", "m", "m/s", "m/s", "rad/s", "rad", "rad", "m"),
    ),
    "goal": (("p_x", "p_y", "d", "theta", "dyaw"), ("m", "m", "m", "rad", "rad")),
    "clearance": (("clearance",), ("m",)),
}

_GUIDE_FIELDS: Fields = {
    "guide": (
        (
            *(f"{q}_u{i}_{c}" for q in ("v", "q") for i in (1, 2) for c in ("x", "y", "wz")),
            "u_w",
            "a_prev",
            "a_prev_2",
        ),
        ("m/s", "m/s", "rad/s") * 2 + ("m/s^2", "m/s^2", "rad/s^2") * 2 + ("1", "1", "1"),
    ),
    "wrist": (("h_u1", "h_u2"), ("m", "m")),
}


def _nav_env(config: NavConfig, *, bank=None, policies):
    return NavEnv(config, bank=bank, guide_policy=policies.get("guide"))


def _lidar_network(config: NavConfig, hidden, init_log_std) -> dict:
    return {
        "class": "ActorCritic",
        "hidden": list(hidden),
        "num_rays": config.num_rays,
        "init_log_std": init_log_std,
    }


def _base_scale(config: NavConfig) -> list[float]:
    robot = config.robot
    return [robot.max_speed, robot.max_speed, robot.max_yaw_rate]


SU = register(
    Task(
        name="su",
        summary="single user: reach and hold the user's HIP among obstacles (Table 4.1)",
        config=NavConfig(num_users=1, weights=rewards.SU_WEIGHTS),
        make_env=_nav_env,
        network=_lidar_network,
        fields=_NAV_FIELDS,
        action=_BASE_ACTION,
        action_scale=_base_scale,
        thesis_parameters=702_674,
        pictures=True,
    )
)
NAV = register(
    dataclasses.replace(
        SU,
        name="nav",
        summary="NavRL: two users, the goal from a GuideRL policy or a scripted source (Table 4.3)",
        config=NavConfig(num_users=2, weights=rewards.NAV_WEIGHTS),
        thesis_parameters=706_770,
        depends={"guide": "guide_run"},
    )
)
GUIDE = register(
    Task(
        name="guide",
        summary="GuideRL: move the user weight toward whoever will request next (eqs. 4.24-4.27)",
        config=GuideConfig(),
        make_env=lambda config, *, bank=None, policies: GuideEnv(config, bank=bank),
        network=lambda config, hidden, init_log_std: {
            "class": "GuideActorCritic",
            "hidden": list(hidden),
            "init_log_std": init_log_std,
        },
        fields=_GUIDE_FIELDS,
        action={"names": ("delta_u_w",), "units": ("1",), "frame": "none"},
        action_scale=lambda config: [GUIDE_MAX_DELTA],
        thesis_parameters=18_690,
        pictures=True,
        ratios={
            "guide/accuracy": Ratio(
                "correct_at_request", "at_request", "guide/requests", "correct user at the request", "acc"
            )
        },
        readme=lambda run_dir: [f"Drive NavRL's goal with it: `python -m train.run nav guide_run={run_dir}`"],
    )
)
