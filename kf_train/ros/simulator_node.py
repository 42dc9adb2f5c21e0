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
* ``rail`` (issue 11): a jerk-limited run through stations (:mod:`kf_train.sim.rail`):
  it stands at a station, accelerates on an S-curve to the line speed, cruises
  (coasting now and then), may pass a slow zone, brakes to a stop at the next
  station, dwells, and goes again, for as long as the node runs. ``rail_family``
  (metro, regional) draws the run's values from ``seed``; ``rail_accel_mps2``,
  ``rail_brake_mps2``, ``rail_jerk_mps3``, ``rail_line_speed_mps``,
  ``rail_station_spacing_m`` and ``rail_dwell_s`` replace them (0 or []: drawn);
  ``rail_texture_speed_mps`` gives the cruise small speed changes (0: none). A
  seed gives exactly the run of ``kf_train.sim.rail_scenario(seed, family,
  gnss_model=...)`` and ``kf-train simulate --scenario rail`` of the same
  ``rail_gnss_model``. Also publishes ``ground_truth_accel``
  (geometry_msgs/AccelStamped, the true acceleration in ``accel.linear.x`` [m/s²],
  frame ``child_frame_id``: the body's x axis is along the track), stamped as the
  ground truth. ``true_velocity`` is not used (the run starts standing).
  ``rail_gnss_model`` (default ``receiver``) measures the position as a real GNSS
  receiver does (:mod:`kf_train.sim.gnss_receiver`): each measurement's variance is
  the reported hAcc² (not ``noise_std``²), an epoch without a fix publishes no
  measurement, and the Doppler speed goes out on ``velocity``
  (geometry_msgs/TwistWithCovarianceStamped, ``twist.twist.linear.x`` [m/s], variance
  speedAcc² in ``twist.covariance[0]``, frame ``child_frame_id``), stamped as the
  measurement, right after it. ``white``: white noise of ``noise_std``, as before.
* ``noise_std``, ``initial_position`` and ``true_velocity`` default to the scenario's
  values (train: 1 m, 0 m, 10 m/s; car: 1 m, 0.2 m, 0 m/s; robot: 0.03 m, 0 m;
  rail: 1 m, 0 m).

``real_time_factor`` (default 1) runs the simulation faster (or slower) than the
wall clock: samples go out every 1/(rate_hz·real_time_factor) s while their stamps
stay 1/rate_hz apart. Above 1 the stamps run ahead of the wall clock; subscribers
that compare stamps with their clock (the estimator's future-stamp check) then need
``use_sim_time`` and this node's ``publish_clock``.

Controls: sample k's control is the input applied over (t_{k-1}, t_k], the interval
that ends at it (the seeds' convention: docs/presets.md); it is stamped t_k, in the
body frame ``child_frame_id``, and published just *before* the measurement stamped
t_k. It is never faulty, but carries the jumped stamp of a clock jump (it comes from
the same clock). A seed's cv-position run is the ``train`` scenario with rate_hz 1,
true_velocity 2 and initial_position -1 (x = 2t − 1).

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

import heapq

from geometry_msgs.msg import (
    AccelStamped, PoseWithCovarianceStamped, TwistWithCovarianceStamped)
from kf_train.filters import NS_PER_S
from kf_train.ros import messages
from kf_train.ros.lifecycle import node_factory
from kf_train.ros.param_spec import ParameterError
from kf_train.ros.parameters import declare_table, watch_changes
from kf_train.ros.qos import OVERRIDES
from kf_train.ros.runner import executor_option, run, StartupError
from kf_train.ros.simulator_params import changed_config, PARAMETERS, simulator_config
from kf_train.sim import ACCELERATION_SCENARIOS, CONTROL_NAMES, FaultInjector, make_stream
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg

QOS_DEPTH = 10
# How long a finished simulator waits for its last samples to be acknowledged.
FLUSH_TIMEOUT_S = 2.0


class SimulatorNode(Node):
    """Publishes simulated measurements (and controls) of a seed scenario and the truth."""

    NODE_NAME = 'simulator'
    GATED_CALLBACKS = ('_on_timer',)
    """What a managed node runs only while active (kf_train.ros.lifecycle)."""

    def __init__(self, **kwargs):
        """Declare the parameters, create the publishers and start the sampling timer."""
        super().__init__(self.NODE_NAME, **kwargs)
        self.done = Future()
        self.configure()

    def configure(self) -> None:
        """Declare and check the parameters, create the publishers and the timers."""
        try:
            self.config = simulator_config(declare_table(self, PARAMETERS))
        except ParameterError as error:
            raise StartupError(str(error)) from None
        config = self.config
        seed = None if config.seed < 0 else config.seed
        self.scenario, self.rate_hz = config.scenario, config.rate_hz
        self.simulation = make_stream(config.scenario, config.rate_hz, seed, **config.stream)
        self.faults = FaultInjector(config.faults, seed)
        self._unwatch = watch_changes(
            self, lambda changes: changed_config(self.config, changes), self._apply_changes)

        self.measurement_pub = self._publisher(PoseWithCovarianceStamped, 'measurement')
        self.truth_pub = self._publisher(Odometry, 'ground_truth')
        self.velocity_pub = None
        if config.stream.get('rail', {}).get('gnss_model') == 'receiver':
            self.velocity_pub = self._publisher(TwistWithCovarianceStamped, 'velocity')
        self.truth_accel_pub = None
        if self.scenario in ACCELERATION_SCENARIOS:
            self.truth_accel_pub = self._publisher(AccelStamped, 'ground_truth_accel')
        self.control_name = CONTROL_NAMES[self.scenario]
        self.control_pub = None
        if self.control_name is not None:
            kind, self._control_msg, _ = messages.CONTROL_MESSAGES[self.control_name]
            self.control_pub = self._publisher(kind, 'control')
        self.clock_pub = None  # created when publish_clock is first needed
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
        self._timer = self.create_timer(
            1.0 / (self.rate_hz * config.values['real_time_factor']), self._on_timer)

    def _publisher(self, kind, topic: str):
        """Create a publisher whose QoS the qos_overrides parameters can change."""
        return self.create_publisher(kind, topic, QOS_DEPTH, qos_overriding_options=OVERRIDES)

    @property
    def options(self):
        """Return the runtime options: frames, max_samples, min_subscribers, publish_clock."""
        return self.config.options

    def _apply_changes(self, changes: dict) -> None:
        """Apply noise, fault, frame and limit changes (the on-set callback validated them)."""
        old = self.config
        self.config = changed_config(old, changes)
        if self.config.faults != old.faults:
            self.faults.reconfigure(self.config.faults)
        stream = self.config.stream
        if 'noise_std' in changes:
            self.simulation.noise_std_m = float(stream['noise_std_m'])
        if 'speed_noise_std' in changes and hasattr(self.simulation, 'speed_noise_std_mps'):
            self.simulation.speed_noise_std_mps = float(stream['speed_noise_std_mps'])

    def _on_timer(self) -> None:
        """Publish the next sample once enough subscribers are there."""
        if self.done.done() or self._sampling_done:
            return
        options = self.options
        if self._start_ns is None:
            if self.measurement_pub.get_subscription_count() < options.min_subscribers or (
                    self.control_pub is not None
                    and self.control_pub.get_subscription_count() < options.min_subscribers):
                return
            self._start_ns = (self.get_clock().now().nanoseconds
                              - round(NS_PER_S / self.rate_hz))
        sample = self.simulation.next_sample()
        stamp_ns = self._start_ns + round(sample.index * NS_PER_S / self.rate_hz)
        variance = (self.simulation.noise_std_m ** 2 if sample.measurement_variance_m2 is None
                    else sample.measurement_variance_m2)
        truth_stamp_ns = self.faults.jumped_stamp_ns(sample.t_s, stamp_ns)
        if options.publish_clock:
            if self.clock_pub is None:
                self.clock_pub = self._publisher(ClockMsg, '/clock')
            self.clock_pub.publish(messages.to_clock_msg(truth_stamp_ns))
        if self.control_pub is not None:
            # The input over (t_{k-1}, t_k], stamped t_k, out before the measurement t_k.
            self.control_pub.publish(self._control_msg(
                truth_stamp_ns, options.child_frame_id, sample.control))
        deliveries = []  # a receiver's epoch without a fix has nothing to deliver
        if sample.measured_position_m is not None:
            deliveries = self.faults.apply(sample.index, sample.t_s, stamp_ns,
                                           sample.measured_position_m)
        self.published += 1
        if options.max_samples and self.published >= options.max_samples:
            deliveries += self.faults.flush()
            self._sampling_done = True
            self._timer.cancel()
        for delivery in deliveries:
            self._send(messages.to_measurement_msg(
                delivery.stamp_ns, options.frame_id, delivery.position_m, variance))
        if self.velocity_pub is not None and sample.doppler_speed_mps is not None:
            self.velocity_pub.publish(messages.to_velocity_msg(
                truth_stamp_ns, options.child_frame_id, sample.doppler_speed_mps,
                sample.doppler_variance_m2_s2))
        self.truth_pub.publish(messages.to_odometry_msg(
            truth_stamp_ns, options.frame_id, options.child_frame_id, sample.true_position_m,
            sample.true_velocity_mps, 0.0, 0.0))
        if self.truth_accel_pub is not None:
            self.truth_accel_pub.publish(messages.to_accel_msg(
                truth_stamp_ns, options.child_frame_id, sample.true_acceleration_mps2))
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
        if self.velocity_pub is not None:
            self.velocity_pub.wait_for_all_acked(timeout=flush_timeout)
        if self.truth_accel_pub is not None:
            self.truth_accel_pub.wait_for_all_acked(timeout=flush_timeout)
        if self.control_pub is not None:
            self.control_pub.wait_for_all_acked(timeout=flush_timeout)
        self.get_logger().info(f'published {self.published} samples; done')
        self.done.set_result(self.published)


def main(args=None) -> int:
    """Run the simulator until Ctrl-C, SIGTERM or max_samples (``--executor events``)."""
    args, executor = executor_option(args)
    return run(node_factory(SimulatorNode, args), args, executor=executor)


if __name__ == '__main__':
    raise SystemExit(main())
