"""Offline replay: a ROS 2 bag (MCAP) of scans, odometry, users and goal -> the controller at 50 Hz
-> a new MCAP with the commands as ``geometry_msgs/msg/Twist`` (Foxglove opens it as it is).

Input topics (names configurable): ``/scan`` ``sensor_msgs/msg/LaserScan`` in the robot frame;
``/odom`` ``nav_msgs/msg/Odometry`` (pose in the world, twist in the robot frame, as ROS does);
``/user<i>/odom`` ``nav_msgs/msg/Odometry`` per user (pose in the world, twist in the user's frame);
``/goal`` ``geometry_msgs/msg/PoseStamped`` in the world. Header stamps are the clock: each tick
uses the newest message of each topic stamped at or before it, so stale or missing inputs reach the
watchdog as they would on the robot. Output: ``/cmd_vel`` (after the safety layer) and
``/cmd_vel_policy`` (the policy's command before it), stamped with the tick's time.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from pathlib import Path

import numpy as np

from methd_jax import ros_messages
from methd_jax.deploy.controller import Controller, Inputs
from methd_jax.deploy.policy import DeployError


@dataclasses.dataclass(frozen=True)
class Topics:
    scan: str = "/scan"
    odom: str = "/odom"
    goal: str = "/goal"
    user: str = "/user{i}/odom"
    cmd_vel: str = "/cmd_vel"
    cmd_vel_policy: str = "/cmd_vel_policy"


def scan_to_rays(
    ranges, angle_min: float, angle_increment: float, range_min: float, range_max: float, num_rays: int
) -> np.ndarray:
    """A LaserScan's ranges resampled to the policy's rays (ray j at 2*pi*j/num_rays): the nearest
    beam within half an increment, else no return (inf). Readings outside [range_min, range_max]
    are no return, as ROS defines them; NaN stays NaN for the watchdog."""
    r = np.asarray(ranges, np.float64)
    if r.size == 0 or not angle_increment > 0:
        return np.full(0, np.nan)
    r = np.where((r < range_min) | (r > range_max), np.inf, r)
    target = 2.0 * np.pi * np.arange(num_rays) / num_rays
    offset = (target - angle_min) % (2.0 * np.pi)
    index = np.rint(offset / angle_increment).astype(np.int64)
    exact = np.abs(offset - index * angle_increment) <= 0.5 * angle_increment + 1e-9
    covered = exact & (index < r.size)
    # a full circle's last beam may sit just below 2*pi: beam 0 of the next turn
    wrap = (index == r.size) & (abs(r.size * angle_increment - 2.0 * np.pi) < 1e-6)
    index = np.where(wrap, 0, index)
    return np.where(covered | wrap, r[np.clip(index, 0, r.size - 1)], np.inf)


def scan_points(
    ranges, angle_min: float, angle_increment: float, range_min: float, range_max: float
) -> np.ndarray:
    """A LaserScan's returns at full resolution as points (M, 2) in the sensor frame: every beam
    with a reading in [range_min, range_max] (what the safety layer checks; the policy sees only
    :func:`scan_to_rays`)."""
    r = np.asarray(ranges, np.float64)
    if r.size == 0 or not angle_increment > 0:
        return np.zeros((0, 2))
    a = angle_min + angle_increment * np.arange(r.size)
    ok = np.isfinite(r) & (r >= range_min) & (r <= range_max)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], -1)


def odometry(msg) -> tuple[np.ndarray, np.ndarray]:
    p, t = msg.pose.pose, msg.twist.twist
    pose = np.array([p.position.x, p.position.y, ros_messages.quaternion_yaw(p.orientation)])
    return pose, np.array([t.linear.x, t.linear.y, t.angular.z])


def user_state(msg) -> np.ndarray:
    """A user's Odometry (twist in the user's frame) as world x, y, yaw, vx, vy, wz."""
    pose, twist = odometry(msg)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.concatenate([pose, [c * twist[0] - s * twist[1], s * twist[0] + c * twist[1], twist[2]]])


def goal_pose(msg) -> np.ndarray:
    """A PoseStamped as world x, y, yaw."""
    p = msg.pose
    return np.array([p.position.x, p.position.y, ros_messages.quaternion_yaw(p.orientation)])


class _Latest:
    """Messages of one topic sorted by stamp; ``at(t)`` the newest at or before t."""

    def __init__(self):
        self.stamps, self.values = [], []

    def finish(self):
        order = np.argsort(self.stamps, kind="stable")
        self.stamps = np.asarray(self.stamps, np.int64)[order]
        self.values = [self.values[i] for i in order]

    def at(self, t_ns: int):
        i = int(np.searchsorted(self.stamps, t_ns, side="right")) - 1
        return (None, None) if i < 0 else (self.stamps[i], self.values[i])


def read_inputs(bag: str | Path, num_rays: int, num_users: int, topics: Topics = Topics()) -> dict:
    """Every input message of ``bag`` by topic, decoded and converted."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    user_topics = [topics.user.format(i=i) for i in range(num_users)]
    wanted = [topics.scan, topics.odom, topics.goal, *user_topics]
    series = {t: _Latest() for t in wanted}
    try:
        with open(bag, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for _, channel, _, msg in reader.iter_decoded_messages(topics=wanted, log_time_order=False):
                s = series[channel.topic]
                s.stamps.append(ros_messages.stamp_ns(msg))
                if channel.topic == topics.scan:
                    geometry = (msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max)
                    s.values.append(
                        (scan_to_rays(msg.ranges, *geometry, num_rays), scan_points(msg.ranges, *geometry))
                    )
                elif channel.topic == topics.goal:
                    s.values.append(goal_pose(msg))
                elif channel.topic == topics.odom:
                    s.values.append(odometry(msg))
                else:
                    s.values.append(user_state(msg))
    except FileNotFoundError:
        raise DeployError(f"{bag}: no such file") from None
    except (McapError, struct.error, EOFError, OSError, UnicodeDecodeError) as e:
        raise DeployError(f"{bag}: unreadable MCAP file ({type(e).__name__}: {e})") from None
    except AttributeError as e:
        raise DeployError(f"{bag}: a message has an unexpected layout ({e})") from None
    except DeployError:
        raise
    except Exception as e:
        raise DeployError(f"{bag}: corrupt MCAP file ({type(e).__name__}: {e})") from None
    for name, s in series.items():
        if not s.stamps:
            raise DeployError(f"{bag}: no messages on {name} (topics needed: {', '.join(wanted)})")
        s.finish()
    check_stamps(series, bag)
    return series


MAX_GAP = 60.0
"""Longest silence of a topic that a replay steps through, s: beyond it a stamp is taken for a
fault (a clock jump), not a pause, and the bag is refused rather than replayed tick by tick."""


def check_stamps(series: dict, bag) -> None:
    """Refuses stamps that would make a replay run for ever: a topic silent for more than
    :data:`MAX_GAP` (one message stamped a day late gave 4.3M ticks)."""
    for name, s in series.items():
        gaps = np.diff(s.stamps) / 1e9
        if gaps.size and gaps.max() > MAX_GAP:
            i = int(np.argmax(gaps)) + 1
            raise DeployError(
                f"{bag}: {name} jumps {gaps.max():.3g} s between two messages (stamp {int(s.stamps[i])} ns); "
                f"more than {MAX_GAP:g} s is a clock fault, not a recording"
            )


def replay(
    controller: Controller,
    bag: str | Path,
    out: str | Path,
    *,
    topics: Topics = Topics(),
    progress=None,
) -> dict:
    """Runs ``controller`` over ``bag`` at its control rate and writes the commands to ``out``."""
    from mcap_ros2.writer import Writer

    if Path(out).resolve() == Path(bag).resolve():
        raise DeployError(f"--out {out} is the input bag; choose another file")
    series = read_inputs(bag, controller.num_rays, controller.num_users, topics)
    user_topics = [topics.user.format(i=i) for i in range(controller.num_users)]
    start = max(int(s.stamps[0]) for s in series.values())
    end = max(int(s.stamps[-1]) for s in series.values())
    step = round(1e9 * controller.dt)
    ticks = np.arange(start, end + 1, step, dtype=np.int64)
    controller.reset()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    before = dict(controller.interventions)
    moved = 0
    with open(out, "wb") as f:
        writer = Writer(f)
        schema = writer.register_msgdef("geometry_msgs/msg/Twist", ros_messages.TWIST)
        for k, t in enumerate(ticks.tolist()):
            scan_t, scan = series[topics.scan].at(t)
            odom_t, odom = series[topics.odom].at(t)
            _, goal = series[topics.goal].at(t)
            users = [series[u].at(t) for u in user_topics]
            x = Inputs(
                ranges=None if scan is None else scan[0],
                scan_points=None if scan is None else scan[1],
                robot_pose=None if odom is None else odom[0],
                velocity=None if odom is None else odom[1],
                users=None if any(u[1] is None for u in users) else np.stack([u[1] for u in users]),
                goal=goal,
                scan_stamp=None if scan_t is None else scan_t / 1e9,
                odom_stamp=None if odom_t is None else odom_t / 1e9,
                users_stamp=None if any(u[0] is None for u in users) else min(u[0] for u in users) / 1e9,
            )
            cmd = controller.tick(x, now=t / 1e9)
            moved += bool(np.any(cmd.twist))
            writer.write_message(
                topics.cmd_vel, schema, ros_messages.twist(*cmd.twist), log_time=t, publish_time=t
            )
            writer.write_message(
                topics.cmd_vel_policy, schema, ros_messages.twist(*cmd.policy), log_time=t, publish_time=t
            )
            if progress is not None:
                progress(k + 1, len(ticks))
        writer.finish()
    counts = {k: v - before.get(k, 0) for k, v in controller.interventions.items() if v - before.get(k, 0)}
    return {
        "ticks": len(ticks),
        "seconds": (end - start) / 1e9,
        "moving_ticks": moved,
        "interventions": counts,
        "out": str(out),
    }
