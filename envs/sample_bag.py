"""A ROS 2 bag (MCAP) recorded from our simulator, for replaying the deployment shim offline.

``python -m envs.sample_bag --out assets/deploy_sample.mcap`` (the shipped sample): one ``su``
episode on the lab twin with a user from the shipped motion sample; the base is driven to the HIP
by the evaluation's navigator (the role of the ROS navigation stack: a wavefront plan around the
obstacles and a 1.6 m keep-out around the user), not by a policy, so the bag shows collision-free
driving among obstacles, the user and the goal.
Topics as :mod:`methd_jax.deploy.mcap_replay` reads them: ``/scan`` LaserScan (720 rays, no noise,
robot frame), ``/odom`` Odometry (world pose, robot-frame twist), ``/user0/odom`` Odometry (world
pose, user-frame twist), ``/goal`` PoseStamped (the HIP), all at 50 Hz.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from envs.nav import NavConfig, NavEnv
from methd_jax import floors, lidar, ros_messages
from methd_jax import robot as robot_lib
from methd_jax.cli import OneLineParser
from methd_jax.control import CONTROL_DT, CONTROL_HZ
from methd_jax.evaluation import navigator as nav

START_NS = 10**9
RANGE_MAX = 30.0


def simulate(seconds: float = 10.0, seed: int = 1, motion: str = "sample") -> dict[str, np.ndarray]:
    """One episode's per-step records (stops early if the episode ends)."""
    env = NavEnv(NavConfig(lab=True, motion=motion, split="all", lidar_noise=0.0, lidar_dropout=0.0))
    steps = round(seconds / CONTROL_DT)
    grid, nav_cfg = nav.costmap(floors.lab()), nav.NavigatorConfig()
    scale = jnp.array([env.config.robot.max_speed, env.config.robot.max_speed, env.config.robot.max_yaw_rate])
    replan = round(CONTROL_HZ)  # once a second, as the evaluation's navigator

    def record(state):
        w = state.pipeline_state
        pose = robot_lib.pose(w.robot)
        user = env.bank.at(w.users[0], w.t)
        return {
            "ranges": lidar.scan(w.floor, pose, num_rays=env.config.num_rays),
            "pose": pose,
            "velocity": robot_lib.velocity(w.robot),
            "user_pose": user["pose"],
            "user_twist": user["vel_local"],
            "goal": w.goal,
            "done": state.done,
        }

    def plan(w):
        user = env.bank.at(w.users[0], w.t)["pose"]
        keepout = jnp.array([[user[0], user[1], 1.6]])
        return nav.distance_field(grid, w.goal[:2], keepout)

    def step(carry, _):
        state, previous, field = carry
        w = state.pipeline_state
        field = jax.lax.cond(w.t % replan == 0, plan, lambda _: field, w)
        previous, command = nav.follow(grid, field, robot_lib.pose(w.robot), previous, w.goal, nav_cfg)
        state = env.step(state, jnp.clip(command / scale, -1.0, 1.0))
        return (state, previous, field), record(state)

    @jax.jit
    def run(key):
        state = env.reset(key)
        carry = (state, jnp.zeros(3), plan(state.pipeline_state))
        _, rows = jax.lax.scan(step, carry, None, length=steps)
        first = record(state)
        return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, rows)

    rows = jax.device_get(run(jax.random.key(seed)))
    done = np.flatnonzero(rows["done"] > 0)
    end = int(done[0]) + 1 if done.size else len(rows["done"])
    return {k: np.asarray(v[:end]) for k, v in rows.items()}


def write(
    path: str | Path, rows: dict[str, np.ndarray], num_rays: int = lidar.NUM_RAYS, drop: dict | None = None
) -> Path:
    """Writes the records of :func:`simulate` as a bag; ``drop`` maps a topic to the ticks whose
    message is left out (sensor dropouts for testing the controller's watchdog)."""
    from mcap_ros2.writer import Writer

    drop = {topic: set(ticks) for topic, ticks in (drop or {}).items()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    increment = 2.0 * math.pi / num_rays
    zeros36 = [0.0] * 36
    with open(path, "wb") as f:
        w = Writer(f)
        schema = {name: w.register_msgdef(name, text) for name, text in ros_messages.SCHEMAS.items()}
        for k in range(len(rows["pose"])):
            ns = START_NS + k * 20_000_000
            ranges = np.where(np.isfinite(rows["ranges"][k]), rows["ranges"][k], np.inf).astype(np.float32)
            scan = {
                "header": ros_messages.header(ns, "base_link"),
                "angle_min": 0.0,
                "angle_max": 2.0 * math.pi - increment,
                "angle_increment": increment,
                "time_increment": 0.0,
                "scan_time": 0.02,
                "range_min": 0.05,
                "range_max": RANGE_MAX,
                "ranges": ranges.tolist(),
                "intensities": [],
            }
            odom = {
                "header": ros_messages.header(ns, "world"),
                "child_frame_id": "base_link",
                "pose": {"pose": ros_messages.pose2d(*rows["pose"][k]), "covariance": zeros36},
                "twist": {"twist": ros_messages.twist(*rows["velocity"][k]), "covariance": zeros36},
            }
            user = {
                "header": ros_messages.header(ns, "world"),
                "child_frame_id": "user0",
                "pose": {"pose": ros_messages.pose2d(*rows["user_pose"][k]), "covariance": zeros36},
                "twist": {"twist": ros_messages.twist(*rows["user_twist"][k]), "covariance": zeros36},
            }
            goal = {"header": ros_messages.header(ns, "world"), "pose": ros_messages.pose2d(*rows["goal"][k])}
            for topic, name, msg in (
                ("/scan", "sensor_msgs/msg/LaserScan", scan),
                ("/odom", "nav_msgs/msg/Odometry", odom),
                ("/user0/odom", "nav_msgs/msg/Odometry", user),
                ("/goal", "geometry_msgs/msg/PoseStamped", goal),
            ):
                if k not in drop.get(topic, ()):
                    w.write_message(topic, schema[name], msg, log_time=ns, publish_time=ns)
        w.finish()
    return path


def main(argv=None) -> int:
    parser = OneLineParser(prog="python -m envs.sample_bag", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="assets/deploy_sample.mcap")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--motion", default="sample", help='"sample", "default" or a directory of MCAP bags')
    args = parser.parse_args(argv)
    if not 0 < args.seconds <= 600:
        parser.error("--seconds must be in (0, 600]")
    rows = simulate(args.seconds, args.seed, args.motion)
    path = write(args.out, rows)
    n = len(rows["pose"])
    print(f"wrote {path}: {n} ticks ({n / 50:.1f} s), {path.stat().st_size:,} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
