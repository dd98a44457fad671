"""Deployment shim: exported policies on a robot PC with numpy and onnxruntime only (no JAX).

``Controller(folder)`` loads what ``python -m train.export RUN`` writes and turns one tick of
inputs (:class:`Inputs`) into a safe velocity command (:class:`Command`); ``GuideGoal(folder)``
runs a GuideRL policy that sets a NavRL controller's goal; a watchdog and a
collision-monitor-style safety layer sit between the policy and the base. ``replay`` runs it over a
ROS 2 bag in MCAP; ``ros_node`` wraps it in rclpy. CLI: ``python -m methd_jax.deploy --help``.
"""

from methd_jax.deploy.controller import Command, Controller, Inputs, WatchdogConfig, latency
from methd_jax.deploy.guide import GuideGoal
from methd_jax.deploy.mcap_replay import Topics, replay, scan_points, scan_to_rays
from methd_jax.deploy.policy import DeployError, NumpyPolicy, OnnxPolicy, load_manifest, load_policy
from methd_jax.deploy.safety import CollisionMonitor, SafetyConfig

__all__ = [
    "CollisionMonitor",
    "Command",
    "Controller",
    "DeployError",
    "GuideGoal",
    "Inputs",
    "NumpyPolicy",
    "OnnxPolicy",
    "SafetyConfig",
    "Topics",
    "WatchdogConfig",
    "latency",
    "load_manifest",
    "load_policy",
    "replay",
    "scan_points",
    "scan_to_rays",
]
