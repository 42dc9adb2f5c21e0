"""
Benchmark baseline: a bare rclpy node with the simulator's topics and no model (row 5).

``node_bare_simulator.py RATE_HZ`` publishes empty, stamped measurements and truths.
"""

import sys

from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node


def main() -> None:
    """Spin the bare simulator until SIGINT."""
    rclpy.init()
    node = Node('simulator')
    measurement = node.create_publisher(PoseWithCovarianceStamped, 'measurement', 10)
    truth = node.create_publisher(Odometry, 'ground_truth', 10)

    def on_timer():
        msg = PoseWithCovarianceStamped()
        msg.header.stamp = node.get_clock().now().to_msg()
        measurement.publish(msg)
        truth.publish(Odometry(header=msg.header))
    node.create_timer(1.0 / float(sys.argv[1]), on_timer)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


if __name__ == '__main__':
    main()
