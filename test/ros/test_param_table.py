"""
The nodes against their parameter tables: declarations, descriptors, start-up and runtime texts.

The tables are pure (test/unit/test_param_tables.py); here rclpy is the judge: what a
node declares and how rclpy refuses a value must be what the table says, word for word.
"""

import os

from kf_train.ros import estimator_params, simulator_params
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.ros.param_spec import (
    is_implicit, ParameterError, parse_override, read_params_file)
from kf_train.ros.parameters import descriptor
from kf_train.ros.runner import one_line, StartupError
from kf_train.ros.simulator_node import SimulatorNode
import pytest
from rcl_interfaces.msg import ParameterType
import rclpy
from rclpy.context import Context
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.parameter import Parameter

NODES = [(SimulatorNode, simulator_params), (EstimatorNode, estimator_params)]
TYPES = {'bool': ParameterType.PARAMETER_BOOL, 'integer': ParameterType.PARAMETER_INTEGER,
         'double': ParameterType.PARAMETER_DOUBLE, 'string': ParameterType.PARAMETER_STRING,
         'double_array': ParameterType.PARAMETER_DOUBLE_ARRAY}


def _declared(node):
    """Return the names a node declared itself."""
    return {name for name in node._parameters if not is_implicit(name)}


@pytest.mark.parametrize('node_class, module', NODES, ids=['simulator', 'estimator'])
@pytest.mark.parametrize('key', ['', 'robot'])
def test_declared_parameters_are_the_table(ros_context, node_class, module, key):
    """Every declared parameter is in the table and vice versa, described as the table says."""
    table = module.PARAMETERS
    overrides = [Parameter(table.key, value=key)] if key else []
    node = node_class(context=ros_context, parameter_overrides=overrides)
    try:
        assert _declared(node) == set(table.names)
        defaults = table.defaults(key or None)
        for spec in table.specs:
            described = node.describe_parameter(spec.name)
            wanted = descriptor(spec)
            assert described.type == TYPES[spec.type], spec.name
            for field in ('description', 'additional_constraints', 'read_only',
                          'floating_point_range', 'integer_range'):
                assert getattr(described, field) == getattr(wanted, field), (spec.name, field)
            value = node.get_parameter(spec.name).value
            assert (list(value) if spec.type == 'double_array' else value) == \
                defaults[spec.name], spec.name
        assert node.config.values == defaults
    finally:
        node.destroy_node()


ESTIMATOR_BAD = ['horizon_s:=3', 'horizon_s:=-1.0', 'process_noise_density:=1e13',
                 'nis_window:=0', 'qos_depth:=1.5', 'reset_on_clock_jump:=1', 'frame_id:=5',
                 'initial_state:=[1, 2]', 'initial_state:=1.0', 'initial_state:=[1.0]',
                 'qos_reliability:=sometimes', 'filter:=foo', 'initialization:=bogus',
                 "frame_id:=''", "child_frame_id:=''", 'preset:=plane',
                 'preset:=range-bearing', 'pf_particles:=0', 'ukf_alpha:=0.0',
                 'initial_covariance:=[1.0, -1.0]', 'preset:=robot',
                 'gate_probability:=.nan']
SIMULATOR_BAD = ['rate_hz:=-1.0', 'rate_hz:=10', 'scenario:=plane', 'seed:=1.5',
                 'publish_clock:=1', "frame_id:=''", 'max_samples:=-3',
                 'dropout_probability:=2.0', 'initial_position:=1e13']


@pytest.mark.parametrize('node_class, module, assignment', [
    *[(EstimatorNode, estimator_params, a) for a in ESTIMATOR_BAD],
    *[(SimulatorNode, simulator_params, a) for a in SIMULATOR_BAD]])
def test_startup_refusals_are_the_tables(ros_context, node_class, module, assignment):
    """A node refuses a start-up value with exactly the line the pure loader raises."""
    load = getattr(module, 'load_estimator_config', None) or module.load_simulator_config
    name, value = parse_override(assignment)
    try:
        load(overrides=[assignment])
        expected = None
    except ParameterError as error:
        expected = str(error)
    try:
        node = node_class(context=ros_context, parameter_overrides=[Parameter(name,
                                                                              value=value)])
    except (StartupError, InvalidParameterValueException,
            InvalidParameterTypeException) as error:
        assert one_line(error) == expected
    else:
        node.destroy_node()
        assert expected is None, f'{assignment}: the node started; the loader refused'


@pytest.mark.parametrize('changes', [
    {'horizon_s': -1.0}, {'horizon_s': 3}, {'history_s': 'long'}, {'gate_probability': 0.3},
    {'preset': 'car'}, {'filter': 'ukf'}, {'qos_depth': 5}, {'nis_window': 0},
    {'initialization': 'bogus'}, {'initial_covariance': [1.0, 2.0, 2.0, 1.0]},
    {'initial_state': [1.0]}, {'frame_id': ''}, {'expected_frame_id': 'map'},
    {'horizon_s': 0.5}, {'initial_state': [1.0, 2.0]}, {'nis_window': 10},
])
def test_runtime_answers_are_the_tables(ros_context, changes):
    """A change is refused with the reason changed_config gives, or applied by post-set."""
    node = EstimatorNode(context=ros_context)
    try:
        before = node.config
        try:
            expected = estimator_params.changed_config(before, changes)
            reason = None
        except ParameterError as error:
            expected, reason = before, error.reason
        result = node.set_parameters_atomically(
            [Parameter(name, value=value) for name, value in changes.items()])
        assert result.successful == (reason is None), (changes, result.reason)
        if reason is not None:
            assert result.reason == reason
            assert node.config is before  # the on-set callback changed nothing
        assert node.config == expected
        assert node.estimator.settings == expected.settings
        assert node._nis.maxlen == expected.options.nis_window
    finally:
        node.destroy_node()


def test_params_file_sections_reach_the_node_as_the_loader_says(domain_id, tmp_path):
    """The sections of a params file reach the node exactly as node_parameters reads them."""
    path = tmp_path / 'params.yaml'
    path.write_text(
        '/**:\n  ros__parameters: {horizon_s: 1.0, timeout_s: 2.0, nis_window: 7}\n'
        '/estimator:\n  ros__parameters: {horizon_s: 1.5, history_s: 0x10}\n'
        '/**/estimator:\n  ros__parameters: {timeout_s: 3.0}\n'
        '/*/estimator:\n  ros__parameters: {nis_window: 9}\n'
        'estimator:\n  ros__parameters: {history_s: 08}\n')
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', str(path), '-p', 'max_future_s:=1e3'],
               context=context, domain_id=domain_id)
    try:
        node = EstimatorNode(context=context)
        expected = estimator_params.load_estimator_config(read_params_file(str(path)),
                                                          ['max_future_s:=1e3'])
        assert node.config == expected
        assert (expected.options.timeout_s, expected.options.nis_window) == (3.0, 7)
        assert (expected.settings.horizon_s, expected.settings.history_s) == (1.5, 8.0)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_the_shipped_config_is_what_the_nodes_declare(ros_context):
    """config/kf_train.yaml, read by the pure loader, is each node's default configuration."""
    config = os.path.join(os.path.dirname(__file__), '..', '..', 'config', 'kf_train.yaml')
    params = read_params_file(config)
    for node_class, module in NODES:
        node = node_class(context=ros_context)
        try:
            load = getattr(module, 'load_estimator_config', None) or \
                module.load_simulator_config
            assert load(params) == node.config
        finally:
            node.destroy_node()
