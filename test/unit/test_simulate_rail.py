"""``kf-train simulate --scenario rail``: the rail run, its true acceleration, bag and CSV."""

import csv

from kf_train.cli import main as kf_train_main
from kf_train.io.bagio_types import ACCEL, ODOMETRY, POSE, TWIST_COVARIANCE, TYPESTORE
from kf_train.sim import make_stream, rail_scenario
import numpy as np
from rosbags.rosbag2 import Reader

NS = 1_000_000_000


def test_rail_csv_is_rail_scenario_with_the_true_acceleration(tmp_path):
    """Seed 3, regional: every column is rail_scenario's, to the last digit."""
    path = tmp_path / 'rail.csv'
    assert kf_train_main(['simulate', '--scenario', 'rail', '--seed', '3', '--duration', '60',
                          '-p', 'rail_family:=regional', '-p', 'rail_gnss_model:=white',
                          '--output', str(path)]) == 0
    with open(path, newline='') as stream:
        rows = list(csv.DictReader(stream))
    assert list(rows[0]) == ['t', 'z_position', 'true_position', 'true_velocity',
                             'true_acceleration']
    scenario, _ = rail_scenario(3, 'regional')
    table = np.array([[float(row[k]) for k in rows[0]] for row in rows])
    assert len(rows) == 600
    np.testing.assert_array_equal(table[:, 0], scenario.t_s[:600])
    np.testing.assert_array_equal(table[:, 1], scenario.z[:600, 0])
    np.testing.assert_array_equal(table[:, 2:], scenario.truth[:600])


def test_rail_csv_defaults_to_the_receiver(tmp_path):
    """The default GNSS model is the receiver: rail_scenario(..., gnss_model='receiver')."""
    path = tmp_path / 'rail.csv'
    assert kf_train_main(['simulate', '--scenario', 'rail', '--seed', '4', '--duration', '300',
                          '--output', str(path)]) == 0
    with open(path, newline='') as stream:
        rows = list(csv.DictReader(stream))
    scenario, _ = rail_scenario(4, 'metro', gnss_model='receiver')
    fixes = [row for row in rows if row['z_position']]
    count = int(np.sum(scenario.t_s <= 300.0 + 1e-9))
    assert len(rows) == 3000 and len(fixes) == count
    np.testing.assert_array_equal([float(row['t']) for row in fixes], scenario.t_s[:count])
    np.testing.assert_array_equal([float(row['z_position']) for row in fixes],
                                  scenario.z[:count, 0])


def test_rail_bag_carries_ground_truth_accel(tmp_path):
    """The bag has the node's topics: ground_truth_accel beside the ground truth."""
    path = tmp_path / 'rail.mcap'
    assert kf_train_main(['simulate', '--scenario', 'rail', '--duration', '120', '-p',
                          'rail_accel_mps2:=1.2', '--output', str(path)]) == 0
    topics = {}
    with Reader(path) as reader:
        for connection, record_ns, raw in reader.messages():
            entry = topics.setdefault(connection.topic, (connection.msgtype, []))
            entry[1].append((record_ns, TYPESTORE.deserialize_cdr(raw, connection.msgtype)))
    assert {topic: kind for topic, (kind, _) in topics.items()} == {
        '/measurement': POSE, '/ground_truth': ODOMETRY, '/ground_truth_accel': ACCEL,
        '/velocity': TWIST_COVARIANCE}
    accel = [m for _, m in topics['/ground_truth_accel'][1]]
    truth = [m for _, m in topics['/ground_truth'][1]]
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in accel] == \
        [(m.header.stamp.sec, m.header.stamp.nanosec) for m in truth]
    assert {m.header.frame_id for m in accel} == {'base_link'}
    values = np.array([m.accel.linear.x for m in accel])
    assert values.max() == 1.2  # the given acceleration, held on leaving the station
    assert values.min() < 0.0 and np.all(values >= -1.3)  # metro brakes at most 1.3 m/s²


def test_receiver_bag_carries_hacc_and_the_doppler_speed(tmp_path):
    """Default receiver: variance hAcc², Doppler speed and speedAcc² on velocity, as streamed."""
    path = tmp_path / 'rail.mcap'
    assert kf_train_main(['simulate', '--scenario', 'rail', '--seed', '2', '--duration', '200',
                          '--output', str(path)]) == 0
    topics = {}
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            topics.setdefault(connection.topic, []).append(
                TYPESTORE.deserialize_cdr(raw, connection.msgtype))
    stream = make_stream('rail', 10.0, 2, rail={'gnss_model': 'receiver'})
    fixes = [s for s in (stream.next_sample() for _ in range(2000))
             if s.measured_position_m is not None]
    measured, velocity = topics['/measurement'], topics['/velocity']
    assert [m.pose.pose.position.x for m in measured] == [s.measured_position_m for s in fixes]
    assert [m.pose.covariance[0] for m in measured] == [s.measurement_variance_m2
                                                        for s in fixes]
    assert [m.twist.twist.linear.x for m in velocity] == [s.doppler_speed_mps for s in fixes]
    assert [m.twist.covariance[0] for m in velocity] == [s.doppler_variance_m2_s2
                                                         for s in fixes]
    assert [m.twist.covariance[7] for m in velocity] == [1e9] * len(fixes)
    assert {m.header.frame_id for m in velocity} == {'base_link'}
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in velocity] == \
        [(m.header.stamp.sec, m.header.stamp.nanosec) for m in measured]
