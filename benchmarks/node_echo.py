"""
Benchmark helper node: republish every measurement on ``echo`` (the transport's cost).

``node_echo.py EXECUTOR [QOS_DEPTH]``: after SIGINT prints one JSON line {received}.
"""

import json
import sys
from typing import List

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.ros.runner import run
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy


def main(argv: List[str]) -> int:
    """Republish every measurement on ``echo``: the transport's own cost."""
    received = [0]

    def make_node() -> Node:
        node = Node('bench_echo')
        publisher = node.create_publisher(PoseWithCovarianceStamped, 'echo', 10)

        def on_message(msg) -> None:
            received[0] += 1
            publisher.publish(msg)
        # The estimator's subscription QoS in row 4: best effort, depth as given.
        node.create_subscription(
            PoseWithCovarianceStamped, 'measurement', on_message,
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT))
        return node

    depth = int(argv[1]) if len(argv) > 1 else 10
    code = run(make_node, ['bench_echo'], executor=argv[0] if argv else 'events')
    print(json.dumps({'received': received[0]}), flush=True)
    return code


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
