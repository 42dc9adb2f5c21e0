"""
The rail scenario and the regime probabilities through the nodes (issue 11).

* The simulator's ``scenario:=rail`` publishes the run of the offline stream, the true
  acceleration on ``ground_truth_accel`` included, stamped as the ground truth.
* With ``rail_gnss_model`` receiver (the default) the measurements are the offline
  receiver's, each with its hAcc² as the variance, and its Doppler speed goes out on
  ``velocity`` with speedAcc².
* The estimator with ``preset:=rail`` publishes ``regime_probabilities`` after every
  estimate, the same numbers ``kf-train replay BAG`` writes into its output bag, and
  puts them into ``/diagnostics``; presets without regimes have no such topic.
"""

import os
import time

from geometry_msgs.msg import (
    AccelStamped, PoseWithCovarianceStamped, TwistWithCovarianceStamped)
from kf_train.cli import main as kf_train_main
from kf_train.io.bagio_simulation import measurement_message
from kf_train.io.bagio_types import POSE, TYPESTORE
from kf_train.ros import launch_params, messages
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.ros.simulator_node import SimulatorNode
from kf_train.sim import make_stream, rail_scenario
from nav_msgs.msg import Odometry
import numpy as np
import rclpy
from rclpy.parameter import Parameter
from ros_helpers import live_estimator_outputs, own_node, spin_until
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from std_msgs.msg import Float64MultiArray

NS = 1_000_000_000
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _add(executor, node):
    """Spin ``node`` in ``executor`` and destroy it after the test."""
    executor.add_node(node)
    own_node(node)
    return node


def test_the_rail_simulator_publishes_the_offline_run_and_its_acceleration(
        ros_context, executor):
    """
    Measurements, truth and true acceleration are the offline stream's, to the bit.

    The rail_* parameters reach the run: a 1-2 s dwell at the start, so the train is off
    within the 40 samples.
    """
    samples = 40
    simulator = _add(executor, SimulatorNode(context=ros_context, parameter_overrides=[
        Parameter('scenario', value='rail'), Parameter('seed', value=5),
        Parameter('rail_family', value='regional'), Parameter('rate_hz', value=10.0),
        Parameter('rail_line_speed_mps', value=30.0), Parameter('rail_dwell_min_s', value=1.0),
        Parameter('rail_dwell_max_s', value=2.0), Parameter('rail_gnss_model', value='white'),
        Parameter('real_time_factor', value=20.0), Parameter('max_samples', value=samples),
        Parameter('min_subscribers', value=1)]))
    probe = _add(executor, rclpy.create_node('probe', context=ros_context))
    received = {'ground_truth': [], 'ground_truth_accel': [], 'measurement': []}
    for topic, kind in (('ground_truth', Odometry), ('ground_truth_accel', AccelStamped),
                        ('measurement', PoseWithCovarianceStamped)):
        probe.create_subscription(kind, topic, received[topic].append, 100)
    assert spin_until(executor, lambda: simulator.done.done(), 30.0)
    assert spin_until(executor, lambda: all(len(m) == samples for m in received.values()),
                      5.0)
    stream = make_stream('rail', 10.0, 5, rail={'family': 'regional', 'line_speed_mps': 30.0,
                                                'dwell_s': (1.0, 2.0)})
    assert stream.parameters.line_speed_mps == 30.0 and stream.parameters.dwell_s == (1.0, 2.0)
    expected = [stream.next_sample() for _ in range(samples)]
    truth = [messages.from_odometry_msg(m) for m in received['ground_truth']]
    accel = received['ground_truth_accel']
    assert [t.position_m for t in truth] == [s.true_position_m for s in expected]
    assert [t.velocity_mps for t in truth] == [s.true_velocity_mps for s in expected]
    assert [m.accel.linear.x for m in accel] == [s.true_acceleration_mps2 for s in expected]
    assert [messages.from_measurement_msg(m).position_m for m in received['measurement']] \
        == [s.measured_position_m for s in expected]
    assert [messages.stamp_to_ns(m.header.stamp) for m in accel] == [t.stamp_ns for t in truth]
    assert {m.header.frame_id for m in accel} == {'base_link'}
    assert max(m.accel.linear.x for m in accel) > 0.0  # it left the station
    # Stamps stay 1/rate_hz apart however fast they went out.
    assert set(np.diff([t.stamp_ns for t in truth])) == {NS // 10}


def test_the_receiver_rail_simulator_publishes_hacc_and_the_doppler_speed(
        ros_context, executor):
    """The default receiver: positions, hAcc² and Doppler speed are the stream's, to the bit."""
    samples = 60
    simulator = _add(executor, SimulatorNode(context=ros_context, parameter_overrides=[
        Parameter('scenario', value='rail'), Parameter('seed', value=6),
        Parameter('real_time_factor', value=20.0), Parameter('max_samples', value=samples),
        Parameter('min_subscribers', value=1)]))
    stream = make_stream('rail', 10.0, 6, rail={'gnss_model': 'receiver'})
    expected = [stream.next_sample() for _ in range(samples)]
    fixes = [s for s in expected if s.measured_position_m is not None]
    probe = _add(executor, rclpy.create_node('probe', context=ros_context))
    received = {'measurement': [], 'velocity': []}
    for topic, kind in (('measurement', PoseWithCovarianceStamped),
                        ('velocity', TwistWithCovarianceStamped)):
        probe.create_subscription(kind, topic, received[topic].append, 100)
    assert spin_until(executor, lambda: simulator.done.done(), 30.0)
    assert spin_until(executor, lambda: (len(received['measurement']) == len(fixes)
                                         and len(received['velocity']) == len(fixes)), 5.0)
    measured = [messages.from_measurement_msg(m) for m in received['measurement']]
    assert [m.position_m for m in measured] == [s.measured_position_m for s in fixes]
    assert [m.variance_m2 for m in measured] == [s.measurement_variance_m2 for s in fixes]
    velocity = received['velocity']
    assert [m.twist.twist.linear.x for m in velocity] == [s.doppler_speed_mps for s in fixes]
    assert [m.twist.covariance[0] for m in velocity] == \
        [s.doppler_variance_m2_s2 for s in fixes]
    assert {m.header.frame_id for m in velocity} == {'base_link'}
    assert [messages.stamp_to_ns(m.header.stamp) for m in velocity] == \
        [messages.stamp_to_ns(m.header.stamp) for m in received['measurement']]


def _rail_sequence(base_ns):
    """Return (stamp_ns, position_m) of a rail run leaving a station, with faults."""
    scenario, _ = rail_scenario(11, 'metro')
    start = int(np.argmax(scenario.truth[:, 1] > 0.0)) - 20  # 2 s before it departs
    sequence = [(base_ns + round(t * NS), float(z))
                for t, z in zip(scenario.t_s[start:start + 80], scenario.z[start:start + 80, 0])]
    sequence[50] = (sequence[50][0], sequence[50][1] + 1e6)  # an outlier (gated)
    sequence[60], sequence[61] = sequence[61], sequence[60]  # out of order (fused late)
    return sequence


def _live(context, executor, sequence, parameters):
    """Send ``sequence`` to an in-process estimator; return (node, its outputs by topic)."""
    published = (lambda node: node.fused + node.corrections)
    return live_estimator_outputs(context, executor, sequence, parameters, {
        'estimate': (Odometry, published),
        'regime_probabilities': (Float64MultiArray, published)})


def _replayed(tmp_path, sequence, parameters):
    """Replay ``sequence`` from a bag; return the output bag's messages by topic."""
    last_ns = max(stamp for stamp, _ in sequence)
    with Writer(tmp_path / 'in', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/measurement', POSE, typestore=TYPESTORE)
        for i, (stamp_ns, position_m) in enumerate(sequence):
            writer.write(connection, last_ns + NS + i * 10_000_000, TYPESTORE.serialize_cdr(
                measurement_message(stamp_ns, 'odom', position_m, 1.0), POSE))
    argv = ['replay', str(tmp_path / 'in'), '--output', str(tmp_path / 'out.mcap')]
    for name, value in parameters.items():
        argv += ['-p', f'{name}:={value!r}' if isinstance(value, float) else f'{name}:={value}']
    assert kf_train_main(argv) == 0
    outputs = {}
    with Reader(tmp_path / 'out.mcap') as reader:
        for connection, _, raw in reader.messages():
            outputs.setdefault(connection.topic.lstrip('/'), []).append(
                TYPESTORE.deserialize_cdr(raw, connection.msgtype))
    return outputs


def test_regime_probabilities_live_equal_the_bag_replay_and_the_diagnostics(
        ros_context, executor, tmp_path):
    """With preset rail: one regime message per estimate, the replay's bit for bit."""
    base_ns = time.time_ns() - 120 * NS  # in the past: no stamp is in the node's future
    sequence = _rail_sequence(base_ns)
    parameters = {'preset': 'rail', 'gate_probability': 0.9999, 'history_s': 5.0}
    node, live = _live(ros_context, executor, sequence, parameters)
    # The 1e6 m outlier is gated (a departure's first metres may be too: the IMM was
    # sure the train stood); the swapped pair is fused late.
    assert node.rejected >= 1 and node.estimator.stats().out_of_sequence == 1
    assert max(m.pose.pose.position.x for m in live['estimate']) < 1e3
    replayed = _replayed(tmp_path, sequence, parameters)
    live_regimes = [messages.from_regime_msg(m) for m in live['regime_probabilities']]
    names = ('stand', 'accelerate', 'cruise', 'brake')
    assert len(live_regimes) == len(replayed['regime_probabilities']) \
        == len(live['estimate']) == len(sequence) - node.rejected
    for (live_names, live_p), msg in zip(live_regimes, replayed['regime_probabilities']):
        assert live_names == names == tuple(msg.layout.dim[0].label.split(','))
        assert msg.layout.dim[0].size == msg.layout.dim[0].stride == 4
        assert live_p == list(msg.data)
        # Probabilities: each in [0, 1], the sum 1 up to the rounding of 4 additions.
        assert min(live_p) >= 0.0 and abs(sum(live_p) - 1.0) <= 1e-12
    # Standing first, then the departure: the IMM moves from stand to accelerate.
    assert live_regimes[5][1][0] > 0.5
    assert live_regimes[-1][1][1] + live_regimes[-1][1][2] > 0.9
    # The last regime message matches the node's state, as /diagnostics shows it.
    status = node.session.diagnostics(time.time_ns())
    values = dict(status.values)
    assert values['regime'] == names[int(np.argmax(live_regimes[-1][1]))]
    for name, p in zip(names, live_regimes[-1][1]):
        assert values[f'regime.{name}'] == f'{p:.4f}'


def test_presets_without_regimes_have_no_regime_topic(ros_context, executor):
    """The train preset (a single KF) declares no regime publisher nor values."""
    node = _add(executor, EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('preset', value='train')]))
    assert node.regime_pub is None and node.regime_names == ()
    topics = dict(node.get_publisher_names_and_types_by_node('estimator', '/'))
    assert '/regime_probabilities' not in topics and '/estimate' in topics
    keys = [key for key, _ in node.session.diagnostics(time.time_ns()).values]
    assert not [key for key in keys if key.startswith('regime')]


def test_the_launch_file_starts_both_nodes_with_scenario_rail(ros_context, executor):
    """kf_train.launch.py scenario:=rail: the rail simulator, the rail preset (its name)."""
    config = launch_params.load_params_file(os.path.join(REPO, 'config', 'kf_train.yaml'))
    simulator_values = launch_params.simulator_parameters(config, '', 'rail', False)
    estimator_values = launch_params.estimator_parameters(config, '', 'rail', False)
    simulator = _add(executor, SimulatorNode(context=ros_context, parameter_overrides=[
        Parameter(name, value=value) for name, value in simulator_values.items()]))
    estimator = _add(executor, EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter(name, value=value) for name, value in estimator_values.items()]))
    assert simulator.scenario == 'rail' and simulator.truth_accel_pub is not None
    assert simulator.get_parameter('noise_std').value == 1.0
    assert estimator.preset.name == 'rail' and estimator.regime_pub is not None
