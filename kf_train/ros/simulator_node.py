"""
The ``simulator`` node: a seed's scenario (the train by default), measured at rate_hz.

Publishes ``measurement`` (geometry_msgs/PoseWithCovarianceStamped, variance
``noise_std``² in ``pose.covariance[0]``) and ``ground_truth`` (nav_msgs/Odometry)
with identical stamps. Sample k is stamped ``start + k / rate_hz`` on the node clock
(so ``use_sim_time`` works), where ``start`` is one period before the first sample is
published; stamps are thus exactly periodic, and the truth is evaluated at t_k = k /
rate_hz.

``scenario`` (fixed at start-up; see :mod:`kf_train.sim.scenario_streams`):

* ``train`` (seed 000): x = ``initial_position`` + ``true_velocity``·t.
* ``car`` / ``car-exact`` (seed 001): from [``initial_position``, ``true_velocity``]
  (default [0.2, 0]) a random walk driven by the commanded acceleration
  ``acceleration_mps2`` (1 m/s²), with the seed's process noise diag(0, 0.05) per
  0.1 s and its B = [0, dt] (``car-exact``: [dt²/2, dt]). Also publishes ``control``
  (geometry_msgs/AccelStamped, ``accel.linear.x`` [m/s²]).
* ``robot`` / ``robot-exact`` (seed 002): x = ``initial_position`` + 0.05·t·cos(2t),
  a range finder with σ = ``noise_std`` (default 0.03 m, R = 0.0009) and a speed
  sensor with σ = ``speed_noise_std`` (0.2 m/s). Also publishes ``control``
  (geometry_msgs/TwistStamped, ``twist.linear.x`` [m/s]): for ``robot`` the speed read
  at the previous sample, as the seed applies it; for ``robot-exact`` the reading of
  the interval itself. ``true_velocity`` is not used.
* ``noise_std``, ``initial_position`` and ``true_velocity`` default to the scenario's
  values (train: 1 m, 0 m, 10 m/s; car: 1 m, 0.2 m, 0 m/s; robot: 0.03 m, 0 m).

Controls: sample k's control is the input applied over (t_{k-1}, t_k], the interval
that ends at it (SEEDS.md); it is stamped t_k, in the body frame ``child_frame_id``,
and published just *before* the measurement stamped t_k. It is never faulty, but
carries the jumped stamp of a clock jump (it comes from the same clock). A seed's
cv-position run is the ``train`` scenario with rate_hz 1, true_velocity 2 and
initial_position -1 (x = 2t − 1).

Fault injection (all off by default, seeded from ``seed`` through a generator of
their own, so the measurement noise is the same with and without faults; see
:mod:`kf_train.sim.faults` for the exact rules): ``dropout_probability``,
``outlier_probability`` / ``outlier_size_m``, ``delay_s`` (a fixed latency, timed on
the steady clock), ``reorder_probability`` (a sample arrives after the next one),
``clock_jump_at_s`` / ``clock_jump_s`` (stamps jump from that sample time on) and
``measurement_bias_m``, for every scenario. The ground truth is never faulty, but
carries the jumped stamp, like the measurement of the same sample. ``publish_clock`` publishes each
sample's stamp on ``/clock`` (rosgraph_msgs/Clock), so that nodes with
``use_sim_time`` see the clock jump too.
"""

import dataclasses
import heapq

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.estimator.estimator import NS_PER_S
from kf_train.ros import messages
from kf_train.ros.parameters import BIG, declare
from kf_train.ros.runner import run, StartupError
from kf_train.sim.faults import FaultInjector, FaultSettings
from kf_train.sim.scenario_streams import (
    CAR_ACCELERATION_MPS2, CONTROL_NAMES, DEFAULT_INITIAL_STATE, DEFAULT_NOISE_STD_M,
    make_stream, ROBOT_SPEED_STD_MPS, SCENARIOS)
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
    """Publishes simulated measurements (and controls) of a seed scenario and the truth."""

    def __init__(self, **kwargs):
        """Declare parameters, create publishers and start the sampling timer."""
        super().__init__('simulator', **kwargs)
        fixed = 'Fixed at start-up (restart to change).'
        default = "Default: the scenario's. "
        self.scenario = declare(
            self, 'scenario', 'train',
            'What is simulated: train (seed 000), car / car-exact (seed 001, publishes '
            'control as AccelStamped), robot / robot-exact (seed 002, publishes control '
            'as TwistStamped). ' + fixed, constraints='one of: ' + ', '.join(SCENARIOS),
            read_only=True)
        if self.scenario not in SCENARIOS:
            raise StartupError('invalid parameter: scenario must be one of '
                               f"{', '.join(SCENARIOS)}, got {self.scenario!r}")
        scenario_position, scenario_velocity = DEFAULT_INITIAL_STATE[self.scenario]
        self.rate_hz = declare(self, 'rate_hz', 10.0, 'Sample rate [Hz]. ' + fixed,
                               float_range=(0.01, 10000.0), read_only=True)
        velocity = declare(self, 'true_velocity', scenario_velocity,
                           "True velocity [m/s]: the train's constant one, the car's "
                           'initial one (robot: not used). ' + default + fixed,
                           float_range=(-1000.0, 1000.0), read_only=True)
        position = declare(self, 'initial_position', scenario_position,
                           'True position at the start time [m] (robot: added to the '
                           "seed's trajectory). " + default + fixed,
                           float_range=(-BIG, BIG), read_only=True)
        noise_std = declare(self, 'noise_std', DEFAULT_NOISE_STD_M[self.scenario],
                            'Standard deviation of the position measurement noise [m]; '
                            'its square is published as the measurement variance. '
                            + default, float_range=(0.0, 1000.0))
        acceleration = declare(self, 'acceleration_mps2', CAR_ACCELERATION_MPS2,
                               'car: the commanded acceleration [m/s²], published on '
                               'control. ' + fixed, float_range=(-1000.0, 1000.0),
                               read_only=True)
        speed_noise_std = declare(self, 'speed_noise_std', ROBOT_SPEED_STD_MPS,
                                  'robot: standard deviation of the speed sensor [m/s] '
                                  'whose readings are published on control.',
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
                                       'Subscribers of measurement (and of control, '
                                       'for car and robot) to wait for before the first '
                                       'sample.', int_range=(0, 1000))
        self.publish_clock = declare(self, 'publish_clock', False,
                                     'Publish each sample stamp on /clock (for nodes '
                                     'with use_sim_time).', constraints='true or false')
        faults = self._declare_faults()
        if not self.frame_id or not self.child_frame_id:
            raise StartupError('frame_id and child_frame_id must not be empty')
        self.simulation = make_stream(
            self.scenario, self.rate_hz, None if seed < 0 else seed, noise_std_m=noise_std,
            initial_position_m=position, velocity_mps=velocity,
            acceleration_mps2=acceleration, speed_noise_std_mps=speed_noise_std)
        try:
            self.faults = FaultInjector(faults, None if seed < 0 else seed)
        except ValueError as error:
            raise StartupError(f'invalid parameter: {error}') from None
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.measurement_pub = self.create_publisher(
            PoseWithCovarianceStamped, 'measurement', QOS_DEPTH)
        self.truth_pub = self.create_publisher(Odometry, 'ground_truth', QOS_DEPTH)
        self.control_name = CONTROL_NAMES[self.scenario]
        self.control_pub = None
        if self.control_name is not None:
            kind, self._control_msg, _ = messages.CONTROL_MESSAGES[self.control_name]
            self.control_pub = self.create_publisher(kind, 'control', QOS_DEPTH)
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
            elif parameter.name == 'speed_noise_std' and hasattr(
                    self.simulation, 'speed_noise_std_mps'):
                self.simulation.speed_noise_std_mps = float(parameter.value)
            elif parameter.name in ('frame_id', 'child_frame_id', 'max_samples',
                                    'min_subscribers', 'publish_clock'):
                setattr(self, parameter.name, parameter.value)
        return SetParametersResult(successful=True)

    def _on_timer(self) -> None:
        """Publish the next sample once enough subscribers are there."""
        if self.done.done() or self._sampling_done:
            return
        if self._start_ns is None:
            if self.measurement_pub.get_subscription_count() < self.min_subscribers or (
                    self.control_pub is not None
                    and self.control_pub.get_subscription_count() < self.min_subscribers):
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
        if self.control_pub is not None:
            # The input over (t_{k-1}, t_k], stamped t_k, out before the measurement t_k.
            self.control_pub.publish(self._control_msg(
                truth_stamp_ns, self.child_frame_id, sample.control))
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
        if self.control_pub is not None:
            self.control_pub.wait_for_all_acked(timeout=flush_timeout)
        self.get_logger().info(f'published {self.published} samples; done')
        self.done.set_result(self.published)


def main(args=None) -> int:
    """Run the simulator until Ctrl-C, SIGTERM or max_samples."""
    return run(SimulatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
