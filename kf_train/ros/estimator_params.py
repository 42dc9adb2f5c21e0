"""
The ``estimator`` node's parameters, each declared once, and the settings they make.

Pure (no rclpy, no message package). :data:`PARAMETERS` is the one table: the node
declares it (:mod:`kf_train.ros.parameters`), ``ros2 param describe`` shows it, and
config/kf_train.yaml and docs/ros.md's tables are generated from it
(tools/parameter_tables.py). :func:`estimator_config` turns parameter values into what
the node runs, checking them as the node does, at start-up and on every change; offline
tools call :func:`load_estimator_config` with a params file and ``-p`` overrides and get
exactly the node's settings, or the node's error.
"""

import dataclasses
from typing import Any, Dict, Iterable, Mapping, NamedTuple, Sequence, Union

from kf_train.estimator import (
    DEFAULT_PRESET, EstimatorSettings, GATE_PROBABILITY_RANGE, HISTORY_S_RANGE, INITIALIZATIONS,
    is_rail, LIVE_PRESETS, LOCKOUT_ACTIONS, MAX_CONSECUTIVE_OUTLIERS_RANGE, MAX_FUTURE_S_RANGE,
    PF_PARTICLES_RANGE, PF_RESAMPLE_THRESHOLD_RANGE, PF_SEED_RANGE, preset_defaults,
    resolve_preset, RESTART_AFTER_STALE_RANGE, UKF_ALPHA_RANGE, UKF_BETA_RANGE,
    UKF_KAPPA_RANGE)
from kf_train.filters import FILTER_KINDS
from kf_train.ros.param_spec import (
    BIG, MANAGED_DESCRIPTION, ParameterError, ParamSpec, ParamTable)
from kf_train.ros.track_input import check_track_values, PARAMETERS_TRACK

QOS_RELIABILITIES = ('best_effort', 'reliable')
VELOCITY_TYPES = ('twist_with_covariance', 'twist', 'none')
"""The ``velocity`` topic's type (parameter velocity_type): TwistWithCovarianceStamped,
TwistStamped (variance measurement_velocity_variance) or no subscription."""
STALE_OUTPUTS = ('stop', 'predict')
"""What a stale state does to estimate and prediction (parameter stale_output)."""
COVARIANCE_REFERENCES = ('receiver', 'absolute')
"""What the published covariances describe (parameter covariance_reference)."""
FRAME_PARAMETERS = ('frame_id', 'child_frame_id')
NOISE_AND_GATE = frozenset(('process_noise_density', 'measurement_variance',
                            'measurement_velocity_variance', 'gate_probability'))
"""Changes that restart the NIS window: the old NIS values judged the old tuning."""
SETTING_NAMES = tuple(field.name for field in dataclasses.fields(EstimatorSettings))
"""The parameters that are EstimatorSettings fields; the others configure the node."""

_CORE = EstimatorSettings()  # the core defaults: rail, gate on (SEED_SWITCH for the seed)
_FIXED = ' Fixed at start-up (restart to change).'
_LIVE = 'Takes effect from the next measurement.'
_AT_INIT = 'Used when the filter (re)initialises.'
_PRESETS = "Default: the preset's. "
_FRAME = 'a non-empty frame name'
_G_FIXED = 'fixed at start-up (restart to change)'
_G_INIT = 'used when the filter (re)initialises'
_G_LIVE = 'take effect from the next measurement'
_G_NODE = 'output frames and diagnostics'


def _double(name, default, description, range_, unit='', **more) -> ParamSpec:
    """Return the spec of a double parameter."""
    return ParamSpec(name, 'double', default, description, range=range_, unit=unit, **more)


def _integer(name, default, description, range_, **more) -> ParamSpec:
    """Return the spec of an integer parameter."""
    return ParamSpec(name, 'integer', default, description, range=range_, **more)


PARAMETERS_FIXED = (
    ParamSpec(
        'preset', 'string', DEFAULT_PRESET,
        'The filter: rail (default: a real train in regimes stand/accelerate/cruise/brake, '
        'an IMM; docs/rail.md), a seed preset (' + ', '.join(LIVE_PRESETS[1:]) + '; '
        'preset:=train with initialization:=prior and gate_probability:=1.0 is seed 000 '
        'exactly) or the path of a preset YAML file. It sets the model, the control topic '
        'and the defaults of initial_state, initial_covariance, nominal_period_s and '
        'horizon_s.' + _FIXED,
        constraints='one of: ' + ', '.join(LIVE_PRESETS) + ', or a .yaml path', live=False,
        group=_G_FIXED),
    ParamSpec(
        'filter', 'string', _CORE.filter,
        'The filter: kf (exact linear Kalman filter, default; with preset rail its IMM of four '
        'Kalman filters, which only kf and ekf run), ekf (the same on these linear '
        'presets), ukf (unscented, ukf_alpha/beta/kappa), pf (regularised particle filter: '
        'first update from the measurement, progressive correction, Metropolis-Hastings '
        'move) or bootstrap-pf (plain bootstrap particle filter, for teaching; give it '
        'process_noise_density > 0, or its particles collapse); both take '
        'pf_particles/pf_seed/pf_resample_threshold.' + _FIXED, choices=FILTER_KINDS,
        live=False, group=_G_FIXED),
    _double('ukf_alpha', _CORE.ukf_alpha, 'UKF sigma-point spread alpha > 0.' + _FIXED,
            UKF_ALPHA_RANGE, live=False, group=_G_FIXED),
    _double('ukf_beta', _CORE.ukf_beta, 'UKF beta (2 is optimal for Gaussians).' + _FIXED,
            UKF_BETA_RANGE, live=False, group=_G_FIXED),
    _double('ukf_kappa', _CORE.ukf_kappa, 'UKF kappa (n + kappa > 0).' + _FIXED,
            UKF_KAPPA_RANGE, live=False, group=_G_FIXED),
    _integer('pf_particles', _CORE.pf_particles,
             'Particle filter: number of particles.' + _FIXED, PF_PARTICLES_RANGE,
             live=False, group=_G_FIXED),
    _integer('pf_seed', _CORE.pf_seed,
             'Particle filter: seed; its generator restarts from it at every '
             '(re)initialisation, so a run is reproducible bit for bit.' + _FIXED,
             PF_SEED_RANGE, live=False, group=_G_FIXED),
    _double('pf_resample_threshold', _CORE.pf_resample_threshold,
            'Particle filter: resample (systematic) when the effective sample size falls '
            'below this fraction of pf_particles.' + _FIXED, PF_RESAMPLE_THRESHOLD_RANGE,
            live=False, group=_G_FIXED),
    ParamSpec(
        'qos_reliability', 'string', 'best_effort',
        'Reliability of the measurement and control subscriptions: best_effort (default; '
        'matches any publisher, drops rather than stalls) or reliable (lossless with '
        'reliable publishers while the node keeps up). Fixed at start-up.',
        choices=QOS_RELIABILITIES, live=False, group=_G_FIXED),
    _integer('qos_depth', 10,
             'History depth of the measurement and control subscriptions (messages queued '
             'while the node is busy). Fixed at start-up.', (1, 100_000), live=False,
             group=_G_FIXED),
    ParamSpec('managed', 'bool', False, MANAGED_DESCRIPTION, live=False, group=_G_FIXED),
    ParamSpec(
        'velocity_type', 'string', VELOCITY_TYPES[0],
        'The velocity topic (a measured speed along the track, e.g. a GNSS Doppler; preset '
        'rail only, the others do not subscribe it): twist_with_covariance (default: '
        'geometry_msgs/TwistWithCovarianceStamped, speed twist.twist.linear.x [m/s], '
        'variance twist.covariance[0]), twist (geometry_msgs/TwistStamped, twist.linear.x, '
        'variance measurement_velocity_variance, which must then be > 0) or none (no '
        'velocity subscription).' + _FIXED, choices=VELOCITY_TYPES, live=False,
        group=_G_FIXED),
)

PARAMETERS_AT_INIT = (
    ParamSpec(
        'initialization', 'string', _CORE.initialization,
        'first_measurement (default): the first measurement sets the position, the other '
        'states start wide (rail: from initial_covariance, its priors; other presets: '
        'first_velocity_std_mps); prior: initial_state/initial_covariance hold '
        'nominal_period_s before the first stamp (seed 000: with preset:=train and '
        'gate_probability:=1.0). ' + _AT_INIT, choices=INITIALIZATIONS, group=_G_INIT),
    ParamSpec(
        'initial_state', 'double_array', None,
        'Initial state: [position m, velocity m/s] (train, car), [position m] (robot), '
        '[position, velocity, acceleration, commanded acceleration, traction A, braking B] '
        '(rail); in first_measurement mode only the unmeasured states are used. '
        + _PRESETS + _AT_INIT,
        constraints='one finite double per state', unit='m, m/s', group=_G_INIT,
        derived=True),
    ParamSpec(
        'initial_covariance', 'double_array', None,
        'Initial covariance [m², m²/s²]: the diagonal (one value per state) or the full '
        'row-major matrix, symmetric positive semi-definite. ' + _PRESETS + _AT_INIT,
        constraints='n or n² finite doubles, symmetric PSD', unit='m², m²/s²', group=_G_INIT,
        derived=True),
    _double('nominal_period_s', None,
            'Prior mode: how long before the first stamp the prior holds [s]. ' + _PRESETS
            + _AT_INIT, (1e-6, 3600.0), 's', group=_G_INIT, derived=True),
    _double('first_velocity_std_mps', _CORE.first_velocity_std_mps,
            'first_measurement mode: standard deviation of the initial velocity [m/s] (not '
            "for rail: its initial_covariance holds the velocity's, 20 m/s). " + _AT_INIT,
            (1e-6, 1e6), 'm/s', group=_G_INIT),
)

PARAMETERS_LIVE = (
    _double('process_noise_density', _CORE.process_noise_density,
            'White-noise acceleration density q [m²/s³]: Q(dt) = q [[dt³/3, dt²/2], '
            "[dt²/2, dt]], added to the preset's process noise (train: 0, as seed 000, which "
            'trusts the constant-velocity model fully). Must be 0 for the robot and for rail '
            '(its regimes have their own noise). ' + _LIVE,
            (0.0, BIG), 'm²/s³', group=_G_LIVE),
    _double('measurement_variance', _CORE.measurement_variance,
            'Position measurement variance R [m²] overriding the message pose.covariance[0]; '
            '0 uses the message. ' + _LIVE, (0.0, BIG), 'm²', group=_G_LIVE),
    _double('measurement_velocity_variance', _CORE.measurement_velocity_variance,
            'Velocity measurement variance [m²/s²] overriding the message twist.covariance[0] '
            '(presets measuring the velocity, and the velocity topic); 0 uses the message. '
            'With velocity_type twist (no covariance in the message) it is the variance, '
            'and must be > 0. ' + _LIVE, (0.0, BIG),
            'm²/s²', group=_G_LIVE),
    _double('horizon_s', None,
            'How far ahead the prediction is [s] (0: the prediction is the estimate). '
            + _PRESETS + _LIVE, (0.0, 86400.0), 's', group=_G_LIVE, derived=True),
    # The node turns on what the seed-faithful core defaults leave off: out-of-sequence
    # fusion (history_s 1, core 0).
    _double('history_s', 1.0,
            'Out-of-sequence window [s]: a measurement older than the newest fused one by '
            'less than this is fused by rewinding and replaying; older ones are rejected as '
            'stale. 0 accepts only increasing stamps. ' + _LIVE, HISTORY_S_RANGE, 's',
            group=_G_LIVE),
    # The χ² gate is on (kf_train.estimator.settings.DEFAULT_GATE_PROBABILITY says why
    # 0.9999). The seed switch turns it off: with Q = 0 and the seed's wrong prior, valid
    # innovations reach a NIS of 25 on some seeds (seed 3), and prior mode must
    # reproduce the seed on any measurements.
    _double('gate_probability', _CORE.gate_probability,
            'χ² gate: a measurement whose NIS exceeds the χ²(m) quantile of this probability '
            'is rejected as an outlier and counted (0.9999: NIS > 15.1 for a position, 1 valid '
            'measurement in 10⁴; a 10⁶ m outlier is always rejected); 1 disables '
            'the gate, as the seed switch (preset:=train, initialization:=prior, '
            'gate_probability:=1.0) needs to reproduce seed 000 on any data. ' + _LIVE,
            GATE_PROBABILITY_RANGE, group=_G_LIVE),
    _integer('max_consecutive_outliers', _CORE.max_consecutive_outliers,
             'After this many gate (repeated-epoch or numerical) rejections in a row that '
             'agree with each other (a line fits them) comes a lock-out (see lockout). '
             + _LIVE,
             MAX_CONSECUTIVE_OUTLIERS_RANGE, group=_G_LIVE),
    ParamSpec(
        'lockout', 'string', _CORE.lockout,
        'What a lock-out does: reacquire (default: the track is kept, widened by the jump '
        'between it and the line through the rejected fixes, and those fixes fused: a run '
        'stays one track through gaps, cold starts and receiver artefacts; counted as '
        'reacquisitions) '
        'or reset (the filter forgets the track and the next measurement initialises it '
        'with the rejected fixes; counted in resets). A speed input fused meanwhile is '
        'kept (the fixes from the track’s stamp on are fused). A lock-out from numerical '
        'failures, out-of-sequence fixes (a fix after its own epoch’s speed is in order) '
        'or with controls always resets. ' + _LIVE,
        choices=LOCKOUT_ACTIONS, group=_G_LIVE),
    _integer('restart_after_stale', _CORE.restart_after_stale,
             'After this many stale measurements in a row the stream counts as restarted: '
             'the filter resets and initialises from the last one. ' + _LIVE,
             RESTART_AFTER_STALE_RANGE, group=_G_LIVE),
    _double('max_future_s', _CORE.max_future_s,
            'A stamp more than this [s] ahead of the node clock is rejected (not checked '
            'while a simulated clock is still 0). ' + _LIVE, MAX_FUTURE_S_RANGE, 's',
            group=_G_LIVE),
    ParamSpec('expected_frame_id', 'string', _CORE.expected_frame_id,
              "Required header.frame_id of measurements; '' accepts any. " + _LIVE,
              constraints="a frame name, or '' for any", group=_G_LIVE),
)

PARAMETERS_NODE = (
    ParamSpec('frame_id', 'string', 'odom',
              'header.frame_id of estimate, prediction and innovation (REP 105).',
              constraints=_FRAME, group=_G_NODE),
    ParamSpec('child_frame_id', 'string', 'base_link',
              'child_frame_id of estimate and prediction.', constraints=_FRAME,
              group=_G_NODE),
    _double('timeout_s', 1.0,
            'Without a fused measurement for this long [s] the diagnostics go to WARN and the '
            'node logs it once.', (1e-3, 86400.0), 's', group=_G_NODE),
    _double('diagnostics_period_s', 1.0, 'Period of /diagnostics [s], on the steady clock.',
            (0.01, 3600.0), 's', group=_G_NODE),
    _integer('nis_window', 100,
             'How many of the latest updates the mean NIS in /diagnostics is taken over.',
             (1, 1_000_000), group=_G_NODE),
    _integer('noise_suggestion_window', 300,
             'How many of the latest fused measurements the suggested process_noise_density '
             'in /diagnostics is estimated from (maximum likelihood, recomputed once per '
             'window; shown from 30 on, with which way and how far to move q). 0 turns '
             'it off; below 10 counts as 10. Presets without q (robot) never show it.',
             (0, 3000), group=_G_NODE),
    _double('expected_period_s', 0.0,
            'Expected period of each input topic (measurement; control for presets with one; '
            "velocity for rail) [s]; 0: the preset's nominal_period_s. Watched on the steady "
            'clock once the topic has delivered a message; a silent velocity never withholds '
            'the estimate.', (0.0, 3600.0), 's', group=_G_NODE),
    _double('stale_warn_periods', 3.0,
            'After this many expected periods without a message on an input topic, '
            '/diagnostics (status <node>: inputs) goes to WARN naming the topic and its age.',
            (1.0, 1e6), group=_G_NODE),
    _double('stale_error_periods', 10.0,
            'After this many expected periods without a message, ERROR (at least '
            'stale_warn_periods); back to OK when messages return.', (1.0, 1e6),
            group=_G_NODE),
    ParamSpec('stale_output', 'string', 'stop',
              'While an input is stale (ERROR): stop (default) publishes no estimate or '
              'prediction (a stale control withholds those of new measurements); predict '
              'publishes, while the measurement is stale, the estimate predicted to now (its '
              'covariance widening) at every stale check.', choices=STALE_OUTPUTS, group=_G_NODE),
    ParamSpec('covariance_reference', 'string', 'receiver',
              'What the covariances of estimate and prediction describe. receiver '
              "(default): the track in the fixes' own frame, which a receiver's slow error "
              'moves with it: the band a later fix falls in. absolute: about the truth: '
              "the rail preset adds absolute_error_scale times the newest fix's variance "
              'to the position variance (docs/rail.md); the other presets publish the same '
              'either way.', choices=COVARIANCE_REFERENCES, group=_G_NODE),
    ParamSpec('reset_on_clock_jump', 'bool', True,
              'Reset the filter when the node clock jumps backwards (use_sim_time, a bag '
              'loop, a simulation reset).', group=_G_NODE),
)


def _preset_defaults(preset: str) -> Dict[str, Any]:
    """Return the derived defaults a preset gives (as parameter values)."""
    try:
        values = preset_defaults(preset)
    except ValueError as error:
        raise ParameterError(str(error)) from None
    return {name: list(value) if isinstance(value, tuple) else value
            for name, value in values.items()}


PARAMETERS = ParamTable('estimator', PARAMETERS_FIXED + PARAMETERS_TRACK + PARAMETERS_AT_INIT
                        + PARAMETERS_LIVE + PARAMETERS_NODE, key='preset',
                        derived_defaults=_preset_defaults)
"""Every parameter of the estimator node, in declaration order."""

DEFAULTS = dataclasses.replace(_CORE, **{
    spec.name: spec.default for spec in PARAMETERS.specs
    if spec.name in SETTING_NAMES and not spec.derived})
"""The node's default EstimatorSettings (preset-derived fields None: the preset's)."""


class NodeOptions(NamedTuple):
    """The parameters that configure the node itself rather than the estimator."""

    frame_id: str
    child_frame_id: str
    timeout_s: float
    diagnostics_period_s: float
    nis_window: int
    noise_suggestion_window: int
    reset_on_clock_jump: bool
    expected_period_s: float
    stale_warn_periods: float
    stale_error_periods: float
    stale_output: str
    covariance_reference: str
    qos_reliability: str
    qos_depth: int
    managed: bool
    velocity_type: str
    measurement_type: str
    track: str
    track_direction: str
    cross_track_max_m: float
    cross_track_sigmas: float
    fix_variance_m2: float


class EstimatorConfig(NamedTuple):
    """What the estimator node runs: core settings, node options, every parameter's value."""

    settings: EstimatorSettings
    options: NodeOptions
    values: Dict[str, Any]
    """Every parameter's value, as ``ros2 param get`` shows it."""


def estimator_config(values: Mapping[str, Any]) -> EstimatorConfig:
    """
    Return the node's configuration from parameter values (missing ones: the defaults).

    Checks everything the node checks, in its order, and raises ParameterError with
    its texts: unknown names, types and ranges (as rclpy checks the descriptors),
    choices, the estimator settings as a whole, non-empty frames.
    """
    values = PARAMETERS.complete(values)
    try:
        settings = EstimatorSettings(
            **{name: _setting_value(name, values[name]) for name in SETTING_NAMES}).validated()
    except ValueError as error:
        raise ParameterError(str(error)) from None
    for name in FRAME_PARAMETERS:
        if not values[name]:
            raise ParameterError(f'{name} must not be empty')
    if values['stale_error_periods'] < values['stale_warn_periods']:
        raise ParameterError('stale_error_periods ({:g}) must be at least stale_warn_periods '
                             '({:g})'.format(values['stale_error_periods'],
                                             values['stale_warn_periods']))
    if values['velocity_type'] == 'twist' and settings.measurement_velocity_variance <= 0.0 \
            and is_rail(resolve_preset(settings.preset)):
        raise ParameterError('measurement_velocity_variance must be > 0 with velocity_type '
                             'twist: a TwistStamped carries no variance')
    check_track_values(values)
    return EstimatorConfig(settings, NodeOptions(**{name: values[name]
                                                    for name in NodeOptions._fields}), values)


def changed_config(config: EstimatorConfig, changes: Mapping[str, Any]) -> EstimatorConfig:
    """Return the configuration after a runtime change, or raise ParameterError (a reason)."""
    return estimator_config(PARAMETERS.changed(config.values, changes))


def load_estimator_config(params_files: Union[Mapping, Sequence[Mapping]] = (),
                          overrides: Iterable[str] = ()) -> EstimatorConfig:
    """
    Return the configuration the node would run with these params files and overrides.

    ``params_files``: one params-file mapping or a sequence of them (ROS format, e.g.
    from :func:`kf_train.ros.param_spec.read_params_file`; the sections for node
    ``estimator``, ``/**`` included, apply); ``overrides``: ``NAME:=VALUE`` strings as
    given to ``-p``. Raises ParameterError; ``str(error)`` is the node's start-up line.
    """
    return estimator_config(PARAMETERS.load(params_files, overrides))


def _setting_value(name: str, value):
    """Return a parameter value in the form EstimatorSettings keeps it."""
    if name in ('initial_state', 'initial_covariance'):
        return tuple(float(v) for v in value)
    return value
