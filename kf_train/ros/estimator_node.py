"""
The ``estimator`` node: a Kalman filter on ``measurement``, estimates and predictions out.

Subscribes ``measurement`` (geometry_msgs/PoseWithCovarianceStamped; QoS from
``qos_reliability``, best-effort by default so that it matches reliable and
best-effort publishers, and ``qos_depth``, 10 by default; rclpy's
``qos_overrides.<topic>.*`` parameters, on every topic, start from them:
:mod:`kf_train.ros.qos`). dt comes from the
message stamps, never from arrival times. After each fused measurement it publishes
``estimate`` (nav_msgs/Odometry, stamped with the newest fused stamp) and
``prediction`` (the state ``horizon_s`` ahead, stamped that stamp + horizon_s).
All the mathematics, and every check of the input contract, is in
:mod:`kf_train.estimator.estimator`; what the node does with its input (counts, logs,
resets) is :mod:`kf_train.ros.session`, shared with ``kf-train replay BAG``; this node
publishes. (An output
topic without subscribers is not published at all: cheaper, and the same to anyone.)

Presets (parameter ``preset``, fixed at start-up): ``rail`` by default (a real train
in regimes stand/accelerate/cruise/brake, an IMM; docs/rail.md), or the filter of a
seed (``train`` is seed 000). The preset brings the model, ``initial_state``,
``initial_covariance``, ``nominal_period_s`` and ``horizon_s``: those parameters
default to the preset's values (``ros2 param get`` shows the values in use), and a
value given explicitly (``-p``, a params file) overrides them. So a params file that
lists them (as config/kf_train.yaml does, with the rail preset's values) overrides
them: leave them out for another preset. ``process_noise_density`` adds white-noise
acceleration to the preset's own process noise (constant-velocity presets only).

* ``car``, ``car-exact`` (seed 001): subscribes ``control``
  (geometry_msgs/AccelStamped, ``accel.linear.x`` = commanded acceleration [m/s²]).
* ``robot``, ``robot-exact`` (seed 002): subscribes ``control``
  (geometry_msgs/TwistStamped, ``twist.linear.x`` = measured speed [m/s]); the state
  is the position alone, so ``estimate`` carries no velocity (``twist.linear.x`` 0,
  variance 1e9, as for every unestimated dimension).
* ``rail``: subscribes ``velocity`` too (``velocity_type``:
  geometry_msgs/TwistWithCovarianceStamped by default, speed ``twist.twist.linear.x``
  [m/s] with variance ``twist.covariance[0]``, as the u-blox and NMEA drivers publish
  a Doppler speed; ``twist`` for geometry_msgs/TwistStamped with the variance
  ``measurement_velocity_variance``; ``none``: no subscription). Each speed corrects
  the IMM (:meth:`~kf_train.estimator.StreamEstimator.process_velocity`: gated on its
  own NIS, out of sequence within ``history_s``, after the position of the same
  stamp) and the corrected estimate and prediction are published; its frame is not
  checked (the body frame, x along the track), its rejections are counted apart
  (``velocities_rejected.<reason>``) and never lock the positions out.
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
  ``/diagnostics`` and logged at most once per ``session.WARN_THROTTLE_S`` per reason.
* Out-of-sequence measurements younger than ``history_s`` are fused by rewinding and
  replaying; the estimate is then republished at the newest stamp, corrected.
* Resets, each logged and counted by reason: ``~/reset`` (manual), ``~/set_state``,
  a backwards jump of the node clock (``reset_on_clock_jump``; e.g. a bag loop with
  ``use_sim_time``), ``restart_after_stale`` stale stamps in a row (the stream
  restarted), ``max_consecutive_outliers`` gate rejections in a row, and a non-finite
  output (never published).
* No fused measurement for ``timeout_s``: ``/diagnostics`` goes to WARN and the node
  logs it once (and again once measurements resume).

Production (docs/ros.md): ``-p managed:=true`` makes it a managed (lifecycle) node
(:mod:`kf_train.ros.lifecycle`); ``/diagnostics`` carries a second status, ``<node
name>: inputs``, with each input topic's age (WARN/ERROR after ``stale_warn_periods``/
``stale_error_periods`` expected periods of silence: :mod:`kf_train.ros.input_watch`)
and incompatible QoS by topic and policy; ``stale_output`` stops or widens a stale
estimate; the filter status carries ``gate_reach_m``, the smallest position jump the
gate would reject now, and each gate rejection is logged at most once a second with
its NIS.

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
  preset, the filter (with ``ukf_regularisations``, or the particle filters'
  ``pf_ess`` and ``pf_resample_count``), input rate, last measurement age, counts
  (received, fused, rejected.<reason>, resets.<reason>; with a control input
  controls_received, controls.accepted / late / provisional,
  controls_rejected.<reason>), the mean NIS
  over the last ``nis_window`` updates against its χ² 99% bounds (WARN
  "inconsistent: noise parameters too small/large"), the gate threshold, the
  covariance condition number and, for a preset with regimes (``rail``), the likeliest
  ``regime`` and each ``regime.<name>`` probability.
* ``regime_probabilities`` (std_msgs/Float64MultiArray; only presets with regimes:
  ``rail``): after each published estimate, the probability of each regime after the
  newest fused measurement, in ``data`` (summing to 1), the regime names in the order
  of ``data`` comma-separated in ``layout.dim[0].label``
  (``stand,accelerate,cruise,brake``). The message type has no header: it goes out
  right after the estimate it belongs to. Why this type: a standard message that
  carries the numbers and their names together, which PlotJuggler, ``ros2 topic
  echo`` and rosbag2 tools read as they are; the same values, with the likeliest
  regime, are in ``/diagnostics`` (``regime``, ``regime.<name>``).
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
``ukf_alpha``/``ukf_beta``/``ukf_kappa``), ``pf`` (regularised particle filter: the
first update drawn from the measurement, progressive correction, a kernel move with a
Metropolis-Hastings step after resampling) or ``bootstrap-pf`` (the plain bootstrap
filter, for teaching); both particle filters take
``pf_particles``/``pf_seed``/``pf_resample_threshold`` and are reproducible bit for bit,
an out-of-sequence replay included. Every one runs with the same input contract, gate
(its own NIS), out-of-sequence replay, controls, resets and diagnostics. The bootstrap
filter needs ``process_noise_density`` > 0 on the train (Q = 0 otherwise: resampled
particles never spread again); ``pf`` does not (its move spreads them).

Parameters: each is declared once, in :data:`kf_train.ros.estimator_params.PARAMETERS`
(name, type, default, range or choices, live or not, unit, description); docs/ros.md's
table and config/kf_train.yaml are generated from it. Every parameter can be changed at
runtime; a change is validated as a whole and refused with a reason (the old values
stay), except ``preset``, ``filter``, the filter's tuning and the QoS, which are
read-only (they fix the state, the topics' types and the model: restart to change
them). Noise and gate changes apply from the next measurement and restart the NIS
window.
"""

import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from kf_train.estimator import NS_PER_S
from kf_train.io import fix_from_msg
from kf_train.ros import input_watch, messages
from kf_train.ros.diagnostics import gate_reach_m, MATCHED_KEYS, regime_names, STATUS_SUFFIX
from kf_train.ros.estimator_params import (
    changed_config, DEFAULTS, estimator_config, FRAME_PARAMETERS, PARAMETERS)
from kf_train.ros.input_watch import InputWatch, watch_period_s
from kf_train.ros.lifecycle import node_factory
from kf_train.ros.param_spec import ParameterError
from kf_train.ros.parameters import declare_table, watch_changes
from kf_train.ros.qos import OVERRIDES, publisher_events, subscription_events
from kf_train.ros.runner import executor_option, run, StartupError
from kf_train.ros.session import EstimatorSession, Measurement
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

__all__ = ['DEFAULTS', 'EstimatorNode', 'main']

QOS_DEPTH = 10
"""History depth of the publishers and of ~/set_state."""
QOS_RELIABILITIES = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
                     'reliable': ReliabilityPolicy.RELIABLE}


class EstimatorNode(Node):
    """Estimates the train's (or a preset's) position and velocity, predicts them ahead."""

    NODE_NAME = 'estimator'
    GATED_CALLBACKS = ('_on_measurement', '_on_velocity', '_on_control', '_on_set_state',
                       '_on_diagnostics_timer', '_on_watch_timer')
    """What a managed node runs only while active (kf_train.ros.lifecycle)."""

    def __init__(self, **kwargs):
        """Declare the parameters, build the filter and wire the topics."""
        super().__init__(self.NODE_NAME, **kwargs)
        self.configure()

    def configure(self) -> None:
        """Declare and check the parameters, build the filter, create the interfaces."""
        try:
            self.session = EstimatorSession(estimator_config(declare_table(self, PARAMETERS)),
                                            time.monotonic, self._log)
        except ParameterError as error:
            raise StartupError(str(error)) from None
        except ValueError as error:
            raise StartupError(f'invalid parameter: {error}') from None
        self.estimator = self.session.estimator
        self.preset = self.session.preset
        self._last_diagnostics = None
        self._create_interfaces()
        self._unwatch = watch_changes(
            self, lambda changes: changed_config(self.config, changes), self._apply_changes)

    # What the session counts, under the names the node has always had.
    config = property(lambda self: self.session.config)
    received = property(lambda self: self.session.received)
    fused = property(lambda self: self.session.fused)
    rejected = property(lambda self: self.session.rejected)
    corrections = property(lambda self: self.session.corrections)
    controls_received = property(lambda self: self.session.controls_received)
    controls_rejected = property(lambda self: self.session.controls_rejected)
    set_state_refused = property(lambda self: self.session.set_state_refused)
    innovations = property(lambda self: self.session.innovations)
    _nis = property(lambda self: self.session.nis)
    _timed_out = property(lambda self: self.session.timed_out)

    @property
    def frame_id(self) -> str:
        """Return header.frame_id of the outputs."""
        return self.config.options.frame_id

    @property
    def child_frame_id(self) -> str:
        """Return child_frame_id of estimate and prediction."""
        return self.config.options.child_frame_id

    def _log(self, level: str, text: str) -> None:
        """Log a line of the session (rclpy wants one severity per call site: two calls)."""
        if level == 'info':
            self.get_logger().info(text)
        else:
            self.get_logger().warning(text)

    def _create_interfaces(self) -> None:
        """Create the subscriptions, publishers, service and timers."""
        options = self.config.options
        # qos_reliability and qos_depth make the profile rclpy's qos_overrides.* start from.
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=options.qos_depth,
                         reliability=QOS_RELIABILITIES[options.qos_reliability])
        # Outgoing messages are filled in place (messages.EstimateWriter): per message
        # only the changed fields are written, nothing is allocated.
        self._estimate_writer = messages.EstimateWriter(
            options.frame_id, options.child_frame_id, self.preset.dim_x)
        self._prediction_writer = messages.EstimateWriter(
            options.frame_id, options.child_frame_id, self.preset.dim_x)
        self._innovation_writer = messages.InnovationWriter(options.frame_id)
        inputs = ['measurement'] + (['control'] if self.preset.control_names else []) + \
            (['velocity'] if self.session.fuses_velocity else [])
        self._inputs = inputs
        self.watch = InputWatch([self.resolve_topic_name(name) for name in inputs])
        self._withhold = False
        self._last_measurement = None
        self.control_subscription = None
        if self.preset.control_names:
            # Created before the measurement subscription: when a control and its
            # measurement are both waiting, the executor takes the control first.
            control = self.preset.control_names[0]
            kind, _, self._read_control = messages.CONTROL_MESSAGES[control]
            self.control_subscription = self._subscribe(kind, 'control', self._on_control, qos)
        self.measures_velocity = self.session.measures_velocity
        # A position measurement arrives serialised and only its four fields are read
        # (messages.measurement_from_serialized): rclpy's deserialisation would cost
        # more than the whole filter step.
        kind = Odometry if self.measures_velocity else PoseWithCovarianceStamped
        self.track = self.session.track     # measurement_type navsatfix: kf_train.ros.track_input
        self.subscription = self._subscribe(
            NavSatFix if self.track else kind, 'measurement', self._on_measurement, qos,
            raw=not (self.measures_velocity or self.track))
        self.velocity_subscription = None
        if self.session.fuses_velocity:
            self.velocity_subscription = self._subscribe(
                messages.VELOCITY_MESSAGES[options.velocity_type], 'velocity',
                self._on_velocity, qos)
        self.estimate_pub = self._publisher(Odometry, 'estimate')
        self.prediction_pub = self._publisher(Odometry, 'prediction')
        self.innovation_pub = self._publisher(Vector3Stamped, 'innovation')
        self.regime_names = regime_names(self.estimator)
        self.regime_pub = None
        if self.regime_names:
            self.regime_pub = self._publisher(Float64MultiArray, 'regime_probabilities')
        self.diagnostics_pub = self._publisher(DiagnosticArray, '/diagnostics')
        self.set_state_subscription = self._subscribe(
            Odometry, '~/set_state', self._on_set_state, QOS_DEPTH)
        self.reset_service = self.create_service(Trigger, '~/reset', self._on_reset_request)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._diagnostics_timer = self.create_timer(
            options.diagnostics_period_s, self._on_diagnostics_timer, clock=steady)
        self._watch_timer = self.create_timer(
            watch_period_s(self._expected_period_s()), self._on_watch_timer, clock=steady)

    def _subscribe(self, kind, topic: str, callback, qos, raw: bool = False):
        """Create a subscription with QoS overrides and its mismatches reported."""
        return self.create_subscription(
            kind, topic, callback, qos, raw=raw, qos_overriding_options=OVERRIDES,
            event_callbacks=subscription_events(self, topic, self.watch.add_qos_incompatible))

    def _publisher(self, kind, topic: str):
        """Create a publisher with QoS overrides and its mismatches reported."""
        return self.create_publisher(
            kind, topic, QOS_DEPTH, qos_overriding_options=OVERRIDES,
            event_callbacks=publisher_events(self, topic, self.watch.add_qos_incompatible))

    def _expected_period_s(self) -> float:
        """Return the expected period of the inputs: the parameter, else the preset's."""
        return self.config.options.expected_period_s or self.config.values['nominal_period_s']

    # -- parameters -------------------------------------------------------------------

    def _apply_changes(self, changes: dict) -> None:
        """Apply a change rclpy has stored (the on-set callback validated it)."""
        old = self.session.apply_changes(changes)
        options = self.config.options
        if options.diagnostics_period_s != old.options.diagnostics_period_s:
            self._diagnostics_timer.timer_period_ns = int(
                options.diagnostics_period_s * NS_PER_S)
            self._diagnostics_timer.reset()
        if options.expected_period_s != old.options.expected_period_s:
            self._watch_timer.timer_period_ns = int(
                watch_period_s(self._expected_period_s()) * NS_PER_S)
            self._watch_timer.reset()
        if any(getattr(options, name) != getattr(old.options, name)
               for name in FRAME_PARAMETERS):
            for writer in (self._estimate_writer, self._prediction_writer):
                writer.set_frames(options.frame_id, options.child_frame_id)
            self._innovation_writer.set_frame(options.frame_id)

    # -- measurements -----------------------------------------------------------------

    def _on_measurement(self, msg) -> None:
        """Fuse one measurement and publish the estimate, the prediction, the innovation."""
        if self.track is not None:
            for outputs in self.session.on_fix(fix_from_msg(msg),
                                               self.get_clock().now().nanoseconds):
                self._publish(outputs)
            self._last_measurement = self.track.last_measurement
            return
        if self.measures_velocity:
            read = messages.from_odometry_msg(msg)
            measurement = Measurement(read.stamp_ns, read.frame_id, read.position_m,
                                      read.position_variance_m2, read.velocity_mps,
                                      read.velocity_variance_m2s2)
        else:
            measurement = (messages.measurement_from_serialized(msg) if type(msg) is bytes
                           else messages.from_measurement_msg(msg))
        self._last_measurement = measurement  # its variances: the gate's reach
        self._publish(self.session.on_measurement(measurement,
                                                  self.get_clock().now().nanoseconds))

    def _on_velocity(self, msg) -> None:
        """Fuse one measured speed; publish the estimate and prediction it corrected."""
        self._publish(self.session.on_velocity(messages.from_velocity_msg(msg),
                                               self.get_clock().now().nanoseconds))

    def _on_control(self, msg) -> None:
        """Take one control; publish the estimate again if it corrected it."""
        self._publish(self.session.on_control(self._read_control(msg),
                                              self.get_clock().now().nanoseconds))

    def _publish(self, outputs) -> None:
        """Publish what the session returned: estimate and prediction, innovation."""
        # A topic nobody subscribes to is not published: a publish costs ~20 µs, the
        # count ~1 µs, and a message without a matched reader would go nowhere anyway.
        step = outputs.step
        if step is not None and not self._withhold:
            if self.estimate_pub.get_subscription_count():
                self.estimate_pub.publish(
                    self._estimate_writer.fill(step.stamp_ns, step.x, step.P))
            if self.prediction_pub.get_subscription_count():
                self.prediction_pub.publish(self._prediction_writer.fill(
                    step.prediction_stamp_ns, step.predicted_x, step.predicted_P))
            if self.regime_pub is not None and self.regime_pub.get_subscription_count():
                regimes = self.estimator.mode_probabilities()  # the step's: the newest
                if regimes is not None:
                    self.regime_pub.publish(messages.to_regime_msg(*regimes))
        update = outputs.update
        if update is not None and step is None:
            self.get_logger().warning(
                f'gate rejected the measurement at {outputs.innovation_stamp_ns} ns: NIS '
                f'{update.nis:.4g} > {self.estimator.gate_threshold:.4g} (innovation '
                f'{update.innovation[0]:.4g} m); at most one such line a second',
                throttle_duration_sec=1.0)
        if update is not None and self.innovation_pub.get_subscription_count():
            self.innovation_pub.publish(self._innovation_writer.fill(
                outputs.innovation_stamp_ns, update.innovation[0],
                update.innovation_covariance[0, 0], update.nis))

    # -- services and state -------------------------------------------------------------

    def _on_reset_request(self, request, response):
        """Handle ~/reset: forget the state."""
        self.session.reset()
        response.success = True
        response.message = 'filter reset; the next measurement initialises it'
        return response

    def _on_set_state(self, msg: Odometry) -> None:
        """Handle ~/set_state: replace the state with the one the message carries."""
        state = messages.from_state_odometry_msg(msg)
        self.session.set_state(state.stamp_ns, state.frame_id, state.x, state.P,
                               self.get_clock().now().nanoseconds)

    # -- diagnostics --------------------------------------------------------------------

    def _on_diagnostics_timer(self) -> None:
        """Publish /diagnostics (filter and inputs) and say once when measurements stop."""
        now_ns = self.get_clock().now().nanoseconds
        status = self.session.diagnostics(now_ns)
        msg = messages.to_diagnostics_msg(
            self.get_clock().now().nanoseconds, f'{self.get_name()}: {STATUS_SUFFIX}',
            'kf_train', status.level, status.message,
            list(status.values) + self._matched_values() + self._reach_values())
        inputs = self.watch.status(time.monotonic(), self._expected_period_s())
        msg.status += messages.to_diagnostics_msg(
            now_ns, f'{self.get_name()}: {input_watch.STATUS_SUFFIX}', 'kf_train',
            inputs.level, inputs.message, inputs.values).status
        self._last_diagnostics = msg
        self.diagnostics_pub.publish(msg)

    def _reach_values(self):
        """Return the gate's reach now (gate_reach_m), when there is a state and an R."""
        measurement = self._last_measurement
        # "Now" in the stamps' time base: the newest stamp plus its age on the steady
        # clock (a bag's or a simulation's stamps need not be near the node clock).
        now_ns = self.session.newest_stamp_now_ns()
        if measurement is None or now_ns is None or not self.estimator.initialized:
            return []
        variances = ((measurement.variance_m2, measurement.velocity_variance_m2s2)
                     if self.measures_velocity else (measurement.variance_m2,))
        return [('gate_reach_m', f'{gate_reach_m(self.estimator, now_ns, variances):.6g}')]

    def _on_watch_timer(self) -> None:
        """Check the inputs for silence; log changes; withhold or widen a stale estimate."""
        options = self.config.options
        names = self.watch.topics
        session = self.session
        # A NavSatFix topic counts every fix that arrived (no-fix ones too: it is alive).
        received = {'measurement': session.received if self.track is None
                    else self.track.fixes.counts.fixes,
                    'control': session.controls_received,
                    'velocity': session.velocities_received}
        counts = {name: received[kind] for name, kind in zip(names, self._inputs)}
        changes = self.watch.check(counts, time.monotonic(), self._expected_period_s(),
                                   options.stale_warn_periods, options.stale_error_periods)
        for _, level, line in changes:
            if level == 'OK':
                self.get_logger().info(line)
            else:
                self.get_logger().warning(line)
        stale = self.watch.stale
        # A stale control makes the estimate stale; a stale measurement makes none, nor
        # does a silent speed (the positions carry the track on without it).
        self._withhold = options.stale_output == 'stop' and any(
            name in stale for name, kind in zip(names, self._inputs) if kind == 'control')
        if names[0] in stale and options.stale_output == 'predict' and \
                self.estimator.initialized:
            self._publish_prediction_to_now()
        if changes:
            self._on_diagnostics_timer()

    def _publish_prediction_to_now(self) -> None:
        """Publish the estimate predicted to now and its prediction (stale_output predict)."""
        # Now in the stamps' time base (see _reach_values).
        now_ns = self.session.newest_stamp_now_ns()
        if now_ns is None:
            return
        horizon_ns = round(self.config.values['horizon_s'] * NS_PER_S)
        absolute = self.config.options.covariance_reference == 'absolute'
        for stamp_ns, publisher, writer in ((now_ns, self.estimate_pub, self._estimate_writer),
                                            (now_ns + horizon_ns, self.prediction_pub,
                                             self._prediction_writer)):
            x, P = self.estimator.predict_to(stamp_ns)
            if absolute:
                P = self.estimator.absolute_covariance(P)   # as the session's steps
            publisher.publish(writer.fill(stamp_ns, x, P))

    def _matched_values(self):
        """Return the DDS endpoints matched on this node's side (MATCHED_KEYS)."""
        # The graph (ros2 topic info) lists an endpoint before DDS matches it and also
        # one whose QoS is incompatible: only these counts say what really connects.
        counts = (self.subscription.get_publisher_count(),
                  self.estimate_pub.get_subscription_count(),
                  self.prediction_pub.get_subscription_count())
        return [(key, str(count)) for key, count in zip(MATCHED_KEYS, counts)]


def main(args=None) -> int:
    """Run the estimator until Ctrl-C or SIGTERM (``--executor events``: see runner.py)."""
    args, executor = executor_option(args)
    return run(node_factory(EstimatorNode, args), args, executor=executor)


if __name__ == '__main__':
    raise SystemExit(main())
