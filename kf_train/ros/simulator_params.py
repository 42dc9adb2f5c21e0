"""
The ``simulator`` node's parameters, each declared once, and the simulation they make.

Pure (no rclpy, no message package), like :mod:`kf_train.ros.estimator_params`:
:data:`PARAMETERS` is the one table the node declares and the docs are generated from;
:func:`simulator_config` checks values as the node does.
"""

from typing import Any, Dict, Iterable, Mapping, NamedTuple, Sequence, Union

from kf_train.ros.param_spec import (
    BIG, MANAGED_DESCRIPTION, ParameterError, ParamSpec, ParamTable)
from kf_train.sim import (
    CAR_ACCELERATION_MPS2, DEFAULT_GNSS_MODEL, DEFAULT_INITIAL_STATE, DEFAULT_NOISE_STD_M,
    DEFAULT_RAIL_FAMILY, FaultSettings, GNSS_MODELS, RAIL_FAMILIES, rail_parameters,
    ROBOT_SPEED_STD_MPS, SCENARIOS)

FRAME_PARAMETERS = ('frame_id', 'child_frame_id')
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
"""Fault parameter -> FaultSettings field."""

_FIXED = 'Fixed at start-up (restart to change).'
_SCENARIOS = "Default: the scenario's. "
_FAULT = ' Changeable at runtime; applies from the next sample. Default off.'
_PROBABILITY = (0.0, 1.0)
_FRAME = 'a non-empty frame name'
_G_FIXED = 'fixed at start-up (restart to change)'
_G_LIVE = 'changeable at runtime'
_G_FAULTS = 'fault injection: all off by default, applied from the next sample'
_G_RAIL = 'scenario rail: fixed at start-up (restart to change)'
_DRAWN = " 0 (default): drawn from rail_family's range by seed."
_DRAWN_PAIR = " Max 0 (default): rail_family's range."
RAIL_PARAMETERS = {
    'rail_accel_mps2': 'accel_mps2', 'rail_brake_mps2': 'brake_mps2',
    'rail_jerk_mps3': 'jerk_mps3', 'rail_line_speed_mps': 'line_speed_mps',
    'rail_texture_speed_mps': 'texture_speed_mps'}
"""Rail parameter -> keyword of kf_train.sim.rail_parameters (0: drawn; texture 0: none)."""
RAIL_RANGE_PARAMETERS = {
    'station_spacing_m': ('rail_station_spacing_min_m', 'rail_station_spacing_max_m'),
    'dwell_s': ('rail_dwell_min_s', 'rail_dwell_max_s')}
"""Keyword of kf_train.sim.rail_parameters -> its (min, max) parameters (max 0: drawn)."""


def _double(name, default, description, range_, unit='', **more) -> ParamSpec:
    """Return the spec of a double parameter."""
    return ParamSpec(name, 'double', default, description, range=range_, unit=unit, **more)


def _rail(name, default, description, range_, unit) -> ParamSpec:
    """Return the spec of a rail run parameter (a double, fixed at start-up)."""
    return ParamSpec(name, 'double', default, 'rail: ' + description + ' ' + _FIXED,
                     range=range_, unit=unit, live=False, group=_G_RAIL)


def _fault(name, default, description, range_, unit='') -> ParamSpec:
    """Return the spec of a fault-injection parameter (a double, live)."""
    return _double(name, default, description + _FAULT, range_, unit, group=_G_FAULTS)


PARAMETERS = ParamTable('simulator', key='scenario', specs=(
    ParamSpec('scenario', 'string', 'train',
              'What is simulated: train (seed 000), car / car-exact (seed 001, publishes '
              'control as AccelStamped), robot / robot-exact (seed 002, publishes control as '
              'TwistStamped), rail (a jerk-limited run through stations, the rail_* '
              'parameters; publishes the true acceleration on ground_truth_accel). '
              + _FIXED, choices=SCENARIOS, live=False, group=_G_FIXED),
    _double('rate_hz', 10.0, 'Sample rate [Hz]. ' + _FIXED, (0.01, 10000.0), 'Hz',
            live=False, group=_G_FIXED),
    ParamSpec('managed', 'bool', False, MANAGED_DESCRIPTION, live=False, group=_G_FIXED),
    _double('real_time_factor', 1.0,
            'Simulated seconds per wall-clock second: samples go out every '
            '1/(rate_hz·real_time_factor) s, stamped 1/rate_hz apart, so above 1 the stamps '
            'run ahead of the wall clock (give the subscribers use_sim_time and this node '
            'publish_clock). Live node only. ' + _FIXED, (0.01, 1000.0), '',
            live=False, group=_G_FIXED),
    _double('true_velocity', None,
            "True velocity [m/s]: the train's constant one, the car's initial one (robot: "
            'not used). ' + _SCENARIOS + _FIXED, (-1000.0, 1000.0), 'm/s', live=False,
            group=_G_FIXED, derived=True),
    _double('initial_position', None,
            "True position at the start time [m] (robot: added to the seed's trajectory). "
            + _SCENARIOS + _FIXED, (-BIG, BIG), 'm', live=False, group=_G_FIXED,
            derived=True),
    _double('acceleration_mps2', CAR_ACCELERATION_MPS2,
            'car: the commanded acceleration [m/s²], published on control. ' + _FIXED,
            (-1000.0, 1000.0), 'm/s²', live=False, group=_G_FIXED),
    ParamSpec('seed', 'integer', 0,
              'Seed of the measurement noise and of the faults; -1 draws fresh entropy. '
              + _FIXED, range=(-1, 2 ** 31 - 1), live=False, group=_G_FIXED),
    ParamSpec('rail_family', 'string', DEFAULT_RAIL_FAMILY,
              'rail: the kind of line whose ranges the run is drawn from by seed: metro '
              '(accel 0.8-1.3 m/s², brake 0.8-1.3 m/s², jerk 0.5-1 m/s³, line speed 15-25 m/s, '
              'stations 600-1500 m apart, dwell 15-40 s) or regional (0.4-0.9, 0.5-1.1, '
              '0.3-0.7, 30-45 m/s, 2500-8000 m, 30-90 s). ' + _FIXED, choices=RAIL_FAMILIES,
              live=False, group=_G_RAIL),
    ParamSpec('rail_gnss_model', 'string', DEFAULT_GNSS_MODEL,
              'rail: the GNSS error model. receiver (default): a real receiver, calibrated '
              'to u-blox M8N logs of a train (kf_train.sim.gnss_receiver): a slow, '
              'time-correlated error, position hold at standstill, the reported hAcc² as '
              'the measurement variance, a Doppler speed published on velocity '
              '(TwistWithCovarianceStamped, variance speedAcc²), dropped epochs, outages, '
              'multipath jumps, a cold start. white: white noise of noise_std, as before. '
              + _FIXED, choices=GNSS_MODELS, live=False, group=_G_RAIL),
    _rail('rail_accel_mps2', 0.0, 'acceleration held on leaving a station [m/s²] '
          '(0.05-1.3).' + _DRAWN, (0.0, 1.3), 'm/s²'),
    _rail('rail_brake_mps2', 0.0, 'service braking [m/s²] (0.05-1.5).' + _DRAWN,
          (0.0, 1.5), 'm/s²'),
    _rail('rail_jerk_mps3', 0.0, 'jerk limit of every speed change [m/s³] (0.3-1).' + _DRAWN,
          (0.0, 1.0), 'm/s³'),
    _rail('rail_line_speed_mps', 0.0, 'cruising speed between stations [m/s] (10-45).'
          + _DRAWN, (0.0, 45.0), 'm/s'),
    _rail('rail_texture_speed_mps', 0.0, "std of a cruise's small speed changes (gradients, "
          'traction notches, varying coasting) [m/s] (0-3), about once per 20 s. 0 (default): '
          'none, the cruise of the runs before.', (0.0, 3.0), 'm/s'),
    _rail('rail_station_spacing_min_m', 0.0, 'shortest station-to-station distance [m] '
          '(>= 100; with rail_station_spacing_max_m).', (0.0, 1e6), 'm'),
    _rail('rail_station_spacing_max_m', 0.0, 'longest station-to-station distance [m] (>= '
          'rail_station_spacing_min_m).' + _DRAWN_PAIR, (0.0, 1e6), 'm'),
    _rail('rail_dwell_min_s', 0.0, 'shortest dwell at a station [s] (with rail_dwell_max_s).',
          (0.0, 3600.0), 's'),
    _rail('rail_dwell_max_s', 0.0, 'longest dwell at a station [s] (>= rail_dwell_min_s).'
          + _DRAWN_PAIR, (0.0, 3600.0), 's'),
    _double('noise_std', None,
            'Standard deviation of the position measurement noise [m]; its square is '
            'published as the measurement variance. ' + _SCENARIOS, (0.0, 1000.0), 'm',
            group=_G_LIVE, derived=True),
    _double('speed_noise_std', ROBOT_SPEED_STD_MPS,
            'robot: standard deviation of the speed sensor [m/s] whose readings are '
            'published on control.', (0.0, 1000.0), 'm/s', group=_G_LIVE),
    ParamSpec('frame_id', 'string', 'odom',
              'Frame of the measurements and the truth (REP 105).', constraints=_FRAME,
              group=_G_LIVE),
    ParamSpec('child_frame_id', 'string', 'base_link',
              'child_frame_id of the ground truth odometry.', constraints=_FRAME,
              group=_G_LIVE),
    ParamSpec('max_samples', 'integer', 0,
              'Samples to publish before finishing; 0 runs forever.', range=(0, 2 ** 31 - 1),
              group=_G_LIVE),
    ParamSpec('min_subscribers', 'integer', 0,
              'Subscribers of measurement (and of control, for car and robot) to wait for '
              'before the first sample.', range=(0, 1000), group=_G_LIVE),
    ParamSpec('publish_clock', 'bool', False,
              'Publish each sample stamp on /clock (for nodes with use_sim_time).',
              group=_G_LIVE),
    _fault('dropout_probability', 0.0, 'Probability that a sample is lost.', _PROBABILITY),
    _fault('outlier_probability', 0.0, 'Probability that a sample is off by ±outlier_size_m.',
           _PROBABILITY),
    _fault('outlier_size_m', 10.0, 'Size of an outlier [m], added with a random sign.',
           (0.0, 1e6), 'm'),
    _fault('delay_s', 0.0, 'Latency between taking and publishing a sample [s].',
           (0.0, 60.0), 's'),
    _fault('reorder_probability', 0.0,
           'Probability that a sample is published after the next one.', _PROBABILITY),
    _fault('clock_jump_at_s', 0.0,
           'Sample time [s] from which clock_jump_s is added to every stamp; 0 = never.',
           (0.0, 1e9), 's'),
    _fault('clock_jump_s', 0.0,
           'Stamp jump [s] from clock_jump_at_s on; negative jumps back (a restarted sensor '
           'clock).', (-1e9, 1e9), 's'),
    _fault('measurement_bias_m', 0.0, 'Constant bias added to every measurement [m].',
           (-1e6, 1e6), 'm'),
), derived_defaults=lambda scenario: {
    'initial_position': DEFAULT_INITIAL_STATE[scenario][0],
    'true_velocity': DEFAULT_INITIAL_STATE[scenario][1],
    'noise_std': DEFAULT_NOISE_STD_M[scenario]})
"""Every parameter of the simulator node, in declaration order."""


class SimulatorOptions(NamedTuple):
    """The parameters that configure the node's publishing (all but managed: at runtime)."""

    frame_id: str
    child_frame_id: str
    max_samples: int
    min_subscribers: int
    publish_clock: bool
    managed: bool


class SimulatorConfig(NamedTuple):
    """What the simulator node runs."""

    scenario: str
    rate_hz: float
    seed: int
    """-1: fresh entropy."""
    stream: Dict[str, float]
    """The keyword arguments of kf_train.sim.scenario_streams.make_stream."""
    faults: FaultSettings
    options: SimulatorOptions
    values: Dict[str, Any]
    """Every parameter's value, as ``ros2 param get`` shows it."""


def simulator_config(values: Mapping[str, Any]) -> SimulatorConfig:
    """Return the simulator's configuration from parameter values, checked as the node does."""
    values = PARAMETERS.complete(values)
    for name in FRAME_PARAMETERS:
        if not values[name]:
            raise ParameterError(f'{name} must not be empty')
    try:
        faults = FaultSettings(**{field: values[name] for name, field
                                  in FAULT_PARAMETERS.items()}).validated()
    except ValueError as error:
        raise ParameterError(str(error)) from None
    stream = {'noise_std_m': values['noise_std'],
              'initial_position_m': values['initial_position'],
              'velocity_mps': values['true_velocity'],
              'acceleration_mps2': values['acceleration_mps2'],
              'speed_noise_std_mps': values['speed_noise_std']}
    if values['scenario'] == 'rail':
        stream['rail'] = rail_options(values)
    options = SimulatorOptions(**{name: values[name] for name in SimulatorOptions._fields})
    return SimulatorConfig(values['scenario'], values['rate_hz'], values['seed'], stream,
                           faults, options, values)


def rail_options(values: Mapping[str, Any]) -> Dict[str, Any]:
    """Return make_stream's ``rail`` options from the rail_* values; ParameterError if bad."""
    options = {'family': values['rail_family']}
    names = dict(RAIL_PARAMETERS)
    for name, keyword in RAIL_PARAMETERS.items():
        if values[name]:  # 0: the family draws it
            options[keyword] = values[name]
    for keyword, (low, high) in RAIL_RANGE_PARAMETERS.items():
        names[f'{low}/{high}'] = keyword
        if values[high]:  # max 0: the family's range
            options[keyword] = (values[low], values[high])
        elif values[low]:
            raise ParameterError(f"{low} needs {high} too ({high} 0: the family's range)")
    try:  # the ranges of one run (e.g. min <= max, jerk >= 0.3), checked at once
        rail_parameters(seed=0, **options)
    except ValueError as error:
        name = next((n for n, k in names.items() if k in str(error)), 'rail')
        raise ParameterError(f'{name}: {error}') from None
    options['gnss_model'] = values['rail_gnss_model']
    return options


def changed_config(config: SimulatorConfig, changes: Mapping[str, Any]) -> SimulatorConfig:
    """Return the configuration after a runtime change, or raise ParameterError (a reason)."""
    return simulator_config(PARAMETERS.changed(config.values, changes))


def load_simulator_config(params_files: Union[Mapping, Sequence[Mapping]] = (),
                          overrides: Iterable[str] = ()) -> SimulatorConfig:
    """Return the configuration the node would run with these params files and overrides."""
    return simulator_config(PARAMETERS.load(params_files, overrides))
