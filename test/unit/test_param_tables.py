"""
The nodes' parameter tables without ROS: one table, the documents made from it, its checks.

rclpy's own behaviour (descriptors, start-up and runtime refusals) is compared with these
tables in test/ros/test_param_table.py; here the tables, the params-file and ``-p``
parser, the offline configuration functions and the generated files are tested alone.
"""

import dataclasses
import io
import math
import os
import subprocess
import sys

from kf_train.estimator import EstimatorSettings, preset_defaults
from kf_train.ros import estimator_params, simulator_params
from kf_train.ros.estimator_params import (
    changed_config, DEFAULTS, estimator_config, load_estimator_config, NodeOptions)
from kf_train.ros.param_docs import CONFIG_HEADER, params_file, reference_tables
from kf_train.ros.param_spec import (
    node_parameters, ParameterError, ParamSpec, parse_override, parse_value,
    read_params_file, ros_scalar, yaml_scalar)
from kf_train.ros.simulator_params import load_simulator_config, SimulatorOptions
from kf_train.sim import FaultSettings
import pytest
import yaml

REPO = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..')
CONFIG = os.path.join(REPO, 'config', 'kf_train.yaml')
REFERENCE = os.path.join(REPO, 'docs', 'ros.md')
TABLES = (simulator_params.PARAMETERS, estimator_params.PARAMETERS)
ESTIMATOR = estimator_params.PARAMETERS


def _read(path):
    """Return a file's text."""
    with open(path, encoding='utf-8') as stream:
        return stream.read()


# -- the tables and what is generated from them ---------------------------------------------

def test_the_estimator_table_is_the_settings_and_the_node_options():
    """Every EstimatorSettings field and every node option is a parameter, nothing else."""
    settings = {field.name for field in dataclasses.fields(EstimatorSettings)}
    assert set(ESTIMATOR.names) == settings | set(NodeOptions._fields)
    assert not settings & set(NodeOptions._fields)
    # The node differs from the core only by out-of-sequence fusion (history_s 1).
    assert DEFAULTS == dataclasses.replace(EstimatorSettings(), history_s=1.0)
    assert (DEFAULTS.preset, DEFAULTS.gate_probability) == ('rail', 0.9999)


def test_the_simulator_table_is_the_stream_the_faults_and_the_options():
    """Every simulator parameter feeds the stream, the faults or the options."""
    config = load_simulator_config()
    faults = set(simulator_params.FAULT_PARAMETERS)
    assert set(simulator_params.FAULT_PARAMETERS.values()) == {
        field.name for field in dataclasses.fields(FaultSettings)}
    assert set(simulator_params.PARAMETERS.names) == (
        {'scenario', 'rate_hz', 'seed', 'noise_std', 'initial_position', 'true_velocity',
         'acceleration_mps2', 'speed_noise_std', 'real_time_factor', 'rail_family',
         'rail_gnss_model'}
        | set(simulator_params.RAIL_PARAMETERS) | faults | set(SimulatorOptions._fields)
        | {name for pair in simulator_params.RAIL_RANGE_PARAMETERS.values() for name in pair})
    assert config.faults == FaultSettings()
    assert config.stream == {'noise_std_m': 1.0, 'initial_position_m': 0.0,
                             'velocity_mps': 10.0, 'acceleration_mps2': 1.0,
                             'speed_noise_std_mps': 0.2}


@pytest.mark.parametrize('table', TABLES, ids=lambda table: table.node)
def test_every_spec_is_complete(table):
    """Each spec has a description, a unit where its name has one, sane defaults and ranges."""
    for spec in table.specs:
        assert spec.description.strip() and spec.group, spec.name
        assert spec.accepts, spec.name
        if spec.name.endswith(('_s', '_hz', '_m', '_mps', '_mps2')):
            assert spec.unit, spec.name
        if spec.range is not None:
            assert spec.range[0] < spec.range[1], spec.name
        assert spec.live == ('Fixed at start-up' not in spec.description), spec.name
    defaults = table.defaults()
    assert set(defaults) == set(table.names)


def test_a_wrong_spec_is_refused():
    """A table cannot be built from a spec whose default breaks its own rules."""
    with pytest.raises(ParameterError, match='must be of type DOUBLE, not INTEGER'):
        ParamSpec('rate_hz', 'double', 10, 'x', range=(0.0, 1.0))
    with pytest.raises(ParameterError, match='must be a double in'):
        ParamSpec('rate_hz', 'double', 10.0, 'x', range=(0.0, 1.0))
    with pytest.raises(ValueError, match='derived'):
        ParamSpec('rate_hz', 'double', None, 'x')
    with pytest.raises(ValueError, match='type must be one of'):
        ParamSpec('rate_hz', 'float', 1.0, 'x')


def test_the_config_file_is_generated_from_the_tables():
    """config/kf_train.yaml is exactly what the tables make (tools/parameter_tables.py)."""
    assert _read(CONFIG) == params_file([(table, None) for table in TABLES], CONFIG_HEADER)


def test_the_reference_tables_are_generated_from_the_tables():
    """docs/ros.md holds exactly the tables the parameter tables make."""
    assert reference_tables(TABLES) in _read(REFERENCE)


def test_the_config_file_reads_the_same_in_rcl_and_pyyaml_and_gives_the_defaults():
    """Every value in the config file has one type for rcl and PyYAML; they are the defaults."""
    params = read_params_file(CONFIG)
    assert params == yaml.safe_load(_read(CONFIG))
    for table in TABLES:
        listed = params[table.node]['ros__parameters']
        assert listed == table.defaults()
        assert [type(v) for v in listed.values()] == [
            type(v) for v in table.defaults().values()]
    assert load_estimator_config(params) == estimator_config({})
    assert load_simulator_config(params) == load_simulator_config()


def test_a_tuned_params_file_lists_only_what_is_given():
    """params_file with values writes an estimator section that reads back to them."""
    values = {'preset': 'train', 'process_noise_density': 0.25, 'gate_probability': 0.99}
    text = params_file([(ESTIMATOR, values)], comments=False)
    assert text == ('estimator:\n  ros__parameters:\n    preset: train\n'
                    '    process_noise_density: 0.25\n    gate_probability: 0.99\n')
    config = load_estimator_config(read_params_file(io.StringIO(text)))
    assert (config.settings.process_noise_density, config.settings.gate_probability) == (
        0.25, 0.99)


# -- rcl's typing of values -------------------------------------------------------------

@pytest.mark.parametrize('text, value', [
    ('true', True), ('y', True), ('Yes', True), ('ON', True), ('n', False), ('off', False),
    ('FALSE', False), ('10', 10), ('-3', -3), ('+5', 5), ('0x10', 16), ('010', 8),
    ('0', 0), ('08', 8.0), ('10.0', 10.0), ('1e3', 1000.0), ('-2.5E-1', -0.25),
    ('.5', 0.5), ('5.', 5.0), ('.inf', math.inf), ('-.Inf', -math.inf), ('inf', math.inf),
    ('Infinity', math.inf), ('9223372036854775807', 2 ** 63 - 1),
    ('9223372036854775808', 9.223372036854776e18), ('0x1p3', 8.0),
    ('1e400', '1e400'), ('1e-400', '1e-400'), ('1_000', '1_000'), ('null', 'null'),
    ('~', '~'), ('abc', 'abc'), ('True!', 'True!'), ('yes please', 'yes please'),
])
def test_scalars_are_typed_as_rcl_types_them(text, value):
    """Unquoted scalars: rcl's bool words, strtol, strtod, else a string."""
    result = ros_scalar(text)
    assert type(result) is type(value) and result == value, (text, result)
    assert ros_scalar(text, quoted=True) == text


def test_nan_is_a_double():
    """.nan and nan are doubles (NaN)."""
    for text in ('.nan', '.NaN', 'nan', 'NAN'):
        assert math.isnan(ros_scalar(text))


@pytest.mark.parametrize('assignment, name, value', [
    ('rate_hz:=10.0', 'rate_hz', 10.0),
    ("frame_id:='5'", 'frame_id', '5'),
    ('frame_id:="true"', 'frame_id', 'true'),
    ("frame_id:=''", 'frame_id', ''),
    ('initial_state:=[1.0, 2.0]', 'initial_state', [1.0, 2.0]),
    ('initial_state:=[1, 2]', 'initial_state', [1, 2]),
    ('x:=a:=b', 'x', 'a:=b'),
])
def test_overrides_are_parsed_as_ros_parses_them(assignment, name, value):
    """NAME:=VALUE splits at the first :=, the value typed by rcl's rules."""
    assert parse_override(assignment) == (name, value)


@pytest.mark.parametrize('assignment, words', [
    ('rate_hz', 'is not NAME:=VALUE'),
    (':=1.0', 'is not NAME:=VALUE'),
    ('frame_id:=', 'frame_id has no value'),
    ('initial_state:=[1.0, 2]', 'a sequence must hold values of one type'),
    ('initial_state:={a: 1}', 'must be a scalar or a sequence of scalars'),
    ('initial_state:=[1.0', 'not a YAML value'),
])
def test_bad_overrides_are_refused(assignment, words):
    """A malformed override raises ParameterError saying why."""
    with pytest.raises(ParameterError, match=words):
        parse_override(assignment)


@pytest.mark.parametrize('value', [
    True, False, 0, -7, 1.0, 0.1, 1e-06, 1e+20, -0.999, math.inf, '', 'odom', 'true', 'y',
    '10', '1e3', 'null', "it's", 'a b', '#x', 'cv-position', 'p/x.yaml', [0.0, 5.0], []])
def test_yaml_scalars_read_back_as_themselves(value):
    """yaml_scalar writes what rcl and PyYAML both read back unchanged."""
    text = yaml_scalar(value)
    assert parse_value(text) == value, (value, text)
    assert yaml.safe_load(f'x: {text}')['x'] == value, (value, text)


def test_params_file_sections_apply_as_in_rclpy():
    """/**, /*, NAME, /NAME and /**/NAME apply, in file order; other nodes do not."""
    text = ('/**:\n  ros__parameters: {a: 1, b: 1, c: 1, d: 1, e: 1, f: 1}\n'
            '/estimator:\n  ros__parameters: {b: 2}\n'
            'estimator:\n  ros__parameters: {c: 3}\n'
            '/**/estimator:\n  ros__parameters: {d: 4}\n'
            '/*:\n  ros__parameters: {e: 5}\n'
            '/*/estimator:\n  ros__parameters: {f: 6}\n'
            'other:\n  ros__parameters: {a: 99}\n'
            'ns:\n  estimator:\n    ros__parameters: {g: {x: 7}}\n')
    params = read_params_file(io.StringIO(text))
    # (rclpy gives node /estimator exactly these; test/ros checks it on a node.)
    assert node_parameters(params, 'estimator') == {'a': 1, 'b': 2, 'c': 3, 'd': 4, 'e': 5,
                                                    'f': 1}
    assert node_parameters(params, 'estimator', '/ns') == {
        'a': 1, 'b': 1, 'c': 1, 'd': 4, 'e': 1, 'f': 6, 'g.x': 7}
    later = read_params_file(io.StringIO(
        'estimator:\n  ros__parameters: {b: 2}\n/**:\n  ros__parameters: {b: 1}\n'))
    assert node_parameters(later, 'estimator') == {'b': 1}


def test_a_params_file_must_be_a_mapping_of_nodes():
    """A file that is not node: ros__parameters: ... is refused."""
    with pytest.raises(ParameterError, match='must map node names'):
        read_params_file(io.StringIO('- a\n- b\n'))
    with pytest.raises(ParameterError, match='must be a mapping'):
        node_parameters({'estimator': 5}, 'estimator')
    assert read_params_file(io.StringIO('')) == {}


# -- the estimator's configuration, offline -------------------------------------------------

def test_params_files_and_overrides_make_the_nodes_configuration():
    """Files in order, then -p overrides; the preset's defaults fill what is not given."""
    first = {'/**': {'ros__parameters': {'horizon_s': 1.5, 'frame_id': 'map'}}}
    second = {'estimator': {'ros__parameters': {'preset': 'car', 'horizon_s': 0.5}},
              'simulator': {'ros__parameters': {'rate_hz': 50.0}}}
    config = load_estimator_config([first, second], ['gate_probability:=0.999',
                                                     'use_sim_time:=true'])
    car = preset_defaults('car')
    assert config.settings == dataclasses.replace(
        DEFAULTS, preset='car', horizon_s=0.5, gate_probability=0.999,
        initial_state=car['initial_state'], initial_covariance=car['initial_covariance'],
        nominal_period_s=car['nominal_period_s'])
    assert config.options.frame_id == 'map' and config.options.qos_depth == 10
    assert config.values['initial_state'] == list(car['initial_state'])
    assert 'use_sim_time' not in config.values


@pytest.mark.parametrize('assignment, line', [
    # rclpy's descriptor checks, as kf_train.ros.runner words them
    ('horizon_s:=3', 'invalid parameter horizon_s:=3: must be of type DOUBLE, not INTEGER '
     '(write 3.0)'),
    ('horizon_s:=-1.0', 'invalid parameter horizon_s:=-1.0: must be a double in [0.0, 86400.0]'),
    ('horizon_s:=.nan', 'invalid parameter horizon_s:=nan: must be a double in [0.0, 86400.0]'),
    ('process_noise_density:=1e13', 'invalid parameter process_noise_density:='
     '10000000000000.0: must be a double in [0.0, 1000000000000.0]'),
    ('nis_window:=0', 'invalid parameter nis_window:=0: must be an integer in [1, 1000000]'),
    ('qos_depth:=1.5', 'invalid parameter qos_depth:=1.5: must be of type INTEGER, not DOUBLE'),
    ('reset_on_clock_jump:=1', 'invalid parameter reset_on_clock_jump:=1: must be of type '
     'BOOL, not INTEGER'),
    ('frame_id:=5', 'invalid parameter frame_id:=5: must be of type STRING, not INTEGER'),
    ('initial_state:=[1, 2]', 'invalid parameter initial_state:=[1, 2]: must be of type '
     'DOUBLE_ARRAY, not INTEGER_ARRAY'),
    ('initial_state:=1.0', 'invalid parameter initial_state:=1.0: must be of type '
     'DOUBLE_ARRAY, not DOUBLE'),
    # the node's own checks
    ('initial_state:=[1.0]', 'invalid parameter: initial_state must have length 6, got 1'),
    ('qos_reliability:=sometimes', 'invalid parameter: qos_reliability must be one of '
     "best_effort, reliable, got 'sometimes'"),
    ('filter:=foo', 'invalid parameter: filter must be one of kf, ekf, ukf, pf, bootstrap-pf, '
     "got 'foo'"),
    ('initialization:=bogus', 'invalid parameter: initialization must be one of '
     "first_measurement, prior, got 'bogus'"),
    ("frame_id:=''", 'invalid parameter: frame_id must not be empty'),
    ('preset:=plane', 'invalid parameter: preset must be one of rail, train, car, car-exact, '
     'robot, robot-exact, cv-position, cv-position-velocity or the path of a preset YAML '
     "file, got 'plane'"),
    ('horizon:=2.0', "invalid parameter: the estimator node has no parameter 'horizon' "
     '(did you mean horizon_s?)'),
])
def test_bad_values_are_refused_with_the_nodes_text(assignment, line):
    """Each refusal is the one line the node prints at start-up (after 'error: ')."""
    with pytest.raises(ParameterError) as raised:
        load_estimator_config(overrides=[assignment])
    assert str(raised.value) == line


def test_preset_specific_checks_come_from_the_core():
    """The robot's state is the position alone; process noise must be 0 for it."""
    config = load_estimator_config(overrides=['preset:=robot'])
    assert config.values['initial_state'] == [0.0]
    with pytest.raises(ParameterError, match='process_noise_density must be 0'):
        load_estimator_config(overrides=['preset:=robot', 'process_noise_density:=1.0'])


def test_runtime_changes_are_checked_against_the_running_configuration():
    """A change is checked whole; read-only ones are refused; the reasons are the node's."""
    config = estimator_config({})
    changed = changed_config(config, {'horizon_s': 0.5, 'frame_id': 'map'})
    assert changed.settings.horizon_s == 0.5 and changed.options.frame_id == 'map'
    assert config.settings.horizon_s == 2.0  # the old one is untouched
    for changes, reason in [
            ({'preset': 'car'}, 'Trying to set a read-only parameter: preset.'),
            ({'frame_id': ''}, 'frame_id must not be empty'),
            ({'horizon_s': 3}, "Wrong parameter type, expected 'Type.DOUBLE' got "
                               "'Type.INTEGER'"),
            ({'gate_probability': 0.3}, 'Parameter gate_probability out of range Min: 0.5, '
                                        'Max: 1.0, value: 0.3'),
            ({'max_consecutive_outliers': 0}, 'Parameter max_consecutive_outliers out of '
                                              'range. Min: 1, Max: 1000000, value: 0'),
            ({'initial_covariance': [1.0, 2.0, 2.0, 1.0]}, 'must have 6 (diagonal) or 36'),
            # The identity with P[0, 1] = P[1, 0] = 2: symmetric, eigenvalue -1.
            ({'initial_covariance': [1.0, 2.0] + [0.0] * 4 + [2.0, 1.0] + [0.0] * 4
              + [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
              + [0.0] * 4 + [1.0, 0.0] + [0.0] * 5 + [1.0]}, 'positive semi-definite')]:
        with pytest.raises(ParameterError) as raised:
            changed_config(config, changes)
        assert reason in raised.value.reason, changes
    assert changed_config(config, {'preset': 'rail', 'use_sim_time': True}) == config


def test_the_simulators_configuration_offline():
    """Scenario defaults, faults and the node's texts."""
    robot = load_simulator_config(overrides=['scenario:=robot', 'dropout_probability:=0.5'])
    assert robot.stream['noise_std_m'] == 0.03 and robot.faults.dropout_probability == 0.5
    for assignment, line in [
            ('rate_hz:=-1.0', 'invalid parameter rate_hz:=-1.0: must be a double in '
                              '[0.01, 10000.0]'),
            ('rate_hz:=10', 'invalid parameter rate_hz:=10: must be of type DOUBLE, not '
                            'INTEGER (write 10.0)'),
            ('scenario:=plane', 'invalid parameter: scenario must be one of train, car, '
                                "car-exact, robot, robot-exact, rail, got 'plane'"),
            ("child_frame_id:=''", 'invalid parameter: child_frame_id must not be empty'),
            ('rail_jerk_mps3:=0.1', 'invalid parameter: rail_jerk_mps3: jerk_mps3 must be in '
                                    '[0.3, 1], got 0.1'),
            ('rail_dwell_min_s:=30.0', 'invalid parameter: rail_dwell_min_s needs '
                                       'rail_dwell_max_s too (rail_dwell_max_s 0: the '
                                       "family's range)"),
            ('rail_station_spacing_max_m:=900.0',
             'invalid parameter: rail_station_spacing_min_m/rail_station_spacing_max_m: '
             'station_spacing_m[0] must be in [100, 1e+06], got 0.0')]:
        with pytest.raises(ParameterError) as raised:
            load_simulator_config(overrides=['scenario:=rail', assignment])
        assert str(raised.value) == line


def test_the_rail_scenario_takes_its_values_or_draws_them():
    """0 and [] leave a value to the family's draw; the others reach the stream."""
    drawn = load_simulator_config(overrides=['scenario:=rail'])
    assert drawn.stream['rail'] == {'family': 'metro', 'gnss_model': 'receiver'}
    assert drawn.stream['noise_std_m'] == 1.0 and drawn.stream['initial_position_m'] == 0.0
    given = load_simulator_config(overrides=[
        'scenario:=rail', 'rail_family:=regional', 'rail_accel_mps2:=0.5',
        'rail_line_speed_mps:=30.0', 'rail_station_spacing_min_m:=2000.0',
        'rail_station_spacing_max_m:=3000.0', 'rail_gnss_model:=white'])
    assert given.stream['rail'] == {'family': 'regional', 'accel_mps2': 0.5,
                                    'line_speed_mps': 30.0,
                                    'station_spacing_m': (2000.0, 3000.0),
                                    'gnss_model': 'white'}
    assert 'rail' not in load_simulator_config().stream


def test_tables_diagnostics_and_docs_import_no_ros():
    """The tables, their checks, the docs and the diagnostics need neither ROS nor scipy."""
    code = ('import sys\n'
            'import kf_train.ros.estimator_params, kf_train.ros.simulator_params, '
            'kf_train.ros.param_docs, kf_train.ros.diagnostics\n'
            'print(sorted(m for m in sys.modules if m.split(".")[0] in {"scipy", "rclpy", '
            '"rcl_interfaces", "diagnostic_msgs", "geometry_msgs", "nav_msgs"}))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.strip() == '[]'
