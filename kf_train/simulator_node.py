"""
The ``simulator`` node: a train at constant velocity, measured with noise at rate_hz.

Publishes ``measurement`` (geometry_msgs/PoseWithCovarianceStamped) and
``ground_truth`` (nav_msgs/Odometry) with identical stamps. Sample k is stamped
``start + k / rate_hz`` on the node clock (so ``use_sim_time`` works), where
``start`` is one period before the first sample is published; stamps are thus exactly
periodic, and the truth ``x0 + v·t`` is evaluated at the stamp.

Fault injection (all off by default, seeded from ``seed`` through a generator of
their own, so the measurement noise is the same with and without faults; see
:mod:`kf_train.core.faults` for the exact rules): ``dropout_probability``,
``outlier_probability`` / ``outlier_size_m``, ``delay_s`` (a fixed latency, timed on
the steady clock), ``reorder_probability`` (a sample arrives after the next one),
``clock_jump_at_s`` / ``clock_jump_s`` (stamps jump from that sample time on) and
``measurement_bias_m``. The ground truth is never faulty, but carries the jumped
stamp, like the measurement of the same sample. ``publish_clock`` publishes each
sample's stamp on ``/clock`` (rosgraph_msgs/Clock), so that nodes with
``use_sim_time`` see the clock jump too.
"""

import dataclasses
import heapq

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train import messages
from kf_train.core.estimator import NS_PER_S
from kf_train.core.faults import FaultInjector, FaultSettings
from kf_train.core.simulation import TrainSimulation
from kf_train.parameters import BIG, declare
from kf_train.runner import run, StartupError
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg

QOS_DEPTH = 10
# How long a finished simulator waits for its last samples to be acknowledged.
FLUSH_TIMEOUT_S = 2.0
# Fault parameter -> FaultSettings field.
FAULT_PARAMETERS = {
    'dropout_probability': 'dropout_probability',
    'outlier_probability': 'outlier_probability',
    'outlier_size_m': 'outlier_size_m',
    'delay_s': 'delay_s',
    'reorder_probability': 'reorder_probability',
    'clock_jump_at_s': 'clock_jump_at_s',
    'clock_jump_s': 'clock_jump_s',
    'measurement_bias_m': 'bias_m',
}


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
                       'Seed of the measurement noise and of the faults; -1 draws fresh '
                       'entropy. ' + fixed, int_range=(-1, 2 ** 31 - 1), read_only=True)
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
        self.publish_clock = declare(self, 'publish_clock', False,
                                     'Publish each sample stamp on /clock (for nodes '
                                     'with use_sim_time).', constraints='true or false')
        faults = self._declare_faults()
        if not self.frame_id or not self.child_frame_id:
            raise StartupError('frame_id and child_frame_id must not be empty')
        self.simulation = TrainSimulation(position, velocity, noise_std, self.rate_hz,
                                          None if seed < 0 else seed)
        try:
            self.faults = FaultInjector(faults, None if seed < 0 else seed)
        except ValueError as error:
            raise StartupError(f'invalid parameter: {error}') from None
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.measurement_pub = self.create_publisher(
            PoseWithCovarianceStamped, 'measurement', QOS_DEPTH)
        self.truth_pub = self.create_publisher(Odometry, 'ground_truth', QOS_DEPTH)
        self.clock_pub = None  # created when publish_clock is first needed
        self.done = Future()
        self.published = 0
        self.delivered = 0
        self._start_ns = None
        self._sampling_done = False
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._queue = []  # (due steady ns, sequence, message) of delayed measurements
        self._sequence = 0
        self._scheduled_due_ns = None
        self._delivery_timer = self.create_timer(1.0, self._on_delivery_timer,
                                                 clock=self._steady, autostart=False)
        self._timer = self.create_timer(1.0 / self.rate_hz, self._on_timer)

    def _declare_faults(self) -> FaultSettings:
        """Declare the fault-injection parameters; return them as FaultSettings."""
        live = 'Changeable at runtime; applies from the next sample. Default off.'
        probability = (0.0, 1.0)
        values = {
            'dropout_probability': declare(
                self, 'dropout_probability', 0.0,
                'Probability that a sample is lost. ' + live, float_range=probability),
            'outlier_probability': declare(
                self, 'outlier_probability', 0.0,
                'Probability that a sample is off by ±outlier_size_m. ' + live,
                float_range=probability),
            'outlier_size_m': declare(
                self, 'outlier_size_m', 10.0,
                'Size of an outlier [m], added with a random sign. ' + live,
                float_range=(0.0, 1e6)),
            'delay_s': declare(
                self, 'delay_s', 0.0,
                'Latency between taking and publishing a sample [s]. ' + live,
                float_range=(0.0, 60.0)),
            'reorder_probability': declare(
                self, 'reorder_probability', 0.0,
                'Probability that a sample is published after the next one. ' + live,
                float_range=probability),
            'clock_jump_at_s': declare(
                self, 'clock_jump_at_s', 0.0,
                'Sample time [s] from which clock_jump_s is added to every stamp; '
                '0 = never. ' + live, float_range=(0.0, 1e9)),
            'clock_jump_s': declare(
                self, 'clock_jump_s', 0.0,
                'Stamp jump [s] from clock_jump_at_s on; negative jumps back (a '
                'restarted sensor clock). ' + live, float_range=(-1e9, 1e9)),
            'measurement_bias_m': declare(
                self, 'measurement_bias_m', 0.0,
                'Constant bias added to every measurement [m]. ' + live,
                float_range=(-1e6, 1e6)),
        }
        return FaultSettings(**{FAULT_PARAMETERS[name]: value
                                for name, value in values.items()})

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Apply noise, fault, frame and limit changes; rclpy checked the ranges already."""
        fault_changes = {}
        for parameter in parameters:
            if parameter.name in ('frame_id', 'child_frame_id') and not parameter.value:
                return SetParametersResult(successful=False,
                                           reason=f'{parameter.name} must not be empty')
            if parameter.name in FAULT_PARAMETERS:
                fault_changes[FAULT_PARAMETERS[parameter.name]] = parameter.value
        try:
            faults = dataclasses.replace(self.faults.settings, **fault_changes).validated()
        except ValueError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self.faults.reconfigure(faults)
        for parameter in parameters:
            if parameter.name == 'noise_std':
                self.simulation.noise_std_m = float(parameter.value)
            elif parameter.name in ('frame_id', 'child_frame_id', 'max_samples',
                                    'min_subscribers', 'publish_clock'):
                setattr(self, parameter.name, parameter.value)
        return SetParametersResult(successful=True)

    def _on_timer(self) -> None:
        """Publish the next sample once enough subscribers are there."""
        if self.done.done() or self._sampling_done:
            return
        if self._start_ns is None:
            if self.measurement_pub.get_subscription_count() < self.min_subscribers:
                return
            self._start_ns = (self.get_clock().now().nanoseconds
                              - round(NS_PER_S / self.rate_hz))
        sample = self.simulation.next_sample()
        stamp_ns = self._start_ns + round(sample.index * NS_PER_S / self.rate_hz)
        variance = self.simulation.noise_std_m ** 2
        truth_stamp_ns = self.faults.jumped_stamp_ns(sample.t_s, stamp_ns)
        if self.publish_clock:
            if self.clock_pub is None:
                self.clock_pub = self.create_publisher(ClockMsg, '/clock', QOS_DEPTH)
            self.clock_pub.publish(messages.to_clock_msg(truth_stamp_ns))
        deliveries = self.faults.apply(sample.index, sample.t_s, stamp_ns,
                                       sample.measured_position_m)
        self.published += 1
        if self.max_samples and self.published >= self.max_samples:
            deliveries += self.faults.flush()
            self._sampling_done = True
            self._timer.cancel()
        for delivery in deliveries:
            self._send(messages.to_measurement_msg(
                delivery.stamp_ns, self.frame_id, delivery.position_m, variance))
        self.truth_pub.publish(messages.to_odometry_msg(
            truth_stamp_ns, self.frame_id, self.child_frame_id, sample.true_position_m,
            sample.true_velocity_mps, 0.0, 0.0))
        self._finish_if_done()

    def _send(self, msg: PoseWithCovarianceStamped) -> None:
        """Publish a measurement now, or after delay_s."""
        delay_ns = round(self.faults.settings.delay_s * NS_PER_S)
        if delay_ns == 0 and not self._queue:
            self.measurement_pub.publish(msg)
            self.delivered += 1
            return
        due_ns = self._steady.now().nanoseconds + delay_ns
        heapq.heappush(self._queue, (due_ns, self._sequence, msg))
        self._sequence += 1
        if self._scheduled_due_ns is None or due_ns < self._scheduled_due_ns:
            self._schedule(due_ns)

    def _schedule(self, due_ns: int) -> None:
        """Make the delivery timer fire at due_ns on the steady clock."""
        self._scheduled_due_ns = due_ns
        wait_ns = max(due_ns - self._steady.now().nanoseconds, 1000)
        self._delivery_timer.timer_period_ns = wait_ns
        self._delivery_timer.reset()

    def _on_delivery_timer(self) -> None:
        """Publish every delayed measurement that is due; schedule the next one."""
        now_ns = self._steady.now().nanoseconds
        while self._queue and self._queue[0][0] <= now_ns:
            self.measurement_pub.publish(heapq.heappop(self._queue)[2])
            self.delivered += 1
        if self._queue:
            self._schedule(self._queue[0][0])
        else:
            self._scheduled_due_ns = None
            self._delivery_timer.cancel()
        self._finish_if_done()

    def _finish_if_done(self) -> None:
        """Finish once max_samples are taken and every delayed one is out."""
        if self._sampling_done and not self._queue and not self.done.done():
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
