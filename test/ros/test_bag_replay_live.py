"""
The live estimator node and ``kf-train replay BAG`` publish the same numbers, bit for bit.

One message sequence with faults in it (an outlier, a non-finite value, an
out-of-order pair, a duplicate stamp) goes to the in-process node over DDS, one
message at a time, and into a bag replayed with the same parameters; every
``estimate``, ``prediction`` and ``innovation`` must be equal.
"""

import math
import time

from geometry_msgs.msg import Vector3Stamped
from kf_train.cli import main as kf_train_main
from kf_train.io.bagio_types import POSE, TYPESTORE
from nav_msgs.msg import Odometry
import numpy as np
import pytest
from ros_helpers import live_estimator_outputs
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

NS = 1_000_000_000
PERIOD_NS = 100_000_000
T = TYPESTORE.types


def fault_sequence(base_ns):
    """Return (stamp_ns, position_m) of 40 measurements of a 10 m/s train, with faults."""
    def good(k):
        return base_ns + k * PERIOD_NS, 10.0 * k * PERIOD_NS / NS + 0.3 * math.sin(k)
    sequence = [good(k) for k in range(1, 41)]
    sequence[25] = (sequence[25][0], sequence[25][1] + 200.0)  # an outlier (gated)
    sequence[14] = (sequence[14][0], math.nan)  # a non-finite value (refused)
    sequence[20], sequence[21] = sequence[21], sequence[20]  # out of order (fused late)
    sequence.insert(30, sequence[29])  # a duplicate stamp (refused)
    return sequence


def bag_message(stamp_ns, position_m):
    """Return the rosbags PoseWithCovarianceStamped the simulator would send."""
    sec, nanosec = divmod(stamp_ns, NS)
    covariance = [0.0] * 36
    for i in range(6):
        covariance[7 * i] = 1e9
    covariance[0] = 1.0
    return T[POSE](
        header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
            sec=sec, nanosec=nanosec), frame_id='odom'),
        pose=T['geometry_msgs/msg/PoseWithCovariance'](
            pose=T['geometry_msgs/msg/Pose'](
                position=T['geometry_msgs/msg/Point'](x=position_m, y=0.0, z=0.0),
                orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.array(covariance)))


def live_outputs(context, executor, sequence, parameters):
    """Send ``sequence`` to an in-process node; return its outputs by topic."""
    published = (lambda node: node.fused + node.corrections)
    node, outputs = live_estimator_outputs(context, executor, sequence, parameters, {
        'estimate': (Odometry, published), 'prediction': (Odometry, published),
        'innovation': (Vector3Stamped, lambda node: node.innovations)})
    assert node.rejected >= 3 and node.estimator.stats().out_of_sequence >= 1
    return outputs


def replay_outputs(tmp_path, sequence, parameters):
    """Replay ``sequence`` from a bag with ``parameters``; return the output bag's topics."""
    last_stamp_ns = max(stamp for stamp, _ in sequence)
    with Writer(tmp_path / 'in', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/measurement', POSE, typestore=TYPESTORE)
        for i, (stamp_ns, position_m) in enumerate(sequence):
            # Recorded in sending order, after every stamp (as the live node's clock is).
            writer.write(connection, last_stamp_ns + NS + i * 10_000_000,
                         TYPESTORE.serialize_cdr(bag_message(stamp_ns, position_m), POSE))
    argv = ['replay', str(tmp_path / 'in'), '--output', str(tmp_path / 'out.mcap')]
    for name, value in parameters.items():
        argv += ['-p', f'{name}:={value!r}' if isinstance(value, float) else
                 f'{name}:={value}']
    assert kf_train_main(argv) == 0
    outputs = {'estimate': [], 'prediction': [], 'innovation': []}
    with Reader(tmp_path / 'out.mcap') as reader:
        for c, _, raw in reader.messages():
            name = c.topic.lstrip('/')
            if name in outputs:
                outputs[name].append(TYPESTORE.deserialize_cdr(raw, c.msgtype))
    return outputs


def odometry_numbers(msg):
    """Return an Odometry's stamp and the numbers the estimator fills."""
    return (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.pose.pose.position.x,
            msg.twist.twist.linear.x, msg.pose.covariance[0], msg.twist.covariance[0])


def vector_numbers(msg):
    """Return a Vector3Stamped's stamp and vector."""
    return (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.vector.x, msg.vector.y,
            msg.vector.z)


@pytest.mark.parametrize('parameters', [
    {'preset': 'train', 'process_noise_density': 0.5, 'history_s': 5.0,
     'gate_probability': 0.9999},
    {'history_s': 5.0},  # the defaults: the rail IMM, the gate at 0.9999
])
def test_live_node_and_bag_replay_are_bit_equal(ros_context, executor, tmp_path, parameters):
    """Same messages, same parameters: the same estimates, predictions and innovations."""
    base_ns = time.time_ns() - 60 * NS  # in the past: no stamp is in the node's future
    sequence = fault_sequence(base_ns)
    live = live_outputs(ros_context, executor, sequence, parameters)
    replayed = replay_outputs(tmp_path, sequence, parameters)
    for topic, numbers in (('estimate', odometry_numbers), ('prediction', odometry_numbers),
                           ('innovation', vector_numbers)):
        assert len(live[topic]) == len(replayed[topic]) > 30, topic
        assert [numbers(m) for m in live[topic]] == [numbers(m) for m in replayed[topic]]
    # The outlier's innovation was published with NIS above the gate, and not fused.
    assert max(m.vector.z for m in live['innovation']) > 100.0
