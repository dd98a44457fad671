"""The CoboDeck base as an MJX model: a 130 kg holonomic body driven by saturating velocity servos.

The model (``assets/kairos_base.xml``) has three joints (slide x, slide y, hinge yaw, in the world
frame) and three velocity servos along the robot's own forward, left and yaw axes, so a command is
a robot-frame velocity that a turning base keeps. :meth:`Robot.step` takes such a command at the
control rate (50 Hz), saturates it to the speed limits, and integrates the physics substeps. The
servos' force and torque limits make the base accelerate at a finite rate (3 m/s^2 per axis,
6 rad/s^2) instead of jumping to the commanded velocity.

Everything is pure and vmappable: ``jax.vmap(robot.step)(data, commands)`` steps a fleet.
:func:`predict` integrates the same servo model without MJX (:meth:`Robot.servo` reads its gains
and limits from the model), for a guard that asks where the base will coast.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from methd_jax.control import CONTROL_DT
from methd_jax.floors import ASSETS
from methd_jax.geometry import rotate, wrap_angle

ROBOT_ASSET = ASSETS / "kairos_base.xml"


class Servo(NamedTuple):
    """The base's velocity servos as its model sets them, for predicting motion outside MJX: per
    robot axis (forward, left, yaw) the acceleration is ``gain * (command - velocity)`` clipped to
    ``+-limit``, integrated by explicit Euler at ``timestep`` as MuJoCo does."""

    gain: tuple[float, float, float]
    """kv over the mass (forward, left) and over the yaw inertia, 1/s."""
    limit: tuple[float, float, float]
    """Force limit over the mass, m/s^2, and torque limit over the inertia, rad/s^2."""
    timestep: float
    """The model's physics timestep, s."""


@dataclasses.dataclass(frozen=True)
class RobotConfig:
    """Limits and rates of the base (the servo gains and force limits live in the MJCF)."""

    max_speed: float = 3.0
    """Top linear speed, m/s: the norm of (vx, vy) is clipped to it (a user walks at <= 1.9 m/s)."""
    max_yaw_rate: float = 2.0
    """Top yaw rate, rad/s."""
    mjcf: str = str(ROBOT_ASSET)
    """Path of the base's MJCF."""

    def __post_init__(self):
        for name in ("max_speed", "max_yaw_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RobotConfig.{name} must be positive, got {getattr(self, name)}")


class Robot:
    """The base's MJX model plus the functions that command it. Construct once, outside ``jit``."""

    def __init__(self, cfg: RobotConfig = RobotConfig()):
        self.cfg = cfg
        path = Path(cfg.mjcf)
        if not path.is_file():
            raise FileNotFoundError(f"robot MJCF not found: {path}")
        self.mj_model = mujoco.MjModel.from_xml_path(str(path))
        names = [self.mj_model.joint(i).name for i in range(self.mj_model.njnt)]
        actuators = [self.mj_model.actuator(i).name for i in range(self.mj_model.nu)]
        if names != ["x", "y", "yaw"] or actuators != ["vx", "vy", "vyaw"]:
            raise ValueError(
                f"{path}: expected joints x, y, yaw and actuators vx, vy, vyaw, got {names}, {actuators}"
            )
        ratio = CONTROL_DT / self.mj_model.opt.timestep
        self.substeps = round(ratio)
        if self.substeps < 1 or abs(ratio - self.substeps) > 1e-6:
            raise ValueError(
                f"{path}: the control period {CONTROL_DT} s is not a whole number of its timesteps "
                f"({self.mj_model.opt.timestep} s)"
            )
        # this process's own device: MJX's default, jax.devices()[0], belongs to process 0 when
        # several processes train together (jax.distributed)
        self.model = mjx.put_model(self.mj_model, device=jax.local_devices()[0])

    def servo(self) -> Servo:
        """The servos' gains and limits (see :class:`Servo`) read from the model."""
        m = self.mj_model
        body = int(m.jnt_bodyid[0])  # the base: all three joints move it
        inertia = (float(m.body_mass[body]),) * 2 + (float(m.body_inertia[body][2]),)
        kv = m.actuator_gainprm[:, 0]
        force = m.actuator_forcerange[:, 1]
        return Servo(
            gain=tuple(float(k / i) for k, i in zip(kv, inertia, strict=True)),
            limit=tuple(float(f / i) for f, i in zip(force, inertia, strict=True)),
            timestep=float(m.opt.timestep),
        )

    def init(self, pose: jax.Array) -> mjx.Data:
        """A base at rest at ``pose`` = (x, y, yaw)."""
        data = mjx.make_data(self.model)
        return data.replace(qpos=jnp.asarray(pose, data.qpos.dtype))

    def saturate(self, command: jax.Array) -> jax.Array:
        """Clips a robot-frame command (vx, vy, wz) to the limits; non-finite commands stop the base."""
        command = jnp.where(jnp.all(jnp.isfinite(command)), command, 0.0)
        v = command[:2]
        speed = jnp.linalg.norm(v)
        v = v * jnp.minimum(1.0, self.cfg.max_speed / jnp.maximum(speed, 1e-12))
        w = jnp.clip(command[2], -self.cfg.max_yaw_rate, self.cfg.max_yaw_rate)
        return jnp.concatenate([v, w[None]])

    def scaled_model(self, mass_scale: jax.Array, force_scale: jax.Array) -> mjx.Model:
        """The model with mass and inertia times ``mass_scale`` and the servos' force and torque limits
        times ``force_scale`` (domain randomisation; the scales may be traced and vmapped)."""
        m = self.model
        return m.replace(
            body_mass=m.body_mass * mass_scale,
            body_inertia=m.body_inertia * mass_scale,
            actuator_forcerange=m.actuator_forcerange * force_scale,
        )

    def step(self, data: mjx.Data, command: jax.Array, model: mjx.Model | None = None) -> mjx.Data:
        """Advances one control period under the robot-frame velocity ``command`` (m/s, m/s, rad/s).

        ``model`` replaces the nominal model (see :meth:`scaled_model`).
        """
        model = self.model if model is None else model
        data = data.replace(ctrl=self.saturate(command).astype(data.ctrl.dtype))
        return jax.lax.fori_loop(0, self.substeps, lambda _, d: mjx.step(model, d), data)


def pose(data: mjx.Data) -> jax.Array:
    """(x, y, yaw) of the base, yaw wrapped to [-pi, pi)."""
    return jnp.concatenate([data.qpos[:2], wrap_angle(data.qpos[2:3])])


def velocity(data: mjx.Data) -> jax.Array:
    """(vx, vy, wz) of the base in the robot frame."""
    return jnp.concatenate([rotate(-data.qpos[2], data.qvel[:2]), data.qvel[2:3]])


def predict(servo: Servo, velocity: jax.Array, commands: jax.Array) -> jax.Array:
    """Poses (x, y, yaw) after each of ``commands`` (T, 3), robot-frame twists held one control
    period each, for a base now at the origin moving at the robot-frame ``velocity``: (T, 3) in
    the base's present frame. The servo model of :class:`Servo`; commands are taken as within the
    speed limits."""
    gain, limit = jnp.asarray(servo.gain), jnp.asarray(servo.limit)
    h = servo.timestep
    substeps = max(1, round(CONTROL_DT / h))

    def substep(state, command):
        xy, th, v, w = state  # v: the linear velocity in the start frame
        ax = jnp.clip(gain[:2] * (command[:2] - rotate(-th, v)), -limit[:2], limit[:2])
        aw = jnp.clip(gain[2] * (command[2] - w), -limit[2], limit[2])
        v, w = v + h * rotate(th, ax), w + h * aw  # velocities first, then positions (MuJoCo's Euler)
        return (xy + h * v, th + h * w, v, w), None

    def period(state, command):
        for _ in range(substeps):
            state, _ = substep(state, command)
        return state, jnp.concatenate([state[0], state[1][None]])

    v0 = jnp.asarray(velocity, jnp.float32)
    start = (jnp.zeros(2), jnp.float32(0.0), v0[:2], v0[2])
    _, poses = jax.lax.scan(period, start, jnp.asarray(commands, jnp.float32))
    return poses


def acceleration(data: mjx.Data) -> jax.Array:
    """(ax, ay, dwz) of the base's last substep in the robot frame."""
    return jnp.concatenate([rotate(-data.qpos[2], data.qacc[:2]), data.qacc[2:3]])
