"""
The live estimator node's /diagnostics tells which way to move q (rclpy in-process).

The node runs with a q that does not fit its measurements (a random-force train with
q = 2 while the node runs q = 0; a train at constant speed while it runs q = 200); a
probe feeds it the measurements one at a time (waiting until each is taken: the
subscription is best effort) and echoes /diagnostics until the suggestion is in it.
The diagnostics start after the feed (``diagnostics_period_s`` set live from an hour to
0.1 s), so the first suggestion is computed on the whole window, whatever the timing.
"""

import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.estimator import NS_PER_S
from kf_train.ros import messages
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.sim import white_noise_acceleration_scenario
import pytest
import rclpy
from rclpy.parameter import Parameter
from ros_helpers import spin_until

ROWS = 150


@pytest.mark.parametrize('q_true, node_q, way', [(2.0, 0.0, 'increase q'),
                                                 (0.0, 200.0, 'decrease q')])
def test_diagnostics_suggest_which_way_to_move_q(ros_context, executor, q_true, node_q, way):
    """The suggested q's interval holds the true q and the advice points the right way."""
    node = EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('process_noise_density', value=node_q),
        Parameter('noise_suggestion_window', value=ROWS),
        Parameter('diagnostics_period_s', value=3600.0)])
    probe = rclpy.create_node('probe', context=ros_context)
    publisher = probe.create_publisher(PoseWithCovarianceStamped, 'measurement', 10)
    echoed = []
    probe.create_subscription(DiagnosticArray, '/diagnostics', echoed.append, 100)
    for each in (node, probe):
        executor.add_node(each)
    try:
        assert spin_until(executor, lambda: publisher.get_subscription_count() == 1
                          and node.diagnostics_pub.get_subscription_count() >= 1, 10.0)
        scenario = white_noise_acceleration_scenario(q_true, 1.0, ROWS, seed=21)
        base_ns = time.time_ns() - 60 * NS_PER_S      # in the past: no future-stamp check
        for t, z in zip(scenario.t_s.tolist(), scenario.z[:, 0].tolist()):
            received = node.received
            publisher.publish(messages.to_measurement_msg(
                base_ns + round(t * NS_PER_S), 'odom', z, 1.0))
            assert spin_until(executor, lambda: node.received == received + 1, 5.0)
        assert node.fused == ROWS
        assert node.set_parameters([Parameter('diagnostics_period_s', value=0.1)])[0].successful

        def suggested():
            for array in reversed(echoed):
                values = {kv.key: kv.value for kv in array.status[0].values}
                if values.get('suggested_process_noise_window') == str(ROWS - 1):
                    return array.status[0], values
            return None
        assert spin_until(executor, lambda: suggested() is not None, 10.0)
        status, values = suggested()
    finally:
        executor.remove_node(node)
        executor.remove_node(probe)
        node.destroy_node()
        probe.destroy_node()
    low = float(values['suggested_process_noise_density_low_95'])
    high = float(values['suggested_process_noise_density_high_95'])
    assert low <= q_true <= high and not low <= node_q <= high
    assert values['process_noise_advice'].startswith(way)
    assert status.message.endswith(values['process_noise_advice'])
    assert f'now {node_q:g}' in status.message
