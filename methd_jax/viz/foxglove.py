"""A :class:`~methd_jax.viz.episode.Rollout` as an MCAP file with Foxglove's own schemas.

Written with the maintained ``foxglove-schemas-protobuf`` messages through ``mcap-protobuf-support``,
so Foxglove opens the file with no conversion (a 3D panel on ``/floor`` + ``/scene``, the scan on
``/scan``). Channels, timestamps on the episode's clock (t = 0 at the reset):

==================  =====================  ===========================================================
``/floor``          foxglove.SceneUpdate   once: obstacles (cylinders, polygon prisms), lifetime forever
``/scene``          foxglove.SceneUpdate   every step: robot box, users (body, d_coll and d_crit
                                           rings, view arrow), HIPs, goal, a status text
``/tf``             foxglove.FrameTransform  every step with a robot: ``world`` -> ``base_link``
``/scan``           foxglove.LaserScan     every step with a robot: the observation's ranges, in
                                           ``base_link``, ray 0 forward, counter-clockwise
``/robot/pose``     foxglove.PoseInFrame   every step with a robot
``/goal``           foxglove.PoseInFrame   every step with a robot
``/user<i>/pose``   foxglove.PoseInFrame   every step, one channel per user (i from 1)
==================  =====================  ===========================================================
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap_protobuf.writer import Writer

from methd_jax.viz.draw import OBSTACLE_COLOUR, ROBOT_COLOUR, USER_COLOURS
from methd_jax.viz.episode import Rollout

OBSTACLE_HEIGHT = 1.0
ROBOT_HEIGHT = 0.5
USER_HEIGHT = 1.7


def _colour(hex_colour: str, alpha: float = 1.0) -> Color:
    r, g, b = (int(hex_colour[i : i + 2], 16) / 255 for i in (1, 3, 5))
    return Color(r=r, g=g, b=b, a=alpha)


def _pose(x: float, y: float, yaw: float = 0.0, z: float = 0.0) -> Pose:
    return Pose(
        position=Vector3(x=float(x), y=float(y), z=float(z)),
        orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
    )


def _stamp(seconds: float) -> Timestamp:
    ns = round(seconds * 1e9)
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _ring(x: float, y: float, r: float, colour: Color, n: int = 48) -> LinePrimitive:
    a = np.linspace(0, 2 * np.pi, n + 1)
    pts = [Point3(x=float(x + r * np.cos(t)), y=float(y + r * np.sin(t)), z=0.02) for t in a]
    return LinePrimitive(
        type=LinePrimitive.LINE_STRIP, pose=_pose(0, 0), thickness=0.03, points=pts, color=colour
    )


def _prism(vertices: np.ndarray, height: float, colour: Color) -> TriangleListPrimitive:
    """A convex polygon extruded to ``height``: top fan and side quads as one triangle list."""
    pts = []
    top = [Point3(x=float(x), y=float(y), z=height) for x, y in vertices]
    for k in range(1, len(vertices) - 1):
        pts += [top[0], top[k], top[k + 1]]
    for k in range(len(vertices)):
        (x0, y0), (x1, y1) = vertices[k], vertices[(k + 1) % len(vertices)]
        a, b = Point3(x=float(x0), y=float(y0), z=0.0), Point3(x=float(x1), y=float(y1), z=0.0)
        c, d = Point3(x=float(x1), y=float(y1), z=height), Point3(x=float(x0), y=float(y0), z=height)
        pts += [a, b, c, a, c, d]
    return TriangleListPrimitive(pose=_pose(0, 0), points=pts, color=colour)


def floor_update(rollout: Rollout) -> SceneUpdate:
    """The floor's obstacles as one entity that lives for the whole recording."""
    floor, grey = rollout.floor, _colour(OBSTACLE_COLOUR)
    cylinders = [
        CylinderPrimitive(
            pose=_pose(x, y, z=OBSTACLE_HEIGHT / 2),
            size=Vector3(x=2 * r, y=2 * r, z=OBSTACLE_HEIGHT),
            color=grey,
        )
        for (x, y, r), on in zip(floor.circles, floor.circle_mask, strict=True)
        if on
    ]
    prisms = [
        _prism(poly[vmask], OBSTACLE_HEIGHT, grey)
        for poly, on, vmask in zip(floor.polygons, floor.polygon_mask, floor.vertex_mask, strict=True)
        if on
    ]
    entity = SceneEntity(
        timestamp=_stamp(0.0), frame_id="world", id="floor", cylinders=cylinders, triangles=prisms
    )
    return SceneUpdate(entities=[entity])


def scene_update(rollout: Rollout, i: int) -> SceneUpdate:
    """Robot, users, HIPs, goal and a status line at step ``i`` (entities replaced by id)."""
    r, stamp, entities = rollout, _stamp(rollout.t[i]), []
    for j in range(r.num_users):
        col = _colour(USER_COLOURS[j % len(USER_COLOURS)])
        x, y, yaw = (float(v) for v in r.users[i, j])
        hx, hy, hyaw = (float(v) for v in r.hips[i, j])
        served = bool(r.requested[i]) and j == r.requester
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id="world",
                id=f"user{j + 1}",
                cylinders=[
                    CylinderPrimitive(
                        pose=_pose(x, y, z=USER_HEIGHT / 2),
                        size=Vector3(x=0.5, y=0.5, z=USER_HEIGHT),
                        color=col,
                    )
                ],
                lines=[
                    _ring(x, y, r.collision_distance, col),
                    _ring(x, y, r.critical_distance, _colour(USER_COLOURS[j % len(USER_COLOURS)], 0.4)),
                ],
                arrows=[
                    ArrowPrimitive(
                        pose=_pose(x, y, yaw, z=USER_HEIGHT),
                        shaft_length=0.5,
                        shaft_diameter=0.05,
                        head_length=0.2,
                        head_diameter=0.15,
                        color=col,
                    ),
                    ArrowPrimitive(
                        pose=_pose(hx, hy, hyaw, z=0.05),
                        shaft_length=0.3,
                        shaft_diameter=0.08 if served else 0.04,
                        head_length=0.15,
                        head_diameter=0.2,
                        color=col,
                    ),
                ],
            )
        )
    status = f"{r.env}  t = {r.t[i]:.2f} s"
    if r.u_w is not None:
        status += f"  u_w = {r.u_w[i]:+.2f}"
    if r.requested[i]:
        status += f"  user {r.requester + 1} requested"
    if r.robot is not None:
        rx, ry, ryaw = (float(v) for v in r.robot[i])
        length, width = r.footprint
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id="world",
                id="robot",
                cubes=[
                    CubePrimitive(
                        pose=_pose(rx, ry, ryaw, z=ROBOT_HEIGHT / 2),
                        size=Vector3(x=length, y=width, z=ROBOT_HEIGHT),
                        color=_colour(ROBOT_COLOUR),
                    )
                ],
            )
        )
        gx, gy, gyaw = (float(v) for v in r.goal[i])
        entities.append(
            SceneEntity(
                timestamp=stamp,
                frame_id="world",
                id="goal",
                arrows=[
                    ArrowPrimitive(
                        pose=_pose(gx, gy, gyaw, z=0.1),
                        shaft_length=0.4,
                        shaft_diameter=0.06,
                        head_length=0.2,
                        head_diameter=0.2,
                        color=_colour("#7b2cbf"),
                    )
                ],
            )
        )
    x0, y0 = (float(v) for v in r.floor.bounds[:2])
    entities.append(
        SceneEntity(
            timestamp=stamp,
            frame_id="world",
            id="status",
            texts=[
                TextPrimitive(
                    pose=_pose(x0, y0, z=2.0),
                    billboard=True,
                    font_size=14,
                    text=status,
                    color=_colour("#000000"),
                )
            ],
        )
    )
    return SceneUpdate(entities=entities)


def _pose_in_frame(stamp: Timestamp, pose: np.ndarray) -> PoseInFrame:
    return PoseInFrame(timestamp=stamp, frame_id="world", pose=_pose(*(float(v) for v in pose)))


def to_mcap(rollout: Rollout, path: str | Path, *, stride: int = 1) -> Path:
    """Writes every ``stride``-th step (and the last) of ``rollout`` to ``path`` (see the module
    docstring for the channels); returns the path."""
    steps = rollout.strided(stride)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f, Writer(f) as writer:
        writer.write_message("/floor", floor_update(rollout), log_time=0, publish_time=0)
        for i in steps:
            ns = round(float(rollout.t[i]) * 1e9)
            stamp = _stamp(rollout.t[i])

            def put(topic, msg, ns=ns):
                writer.write_message(topic, msg, log_time=ns, publish_time=ns)

            put("/scene", scene_update(rollout, i))
            for j in range(rollout.num_users):
                put(f"/user{j + 1}/pose", _pose_in_frame(stamp, rollout.users[i, j]))
            if rollout.robot is None:
                continue
            rx, ry, ryaw = (float(v) for v in rollout.robot[i])
            put(
                "/tf",
                FrameTransform(
                    timestamp=stamp,
                    parent_frame_id="world",
                    child_frame_id="base_link",
                    translation=Vector3(x=rx, y=ry, z=0.0),
                    rotation=_pose(0, 0, ryaw).orientation,
                ),
            )
            n = rollout.ranges.shape[1]
            put(
                "/scan",
                LaserScan(
                    timestamp=stamp,
                    frame_id="base_link",
                    pose=_pose(0, 0),
                    start_angle=0.0,
                    end_angle=2 * math.pi * (n - 1) / n,
                    ranges=[float(v) for v in rollout.ranges[i]],
                ),
            )
            put("/robot/pose", _pose_in_frame(stamp, rollout.robot[i]))
            put("/goal", _pose_in_frame(stamp, rollout.goal[i]))
    return path
