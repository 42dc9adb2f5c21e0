"""
The ``estimator`` node: a Kalman filter on ``measurement``, estimates and predictions out.

Subscribes ``measurement`` (geometry_msgs/PoseWithCovarianceStamped; QoS from
``qos_reliability``, best-effort by default so that it matches reliable and
best-effort publishers, and ``qos_depth``, 10 by default). dt comes from the
message stamps, never from arrival times. After each fused measurement it publishes
``estimate`` (nav_msgs/Odometry, stamped with the newest fused stamp) and
``prediction`` (the state ``horizon_s`` ahead, stamped that stamp + horizon_s).
All the mathematics, and every check of the input contract, is in
:mod:`kf_train.core.estimator`; this node counts, logs and publishes. (An output
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
``prediction`` again (see :mod:`kf_train.core.estimator`).

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
  preset, the filter (with ``ukf_regularisations``, or the particle filters'
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
``ukf_alpha``/``ukf_beta``/``ukf_kappa``), ``pf`` (regularised particle filter: the
first update drawn from the measurement, progressive correction, a kernel move with a
Metropolis-Hastings step after resampling) or ``bootstrap-pf`` (the plain bootstrap
filter, for teaching); both particle filters take
``pf_particles``/``pf_seed``/``pf_resample_threshold`` and are reproducible bit for bit,
an out-of-sequence replay included. Every one runs with the same input contract, gate
(its own NIS), out-of-sequence replay, controls, resets and diagnostics. The bootstrap
filter needs ``process_noise_density`` > 0 on the train (Q = 0 otherwise: resampled
particles never spread again); ``pf`` does not (its move spreads them).

Every parameter can be changed at runtime; a change is validated as a whole and
refused with a reason (the old values stay), except ``preset``, ``filter`` and the
filter's tuning, which are read-only (they fix the state, the topics' types and the
model: restart to change them). Noise and gate changes apply from the next
measurement and restart the NIS window.
"""

import collections
import dataclasses
import math
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from kf_train import messages
from kf_train.core.chi2 import chi2_mean_bounds
from kf_train.core.estimator import (
    EstimatorSettings, GATE_PROBABILITY_RANGE, HISTORY_S_RANGE, INITIALIZATIONS,
    LIVE_PRESETS, MAX_CONSECUTIVE_OUTLIERS_RANGE, MAX_FUTURE_S_RANGE, NS_PER_S,
    PF_PARTICLES_RANGE, PF_RESAMPLE_THRESHOLD_RANGE, PF_SEED_RANGE, preset_defaults, Rejected,
    RESTART_AFTER_STALE_RANGE, TrainEstimator, UKF_ALPHA_RANGE, UKF_BETA_RANGE,
    UKF_KAPPA_RANGE)
from kf_train.core.filters import FILTER_KINDS, PARTICLE_KINDS
from kf_train.parameters import BIG, declare
from kf_train.runner import executor_option, run, StartupError
from nav_msgs.msg import Odometry
import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

QOS_DEPTH = 10
QOS_DEPTH_RANGE = (1, 100_000)
QOS_RELIABILITIES = {'best_effort': ReliabilityPolicy.BEST_EFFORT,
                     'reliable': ReliabilityPolicy.RELIABLE}
WARN_THROTTLE_S = 5.0
# The node turns on what the seed-faithful core defaults leave off: out-of-sequence
# fusion. The χ² gate stays off (1.0): with Q = 0 and the seed's wrong prior, valid
# innovations reach a NIS of 25 on some seeds (seed 3), which a 0.9999 gate would
# reject, and prior mode must reproduce the seed on any measurements. Real sensors:
# set e.g. 0.999.
DEFAULTS = dataclasses.replace(EstimatorSettings(), history_s=1.0, gate_probability=1.0)
DEFAULT_PRESET = 'train'
SETTING_NAMES = frozenset(field.name for field in dataclasses.fields(EstimatorSettings))
FRAME_PARAMETERS = ('frame_id', 'child_frame_id')
NOISE_AND_GATE = frozenset(('process_noise_density', 'measurement_variance',
                            'measurement_velocity_variance', 'gate_probability'))
CONSISTENCY_CONFIDENCE = 0.99
# Condition number of P above which the diagnostics warn: beyond ~1e12 a double
# keeps only a few significant digits of the smaller eigen-direction.
MAX_CONDITION = 1e12
TIMEOUT_RANGE = (1e-3, 86400.0)
DIAGNOSTICS_PERIOD_RANGE = (0.01, 3600.0)
NIS_WINDOW_RANGE = (1, 1_000_000)


class EstimatorNode(Node):
    """Estimates the train's (or a preset's) position and velocity, predicts them ahead."""

    def __init__(self, **kwargs):
        """Declare parameters, build the filter and wire the topics."""
        super().__init__('estimator', **kwargs)
        preset = declare(
            self, 'preset', DEFAULT_PRESET,
            'The filter: a seed preset (' + ', '.join(LIVE_PRESETS) + ') or the path of '
            'a preset YAML file. It sets the model, the control topic and the defaults of '
            'initial_state, initial_covariance, nominal_period_s and horizon_s. Fixed at '
            'start-up (restart to change).',
            constraints='one of: ' + ', '.join(LIVE_PRESETS) + ', or a .yaml path',
            read_only=True)
        try:
            preset_values = preset_defaults(preset)
        except ValueError as error:
            raise StartupError(f'invalid parameter: {error}') from None
        values = self._declare_settings(preset_values)
        values['preset'] = preset
        self.frame_id = declare(self, 'frame_id', 'odom',
                                'header.frame_id of estimate, prediction and innovation '
                                '(REP 105).', constraints='a non-empty frame name')
        self.child_frame_id = declare(self, 'child_frame_id', 'base_link',
                                      'child_frame_id of estimate and prediction.',
                                      constraints='a non-empty frame name')
        self.timeout_s = declare(
            self, 'timeout_s', 1.0,
            'Without a fused measurement for this long [s] the diagnostics go to WARN '
            'and the node logs it once.', float_range=TIMEOUT_RANGE)
        self.diagnostics_period_s = declare(
            self, 'diagnostics_period_s', 1.0,
            'Period of /diagnostics [s], on the steady clock.',
            float_range=DIAGNOSTICS_PERIOD_RANGE)
        nis_window = declare(
            self, 'nis_window', 100,
            'How many of the latest updates the mean NIS in /diagnostics is taken over.',
            int_range=NIS_WINDOW_RANGE)
        self.reset_on_clock_jump = declare(
            self, 'reset_on_clock_jump', True,
            'Reset the filter when the node clock jumps backwards (use_sim_time, a bag '
            'loop, a simulation reset).', constraints='true or false')
        qos_reliability = declare(
            self, 'qos_reliability', 'best_effort',
            'Reliability of the measurement and control subscriptions: best_effort '
            '(default; matches any publisher, drops rather than stalls) or reliable '
            '(lossless with reliable publishers while the node keeps up). Fixed at '
            'start-up.', constraints='one of: ' + ', '.join(QOS_RELIABILITIES),
            read_only=True)
        qos_depth = declare(
            self, 'qos_depth', QOS_DEPTH,
            'History depth of the measurement and control subscriptions (messages queued '
            'while the node is busy). Fixed at start-up.', int_range=QOS_DEPTH_RANGE,
            read_only=True)
        if qos_reliability not in QOS_RELIABILITIES:
            raise StartupError(f'invalid parameter: qos_reliability must be one of '
                               f"{', '.join(QOS_RELIABILITIES)}, got {qos_reliability!r}")
        try:
            settings = EstimatorSettings(
                **{name: _setting_value(name, value) for name, value in values.items()})
            self.estimator = TrainEstimator(settings)
        except ValueError as error:
            raise StartupError(f'invalid parameter: {error}') from None
        self.preset = self.estimator.preset
        if not self.frame_id or not self.child_frame_id:
            raise StartupError('invalid parameter: frame_id and child_frame_id must not '
                               'be empty')

        self.received = 0
        self.fused = 0
        self.corrections = 0
        """Estimates republished because a late control changed them."""
        self.controls_received = 0
        self.controls_rejected = 0
        self.rejected = 0
        self.set_state_refused = 0
        self.innovations = 0
        self._nis = collections.deque(maxlen=nis_window)
        self._bounds_cache = {}
        self._warned = {}
        self._start_mono = self._tick_mono = time.monotonic()
        self._last_fused_mono = None
        self._received_at_tick = self._fused_at_tick = 0
        self._timed_out = False
        self._last_clock_ns = 0
        self._last_diagnostics = None

        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=qos_depth,
                         reliability=QOS_RELIABILITIES[qos_reliability])
        # Outgoing messages are filled in place (messages.EstimateWriter): per message
        # only the changed fields are written, nothing is allocated.
        self._estimate_writer = messages.EstimateWriter(
            self.frame_id, self.child_frame_id, self.preset.dim_x)
        self._prediction_writer = messages.EstimateWriter(
            self.frame_id, self.child_frame_id, self.preset.dim_x)
        self._innovation_writer = messages.InnovationWriter(self.frame_id)
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
            self.diagnostics_period_s, self._on_diagnostics_timer,
            clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def _declare_settings(self, preset: dict) -> dict:
        """Declare the parameters that configure the core estimator; return their values."""
        live = 'Takes effect from the next measurement.'
        at_init = 'Used when the filter (re)initialises.'
        default = "Default: the preset's. "
        fixed = ' Fixed at start-up (restart to change).'
        return {
            'filter': declare(
                self, 'filter', DEFAULTS.filter,
                'The filter: kf (exact linear Kalman filter, default), ekf (the same on '
                'these linear presets), ukf (unscented, ukf_alpha/beta/kappa), pf '
                '(regularised particle filter: first update from the measurement, '
                'progressive correction, Metropolis-Hastings move) or bootstrap-pf (plain '
                'bootstrap particle filter, for teaching; give it process_noise_density '
                '> 0, or its particles collapse); both take '
                'pf_particles/pf_seed/pf_resample_threshold.' + fixed,
                constraints='one of: ' + ', '.join(FILTER_KINDS), read_only=True),
            'ukf_alpha': declare(
                self, 'ukf_alpha', DEFAULTS.ukf_alpha,
                'UKF sigma-point spread alpha > 0.' + fixed, float_range=UKF_ALPHA_RANGE,
                read_only=True),
            'ukf_beta': declare(
                self, 'ukf_beta', DEFAULTS.ukf_beta,
                'UKF beta (2 is optimal for Gaussians).' + fixed, float_range=UKF_BETA_RANGE,
                read_only=True),
            'ukf_kappa': declare(
                self, 'ukf_kappa', DEFAULTS.ukf_kappa,
                'UKF kappa (n + kappa > 0).' + fixed, float_range=UKF_KAPPA_RANGE,
                read_only=True),
            'pf_particles': declare(
                self, 'pf_particles', DEFAULTS.pf_particles,
                'Particle filter: number of particles.' + fixed, int_range=PF_PARTICLES_RANGE,
                read_only=True),
            'pf_seed': declare(
                self, 'pf_seed', DEFAULTS.pf_seed,
                'Particle filter: seed; its generator restarts from it at every '
                '(re)initialisation, so a run is reproducible bit for bit.' + fixed,
                int_range=PF_SEED_RANGE, read_only=True),
            'pf_resample_threshold': declare(
                self, 'pf_resample_threshold', DEFAULTS.pf_resample_threshold,
                'Particle filter: resample (systematic) when the effective sample size '
                'falls below this fraction of pf_particles.' + fixed,
                float_range=PF_RESAMPLE_THRESHOLD_RANGE, read_only=True),
            'initial_state': declare(
                self, 'initial_state', list(preset['initial_state']),
                'Initial [position m, velocity m/s] ([position m] for the robot); in '
                'first_measurement mode only the unmeasured velocity is used. ' + default
                + at_init, constraints='one finite double per state'),
            'initial_covariance': declare(
                self, 'initial_covariance', list(preset['initial_covariance']),
                'Initial covariance [m², m²/s²]: the diagonal (one value per state) or the '
                'full row-major matrix, symmetric positive semi-definite. ' + default
                + at_init, constraints='n or n² finite doubles, symmetric PSD'),
            'process_noise_density': declare(
                self, 'process_noise_density', DEFAULTS.process_noise_density,
                'White-noise acceleration density q [m²/s³]: Q(dt) = q [[dt³/3, dt²/2], '
                "[dt²/2, dt]], added to the preset's process noise (train: 0, as seed 000, "
                'which trusts the constant-velocity model fully). Must be 0 for the robot. '
                + live, float_range=(0.0, BIG)),
            'measurement_variance': declare(
                self, 'measurement_variance', DEFAULTS.measurement_variance,
                'Position measurement variance R [m²] overriding the message '
                'pose.covariance[0]; 0 uses the message. ' + live, float_range=(0.0, BIG)),
            'measurement_velocity_variance': declare(
                self, 'measurement_velocity_variance',
                DEFAULTS.measurement_velocity_variance,
                'Velocity measurement variance [m²/s²] overriding the message '
                'twist.covariance[0] (presets measuring the velocity); 0 uses the '
                'message. ' + live, float_range=(0.0, BIG)),
            'horizon_s': declare(
                self, 'horizon_s', preset['horizon_s'],
                'How far ahead the prediction is [s] (0: the prediction is the estimate). '
                + default + live, float_range=(0.0, 86400.0)),
            'initialization': declare(
                self, 'initialization', DEFAULTS.initialization,
                'first_measurement: the first measurement sets the position, the velocity '
                'starts wide; prior: initial_state/initial_covariance hold '
                'nominal_period_s before the first stamp (seed 000). ' + at_init,
                constraints='one of: ' + ', '.join(INITIALIZATIONS)),
            'nominal_period_s': declare(
                self, 'nominal_period_s', preset['nominal_period_s'],
                'Prior mode: how long before the first stamp the prior holds [s]. '
                + default + at_init, float_range=(1e-6, 3600.0)),
            'first_velocity_std_mps': declare(
                self, 'first_velocity_std_mps', DEFAULTS.first_velocity_std_mps,
                'first_measurement mode: standard deviation of the initial velocity '
                '[m/s]. ' + at_init, float_range=(1e-6, 1e6)),
            'history_s': declare(
                self, 'history_s', DEFAULTS.history_s,
                'Out-of-sequence window [s]: a measurement older than the newest fused one '
                'by less than this is fused by rewinding and replaying; older ones are '
                'rejected as stale. 0 accepts only increasing stamps. ' + live,
                float_range=HISTORY_S_RANGE),
            'gate_probability': declare(
                self, 'gate_probability', DEFAULTS.gate_probability,
                'χ² gate: a measurement whose NIS exceeds the χ²(m) quantile of this '
                'probability is rejected as an outlier; 1 (default) disables the gate, so '
                'that prior mode reproduces the seeds on any data. For real sensors use '
                'e.g. 0.999. ' + live,
                float_range=GATE_PROBABILITY_RANGE),
            'max_consecutive_outliers': declare(
                self, 'max_consecutive_outliers', DEFAULTS.max_consecutive_outliers,
                'After this many gate (or numerical) rejections in a row the filter '
                'resets and the next measurement initialises it. ' + live,
                int_range=MAX_CONSECUTIVE_OUTLIERS_RANGE),
            'restart_after_stale': declare(
                self, 'restart_after_stale', DEFAULTS.restart_after_stale,
                'After this many stale measurements in a row the stream counts as '
                'restarted: the filter resets and initialises from the last one. ' + live,
                int_range=RESTART_AFTER_STALE_RANGE),
            'max_future_s': declare(
                self, 'max_future_s', DEFAULTS.max_future_s,
                'A stamp more than this [s] ahead of the node clock is rejected (not '
                'checked while a simulated clock is still 0). ' + live,
                float_range=MAX_FUTURE_S_RANGE),
            'expected_frame_id': declare(
                self, 'expected_frame_id', DEFAULTS.expected_frame_id,
                "Required header.frame_id of measurements; '' accepts any. " + live,
                constraints="a frame name, or '' for any"),
        }

    # -- parameters -------------------------------------------------------------------

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Validate a change as a whole; apply it only if all of it is valid."""
        changes = {}
        node_values = {}
        for parameter in parameters:
            name, value = parameter.name, parameter.value
            if name in FRAME_PARAMETERS and not value:
                return SetParametersResult(successful=False, reason=f'{name} must not be empty')
            if name in SETTING_NAMES:
                changes[name] = value
            elif name in FRAME_PARAMETERS or name in (
                    'timeout_s', 'diagnostics_period_s', 'nis_window', 'reset_on_clock_jump'):
                node_values[name] = value
        try:
            changes = {name: _setting_value(name, value) for name, value in changes.items()}
            settings = dataclasses.replace(self.estimator.settings, **changes).validated()
        except (ValueError, TypeError) as error:
            return SetParametersResult(successful=False, reason=str(error))
        self.estimator.reconfigure(settings)
        for name, value in node_values.items():
            if name == 'nis_window':
                self._nis = collections.deque(self._nis, maxlen=value)
            elif name == 'diagnostics_period_s':
                self._diagnostics_timer.timer_period_ns = int(value * NS_PER_S)
                self._diagnostics_timer.reset()
            setattr(self, name, value)
        if FRAME_PARAMETERS[0] in node_values or FRAME_PARAMETERS[1] in node_values:
            for writer in (self._estimate_writer, self._prediction_writer):
                writer.set_frames(self.frame_id, self.child_frame_id)
            self._innovation_writer.set_frame(self.frame_id)
        if NOISE_AND_GATE & changes.keys():
            self._nis.clear()  # the old NIS values judged the old tuning
        return SetParametersResult(successful=True)

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
            if not self.reset_on_clock_jump:
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

    def _nis_bounds(self, count: int):
        """Return (cached) 99% bounds of the mean of count NIS values."""
        key = (count, self.estimator.model.dim_z)
        if key not in self._bounds_cache:
            if len(self._bounds_cache) > 1000:
                self._bounds_cache.clear()
            self._bounds_cache[key] = chi2_mean_bounds(count, key[1], CONSISTENCY_CONFIDENCE)
        return self._bounds_cache[key]

    def _on_diagnostics_timer(self) -> None:
        """Publish /diagnostics and say once when measurements stop."""
        self._check_clock()
        now = time.monotonic()
        elapsed = max(now - self._tick_mono, 1e-9)
        input_rate = (self.received - self._received_at_tick) / elapsed
        fused_rate = (self.fused - self._fused_at_tick) / elapsed
        self._tick_mono, self._received_at_tick, self._fused_at_tick = (
            now, self.received, self.fused)
        warnings = []
        since = self._last_fused_mono if self._last_fused_mono is not None else self._start_mono
        age = now - since
        if age > self.timeout_s:
            what = ('no measurement fused yet' if self._last_fused_mono is None
                    else 'no measurement fused')
            warnings.append(f'{what} for {age:.1f} s (timeout_s {self.timeout_s:g})')
            if not self._timed_out:
                self.get_logger().warning(warnings[-1])
                self._timed_out = True
        elif self._timed_out:
            self.get_logger().info('measurements are being fused again')
            self._timed_out = False
        settings = self.estimator.settings
        values = [
            ('preset', self.preset.name),
            ('filter', settings.filter),
            ('initialized', str(self.estimator.initialized).lower()),
            ('input_rate_hz', f'{input_rate:.3f}'),
            ('fused_rate_hz', f'{fused_rate:.3f}'),
            ('last_measurement_age_s',
             'never' if self._last_fused_mono is None else f'{age:.3f}'),
            ('received', str(self.received)),
            ('fused', str(self.fused)),
            ('fused_out_of_sequence', str(self.estimator.out_of_sequence_count)),
            ('rejected', str(self.rejected)),
        ]
        values += [(f'rejected.{reason}', str(count))
                   for reason, count in self.estimator.rejection_counts.items()]
        resets = self.estimator.reset_counts
        values.append(('resets', str(sum(resets.values()))))
        values += [(f'resets.{reason}', str(count)) for reason, count in resets.items()]
        values.append(('set_state_refused', str(self.set_state_refused)))
        if self.estimator.has_control:
            values.append(('controls_received', str(self.controls_received)))
            values += [(f'controls.{key}', str(count))
                       for key, count in self.estimator.control_counts.items()]
            values.append(('controls_rejected', str(self.controls_rejected)))
            values += [(f'controls_rejected.{reason}', str(count)) for reason, count
                       in self.estimator.control_rejection_counts.items()]
        model = self.estimator.model
        regularisations = getattr(model, 'regularisations', None)
        if regularisations is not None:
            values.append(('ukf_regularisations', str(regularisations)))
        if settings.filter in PARTICLE_KINDS and self.estimator.initialized:
            # The particles last stepped: those of the newest estimate.
            values += [('pf_ess', f'{model.filter.ess:.1f}'),
                       ('pf_resample_count', str(model.filter.resample_count))]
        values += [('gate_probability', f'{settings.gate_probability:g}'),
                   ('gate_threshold', f'{self.estimator.gate_threshold:.6g}')]
        count = len(self._nis)
        values.append(('nis_window_count', str(count)))
        if count:
            mean = math.fsum(self._nis) / count
            lower, upper = self._nis_bounds(count)
            values += [('nis_window_mean', f'{mean:.6g}'),
                       ('nis_lower_99', f'{lower:.6g}'), ('nis_upper_99', f'{upper:.6g}')]
            if mean > upper:
                warnings.append(f'inconsistent: noise parameters too small (mean NIS '
                                f'{mean:.3g} > {upper:.3g} over {count} updates)')
            elif mean < lower:
                warnings.append(f'inconsistent: noise parameters too large (mean NIS '
                                f'{mean:.3g} < {lower:.3g} over {count} updates)')
        state = self.estimator.state
        if state is not None:
            condition = float(np.linalg.cond(state[1]))
            values.append(('covariance_condition', f'{condition:.6g}'))
            if not condition <= MAX_CONDITION:
                warnings.append(f'ill-conditioned covariance (condition {condition:.3g})')
        if warnings:
            level, message = 'WARN', '; '.join(warnings)
        else:
            level = 'OK'
            message = 'ok' if self.estimator.initialized else 'waiting for measurements'
        now_ns = self.get_clock().now().nanoseconds
        msg = messages.to_diagnostics_msg(now_ns, f'{self.get_name()}: filter', 'kf_train',
                                          level, message, values)
        self._last_diagnostics = msg
        self.diagnostics_pub.publish(msg)


def _setting_value(name: str, value):
    """Return a parameter value in the form EstimatorSettings keeps it."""
    if name in ('initial_state', 'initial_covariance'):
        return tuple(float(v) for v in value)
    return value


def main(args=None) -> int:
    """Run the estimator until Ctrl-C or SIGTERM (``--executor events``: see runner.py)."""
    args, executor = executor_option(args)
    return run(EstimatorNode, args, executor=executor)


if __name__ == '__main__':
    raise SystemExit(main())
