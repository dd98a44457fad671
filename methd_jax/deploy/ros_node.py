"""A thin ROS 2 node around :class:`~methd_jax.deploy.controller.Controller` (needs rclpy).

Subscribes to ``/scan`` (LaserScan), ``/odom`` (Odometry), ``/user<i>/odom`` (Odometry) and
``/goal`` (PoseStamped) and publishes ``/cmd_vel`` (Twist) from a timer at the policy's control
rate. The same conversions as the offline replay (:mod:`methd_jax.deploy.mcap_replay`), so what a bag
replay shows is what the node does. Importing this module does not need ROS; running it does.
"""

from __future__ import annotations

import numpy as np

from methd_jax import ros_messages
from methd_jax.deploy.controller import Controller, Inputs
from methd_jax.deploy.mcap_replay import Topics, goal_pose, odometry, scan_points, scan_to_rays, user_state


def _rclpy():
    try:
        import rclpy
        from geometry_msgs.msg import PoseStamped, Twist
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import LaserScan
    except ImportError:
        return None
    return rclpy, PoseStamped, Twist, Odometry, LaserScan


def available() -> bool:
    """Whether rclpy and the message packages can be imported (a sourced ROS 2 install)."""
    return _rclpy() is not None


def run(policy_dir: str, topics: Topics | None = None, backend: str = "onnx") -> None:
    """Spins the node until shutdown (``topics``: default :class:`Topics`); raises RuntimeError when
    ROS 2 is not available."""
    topics = topics or Topics()
    ros = _rclpy()
    if ros is None:
        raise RuntimeError("rclpy is not importable: source a ROS 2 installation (setup.bash) first")
    rclpy, PoseStamped, Twist, Odometry, LaserScan = ros
    controller = Controller(policy_dir, backend=backend)
    rclpy.init()
    node = rclpy.create_node("methd_jax_controller")
    latest: dict = {}

    def stamp(msg) -> float:
        return ros_messages.stamp_ns(msg) / 1e9

    def on_scan(msg):
        geometry = (msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max)
        scan = (scan_to_rays(msg.ranges, *geometry, controller.num_rays), scan_points(msg.ranges, *geometry))
        latest["scan"] = (stamp(msg), scan)

    def on_odom(msg):
        latest["odom"] = (stamp(msg), odometry(msg))

    def on_goal(msg):
        latest["goal"] = goal_pose(msg)

    def on_user(i):
        def callback(msg):
            latest[f"user{i}"] = (stamp(msg), user_state(msg))

        return callback

    node.create_subscription(LaserScan, topics.scan, on_scan, 10)
    node.create_subscription(Odometry, topics.odom, on_odom, 10)
    node.create_subscription(PoseStamped, topics.goal, on_goal, 10)
    for i in range(controller.num_users):
        node.create_subscription(Odometry, topics.user.format(i=i), on_user(i), 10)
    publisher = node.create_publisher(Twist, topics.cmd_vel, 10)

    def on_timer():
        scan, odom = latest.get("scan"), latest.get("odom")
        users = [latest.get(f"user{i}") for i in range(controller.num_users)]
        x = Inputs(
            ranges=None if scan is None else scan[1][0],
            scan_points=None if scan is None else scan[1][1],
            robot_pose=None if odom is None else odom[1][0],
            velocity=None if odom is None else odom[1][1],
            users=None if any(u is None for u in users) else np.stack([u[1] for u in users]),
            goal=latest.get("goal"),
            scan_stamp=None if scan is None else scan[0],
            odom_stamp=None if odom is None else odom[0],
            users_stamp=None if any(u is None for u in users) else min(u[0] for u in users),
        )
        now = node.get_clock().now().nanoseconds * 1e-9
        cmd = controller.tick(x, now=now)
        msg = Twist()
        msg.linear.x, msg.linear.y, msg.angular.z = (float(v) for v in cmd.twist)
        publisher.publish(msg)

    node.create_timer(controller.dt, on_timer)
    try:
        rclpy.spin(node)
    finally:
        node.get_logger().info(f"interventions: {dict(controller.interventions)}")
        node.destroy_node()
        rclpy.shutdown()
