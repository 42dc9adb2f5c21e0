"""The launch files' parameter resolution (kf_train.launch_params), without launch."""

import os

from kf_train.ros import estimator_params, launch_params, simulator_params
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.ros.runner import StartupError
from kf_train.ros.simulator_node import SimulatorNode
import pytest
from rclpy.parameter import Parameter

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CONFIG = os.path.join(REPO, 'config', 'kf_train.yaml')


def make_node(node_class, context, values):
    """Return ``node_class`` started with ``values`` as parameter overrides."""
    overrides = [Parameter(name, value=value) for name, value in values.items()]
    return node_class(context=context, parameter_overrides=overrides)


def test_derived_parameters_are_left_out_for_another_choice():
    """Exactly the tables' derived parameters depend on the preset (scenario)."""
    config = launch_params.load_params_file(CONFIG)
    for table, other in ((estimator_params.PARAMETERS, 'robot'),
                         (simulator_params.PARAMETERS, 'car')):
        listed = launch_params.node_parameters(config, table.node)
        kept = launch_params.choose(table, listed, other)
        derived = {spec.name for spec in table.specs if spec.derived}
        assert derived and derived <= set(listed)
        assert set(listed) - set(kept) == derived
        assert launch_params.choose(table, listed, table.spec(table.key).default) == listed


@pytest.mark.parametrize('preset', ['robot', 'car', 'cv-position'])
def test_default_config_starts_the_estimator_with_another_preset(ros_context, preset):
    """The installed file with preset:=X starts X with X's own initial values."""
    values = launch_params.estimator_parameters(
        launch_params.load_params_file(CONFIG), '', preset, False)
    node = make_node(EstimatorNode, ros_context, values)
    try:
        assert node.preset.name == preset
        assert node.get_parameter('use_sim_time').value is False
        assert node.get_parameter('history_s').value == 1.0  # the file's other values
    finally:
        node.destroy_node()


def test_the_file_unfiltered_would_not_start_the_robot(ros_context):
    """Why the dependent values are left out: the train's two-state prior stops the robot."""
    values = launch_params.node_parameters(launch_params.load_params_file(CONFIG),
                                           'estimator')
    values['preset'] = 'robot'
    with pytest.raises(StartupError, match='initial_state'):
        make_node(EstimatorNode, ros_context, values)


def test_default_config_with_another_scenario(ros_context):
    """scenario:=car drops the train's true_velocity/initial_position/noise_std."""
    values = launch_params.simulator_parameters(
        launch_params.load_params_file(CONFIG), 'ns', 'car', True)
    node = make_node(SimulatorNode, ros_context, values)
    try:
        assert node.get_parameter('initial_position').value == 0.2  # seed 001's
        assert node.get_parameter('use_sim_time').value is True
    finally:
        node.destroy_node()


def test_sections_apply_with_or_without_the_namespace_in_file_order():
    """A namespaced node takes 'estimator' too; later sections win, as in rcl."""
    params = {
        '/**': {'ros__parameters': {'a': 1, 'b': 1, 'c': 1, 'd': 1}},
        '/**/estimator': {'ros__parameters': {'b': 2, 'c': 2, 'd': 2}},
        'estimator': {'ros__parameters': {'c': 3}},
        '/ns/estimator': {'ros__parameters': {'d': 4}},
        'simulator': {'ros__parameters': {'a': 9}},
        'ns': {'*': {'ros__parameters': {'e': 5}}},
    }
    assert launch_params.node_parameters(params, 'estimator', '/ns/') == {
        'a': 1, 'b': 2, 'c': 3, 'd': 4, 'e': 5}
    assert launch_params.node_parameters(params, 'estimator') == {
        'a': 1, 'b': 2, 'c': 3, 'd': 2}
    assert launch_params.node_parameters({}, 'estimator') == {}
    later = {'estimator': {'ros__parameters': {'a': 3}}, '/**': {'ros__parameters': {'a': 1}}}
    assert launch_params.node_parameters(later, 'estimator', 'ns') == {'a': 1}


def test_choose_keeps_derived_values_for_the_files_own_choice():
    """The same preset as the file's (or the default) keeps the file's values."""
    table = estimator_params.PARAMETERS
    values = {'initial_state': [1.0, 2.0], 'horizon_s': 3.0, 'history_s': 0.5}
    assert launch_params.choose(table, values, '') == values
    # The default preset is rail (issue 11): choosing it keeps the file's values, choosing
    # another one (train) leaves out what was made for the default.
    assert launch_params.choose(table, values, 'rail') == dict(values, preset='rail')
    assert launch_params.choose(table, values, 'train') == {'history_s': 0.5,
                                                            'preset': 'train'}
    assert launch_params.choose(table, dict(values, preset='train'), 'train') == dict(
        values, preset='train')
    changed = launch_params.choose(table, dict(values, preset='car'), 'robot')
    assert changed == {'history_s': 0.5, 'preset': 'robot'}
    assert 'initial_state' in values  # the input is not changed


@pytest.mark.parametrize('content, words', [
    (None, ['does not exist']),
    ('estimator: [unclosed', ['not YAML']),
    ('- a list', ['must map node names']),
    ('estimator: 3', ['estimator', 'must be a mapping']),
])
def test_bad_params_files_raise_one_line(tmp_path, content, words):
    """A missing, malformed or misshaped params file: a ValueError naming the problem."""
    path = tmp_path / 'params.yaml'
    if content is not None:
        path.write_text(content)
    with pytest.raises(ValueError) as error:
        launch_params.node_parameters(launch_params.load_params_file(str(path)),
                                      'estimator')
    assert '\n' not in str(error.value)
    for word in words:
        assert word in str(error.value)


def test_parse_bool():
    """Launch booleans: the usual words, anything else refused naming the argument."""
    assert launch_params.parse_bool('use_sim_time', 'True') is True
    assert launch_params.parse_bool('use_sim_time', 'false') is False
    with pytest.raises(ValueError, match='use_sim_time'):
        launch_params.parse_bool('use_sim_time', 'maybe')


def test_managed_argument_overrides_the_file_only_when_given():
    """managed:='' keeps the file's value; true/false replace it; anything else refused."""
    values = {'preset': 'train', 'managed': True}
    assert launch_params.with_managed(values, '') == values
    assert launch_params.with_managed(values, 'false')['managed'] is False
    assert launch_params.with_managed({}, 'True') == {'managed': True}
    with pytest.raises(ValueError, match='managed'):
        launch_params.with_managed({}, 'maybe')
