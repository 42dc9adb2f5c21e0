"""
Benchmark helper node: publish paced measurements of a train (``make bench`` rows 4, 5).

``node_publisher.py RATE_HZ COUNT [SETTLE_S]``: prints ``up``, ``start``, and at the
end one JSON line {published, start_ns, end_ns, max_burst}.
"""

import json
import math
import random
import sys
import time
from typing import List

from bench_common import NS_PER_S, R_M2, TRAIN_SPEED_MPS
from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.ros import messages
import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy


def main(argv: List[str]) -> int:
    """
    Publish ``count`` (0: until SIGINT) paced measurements of a train at ``rate_hz``.

    Publishing starts ``settle_s`` (default 0.5) after the first subscriber is seen,
    or at once for a negative ``settle_s``.
    """
    rate_hz, count = float(argv[0]), int(argv[1])
    settle_s = float(argv[2]) if len(argv) > 2 else 0.5  # < 0: do not wait for anyone
    rclpy.init()
    node = Node('bench_publisher')
    # Best effort, as a sensor driver publishes (rclpy's qos_profile_sensor_data): a
    # reliable writer stalls publish() for milliseconds at a time at these rates, and
    # the stream would come out in bursts.
    publisher = node.create_publisher(
        PoseWithCovarianceStamped, 'measurement',
        QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    print('up', flush=True)
    published = max_burst = 0
    start_ns = end_ns = time.time_ns()
    try:
        while settle_s >= 0.0 and publisher.get_subscription_count() < 1:
            time.sleep(0.005)
        time.sleep(max(settle_s, 0.0))  # let the subscriber's side of the match settle
        rng = random.Random(7)
        print('start', flush=True)
        period_ns = NS_PER_S / rate_hz
        start_ns = last_ns = time.time_ns()
        next_ns = float(start_ns)
        while count == 0 or published < count:
            now_ns = time.time_ns()
            burst = published
            while next_ns <= now_ns and (count == 0 or published < count):
                stamp_ns = max(time.time_ns(), last_ns + 1)
                position = TRAIN_SPEED_MPS * (stamp_ns - start_ns) / NS_PER_S + rng.gauss(
                    0.0, math.sqrt(R_M2))
                publisher.publish(messages.to_measurement_msg(stamp_ns, 'odom', position,
                                                              R_M2))
                last_ns = stamp_ns
                published += 1
                next_ns += period_ns
            max_burst = max(max_burst, published - burst)
            delay_s = (next_ns - time.time_ns()) / NS_PER_S
            if delay_s > 0.0:
                time.sleep(delay_s)
        end_ns = time.time_ns()
    except KeyboardInterrupt:
        end_ns = time.time_ns()
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(json.dumps({'published': published, 'start_ns': start_ns, 'end_ns': end_ns,
                      'max_burst': max_burst}), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
