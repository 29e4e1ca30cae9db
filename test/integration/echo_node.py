"""A tiny rclpy node run as a separate process by the tests: echoes a message type from ~/in to ~/out.

usage: python echo_node.py <package/msg/Type> [--node-name NAME]
"""
import argparse
import importlib

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("type")
    ap.add_argument("--node-name", default="echo")
    args, ros_args = ap.parse_known_args()
    pkg, _, name = args.type.split("/")
    msg_type = getattr(importlib.import_module(f"{pkg}.msg"), name)
    rclpy.init(args=ros_args)
    node = Node(args.node_name)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    pub = node.create_publisher(msg_type, "~/out", qos)
    node.create_subscription(msg_type, "~/in", pub.publish, qos)
    node.get_logger().info(f"echoing {args.type}")
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
