"""ROS 2 message definitions and small conversions for writing and reading bags in MCAP.

One place for the ``.msg`` text that ``mcap_ros2`` needs to encode messages (cdr), shared by the
motion data layer and the deployment shim. Numpy only: the deployment shim imports this without JAX.
"""

from __future__ import annotations

import math

SEP = "=" * 80 + "\n"
"""Separator between a message's definition and those of the types it uses (ROS 2's ``.msg`` bundles)."""

_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
_POINT = "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n"
_QUATERNION = "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
_POSE = "MSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n"
_VECTOR3 = "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
_TWIST = "MSG: geometry_msgs/Twist\nVector3 linear\nVector3 angular\n"


def _bundle(body: str, *deps: str) -> str:
    return body + "".join(SEP + d for d in deps)


POSE_STAMPED = _bundle(
    "std_msgs/Header header\ngeometry_msgs/Pose pose\n", _HEADER, _TIME, _POSE, _POINT, _QUATERNION
)
BOOL = "bool data\n"
TWIST = _bundle("Vector3 linear\nVector3 angular\n", _VECTOR3)
LASER_SCAN = _bundle(
    "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n"
    "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n"
    "float32[] ranges\nfloat32[] intensities\n",
    _HEADER,
    _TIME,
)
ODOMETRY = _bundle(
    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
    "geometry_msgs/TwistWithCovariance twist\n",
    _HEADER,
    _TIME,
    "MSG: geometry_msgs/PoseWithCovariance\nPose pose\nfloat64[36] covariance\n",
    _POSE,
    _POINT,
    _QUATERNION,
    "MSG: geometry_msgs/TwistWithCovariance\nTwist twist\nfloat64[36] covariance\n",
    _TWIST,
    _VECTOR3,
)

SCHEMAS = {
    "geometry_msgs/msg/PoseStamped": POSE_STAMPED,
    "std_msgs/msg/Bool": BOOL,
    "geometry_msgs/msg/Twist": TWIST,
    "sensor_msgs/msg/LaserScan": LASER_SCAN,
    "nav_msgs/msg/Odometry": ODOMETRY,
}


def header(stamp_ns: int, frame_id: str) -> dict:
    return {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9}, "frame_id": frame_id}


def stamp_ns(msg) -> int:
    """A decoded message's header stamp in nanoseconds."""
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


def yaw_quaternion(yaw: float) -> dict:
    return {"x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw), "w": math.cos(0.5 * yaw)}


def quaternion_yaw(q) -> float:
    """Yaw (rotation about z) of a quaternion with fields x, y, z, w."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def pose2d(x: float, y: float, yaw: float) -> dict:
    return {"position": {"x": float(x), "y": float(y), "z": 0.0}, "orientation": yaw_quaternion(float(yaw))}


def twist(vx: float, vy: float, wz: float) -> dict:
    return {
        "linear": {"x": float(vx), "y": float(vy), "z": 0.0},
        "angular": {"x": 0.0, "y": 0.0, "z": float(wz)},
    }
