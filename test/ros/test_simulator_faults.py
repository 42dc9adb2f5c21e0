"""
Fault injection through the nodes: the simulator and the estimator in one process.

They compare with the core run offline on exactly what the simulator delivered; the core's
own fault tests are in test/unit/test_faults.py.
"""

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.estimator import Rejected, StreamEstimator
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.ros.messages import from_measurement_msg, stamp_to_ns
from kf_train.ros.simulator_node import SimulatorNode
from kf_train.sim import FaultSettings
from nav_msgs.msg import Odometry
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
import ros_helpers


def _pipeline(ros_context, executor, simulator_parameters, estimator_parameters=None):
    """Return (simulator, estimator, delivered measurements) nodes spinning in executor."""
    simulator = SimulatorNode(context=ros_context, parameter_overrides=[
        Parameter('rate_hz', value=50.0), Parameter('min_subscribers', value=2),
        *[Parameter(k, value=v) for k, v in simulator_parameters.items()]])
    estimator = EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter(k, value=v) for k, v in (estimator_parameters or {}).items()])
    tap = rclpy.create_node('tap', context=ros_context)
    delivered = []
    tap.create_subscription(PoseWithCovarianceStamped, 'measurement', delivered.append, 100)
    for node in (simulator, estimator, tap):
        executor.add_node(node)
        ros_helpers.own_node(node)
    return simulator, estimator, delivered


def test_simulator_and_estimator_nodes_with_every_fault(ros_context, executor):
    """
    Run dropouts, outliers, delay and reordering end to end through both nodes.

    The node's final estimate is the core's in-order result over what the simulator
    delivered, outliers excluded.
    """
    simulator, estimator, delivered = _pipeline(ros_context, executor, {
        'max_samples': 150, 'dropout_probability': 0.1, 'outlier_probability': 0.05,
        'outlier_size_m': 30.0, 'delay_s': 0.05, 'reorder_probability': 0.15},
        {'gate_probability': 0.9999})  # the node's default (rail IMM, gate 0.9999)
    estimates = []
    listener = rclpy.create_node('listener', context=ros_context)
    listener.create_subscription(Odometry, 'estimate', estimates.append, 100)
    executor.add_node(listener)
    ros_helpers.own_node(listener)
    assert ros_helpers.spin_until(executor, lambda: simulator.done.done(), 30.0)
    assert ros_helpers.spin_until(
        executor, lambda: estimator.received == simulator.delivered == len(delivered), 5.0)
    faults = simulator.faults
    assert faults.dropped > 0 and faults.outliers > 0 and faults.reordered > 0
    assert simulator.delivered == 150 - faults.dropped
    measurements = [from_measurement_msg(m) for m in delivered]
    outliers = estimator.estimator.stats().rejections['outlier']
    assert outliers > 0 and outliers == estimator.rejected
    offline = StreamEstimator(estimator.estimator.settings)
    rejected = set()
    for m in sorted(measurements, key=lambda m: m.stamp_ns):
        try:
            offline.process(m.stamp_ns, m.position_m, m.variance_m2)
        except Rejected:
            rejected.add(m.stamp_ns)
    assert len(rejected) == outliers
    # In arrival order, a fused measurement older than the newest fused one came late.
    newest, late = 0, 0
    for m in measurements:
        if m.stamp_ns not in rejected:
            late += m.stamp_ns < newest
            newest = max(newest, m.stamp_ns)
    assert estimator.estimator.stats().out_of_sequence == late > 0
    np.testing.assert_allclose(estimator.estimator.state[0], offline.state[0], rtol=1e-9,
                               atol=1e-9)
    assert ros_helpers.spin_until(executor, lambda: len(estimates) == estimator.fused, 5.0)
    assert stamp_to_ns(estimates[-1].header.stamp) == offline.last_stamp_ns
    assert estimates[-1].pose.pose.position.x == pytest.approx(offline.state[0][0], abs=1e-9)


def test_fault_parameters_change_at_runtime(ros_context):
    """Fault parameters are live; out-of-range values are refused and the old ones stay."""
    simulator = SimulatorNode(context=ros_context)
    ros_helpers.own_node(simulator)
    assert simulator.faults.settings == FaultSettings()
    assert simulator.clock_pub is None  # /clock is advertised only with publish_clock
    results = simulator.set_parameters([Parameter('dropout_probability', value=0.25),
                                        Parameter('measurement_bias_m', value=-1.5)])
    assert all(r.successful for r in results)
    assert simulator.faults.settings == FaultSettings(dropout_probability=0.25, bias_m=-1.5)
    for name, value in (('outlier_probability', 1.5), ('delay_s', -1.0),
                        ('reorder_probability', 'often')):
        assert not simulator.set_parameters([Parameter(name, value=value)])[0].successful
    assert simulator.faults.settings == FaultSettings(dropout_probability=0.25, bias_m=-1.5)


def test_a_simulated_clock_jump_resets_the_estimator(ros_context, executor):
    """With publish_clock and use_sim_time, a backwards jump of /clock resets the filter once."""
    simulator, estimator, _ = _pipeline(
        ros_context, executor,
        {'max_samples': 100, 'publish_clock': True, 'clock_jump_at_s': 1.0, 'clock_jump_s': -30.0},
        {'use_sim_time': True})
    assert ros_helpers.spin_until(executor, lambda: simulator.done.done(), 30.0)
    assert ros_helpers.spin_until(executor, lambda: estimator.received == 100, 5.0)
    resets = estimator.estimator.stats().resets
    assert resets['clock_jump'] == 1, resets
    assert resets['stream_restart'] == 0
    # It fused the stream after the jump: everything but at most a sample in flight.
    assert estimator.fused >= 98 and estimator.estimator.initialized
