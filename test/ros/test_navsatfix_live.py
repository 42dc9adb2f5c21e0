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

from kf_train.ros import messages
from kf_train.ros.estimator_node import EstimatorNode
from nav_msgs.msg import Odometry
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from ros_helpers import own_node, spin_until
from sensor_msgs.msg import NavSatFix, NavSatStatus

pyproj = pytest.importorskip('pyproj')

NS = 1_000_000_000
PERIOD_NS = 400_000_000
SPEED_MPS = 10.0
START = (4.48, 50.90)                       # lon, lat
AZIMUTH_DEG = 60.0
GEOD = pyproj.Geod(ellps='WGS84')


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
    """Send the fixes one by one to an in-process node; return (node, estimates)."""
    node = own_node(EstimatorNode(context=context, parameter_overrides=[
        Parameter(name, value=value) for name, value in parameters.items()]))
    probe = own_node(rclpy.create_node('probe', context=context))
    executor.add_node(node)
    executor.add_node(probe)
    publisher = probe.create_publisher(NavSatFix, 'measurement', 10)
    estimates = []
    probe.create_subscription(Odometry, 'estimate', estimates.append, 1000)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1
                      and node.estimate_pub.get_subscription_count() == 1, 10.0)
    counts = node.session.track.fixes.counts
    for sent, msg in enumerate(fixes, start=1):
        publisher.publish(msg)
        assert spin_until(executor, lambda: counts.fixes == sent, 5.0)
        assert spin_until(executor, lambda: len(estimates) == node.session.fused, 5.0)
    return node, estimates


def test_navsatfix_on_a_track_drawn_against_the_travel(ros_context, executor, tmp_path):
    """Along-track x grows with the travel; off-track and no-fix are counted, not fused."""
    track = write_track(tmp_path / 'track.geojson')
    fixes = fix_sequence(time.time_ns() - 60 * NS)
    node, estimates = live_fix_outputs(ros_context, executor, fixes, {
        'measurement_type': 'navsatfix', 'track': str(track), 'history_s': 5.0})
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
