"""
The estimator node takes sensor_msgs/NavSatFix on a track file (measurement_type navsatfix).

A synthetic track (pyproj geodesics near Brussels) drawn against the direction of
travel; a train runs along it at 10 m/s with 1-m fixes, among them a no-fix, a fix
200 m off the track and fixes carrying their own covariance. Sent one by one to the
in-process node over DDS: x grows with the travel, the off-track fix and the no-fix
are counted in /diagnostics and never reach the filter.
"""

import json
import time

from geometry_msgs.msg import Vector3Stamped
from kf_train.cli import main as kf_train_main
from kf_train.io.bagio_types import NAVSATFIX, TYPESTORE
from kf_train.ros import messages
from nav_msgs.msg import Odometry
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from ros_helpers import estimator_and_probe, spin_until
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from sensor_msgs.msg import NavSatFix, NavSatStatus
from test_bag_replay_live import odometry_numbers, vector_numbers

pyproj = pytest.importorskip('pyproj')

NS = 1_000_000_000
PERIOD_NS = 400_000_000
SPEED_MPS = 10.0
START = (4.48, 50.90)                       # lon, lat
AZIMUTH_DEG = 60.0
GEOD = pyproj.Geod(ellps='WGS84')
OUTPUTS = {'estimate': Odometry, 'prediction': Odometry, 'innovation': Vector3Stamped}


def write_track(path, length_m=2000.0, step_m=100.0):
    """Write a straight GeoJSON track from its far end back to START (against the travel)."""
    points = [START]
    for _ in range(int(length_m / step_m)):
        lon, lat, _ = GEOD.fwd(*points[-1], AZIMUTH_DEG, step_m)
        points.append((lon, lat))
    path.write_text(json.dumps({'type': 'Feature', 'properties': {}, 'geometry': {
        'type': 'LineString', 'coordinates': [list(p) for p in points[::-1]]}}))
    return path


def fix_sequence(base_ns, count=60):
    """Return NavSatFix messages of a train from START along AZIMUTH_DEG, faults in."""
    rng = np.random.default_rng(3)
    fixes = []
    for k in range(count):
        along_m = 50.0 + SPEED_MPS * k * PERIOD_NS / NS + rng.normal(0.0, 1.0)
        lon, lat, _ = GEOD.fwd(*START, AZIMUTH_DEG, along_m)
        side_m = 200.0 if k == 30 else rng.normal(0.0, 1.0)      # k = 30: gross, sideways
        lon, lat, _ = GEOD.fwd(lon, lat, AZIMUTH_DEG - 90.0, side_m)
        msg = NavSatFix()
        msg.header.stamp = messages.ns_to_stamp(base_ns + k * PERIOD_NS)
        msg.header.frame_id = 'gps'
        msg.status.status = NavSatStatus.STATUS_NO_FIX if k == 20 else NavSatStatus.STATUS_FIX
        msg.latitude, msg.longitude, msg.altitude = lat, lon, 50.0
        if k >= 40:                              # its own covariance, ENU: 2 m east, 1 m north
            msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
            msg.position_covariance[0], msg.position_covariance[4] = 4.0, 1.0
        fixes.append(msg)
    return fixes


def live_fix_outputs(context, executor, fixes, parameters):
    """Send the fixes one by one to an in-process node; return (node, outputs by topic)."""
    node, publishers, outputs = estimator_and_probe(
        context, executor, parameters, {'measurement': NavSatFix}, OUTPUTS)
    counts = node.session.track.fixes.counts
    for sent, msg in enumerate(fixes, start=1):
        publishers['measurement'].publish(msg)
        assert spin_until(executor, lambda: counts.fixes == sent, 5.0)
        assert spin_until(executor, lambda: len(outputs['estimate']) == node.session.fused
                          and len(outputs['prediction']) == node.session.fused
                          and len(outputs['innovation']) == node.session.innovations, 5.0)
    return node, outputs


def test_navsatfix_on_a_track_drawn_against_the_travel(ros_context, executor, tmp_path):
    """Along-track x grows with the travel; off-track and no-fix are counted, not fused."""
    track = write_track(tmp_path / 'track.geojson')
    fixes = fix_sequence(time.time_ns() - 60 * NS)
    node, outputs = live_fix_outputs(ros_context, executor, fixes, {
        'measurement_type': 'navsatfix', 'track': str(track), 'history_s': 5.0})
    estimates = outputs['estimate']
    counts = node.session.track.fixes.counts
    assert counts.direction == 'reverse'
    assert counts.no_fix == 1 and counts.off_track == 1
    assert counts.fused == len(fixes) - 2 == node.session.received
    x = np.array([m.pose.pose.position.x for m in estimates])
    assert len(x) == node.session.fused > 50
    # Along the reversed track x is the distance from START: 50 m + 10 m/s t, 1-m noise.
    t_s = np.array([messages.stamp_to_ns(m.header.stamp) - messages.stamp_to_ns(
        fixes[0].header.stamp) for m in estimates]) / NS
    assert np.all(np.abs(x - (50.0 + SPEED_MPS * t_s))[10:] < 5.0)
    assert x[-1] > x[0] + 200.0
    values = dict(node.session.diagnostics(0).values)
    assert values['fixes.off_track'] == '1' and values['fixes.no_fix'] == '1'
    assert values['track_direction'] == 'reverse'


def test_known_covariance_is_projected_on_the_track(ros_context, executor, tmp_path):
    """A DIAGONAL_KNOWN covariance's along-track form is the variance fused."""
    track = write_track(tmp_path / 'track.geojson')
    fixes = fix_sequence(time.time_ns() - 60 * NS, count=50)
    node, _ = live_fix_outputs(ros_context, executor, fixes, {
        'measurement_type': 'navsatfix', 'track': str(track), 'track_direction': 'reverse'})
    # Bearing 60° (the reversed track's, as the travel): sin² 60° 4 + cos² 60° 1 = 3.25.
    assert node.session.track.last_measurement.variance_m2 == pytest.approx(3.25, abs=0.01)
    assert node.session.track.fixes.counts.direction == 'reverse'
    assert node.session.fused == len(fixes) - 2       # no pending with a direction given


def replay_fix_outputs(tmp_path, fixes, track, overrides):
    """Replay the fixes from a bag (topic /fix) with --track; return the output topics."""
    last_ns = max(messages.stamp_to_ns(m.header.stamp) for m in fixes)
    with Writer(tmp_path / 'in', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/fix', NAVSATFIX, typestore=TYPESTORE)
        for i, msg in enumerate(fixes):    # recorded after the last stamp, in sending order
            writer.write(connection, last_ns + NS + i * 10_000_000, serialize_message(msg))
    argv = ['replay', str(tmp_path / 'in'), '--output', str(tmp_path / 'out.mcap'),
            '--track', str(track)]
    for assignment in overrides:
        argv += ['-p', assignment]
    assert kf_train_main(argv) == 0
    outputs = {'estimate': [], 'prediction': [], 'innovation': []}
    with Reader(tmp_path / 'out.mcap') as reader:
        for c, _, raw in reader.messages():
            name = c.topic.lstrip('/')
            if name in outputs:
                outputs[name].append(TYPESTORE.deserialize_cdr(raw, c.msgtype))
    return outputs


def live_and_replayed(context, executor, tmp_path, track):
    """Send the fixes live and from a bag on a track or network file; assert bit-equal."""
    fixes = fix_sequence(time.time_ns() - 60 * NS)
    node, live = live_fix_outputs(context, executor, fixes, {
        'measurement_type': 'navsatfix', 'track': str(track), 'history_s': 5.0})
    replayed = replay_fix_outputs(tmp_path, fixes, track, ['history_s:=5.0'])
    for topic, numbers in (('estimate', odometry_numbers), ('prediction', odometry_numbers),
                           ('innovation', vector_numbers)):
        assert len(live[topic]) == len(replayed[topic]) > 50, topic
        assert [numbers(m) for m in live[topic]] == [numbers(m) for m in replayed[topic]]
    return fixes, node, live


def test_navsatfix_live_and_bag_replay_are_bit_equal(ros_context, executor, tmp_path):
    """The same fixes live and from a bag: the same estimates, predictions, innovations."""
    track = write_track(tmp_path / 'track.geojson')
    _, node, _ = live_and_replayed(ros_context, executor, tmp_path, track)
    assert node.session.track.fixes.counts.off_track == 1


def write_network(path, switch_m=150.0):
    """Write a network: A from START to a switch, B straight on, C diverging 8°."""
    switch = GEOD.fwd(*START, AZIMUTH_DEG, switch_m)[:2]
    a = [START, switch]
    b = [switch, GEOD.fwd(*switch, AZIMUTH_DEG, 1000.0)[:2]]
    c = [switch, GEOD.fwd(*switch, AZIMUTH_DEG + 8.0, 1000.0)[:2]]
    path.write_text(json.dumps({'type': 'FeatureCollection', 'features': [
        {'type': 'Feature', 'properties': {'id': name},
         'geometry': {'type': 'LineString', 'coordinates': [list(p) for p in line]}}
        for name, line in (('A', a), ('B', b[::-1]), ('C', c))]}))
    return path


def test_navsatfix_on_a_network_live_and_replayed(ros_context, executor, tmp_path):
    """A network: the path chosen live, through the switch onto B; bit-equal from a bag."""
    network = write_network(tmp_path / 'network.geojson')
    fixes, node, live = live_and_replayed(ros_context, executor, tmp_path, network)
    counts = node.session.track.fixes.counts
    assert counts.no_fix == 1 and counts.off_track == 1
    assert counts.fused == len(fixes) - 2 == node.session.received
    values = dict(node.session.diagnostics(0).values)
    assert values['track_element'] == 'B' and values['track_direction'] == 'forward'
    # x from the first fix (50 m from START, 1-m noise), growing with the travel.
    x = np.array([m.pose.pose.position.x for m in live['estimate']])
    t_s = np.array([messages.stamp_to_ns(m.header.stamp) - messages.stamp_to_ns(
        fixes[0].header.stamp) for m in live['estimate']]) / NS
    assert np.all(np.abs(x - SPEED_MPS * t_s)[10:] < 5.0)
