"""The estimator node takes the params file ``kf-train tune`` writes (rclpy in-process)."""

import contextlib
import io

from kf_train.cli.tune import main as tune_main
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.sim import white_noise_acceleration_scenario
import rclpy
from rclpy.context import Context
import yaml


def _tune(directory, t_s, z_m, preset_args=()) -> str:
    """Write (t, z) as a CSV, run kf-train tune on it quietly; return the params file path."""
    path = directory / 'in.csv'
    path.write_text('t,z_position\n' + ''.join(
        f'{t!r},{z!r}\n' for t, z in zip(t_s.tolist(), z_m.tolist())))
    params = directory / 'params.yaml'
    with contextlib.redirect_stdout(io.StringIO()):
        assert tune_main([*preset_args, str(path), '--output', str(params)]) == 0
    return str(params)


@contextlib.contextmanager
def _node_from(params: str, domain_id: int):
    """Yield an EstimatorNode started with ``--ros-args --params-file params``."""
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', params], context=context,
               domain_id=domain_id)
    try:
        node = EstimatorNode(context=context)
        yield node
        node.destroy_node()
    finally:
        context.try_shutdown()


def _tuned_values(params: str) -> dict:
    """Return the node parameters a params file sets."""
    with open(params) as stream:
        return yaml.safe_load(stream)['estimator']['ros__parameters']


def test_the_estimator_node_takes_the_params_file(tmp_path, domain_id):
    """``--ros-args --params-file PARAMS.yaml`` sets the node's parameters to the tuned values."""
    scenario = white_noise_acceleration_scenario(0.5, 1.0, 300, seed=11)
    params = _tune(tmp_path, scenario.t_s, scenario.z[:, 0], ('--preset', 'train'))
    values = _tuned_values(params)
    with _node_from(params, domain_id) as node:
        for name, value in values.items():
            assert node.get_parameter(name).value == value, name


def test_the_estimator_node_runs_the_tuned_rail_preset(tmp_path, domain_id):
    """The default preset (rail): the params file points the node at the tuned rail preset."""
    from kf_train.sim.rail import rail_scenario
    scenario, _ = rail_scenario(seed=21, family='metro')
    rows = 1200                                     # 120 s at 10 Hz: a departure and a stop
    params = _tune(tmp_path, scenario.t_s[:rows], scenario.z[:rows, 0])
    values = _tuned_values(params)
    with open(values['preset']) as stream:
        tuned = yaml.safe_load(stream)
    with _node_from(params, domain_id) as node:
        for name, value in values.items():
            assert node.get_parameter(name).value == value, name
        assert node.preset.name == 'rail-tuned'
        for name in ('acceleration_noise', 'command_noise'):
            assert getattr(node.preset.parameters, name) == tuned['parameters'][name]
