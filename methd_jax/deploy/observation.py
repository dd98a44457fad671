"""The training observation and command, rebuilt in numpy from one tick of robot inputs.

Mirrors ``envs.nav.NavEnv.observe`` and ``NavEnv.command`` term by term (tests hold the two
together): LiDAR clamped to the training range, robot velocity and acceleration, the last two
policy actions, per user (p_u, v_u, phi_u, theta_u, d_u) in the robot frame (in the order the
deployment's ``user_order`` names: as given, or the goal's user first), the goal with its dead
zones and, where the deployment's ``lidar`` names ``clearance_sectors``, the footprint's clearance
per sector of the scan. The deployed robot sees no simulated noise: ranges are only clamped.
"""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi


def wrap_angle(a):
    """Angles wrapped to [-pi, pi) (as ``methd_jax.geometry.wrap_angle``)."""
    return (np.asarray(a) + np.pi) % TWO_PI - np.pi


def to_local(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """World points ``(..., 2)`` in the frame of ``pose`` (x, y, yaw)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = points - pose[:2]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def rotate(yaw, vectors: np.ndarray) -> np.ndarray:
    """Vectors ``(..., 2)`` rotated counter-clockwise by ``yaw``."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack(
        [c * vectors[..., 0] - s * vectors[..., 1], s * vectors[..., 0] + c * vectors[..., 1]], -1
    )


def boundary_distance(angles: np.ndarray, length: float, width: float) -> np.ndarray:
    """b_r: distance from the centre of a ``length`` x ``width`` rectangle to its edge along each
    ray angle (numpy twin of ``methd_jax.geometry.Footprint.boundary_distance``)."""
    c, s = np.abs(np.cos(angles)), np.abs(np.sin(angles))
    with np.errstate(divide="ignore"):
        to_front = np.where(c > 0, 0.5 * length / np.where(c > 0, c, 1.0), np.inf)
        to_side = np.where(s > 0, 0.5 * width / np.where(s > 0, s, 1.0), np.inf)
    return np.minimum(to_front, to_side)


def sector_clearance(scan: np.ndarray, deployment: dict) -> np.ndarray:
    """The footprint's clearance per sector of ``scan`` (numpy twin of
    ``envs.nav.sector_clearance``): over each sector's rays the least range beyond the footprint,
    in [0, clearance_range]; sector j about the ray at 2 pi j / sectors."""
    lidar, foot = deployment["lidar"], deployment["footprint"]
    sectors = lidar["clearance_sectors"]
    angles = 2.0 * np.pi * np.arange(len(scan)) / len(scan)
    beyond = scan - boundary_distance(angles, foot["length"], foot["width"])
    per = len(scan) // sectors
    beyond = np.roll(beyond, per // 2).reshape(sectors, per)
    return np.clip(beyond.min(axis=1), 0.0, lidar["clearance_range"])


def goal_user_order(users: np.ndarray, goal: np.ndarray, hip: dict) -> np.ndarray:
    """Indices of ``users`` (N, >= 3: x, y, yaw, ...) nearest-first by the distance from ``goal``
    to each one's HIP, ``hip["distance"]`` ahead of and ``hip["lateral"]`` to the left of the user
    (numpy twin of ``envs.nav.goal_user_order``)."""
    c, s = np.cos(users[:, 2]), np.sin(users[:, 2])
    ahead, left = hip["distance"], hip["lateral"]
    hip_xy = users[:, :2] + np.stack([c * ahead - s * left, s * ahead + c * left], 1)
    return np.argsort(np.linalg.norm(hip_xy - np.asarray(goal[:2]), axis=1), kind="stable")


def observe(
    deployment: dict,
    *,
    ranges: np.ndarray,
    robot_pose: np.ndarray,
    velocity: np.ndarray,
    acceleration: np.ndarray,
    actions: np.ndarray,
    users: np.ndarray,
    goal: np.ndarray,
) -> np.ndarray:
    """The observation vector (float32).

    ``ranges`` (num_rays,) robot-frame LiDAR, ray i at 2*pi*i/num_rays counter-clockwise (inf: no
    return); ``robot_pose`` (3,) world x, y, yaw; ``velocity`` / ``acceleration`` (3,) robot frame;
    ``actions`` (2, 3) the policy's a_{t-1}, a_{t-2}; ``users`` (N, 6) world x, y, yaw, vx, vy, wz;
    ``goal`` (3,) world x, y, yaw.
    """
    lidar, g = deployment["lidar"], deployment["goal"]
    pose = np.asarray(robot_pose, np.float64)
    scan = np.clip(np.minimum(ranges, lidar["max_range"]), 0.0, lidar["max_range"])

    if deployment.get("user_order", "fixed") == "goal":
        users = users[goal_user_order(users, goal, deployment["hip"])]
    user_xy = users[:, :2]
    p_u = to_local(pose, user_xy)
    d_u = np.linalg.norm(p_u, axis=1)
    v_u = np.concatenate([rotate(-pose[2], users[:, 3:5]), users[:, 5:6]], 1)
    theta_u = np.arctan2(p_u[:, 1], p_u[:, 0])
    to_robot = pose[:2] - user_xy
    phi_u = wrap_angle(np.arctan2(to_robot[:, 1], to_robot[:, 0]) - users[:, 2])
    s_u = np.concatenate([p_u, v_u, phi_u[:, None], theta_u[:, None], d_u[:, None]], 1)

    p_g = to_local(pose, np.asarray(goal[:2], np.float64))
    d_g = np.linalg.norm(p_g)
    theta_g = 0.0 if d_g < g["tolerance"] else np.arctan2(p_g[1], p_g[0])
    dyaw = wrap_angle(goal[2] - pose[2])
    p_g = np.where(np.abs(p_g) < g["deadzone"], 0.0, p_g)
    dyaw = 0.0 if abs(dyaw) < g["yaw_deadzone"] else dyaw
    s_g = np.array([p_g[0], p_g[1], d_g, theta_g, dyaw])

    parts = [scan, velocity, acceleration, actions[0], actions[1], s_u.reshape(-1), s_g]
    if lidar.get("clearance_sectors", 0):
        parts.append(sector_clearance(scan, deployment))
    return np.concatenate([np.asarray(p, np.float64).reshape(-1) for p in parts]).astype(np.float32)


def command(deployment: dict, action: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """Robot-frame velocity command (vx, vy, wz) for ``action`` after ``previous`` (2, 3): the
    interpolation of eq. 4.18, the scale and the dead zones of eqs. 4.19-4.21."""
    a = deployment["action"]
    w = a["interpolation_weights"]
    blended = w[0] * np.asarray(action, np.float64) + w[1] * previous[0] + w[2] * previous[1]
    cmd = blended * np.asarray(a["scale"])
    cmd[:2] = np.where(np.abs(cmd[:2]) < a["deadzone_linear"], 0.0, cmd[:2])
    if abs(cmd[2]) < a["deadzone_angular"]:
        cmd[2] = 0.0
    return cmd
