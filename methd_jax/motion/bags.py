"""Trajectories as ROS 2 bags in MCAP, one trajectory per file; ROS 1 bags converted to that layout.

Topics: ``/head`` and ``/wrist`` as ``geometry_msgs/msg/PoseStamped`` (frame ``world``, metres,
100 Hz) and ``/haptic_request`` as ``std_msgs/msg/Bool``; the request is the first True. Readers
use the messages' own header stamps as the time base and map the request's log time onto that
clock, so bags recorded with ``ros2 bag record`` load as well as our own. A dataset is a directory
of such files whose names sort in recording order.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from methd_jax import ros_messages
from methd_jax.motion.trajectory import (
    RATE_HZ,
    MotionDataError,
    Trajectory,
    repair_glitches,
)

TOPICS = ("/head", "/wrist", "/haptic_request")
MCAP_MAGIC = b"\x89MCAP0\r\n"
FRAME_ID = "world"

POSE_STAMPED_MSGDEF = ros_messages.POSE_STAMPED
BOOL_MSGDEF = ros_messages.BOOL


# ----------------------------------------------------------------------------------------------
# Writing


def _pose_msg(stamp_ns: int, pose: np.ndarray) -> dict:
    return {
        "header": ros_messages.header(stamp_ns, FRAME_ID),
        "pose": {
            "position": {"x": float(pose[0]), "y": float(pose[1]), "z": float(pose[2])},
            "orientation": {
                "x": float(pose[3]),
                "y": float(pose[4]),
                "z": float(pose[5]),
                "w": float(pose[6]),
            },
        },
    }


def write_bag(path: str | Path, traj: Trajectory) -> Path:
    """Writes one trajectory to an MCAP file (zstd-compressed chunks)."""
    from mcap_ros2.writer import Writer

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stamps = traj.start_ns + np.rint(traj.time * 1e9).astype(np.int64)
    req = traj.request_index
    with open(path, "wb") as f:
        w = Writer(f)
        pose_schema = w.register_msgdef("geometry_msgs/msg/PoseStamped", POSE_STAMPED_MSGDEF)
        bool_schema = w.register_msgdef("std_msgs/msg/Bool", BOOL_MSGDEF)
        for i, ns in enumerate(stamps.tolist()):
            w.write_message("/head", pose_schema, _pose_msg(ns, traj.head[i]), log_time=ns, publish_time=ns)
            w.write_message("/wrist", pose_schema, _pose_msg(ns, traj.wrist[i]), log_time=ns, publish_time=ns)
            w.write_message("/haptic_request", bool_schema, {"data": i >= req}, log_time=ns, publish_time=ns)
        w.finish()
    return path


def save(path: str | Path, trajectories: Trajectory | Sequence[Trajectory], progress=None) -> list[Path]:
    """Writes trajectories as ``<path>/<name>.mcap`` (or one trajectory to ``path`` ending in .mcap)."""
    path = Path(path)
    if isinstance(trajectories, Trajectory):
        trajectories = [trajectories]
    if path.suffix == ".mcap":
        if len(trajectories) != 1:
            raise ValueError(f"{path}: one .mcap file holds one trajectory, got {len(trajectories)}")
        return [write_bag(path, trajectories[0])]
    names = [t.name for t in trajectories]
    if len(set(names)) != len(names):
        raise ValueError("trajectory names must be unique to be saved in one directory")
    out = []
    for i, t in enumerate(trajectories):
        out.append(write_bag(path / f"{t.name}.mcap", t))
        if progress is not None:
            progress(i + 1, len(trajectories))
    return out


# ----------------------------------------------------------------------------------------------
# Reading


class _Topic:
    """Messages of one topic in file order: header stamps, log times and values."""

    def __init__(self):
        self.stamps: list[int] = []
        self.log: list[int] = []
        self.values: list = []


MAX_GAP = 1.0
"""Longest gap between two poses of a topic that is interpolated, s (100 Hz tracking)."""


def _assemble(name: str, topics: dict[str, _Topic], label: str) -> Trajectory:
    """Validates decoded messages and resamples them onto a uniform 100 Hz grid.

    ``name`` names the trajectory; ``label`` (the file) starts every error message.
    """
    for topic in ("/head", "/haptic_request", "/wrist"):
        if not topics[topic].values:
            raise MotionDataError(f"{label}: no messages on {topic}")
    series = {}
    for topic in ("/head", "/wrist"):
        stamps = np.asarray(topics[topic].stamps, np.int64)
        back = np.flatnonzero(np.diff(stamps) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise MotionDataError(
                f"{label}: {topic} timestamps go backwards (or repeat) at message {i} "
                f"({stamps[i - 1]} ns then {stamps[i]} ns)"
            )
        gaps = np.diff(stamps) / 1e9
        if gaps.size and gaps.max() > MAX_GAP:
            i = int(np.argmax(gaps)) + 1
            raise MotionDataError(
                f"{label}: {topic} has a gap of {gaps.max():.3g} s before message {i} (more than "
                f"{MAX_GAP} s cannot be interpolated)"
            )
        poses = np.asarray(topics[topic].values, np.float64)
        bad = np.flatnonzero(~np.all(np.isfinite(poses), axis=1))
        if bad.size:
            raise MotionDataError(f"{label}: {topic} pose {int(bad[0])} is not finite (NaN or inf)")
        norms = np.linalg.norm(poses[:, 3:], axis=1)
        bad = np.flatnonzero((norms < 0.5) | (norms > 2.0))
        if bad.size:
            raise MotionDataError(
                f"{label}: {topic} pose {int(bad[0])} has no valid orientation "
                f"(quaternion norm {norms[bad[0]]:.3g})"
            )
        series[topic] = (stamps, poses)
    (head_s, _), (wrist_s, _) = series["/head"], series["/wrist"]
    overlap = min(head_s[-1], wrist_s[-1]) - max(head_s[0], wrist_s[0])
    if overlap < 0.5 * (head_s[-1] - head_s[0]):
        raise MotionDataError(
            f"{label}: /wrist stamps cover {max(overlap, 0) / 1e9:.3g} s of /head's "
            f"{(head_s[-1] - head_s[0]) / 1e9:.3g} s (offset by {(wrist_s[0] - head_s[0]) / 1e9:.3g} s?)"
        )
    requests = [
        log
        for log, v in zip(topics["/haptic_request"].log, topics["/haptic_request"].values, strict=True)
        if v
    ]
    if not requests:
        raise MotionDataError(f"{label}: no haptic request (no True on /haptic_request)")
    head_stamps, head = series["/head"]
    # the request (a Bool, no header) arrives on the log clock; move it onto the stamp clock
    offset = int(np.median(np.asarray(topics["/head"].log, np.int64) - head_stamps))
    t0 = int(head_stamps[0])
    request_time = (min(requests) - offset - t0) / 1e9
    if request_time > (head_stamps[-1] - t0) / 1e9 + 1.0 / RATE_HZ:
        raise MotionDataError(f"{label}: the haptic request comes after the last /head pose")
    request_time = float(np.clip(request_time, 0.0, (head_stamps[-1] - t0) / 1e9))

    t_head = (head_stamps - t0) / 1e9
    n = int(np.floor(t_head[-1] * RATE_HZ + 1e-6)) + 1
    grid = np.arange(n) / RATE_HZ
    head = repair_glitches(label, t_head, head, "/head")

    def resample(t, poses):
        """Positions linearly, orientations by nlerp between the two neighbouring samples (with the
        second put in the first's hemisphere); samples that lie on the grid come back unchanged."""
        out = np.empty((n, 7))
        for k in range(3):
            out[:, k] = np.interp(grid, t, poses[:, k])
        i = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 1)
        j = np.minimum(i + 1, len(t) - 1)
        a, b = poses[i, 3:], poses[j, 3:]
        b = b * np.where(np.sum(a * b, 1) < 0, -1.0, 1.0)[:, None]
        w = np.clip((grid - t[i]) / np.maximum(t[j] - t[i], 1e-12), 0.0, 1.0)[:, None]
        q = np.where(w == 0, a, (1 - w) * a + w * b)
        out[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
        return out

    wrist_stamps, wrist = series["/wrist"]
    return Trajectory(
        name=name,
        time=grid,
        head=resample(t_head, head),
        wrist=resample((wrist_stamps - t0) / 1e9, wrist),
        request_time=min(request_time, grid[-1]),
        start_ns=t0,
    )


def _pose_values(msg) -> list[float]:
    p, q = msg.pose.position, msg.pose.orientation
    return [p.x, p.y, p.z, q.x, q.y, q.z, q.w]


def read_bag(path: str | Path) -> Trajectory:
    """Reads one trajectory from an MCAP file (ROS 2, cdr); errors name the file and the problem."""
    from mcap.exceptions import EndOfFile, InvalidMagic, McapError
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = Path(path)
    topics = {t: _Topic() for t in TOPICS}
    try:
        with open(path, "rb") as f:
            if f.read(8) != MCAP_MAGIC:
                raise InvalidMagic(b"")
            f.seek(0)
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for _, channel, message, msg in reader.iter_decoded_messages(
                topics=list(TOPICS), log_time_order=False
            ):
                t = topics[channel.topic]
                if channel.topic == "/haptic_request":
                    t.values.append(bool(msg.data))
                    t.stamps.append(message.log_time)
                else:
                    t.values.append(_pose_values(msg))
                    t.stamps.append(ros_messages.stamp_ns(msg))
                t.log.append(message.log_time)
    except FileNotFoundError:
        raise MotionDataError(f"{path}: no such file") from None
    except InvalidMagic:
        raise MotionDataError(f"{path}: not an MCAP file") from None
    except (EndOfFile, struct.error, EOFError) as e:
        raise MotionDataError(f"{path}: truncated or corrupt MCAP file ({type(e).__name__})") from None
    except McapError as e:
        raise MotionDataError(f"{path}: unreadable MCAP file ({e})") from None
    except (AttributeError, KeyError, ValueError) as e:
        raise MotionDataError(f"{path}: unexpected message layout ({e})") from None
    except Exception as e:
        raise MotionDataError(f"{path}: corrupt MCAP file ({type(e).__name__}: {e})") from None
    return _assemble(path.stem, topics, str(path))


def _files(path: Path, suffix: str) -> list[Path]:
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix == suffix)
        if not files:
            raise MotionDataError(f"{path}: no {suffix} files in this directory")
        return files
    if not path.exists():
        raise MotionDataError(f"{path}: no such file or directory")
    return [path]


def _read_all(path: str | Path, suffix: str, read, progress) -> list[Trajectory]:
    """Every ``suffix`` file at ``path`` (a file or a directory, in name order); all or nothing."""
    files = _files(Path(path), suffix)
    out = []
    for i, f in enumerate(files):
        out.append(read(f))
        if progress is not None:
            progress(i + 1, len(files))
    return out


def load(path: str | Path, progress=None) -> list[Trajectory]:
    """Reads a ``.mcap`` file or a directory of them (in name order); all or nothing."""
    return _read_all(path, ".mcap", read_bag, progress)


# ----------------------------------------------------------------------------------------------
# ROS 1


def read_ros1_bag(path: str | Path) -> Trajectory:
    """Reads one trajectory from a ROS 1 ``.bag`` with the same topics (via the rosbags package)."""
    from rosbags.rosbag1 import Reader, ReaderError
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    store = get_typestore(Stores.ROS1_NOETIC)
    topics = {t: _Topic() for t in TOPICS}
    try:
        with Reader(path) as reader:
            conns = [c for c in reader.connections if c.topic in TOPICS]
            for conn, log_ns, raw in reader.messages(connections=conns):
                msg = store.deserialize_ros1(raw, conn.msgtype)
                t = topics[conn.topic]
                if conn.topic == "/haptic_request":
                    t.values.append(bool(msg.data))
                    t.stamps.append(int(log_ns))
                else:
                    t.values.append(_pose_values(msg))
                    t.stamps.append(ros_messages.stamp_ns(msg))
                t.log.append(int(log_ns))
    except FileNotFoundError:
        raise MotionDataError(f"{path}: no such file") from None
    except ReaderError as e:
        raise MotionDataError(f"{path}: not a readable ROS 1 bag ({e})") from None
    except Exception as e:
        raise MotionDataError(f"{path}: not a readable ROS 1 bag ({type(e).__name__}: {e})") from None
    return _assemble(path.stem, topics, str(path))


def write_ros1_bag(path: str | Path, traj: Trajectory) -> Path:
    """Writes a trajectory as a ROS 1 bag (what a lab's ROS 1 recorder produces; for tests/tools)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Pose, Point, Quat = (
        T["geometry_msgs/msg/Pose"],
        T["geometry_msgs/msg/Point"],
        T["geometry_msgs/msg/Quaternion"],
    )
    PoseStamped, Bool = T["geometry_msgs/msg/PoseStamped"], T["std_msgs/msg/Bool"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    stamps = traj.start_ns + np.rint(traj.time * 1e9).astype(np.int64)
    with Writer(path) as w:
        conns = {
            "/head": w.add_connection("/head", PoseStamped.__msgtype__, typestore=store),
            "/wrist": w.add_connection("/wrist", PoseStamped.__msgtype__, typestore=store),
            "/haptic_request": w.add_connection("/haptic_request", Bool.__msgtype__, typestore=store),
        }
        for i, ns in enumerate(stamps.tolist()):
            stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            for topic, arr in (("/head", traj.head), ("/wrist", traj.wrist)):
                p = arr[i]
                msg = PoseStamped(
                    header=Header(seq=i, stamp=stamp, frame_id=FRAME_ID),
                    pose=Pose(
                        position=Point(x=p[0], y=p[1], z=p[2]),
                        orientation=Quat(x=p[3], y=p[4], z=p[5], w=p[6]),
                    ),
                )
                w.write(conns[topic], ns, store.serialize_ros1(msg, PoseStamped.__msgtype__))
            w.write(
                conns["/haptic_request"],
                ns,
                store.serialize_ros1(Bool(data=i >= traj.request_index), Bool.__msgtype__),
            )
    return path


def convert(src: str | Path, dst: str | Path, progress=None) -> list[Path]:
    """Converts a ROS 1 ``.bag`` (or a directory of them) to our MCAP layout under ``dst``.

    Every input is read and checked before anything is written, and nothing that exists is
    overwritten: ``dst`` is a new ``.mcap`` file (one input) or a directory.
    """
    dst = Path(dst)
    if dst.suffix != ".mcap" and dst.exists() and not dst.is_dir():
        raise MotionDataError(f"{dst}: exists and is not a directory; give a directory or a new .mcap file")
    trajectories = _read_all(src, ".bag", read_ros1_bag, progress)
    targets = [dst] if dst.suffix == ".mcap" else [dst / f"{t.name}.mcap" for t in trajectories]
    taken = [str(t) for t in targets if t.exists()]
    if taken:
        raise MotionDataError(
            f"{taken[0]}: already exists; convert does not overwrite ({len(taken)} file(s))"
        )
    return save(dst, trajectories)
