"""
The ``simulator`` node: a train at constant velocity, measured with noise at rate_hz.

Publishes ``measurement`` (geometry_msgs/PoseWithCovarianceStamped) and
``ground_truth`` (nav_msgs/Odometry) with identical stamps. Sample k is stamped
``start + k / rate_hz`` on the node clock (so ``use_sim_time`` works), where
``start`` is one period before the first sample is published; stamps are thus exactly
periodic, and the truth ``x0 + v·t`` is evaluated at the stamp.
"""

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train import messages
from kf_train.core.estimator import NS_PER_S
from kf_train.core.simulation import TrainSimulation
from kf_train.parameters import BIG, declare
from kf_train.runner import run, StartupError
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.task import Future

QOS_DEPTH = 10
# How long a finished simulator waits for its last samples to be acknowledged.
FLUSH_TIMEOUT_S = 2.0


class SimulatorNode(Node):
    """Publishes simulated train measurements and the ground truth."""

    def __init__(self, **kwargs):
        """Declare parameters, create publishers and start the sampling timer."""
        super().__init__('simulator', **kwargs)
        fixed = 'Fixed at start-up (restart to change).'
        self.rate_hz = declare(self, 'rate_hz', 10.0, 'Sample rate [Hz]. ' + fixed,
                               float_range=(0.01, 10000.0), read_only=True)
        velocity = declare(self, 'true_velocity', 10.0,
                           'True constant velocity of the train [m/s]. ' + fixed,
                           float_range=(-1000.0, 1000.0), read_only=True)
        position = declare(self, 'initial_position', 0.0,
                           'True position at the start time [m]. ' + fixed,
                           float_range=(-BIG, BIG), read_only=True)
        noise_std = declare(self, 'noise_std', 1.0,
                            'Standard deviation of the position measurement noise [m]; '
                            'its square is published as the measurement variance.',
                            float_range=(0.0, 1000.0))
        seed = declare(self, 'seed', 0,
                       'Seed of the measurement noise; -1 draws fresh entropy. ' + fixed,
                       int_range=(-1, 2 ** 31 - 1), read_only=True)
        self.frame_id = declare(self, 'frame_id', 'odom',
                                'Frame of the measurements and the truth (REP 105).',
                                constraints='a non-empty frame name')
        self.child_frame_id = declare(self, 'child_frame_id', 'base_link',
                                      'child_frame_id of the ground truth odometry.',
                                      constraints='a non-empty frame name')
        self.max_samples = declare(self, 'max_samples', 0,
                                   'Samples to publish before finishing; 0 runs forever.',
                                   int_range=(0, 2 ** 31 - 1))
        self.min_subscribers = declare(self, 'min_subscribers', 0,
                                       'Subscribers of measurement to wait for before '
                                       'the first sample.', int_range=(0, 1000))
        if not self.frame_id or not self.child_frame_id:
            raise StartupError('frame_id and child_frame_id must not be empty')
        self.simulation = TrainSimulation(position, velocity, noise_std, self.rate_hz,
                                          None if seed < 0 else seed)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.measurement_pub = self.create_publisher(
            PoseWithCovarianceStamped, 'measurement', QOS_DEPTH)
        self.truth_pub = self.create_publisher(Odometry, 'ground_truth', QOS_DEPTH)
        self.done = Future()
        self.published = 0
        self._start_ns = None
        self._timer = self.create_timer(1.0 / self.rate_hz, self._on_timer)

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Apply noise, frame and limit changes; ranges were checked by rclpy already."""
        for parameter in parameters:
            if parameter.name in ('frame_id', 'child_frame_id') and not parameter.value:
                return SetParametersResult(successful=False,
                                           reason=f'{parameter.name} must not be empty')
        for parameter in parameters:
            if parameter.name == 'noise_std':
                self.simulation.noise_std_m = float(parameter.value)
            elif parameter.name == 'frame_id':
                self.frame_id = parameter.value
            elif parameter.name == 'child_frame_id':
                self.child_frame_id = parameter.value
            elif parameter.name == 'max_samples':
                self.max_samples = parameter.value
            elif parameter.name == 'min_subscribers':
                self.min_subscribers = parameter.value
        return SetParametersResult(successful=True)

    def _on_timer(self) -> None:
        """Publish the next sample once enough subscribers are there."""
        if self.done.done():
            return
        if self._start_ns is None:
            if self.measurement_pub.get_subscription_count() < self.min_subscribers:
                return
            self._start_ns = (self.get_clock().now().nanoseconds
                              - round(NS_PER_S / self.rate_hz))
        sample = self.simulation.next_sample()
        stamp_ns = self._start_ns + round(sample.index * NS_PER_S / self.rate_hz)
        variance = self.simulation.noise_std_m ** 2
        self.measurement_pub.publish(messages.to_measurement_msg(
            stamp_ns, self.frame_id, sample.measured_position_m, variance))
        self.truth_pub.publish(messages.to_odometry_msg(
            stamp_ns, self.frame_id, self.child_frame_id, sample.true_position_m,
            sample.true_velocity_mps, 0.0, 0.0))
        self.published += 1
        if self.max_samples and self.published >= self.max_samples:
            self._finish()

    def _finish(self) -> None:
        """Stop sampling and let reliable subscribers receive the last samples."""
        self._timer.cancel()
        flush_timeout = Duration(nanoseconds=int(FLUSH_TIMEOUT_S * NS_PER_S))
        self.measurement_pub.wait_for_all_acked(timeout=flush_timeout)
        self.truth_pub.wait_for_all_acked(timeout=flush_timeout)
        self.get_logger().info(f'published {self.published} samples; done')
        self.done.set_result(self.published)


def main(args=None) -> int:
    """Run the simulator until Ctrl-C, SIGTERM or max_samples."""
    return run(SimulatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
