"""
Benchmark helper node: record stamp and arrival time of every message on a topic.

``node_probe.py TOPIC odometry|measurement [--diagnostics]``: prints ``up``, ``ready``
once a publisher is matched, ``first <ns>`` at the first message, and after SIGINT one
JSON line {count, latency_median_ms, latency_p99_ms, diagnostics}.
"""

import json
import sys
import time
from typing import Dict, List

from bench_common import percentile
from kf_train.ros import messages
from kf_train.ros.runner import run
from rclpy.node import Node
from rclpy.qos import QoSProfile


def main(argv: List[str]) -> int:
    """Record the stamp and arrival time of every message on a topic until SIGINT."""
    topic, kind = argv[0], argv[1]
    with_diagnostics = '--diagnostics' in argv
    if kind == 'odometry':
        from nav_msgs.msg import Odometry as message_type
    else:
        from geometry_msgs.msg import PoseWithCovarianceStamped as message_type
    stamps: List[int] = []
    arrivals: List[int] = []
    diagnostics: Dict[str, str] = {}

    def make_node() -> Node:
        node = Node('bench_probe')

        def on_message(data: bytes) -> None:
            arrivals.append(time.time_ns())
            stamps.append(messages.stamp_ns_from_serialized(data))
            if len(arrivals) == 1:
                print(f'first {arrivals[0]}', flush=True)

        # Raw (serialized) messages: the probe reads only the stamp, so that its own
        # cost on this shared CPU stays small.
        subscription = node.create_subscription(message_type, topic, on_message,
                                                QoSProfile(depth=1000), raw=True)
        if with_diagnostics:
            from diagnostic_msgs.msg import DiagnosticArray

            def on_diagnostics(msg) -> None:
                for status in msg.status:
                    if status.name.endswith(': filter'):
                        diagnostics.update((v.key, v.value) for v in status.values)
            node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics,
                                     QoSProfile(depth=10))
        announced = []

        def on_timer() -> None:
            if not announced and subscription.get_publisher_count() >= 1:
                announced.append(True)
                print('ready', flush=True)
        node.create_timer(0.02, on_timer)
        print('up', flush=True)
        return node

    code = run(make_node, ['bench_probe'], executor='events')
    latencies = sorted((a - s) / 1e6 for a, s in zip(arrivals, stamps))
    print(json.dumps({
        'count': len(latencies), 'latency_median_ms': percentile(latencies, 0.5),
        'latency_p99_ms': percentile(latencies, 0.99), 'diagnostics': diagnostics}),
        flush=True)
    return code


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
