"""
The rail estimator node fuses a ``velocity`` topic, and ``kf-train replay BAG`` equals it.

A measured speed (a GNSS Doppler) comes as geometry_msgs/TwistWithCovarianceStamped
(the default ``velocity_type``) or TwistStamped with ``measurement_velocity_variance``.
One sequence of positions and speeds with faults (a speed before its own position, a
late speed, a gross speed, a non-finite one) goes to the in-process node over DDS one
message at a time, and into a bag replayed with ``--velocity-topic``; every
``estimate`` and ``prediction`` must be equal to the bit.
"""

import math
import time

from geometry_msgs.msg import (
    PoseWithCovarianceStamped, TwistStamped, TwistWithCovarianceStamped, Vector3Stamped)
from kf_train.cli import main as kf_train_main
from kf_train.io.bagio_types import POSE, TWIST_COVARIANCE, TYPESTORE
from kf_train.ros import messages
from nav_msgs.msg import Odometry
import numpy as np
from ros_helpers import estimator_and_probe, spin_until
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from test_bag_replay_live import bag_message, odometry_numbers, vector_numbers

NS = 1_000_000_000
PERIOD_NS = 100_000_000
SPEED_VARIANCE = 0.01
OUTPUTS = {'estimate': Odometry, 'prediction': Odometry, 'innovation': Vector3Stamped}
T = TYPESTORE.types


def speed_sequence(base_ns):
    """Return events ('position' or 'velocity', stamp_ns, value) of a 10-m/s train, faults in."""
    events = []
    for k in range(1, 41):
        stamp = base_ns + k * PERIOD_NS
        events.append(('position', stamp, 10.0 * k * PERIOD_NS / NS + 0.3 * math.sin(k)))
        events.append(('velocity', stamp, 10.0 + 0.05 * math.cos(3 * k)))
    events[30], events[31] = events[31], events[30]     # a speed before its own position
    events.insert(50, events.pop(41))                    # a speed 4 epochs late
    events[61] = ('velocity', events[61][1], 60.0)       # a gross speed (gated)
    events[71] = ('velocity', events[71][1], math.nan)   # a non-finite speed (refused)
    return events


def _velocity_msg(stamp_ns, speed_mps, kind=TwistWithCovarianceStamped):
    """Return the ROS message of a measured speed (with SPEED_VARIANCE when it has one)."""
    msg = kind()
    msg.header.stamp = messages.ns_to_stamp(stamp_ns)
    msg.header.frame_id = 'base_link'
    if kind is TwistStamped:
        msg.twist.linear.x = float(speed_mps)
    else:
        msg.twist.twist.linear.x = float(speed_mps)
        msg.twist.covariance[0] = SPEED_VARIANCE
    return msg


def live_outputs(context, executor, events, parameters, kind=TwistWithCovarianceStamped):
    """Send ``events`` one by one to an in-process node; return (node, outputs by topic)."""
    node, publishers, outputs = estimator_and_probe(
        context, executor, parameters,
        {'measurement': PoseWithCovarianceStamped, 'velocity': kind}, OUTPUTS)
    position_pub, velocity_pub = publishers['measurement'], publishers['velocity']
    session = node.session
    for what, stamp_ns, value in events:
        received = session.received + session.velocities_received
        if what == 'position':
            position_pub.publish(messages.to_measurement_msg(stamp_ns, 'odom', value, 1.0))
        else:
            velocity_pub.publish(_velocity_msg(stamp_ns, value, kind))
        assert spin_until(executor, lambda: session.received + session.velocities_received
                          == received + 1, 5.0)
        published = session.fused + session.velocities_fused
        assert spin_until(executor, lambda: len(outputs['estimate']) == published
                          and len(outputs['prediction']) == published
                          and len(outputs['innovation']) == session.innovations, 5.0)
    return node, outputs


def test_the_rail_node_fuses_speeds_with_their_covariance(ros_context, executor):
    """By default a TwistWithCovarianceStamped's speed and variance are fused."""
    base_ns = time.time_ns() - 60 * NS
    events = [event for event in speed_sequence(base_ns)[:40] if not math.isnan(event[2])]
    node, outputs = live_outputs(ros_context, executor, events, {'history_s': 5.0})
    stats = node.estimator.stats()
    assert stats.velocities['fused'] == node.session.velocities_fused == 20
    assert stats.velocities['out_of_sequence'] == 0 and stats.out_of_sequence == 1
    # 10 m/s measured to 0.1 m/s: the estimate's speed is near it, its variance small.
    assert abs(outputs['estimate'][-1].twist.twist.linear.x - 10.0) < 0.5
    assert outputs['estimate'][-1].twist.covariance[0] < 0.05
    values = dict(node.session.diagnostics(0).values)
    assert values['velocities_fused'] == '20'


def test_twist_stamped_speeds_take_the_parameters_variance(ros_context, executor):
    """velocity_type twist: TwistStamped, R = measurement_velocity_variance."""
    base_ns = time.time_ns() - 60 * NS
    events = speed_sequence(base_ns)[:20]
    node, outputs = live_outputs(ros_context, executor, events, {
        'history_s': 5.0, 'velocity_type': 'twist',
        'measurement_velocity_variance': SPEED_VARIANCE}, TwistStamped)
    assert node.session.velocities_fused == node.estimator.stats().velocities['fused'] == 10
    assert len(outputs['estimate']) == 20
    assert abs(outputs['estimate'][-1].twist.twist.linear.x - 10.0) < 0.5


def replay_outputs(tmp_path, events, parameters):
    """Replay ``events`` from a bag (speeds on /speed); return the output bag's topics."""
    last_stamp_ns = max(stamp for _, stamp, _ in events)
    with Writer(tmp_path / 'in', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        positions = writer.add_connection('/measurement', POSE, typestore=TYPESTORE)
        speeds = writer.add_connection('/speed', TWIST_COVARIANCE, typestore=TYPESTORE)
        for i, (what, stamp_ns, value) in enumerate(events):
            record_ns = last_stamp_ns + NS + i * 10_000_000   # sending order, as live
            if what == 'position':
                writer.write(positions, record_ns,
                             TYPESTORE.serialize_cdr(bag_message(stamp_ns, value), POSE))
            else:
                writer.write(speeds, record_ns, TYPESTORE.serialize_cdr(
                    _bag_velocity(stamp_ns, value), TWIST_COVARIANCE))
    argv = ['replay', str(tmp_path / 'in'), '--output', str(tmp_path / 'out.mcap'),
            '--velocity-topic', 'speed']
    for name, value in parameters.items():
        argv += ['-p', f'{name}:={value!r}']
    assert kf_train_main(argv) == 0
    outputs = {'estimate': [], 'prediction': [], 'innovation': []}
    with Reader(tmp_path / 'out.mcap') as reader:
        for c, _, raw in reader.messages():
            name = c.topic.lstrip('/')
            if name in outputs:
                outputs[name].append(TYPESTORE.deserialize_cdr(raw, c.msgtype))
    return outputs


def _bag_velocity(stamp_ns, speed_mps):
    """Return the rosbags TwistWithCovarianceStamped of a measured speed."""
    sec, nanosec = divmod(stamp_ns, NS)
    covariance = np.zeros(36)
    covariance[0] = SPEED_VARIANCE
    zero = T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0)
    return T[TWIST_COVARIANCE](
        header=T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
            sec=sec, nanosec=nanosec), frame_id='base_link'),
        twist=T['geometry_msgs/msg/TwistWithCovariance'](
            twist=T['geometry_msgs/msg/Twist'](
                linear=T['geometry_msgs/msg/Vector3'](x=speed_mps, y=0.0, z=0.0),
                angular=zero), covariance=covariance))


def test_live_speeds_and_bag_replay_with_a_velocity_topic_are_bit_equal(
        ros_context, executor, tmp_path):
    """Same positions and speeds, same parameters: the same outputs, faults included."""
    base_ns = time.time_ns() - 60 * NS
    events = speed_sequence(base_ns)
    parameters = {'history_s': 5.0}
    node, live = live_outputs(ros_context, executor, events, parameters)
    stats = node.estimator.stats()
    assert stats.velocities['out_of_sequence'] >= 1
    assert stats.velocity_rejections['outlier'] == stats.velocity_rejections['non_finite'] == 1
    assert sum(stats.resets.values()) == 0
    replayed = replay_outputs(tmp_path, events, parameters)
    for topic, numbers in (('estimate', odometry_numbers), ('prediction', odometry_numbers),
                           ('innovation', vector_numbers)):
        assert len(live[topic]) == len(replayed[topic]) > 30, topic
        assert [numbers(m) for m in live[topic]] == [numbers(m) for m in replayed[topic]]
    assert len(live['estimate']) == stats.fused + stats.velocities['fused'] == 40 + 38
