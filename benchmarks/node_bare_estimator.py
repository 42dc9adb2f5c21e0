"""
Benchmark baseline: a bare rclpy node with the estimator's topics and no filter (row 5).

It republishes each measurement's header as an empty estimate: what any rclpy node with
these publishers costs to start, against which the kf_train estimator is measured.
"""

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy


def main() -> None:
    """Spin the bare estimator until SIGINT."""
    rclpy.init()
    node = Node('estimator')
    estimate = node.create_publisher(Odometry, 'estimate', 10)
    node.create_publisher(Odometry, 'prediction', 10)
    node.create_publisher(Vector3Stamped, 'innovation', 10)
    node.create_publisher(DiagnosticArray, '/diagnostics', 10)

    def on_measurement(msg):
        out = Odometry()
        out.header = msg.header
        estimate.publish(out)
    node.create_subscription(PoseWithCovarianceStamped, 'measurement', on_measurement,
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


if __name__ == '__main__':
    main()
