"""The estimator node takes the params file ``kf-train tune`` writes (rclpy in-process)."""

import io
import sys

from kf_train.cli.tune import main as tune_main
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.sim import white_noise_acceleration_scenario
import rclpy
from rclpy.context import Context
import yaml


def main(argv):
    """Run kf-train tune with the train preset unless one is given (the default is rail)."""
    argv = [str(a) for a in argv]
    if '--preset' not in argv and '--config' not in argv:
        argv = ['--preset', 'train'] + argv
    return tune_main(argv)


def _tuned_params_file(directory) -> str:
    """Run kf-train tune on a random-force train; return the params file it wrote."""
    scenario = white_noise_acceleration_scenario(0.5, 1.0, 300, seed=11)
    path = directory / 'in.csv'
    path.write_text('t,z_position\n' + ''.join(
        f'{t!r},{z!r}\n' for t, z in zip(scenario.t_s.tolist(), scenario.z[:, 0].tolist())))
    out = io.StringIO()
    stdout, sys.stdout = sys.stdout, out
    try:
        assert main([str(path), '--output', str(directory / 'params.yaml')]) == 0
    finally:
        sys.stdout = stdout
    return str(directory / 'params.yaml')


def test_the_estimator_node_takes_the_params_file(tmp_path, domain_id):
    """``--ros-args --params-file PARAMS.yaml`` sets the node's parameters to the tuned values."""
    path = _tuned_params_file(tmp_path)
    values = yaml.safe_load(open(path))['estimator']['ros__parameters']
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', path], context=context,
               domain_id=domain_id)
    try:
        node = EstimatorNode(context=context)
        for name, value in values.items():
            assert node.get_parameter(name).value == value, name
        node.destroy_node()
    finally:
        context.try_shutdown()


def test_the_estimator_node_runs_the_tuned_rail_preset(tmp_path, domain_id):
    """The default preset (rail): the params file points the node at the tuned rail preset."""
    from kf_train.sim.rail import rail_scenario
    scenario, _ = rail_scenario(seed=21, family='metro')
    rows = 1200                                     # 120 s at 10 Hz: a departure and a stop
    path = tmp_path / 'rail.csv'
    path.write_text('t,z_position\n' + ''.join(
        f'{t!r},{z!r}\n' for t, z in zip(scenario.t_s[:rows].tolist(),
                                         scenario.z[:rows, 0].tolist())))
    out = io.StringIO()
    stdout, sys.stdout = sys.stdout, out
    try:
        assert tune_main([str(path), '--output', str(tmp_path / 'params.yaml')]) == 0
    finally:
        sys.stdout = stdout
    params = str(tmp_path / 'params.yaml')
    values = yaml.safe_load(open(params))['estimator']['ros__parameters']
    tuned = yaml.safe_load(open(values['preset']))
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', params], context=context,
               domain_id=domain_id)
    try:
        node = EstimatorNode(context=context)
        for name, value in values.items():
            assert node.get_parameter(name).value == value, name
        assert node.preset.name == 'rail-tuned'
        for name in ('acceleration_noise', 'command_noise'):
            assert getattr(node.preset.parameters, name) == tuned['parameters'][name]
        node.destroy_node()
    finally:
        context.try_shutdown()
