"""The estimator node takes the params file ``kf-train tune`` writes (rclpy in-process)."""

import io
import sys

from kf_train.cli.tune import main
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.sim import white_noise_acceleration_scenario
import rclpy
from rclpy.context import Context
import yaml


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
