"""``python -m methd_jax.deploy {replay,latency,node}``: the deployment shim from the command line."""

from __future__ import annotations

import dataclasses
import json
import sys

from methd_jax.cli import OneLineParser
from methd_jax.deploy import ros_node
from methd_jax.deploy.controller import Controller, latency
from methd_jax.deploy.mcap_replay import replay
from methd_jax.deploy.policy import DeployError
from methd_jax.deploy.safety import SafetyConfig


def main(argv=None) -> int:
    parser = OneLineParser(prog="python -m methd_jax.deploy", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("replay", help="run the controller over an MCAP bag and write /cmd_vel to a new MCAP")
    r.add_argument(
        "bag", help="input MCAP (LaserScan /scan, Odometry /odom and /user<i>/odom, PoseStamped /goal)"
    )
    r.add_argument("policy", help="deployment folder from `python -m train.export` (or its run folder)")
    r.add_argument("--out", required=True, help="output MCAP with the commands")
    l = sub.add_parser("latency", help="time one controller tick (median, p99) on random inputs")
    l.add_argument("policy")
    l.add_argument("--ticks", type=int, default=2000)
    n = sub.add_parser("node", help="run the ROS 2 node (needs a sourced ROS 2 with rclpy)")
    n.add_argument("policy")
    for p in (r, l, n):
        p.add_argument("--backend", choices=("onnx", "numpy"), default="onnx")
    for p in (r, l):
        p.add_argument(
            "--no-safety", action="store_true", help="leave the command unfiltered (watchdog stays)"
        )
    args = parser.parse_args(argv)
    try:
        if args.command == "node":
            ros_node.run(args.policy, backend=args.backend)
            return 0
        if getattr(args, "ticks", 1) < 1:
            parser.error("--ticks must be >= 1")
        safety = dataclasses.replace(SafetyConfig(), enabled=not args.no_safety)
        controller = Controller(args.policy, backend=args.backend, safety=safety)
        if args.command == "latency":
            print(json.dumps(latency(controller, args.ticks), indent=2))
        else:
            summary = replay(controller, args.bag, args.out)
            print(json.dumps(summary, indent=2))
    except (DeployError, RuntimeError) as e:
        parser.exit(1, f"{parser.prog}: error: {e}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
