"""
The ``estimator`` node: a Kalman filter on ``measurement``, estimates and predictions out.

Subscribes ``measurement`` (geometry_msgs/PoseWithCovarianceStamped; QoS from
``qos_reliability``, best-effort by default so that it matches reliable and
best-effort publishers, and ``qos_depth``, 10 by default). dt comes from the
message stamps, never from arrival times. After each fused measurement it publishes
``estimate`` (nav_msgs/Odometry, stamped with the newest fused stamp) and
``prediction`` (the state ``horizon_s`` ahead, stamped that stamp + horizon_s).
All the mathematics, and every check of the input contract, is in
:mod:`kf_train.estimator.estimator`; this node counts, logs and publishes. (An output
topic without subscribers is not published at all: cheaper, and the same to anyone.)

Presets (parameter ``preset``, fixed at start-up): the filter of a seed, ``train``
by default (seed 000). The preset brings the model, ``initial_state``,
``initial_covariance``, ``nominal_period_s`` and ``horizon_s``: those parameters
default to the preset's values (``ros2 param get`` shows the values in use), and a
value given explicitly (``-p``, a params file) overrides them. So a params file that
lists them (as config/kf_train.yaml does, with the train's values) overrides them:
leave them out for another preset. ``process_noise_density`` adds white-noise
acceleration to the preset's own process noise (constant-velocity presets only).

* ``car``, ``car-exact`` (seed 001): subscribes ``control``
  (geometry_msgs/AccelStamped, ``accel.linear.x`` = commanded acceleration [m/s²]).
* ``robot``, ``robot-exact`` (seed 002): subscribes ``control``
  (geometry_msgs/TwistStamped, ``twist.linear.x`` = measured speed [m/s]); the state
  is the position alone, so ``estimate`` carries no velocity (``twist.linear.x`` 0,
  variance 1e9, as for every unestimated dimension).
* ``cv-position`` (seed 003, dt = 1 s): as the train.
* ``cv-position-velocity`` (seed 003 variant): ``measurement`` is a nav_msgs/Odometry
  (position ``pose.pose.position.x``, variance ``pose.covariance[0]``; velocity
  ``twist.twist.linear.x``, variance ``twist.covariance[0]``), fused as one
  2-D measurement.
* ``range-bearing`` is 2-D: offline only (``kf-train replay``).

A control stamped t_k is the input over (t_{k-1}, t_k]: the prediction to a
measurement stamped t_k uses it. Its header.frame_id is not checked (the 1-D model
takes linear.x as along the track; the simulator stamps it with its child frame).
The node never waits for a control: a measurement whose control has not arrived yet
is fused with the best one known, and when the control comes (within ``history_s``)
the filter rewinds and replays, and publishes the corrected ``estimate`` and
``prediction`` again (see :mod:`kf_train.estimator.estimator`).

Robustness (see the core module for the exact rules):

* Rejected measurements (bad numbers, zero/duplicate/stale/future stamps, wrong
  frame, χ² outliers) leave the filter unchanged; they are counted by reason in
  ``/diagnostics`` and logged at most once per ``WARN_THROTTLE_S`` per reason.
* Out-of-sequence measurements younger than ``history_s`` are fused by rewinding and
  replaying; the estimate is then republished at the newest stamp, corrected.
* Resets, each logged and counted by reason: ``~/reset`` (manual), ``~/set_state``,
  a backwards jump of the node clock (``reset_on_clock_jump``; e.g. a bag loop with
  ``use_sim_time``), ``restart_after_stale`` stale stamps in a row (the stream
  restarted), ``max_consecutive_outliers`` gate rejections in a row, and a non-finite
  output (never published).
* No fused measurement for ``timeout_s``: ``/diagnostics`` goes to WARN and the node
  logs it once (and again once measurements resume).

Other interfaces:

* ``innovation`` (geometry_msgs/Vector3Stamped, one per gate decision, accepted or
  rejected, stamped with the measurement's stamp, frame ``frame_id``):
  ``vector.x`` = innovation y = z - H x⁻ [m], ``vector.y`` = its variance
  S = H P⁻ Hᵀ + R [m²], ``vector.z`` = NIS y²/S [-]; rejected ones have
  NIS > ``gate_threshold`` (in the diagnostics). For live tuning:
  ``ros2 topic echo /innovation``. With a position-and-velocity measurement, x and y
  are the position's, z the NIS of the whole measurement (χ² with 2 degrees of
  freedom).
* ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, every ``diagnostics_period_s``
  on the steady clock): one status ``<node name>: filter``, level OK or WARN, with the
  preset, the filter (with ``ukf_regularisations``, or the particle filter's
  ``pf_ess`` and ``pf_resample_count``), input rate, last measurement age, counts
  (received, fused, rejected.<reason>, resets.<reason>; with a control input
  controls_received, controls.accepted / late / provisional,
  controls_rejected.<reason>), the mean NIS
  over the last ``nis_window`` updates against its χ² 99% bounds (WARN
  "inconsistent: noise parameters too small/large"), the gate threshold and the
  covariance condition number.
* ``~/reset`` (std_srvs/srv/Trigger): forget the state; the next measurement
  initialises the filter.
* ``~/set_state`` (nav_msgs/Odometry, reliable): set the state to position
  ``pose.pose.position.x`` [m] and velocity ``twist.twist.linear.x`` [m/s] with
  covariance diag(``pose.covariance[0]``, ``twist.covariance[0]``) (the position
  alone for the robot), valid at ``header.stamp`` (0: the newest fused stamp, or now
  before any); ``header.frame_id`` must be empty or ``frame_id``. Refusals are logged
  and counted.

Filters (parameter ``filter``, fixed at start-up): ``kf`` (default, the exact linear
filter), ``ekf`` (identical on these linear presets), ``ukf`` (Merwe sigma points,
``ukf_alpha``/``ukf_beta``/``ukf_kappa``) or ``pf`` (bootstrap particle filter,
``pf_particles``/``pf_seed``/``pf_resample_threshold``; reproducible bit for bit, an
out-of-sequence replay included). Every one runs with the same input contract, gate
(its own NIS), out-of-sequence replay, controls, resets and diagnostics. The particle
filter needs ``process_noise_density`` > 0 on the train (Q = 0 otherwise: resampled
particles never spread again).

Parameters: each is declared once, in :data:`kf_train.ros.estimator_params.PARAMETERS`
(name, type, default, range or choices, live or not, unit, description); the README's
table and config/kf_train.yaml are generated from it. Every parameter can be changed at
runtime; a change is validated as a whole and refused with a reason (the old values
stay), except ``preset``, ``filter``, the filter's tuning and the QoS, which are
read-only (they fix the state, the topics' types and the model: restart to change
them). Noise and gate changes apply from the next measurement and restart the NIS
window.
"""

import collections
import math
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from kf_train.estimator import NS_PER_S, Rejected, StreamEstimator
from kf_train.ros import messages
from kf_train.ros.diagnostics import Activity, filter_status, NodeCounts
from kf_train.ros.estimator_params import (
    changed_config, DEFAULTS, estimator_config, FRAME_PARAMETERS, NOISE_AND_GATE, PARAMETERS)
from kf_train.ros.param_spec import ParameterError
from kf_train.ros.parameters import declare_table, watch_changes
from kf_train.ros.runner import executor_option, run, StartupError
from nav_msgs.msg import Odometry
import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

__all__ = ['DEFAULTS', 'EstimatorNode', 'main']

QOS_DEPTH = 10
"""History depth of the publishers and of ~/set_state."""
QOS_RELIABILITIES = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
                     'reliable': ReliabilityPolicy.RELIABLE}
WARN_THROTTLE_S = 5.0


class EstimatorNode(Node):
    """Estimates the train's (or a preset's) position and velocity, predicts them ahead."""

    def __init__(self, **kwargs):
        """Declare the parameters, build the filter and wire the topics."""
        super().__init__('estimator', **kwargs)
        try:
            self.config = estimator_config(declare_table(self, PARAMETERS))
            self.estimator = StreamEstimator(self.config.settings)
        except ParameterError as error:
            raise StartupError(str(error)) from None
        except ValueError as error:
            raise StartupError(f'invalid parameter: {error}') from None
        self.preset = self.estimator.preset
        self.received = 0
        self.fused = 0
        self.corrections = 0
        """Estimates republished because a late control changed them."""
        self.controls_received = 0
        self.controls_rejected = 0
        self.rejected = 0
        self.set_state_refused = 0
        self.innovations = 0
        self._nis = collections.deque(maxlen=self.config.options.nis_window)
        self._warned = {}
        self._start_mono = self._tick_mono = time.monotonic()
        self._last_fused_mono = None
        self._received_at_tick = self._fused_at_tick = 0
        self._timed_out = False
        self._last_clock_ns = 0
        self._last_diagnostics = None
        self._create_interfaces()
        watch_changes(self, lambda changes: changed_config(self.config, changes),
                      self._apply_changes)

    @property
    def frame_id(self) -> str:
        """Return header.frame_id of the outputs."""
        return self.config.options.frame_id

    @property
    def child_frame_id(self) -> str:
        """Return child_frame_id of estimate and prediction."""
        return self.config.options.child_frame_id

    def _create_interfaces(self) -> None:
        """Create the subscriptions, publishers, service and diagnostics timer."""
        options = self.config.options
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=options.qos_depth,
                         reliability=QOS_RELIABILITIES[options.qos_reliability])
        # Outgoing messages are filled in place (messages.EstimateWriter): per message
        # only the changed fields are written, nothing is allocated.
        self._estimate_writer = messages.EstimateWriter(
            options.frame_id, options.child_frame_id, self.preset.dim_x)
        self._prediction_writer = messages.EstimateWriter(
            options.frame_id, options.child_frame_id, self.preset.dim_x)
        self._innovation_writer = messages.InnovationWriter(options.frame_id)
        self.control_subscription = None
        if self.preset.control_names:
            # Created before the measurement subscription: when a control and its
            # measurement are both waiting, the executor takes the control first.
            control = self.preset.control_names[0]
            kind, _, self._read_control = messages.CONTROL_MESSAGES[control]
            self.control_subscription = self.create_subscription(
                kind, 'control', self._on_control, qos)
        self.measures_velocity = self.preset.measurement_names == ('position', 'velocity')
        # A position measurement arrives serialised and only its four fields are read
        # (messages.measurement_from_serialized): rclpy's deserialisation would cost
        # more than the whole filter step.
        self.subscription = self.create_subscription(
            Odometry if self.measures_velocity else PoseWithCovarianceStamped,
            'measurement', self._on_measurement, qos, raw=not self.measures_velocity)
        self.estimate_pub = self.create_publisher(Odometry, 'estimate', QOS_DEPTH)
        self.prediction_pub = self.create_publisher(Odometry, 'prediction', QOS_DEPTH)
        self.innovation_pub = self.create_publisher(Vector3Stamped, 'innovation', QOS_DEPTH)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                     QOS_DEPTH)
        self.set_state_subscription = self.create_subscription(
            Odometry, '~/set_state', self._on_set_state, QOS_DEPTH)
        self.reset_service = self.create_service(Trigger, '~/reset', self._on_reset_request)
        self._diagnostics_timer = self.create_timer(
            options.diagnostics_period_s, self._on_diagnostics_timer,
            clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- parameters -------------------------------------------------------------------

    def _apply_changes(self, changes: dict) -> None:
        """Apply a change rclpy has stored (the on-set callback validated it)."""
        old = self.config
        self.config = changed_config(old, changes)
        options = self.config.options
        if self.config.settings != old.settings:
            self.estimator.reconfigure(self.config.settings)
        if options.nis_window != old.options.nis_window:
            self._nis = collections.deque(self._nis, maxlen=options.nis_window)
        if options.diagnostics_period_s != old.options.diagnostics_period_s:
            self._diagnostics_timer.timer_period_ns = int(
                options.diagnostics_period_s * NS_PER_S)
            self._diagnostics_timer.reset()
        if any(getattr(options, name) != getattr(old.options, name)
               for name in FRAME_PARAMETERS):
            for writer in (self._estimate_writer, self._prediction_writer):
                writer.set_frames(options.frame_id, options.child_frame_id)
            self._innovation_writer.set_frame(options.frame_id)
        if NOISE_AND_GATE & changes.keys():
            self._nis.clear()  # the old NIS values judged the old tuning

    # -- measurements -----------------------------------------------------------------

    def _on_measurement(self, msg) -> None:
        """Fuse one measurement and publish the estimate, the prediction, the innovation."""
        self.received += 1
        if self.measures_velocity:
            read = messages.from_odometry_msg(msg)
            stamp_ns = read.stamp_ns
            velocity = {'velocity_mps': read.velocity_mps,
                        'velocity_variance_m2s2': read.velocity_variance_m2s2}
            position, variance, frame_id = (read.position_m, read.position_variance_m2,
                                            read.frame_id)
        else:
            read = (messages.measurement_from_serialized(msg) if type(msg) is bytes
                    else messages.from_measurement_msg(msg))
            stamp_ns, position, variance, frame_id = (read.stamp_ns, read.position_m,
                                                      read.variance_m2, read.frame_id)
            velocity = {}
        now_ns = self._check_clock()
        try:
            step = self.estimator.process(stamp_ns, position, variance, frame_id=frame_id,
                                          now_ns=now_ns, **velocity)
        except Rejected as rejection:
            self.rejected += 1
            self._warn_rejection(rejection.reason, str(rejection))
            if rejection.update is not None:
                self._publish_innovation(stamp_ns, rejection.update)
            if rejection.reset is not None:
                self._after_reset(rejection.reset, str(rejection))
            return
        if step.reset is not None:
            self._after_reset(step.reset, f'measurement at {stamp_ns} ns initialises it')
        if not self._publish_step(step):
            return
        self.fused += 1
        self._last_fused_mono = time.monotonic()
        if step.update is not None:
            self._publish_innovation(step.measurement_stamp_ns, step.update)
            self._nis.append(step.update.nis)

    def _on_control(self, msg) -> None:
        """Take one control; publish the estimate again if it corrected it."""
        self.controls_received += 1
        control = self._read_control(msg)
        now_ns = self._check_clock()
        try:
            step = self.estimator.add_control(control.stamp_ns, [control.value], now_ns=now_ns)
        except Rejected as rejection:
            self.controls_rejected += 1
            self._warn_rejection('control.' + rejection.reason, str(rejection), 'control')
            return
        if step is not None and self._publish_step(step):
            self.corrections += 1

    def _publish_step(self, step) -> bool:
        """Publish estimate and prediction; on a non-finite number reset instead, False."""
        # One test for all four: 0·v is 0 for every finite v, NaN for NaN and ±inf.
        if not 0.0 * (sum(step.x.tolist()) + sum(step.P.ravel().tolist())
                      + sum(step.predicted_x.tolist())
                      + sum(step.predicted_P.ravel().tolist())) == 0.0 and not (
                np.isfinite(step.x).all() and np.isfinite(step.P).all()
                and np.isfinite(step.predicted_x).all()
                and np.isfinite(step.predicted_P).all()):
            # The core never produces this; if it ever did, nothing non-finite leaves.
            self.estimator.reset('non_finite')
            self._after_reset('non_finite', 'a non-finite state was not published')
            return False
        # A topic nobody subscribes to is not published: a publish costs ~20 µs, the
        # count ~1 µs, and a message without a matched reader would go nowhere anyway.
        if self.estimate_pub.get_subscription_count():
            self.estimate_pub.publish(self._estimate_writer.fill(step.stamp_ns, step.x, step.P))
        if self.prediction_pub.get_subscription_count():
            self.prediction_pub.publish(self._prediction_writer.fill(
                step.prediction_stamp_ns, step.predicted_x, step.predicted_P))
        return True

    def _publish_innovation(self, stamp_ns: int, update) -> None:
        """Publish one innovation record (first measurement component)."""
        self.innovations += 1
        if not self.innovation_pub.get_subscription_count():
            return  # (see _publish_step)
        self.innovation_pub.publish(self._innovation_writer.fill(
            stamp_ns, update.innovation[0], update.innovation_covariance[0, 0], update.nis))

    def _warn_rejection(self, reason: str, text: str, what: str = 'measurement') -> None:
        """Log a rejection, at most once per WARN_THROTTLE_S for each reason."""
        now = time.monotonic()
        last, suppressed = self._warned.get(reason, (-math.inf, 0))
        if now - last < WARN_THROTTLE_S:
            self._warned[reason] = (last, suppressed + 1)
            return
        more = f' ({suppressed} more since the last such warning)' if suppressed else ''
        self.get_logger().warning(f'{what} rejected ({reason}): {text}{more}')
        self._warned[reason] = (now, 0)

    def _after_reset(self, reason: str, detail: str) -> None:
        """Log a reset the estimator went through and restart the NIS window."""
        self._nis.clear()
        text = f'filter reset ({reason}): {detail}'
        if reason in ('manual', 'set_state'):
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)

    def _check_clock(self) -> int:
        """Return the node clock in ns (0 if unset); reset on a backwards jump."""
        now_ns = self.get_clock().now().nanoseconds
        if now_ns == 0:
            return 0  # a simulated clock that has not started yet
        last, self._last_clock_ns = self._last_clock_ns, now_ns
        if now_ns < last:
            jump = f'node clock jumped back {(last - now_ns) / NS_PER_S:.3f} s'
            if not self.config.options.reset_on_clock_jump:
                self.get_logger().warning(f'{jump}; not resetting (reset_on_clock_jump false)')
            elif self.estimator.initialized:
                self.estimator.reset('clock_jump')
                self._after_reset('clock_jump', jump)
            else:
                self.get_logger().info(jump)
        return now_ns

    # -- services and state -------------------------------------------------------------

    def _on_reset_request(self, request, response):
        """Handle ~/reset: forget the state."""
        self.estimator.reset('manual')
        self._after_reset('manual', 'requested through ~/reset')
        response.success = True
        response.message = 'filter reset; the next measurement initialises it'
        return response

    def _on_set_state(self, msg: Odometry) -> None:
        """Handle ~/set_state: replace the state with the one the message carries."""
        state = messages.from_state_odometry_msg(msg)
        try:
            if state.frame_id and state.frame_id != self.frame_id:
                raise ValueError(f'frame_id {state.frame_id!r} is not {self.frame_id!r}')
            stamp_ns = (state.stamp_ns or self.estimator.last_stamp_ns
                        or self.get_clock().now().nanoseconds)
            n = self.preset.dim_x  # the robot's state is the position alone
            self.estimator.set_state(stamp_ns, state.x[:n], [row[:n] for row in state.P[:n]])
        except ValueError as error:
            self.set_state_refused += 1
            self.get_logger().warning(f'~/set_state refused: {error}')
            return
        self._after_reset('set_state', f'x = {state.x} at {stamp_ns} ns')

    # -- diagnostics --------------------------------------------------------------------

    def _on_diagnostics_timer(self) -> None:
        """Publish /diagnostics and say once when measurements stop."""
        self._check_clock()
        now = time.monotonic()
        elapsed = max(now - self._tick_mono, 1e-9)
        since = self._last_fused_mono if self._last_fused_mono is not None else self._start_mono
        activity = Activity((self.received - self._received_at_tick) / elapsed,
                            (self.fused - self._fused_at_tick) / elapsed, now - since,
                            self._last_fused_mono is not None)
        self._tick_mono, self._received_at_tick, self._fused_at_tick = (
            now, self.received, self.fused)
        counts = NodeCounts(self.received, self.fused, self.rejected, self.set_state_refused,
                            self.controls_received, self.controls_rejected)
        status = filter_status(self.estimator, counts, activity,
                               self.config.options.timeout_s, self._nis)
        if status.timeout_warning is not None and not self._timed_out:
            self.get_logger().warning(status.timeout_warning)
            self._timed_out = True
        elif status.timeout_warning is None and self._timed_out:
            self.get_logger().info('measurements are being fused again')
            self._timed_out = False
        msg = messages.to_diagnostics_msg(
            self.get_clock().now().nanoseconds, f'{self.get_name()}: filter', 'kf_train',
            status.level, status.message, status.values)
        self._last_diagnostics = msg
        self.diagnostics_pub.publish(msg)


def main(args=None) -> int:
    """Run the estimator until Ctrl-C or SIGTERM (``--executor events``: see runner.py)."""
    args, executor = executor_option(args)
    return run(EstimatorNode, args, executor=executor)


if __name__ == '__main__':
    raise SystemExit(main())
