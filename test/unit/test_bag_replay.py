"""Tests of ``kf-train replay BAG``: seed 000 exact, the node's parameters, bad bags, outputs."""

import csv
import math
import os
from pathlib import Path

from kf_train.cli import main as kf_train_main
from kf_train.io.bagio_types import ACCEL, POSE, TYPESTORE
from kf_train.sim.simulation import TrainSimulation
import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

T = TYPESTORE.types
NS = 1_000_000_000
PERIOD_NS = 100_000_000
LATENCY_NS = 1_234_567
SEED_000 = ['-p', 'preset:=train', '-p', 'initialization:=prior',
            '-p', 'gate_probability:=1.0']


def pose_message(stamp_ns, position_m, variance_m2=1.0, frame_id='odom'):
    """Return a PoseWithCovarianceStamped as the simulator fills it (rosbags types)."""
    sec, nanosec = divmod(stamp_ns, NS)
    covariance = np.full(36, 0.0)
    covariance[::7] = 1e9
    covariance[0] = variance_m2
    header = T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
        sec=sec, nanosec=nanosec), frame_id=frame_id)
    pose = T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=position_m, y=0.0, z=0.0),
        orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0))
    return T[POSE](header=header, pose=T['geometry_msgs/msg/PoseWithCovariance'](
        pose=pose, covariance=covariance))


def write_bag(path, records, storage=StoragePlugin.MCAP):
    """Write (topic, type, record_ns, message) records into a rosbag2 directory."""
    connections = {}
    with Writer(path, version=9, storage_plugin=storage) as writer:
        for topic, kind, record_ns, message in records:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, kind, typestore=TYPESTORE)
            writer.write(connections[topic], record_ns, TYPESTORE.serialize_cdr(message, kind))
    return Path(path)


def seed_000_bag(path, storage=StoragePlugin.MCAP):
    """Write seed 000's 100 measurements (stamped k · 0.1 s, recorded a little later)."""
    z = TrainSimulation(seed=0).generate(100).measured_position_m
    stamps = [k * PERIOD_NS for k in range(1, 101)]
    write_bag(path, [('/measurement', POSE, s + LATENCY_NS, pose_message(s, float(v)))
                     for v, s in zip(z, stamps)], storage)
    return Path(path), np.asarray(z, dtype=float)


def seed_000_matlab(measurements, dt=0.1):
    """Return seed 000's Xk and P after each step, transcribed from its MATLAB loop."""
    inv = np.linalg.inv
    Xk_prev = np.array([[0.0], [0.5 * 10.0]])
    Phi = np.array([[1.0, dt], [0.0, 1.0]])
    P = np.eye(2)
    M = np.array([[1.0, 0.0]])
    R = 1.0
    xs, Ps = [], []
    for Z in measurements:
        P1 = Phi @ P @ Phi.T
        S = M @ P1 @ M.T + R
        K = P1 @ M.T @ inv(S)
        P = P1 - K @ M @ P1
        Xk = Phi @ Xk_prev + K @ (Z - M @ Phi @ Xk_prev)
        xs.append(Xk.ravel())
        Ps.append(P)
        Xk_prev = Xk
    return np.array(xs), np.array(Ps)


def read_csv(path):
    """Return the CSV's header and its rows as lists of floats (empty cells NaN)."""
    with open(path, newline='') as stream:
        rows = list(csv.reader(stream))
    return rows[0], np.array([[float(c) if c else math.nan for c in row] for row in rows[1:]])


def replay(*argv):
    """Run ``kf-train replay`` with argv; return its exit code."""
    return kf_train_main(['replay', *map(str, argv)])


@pytest.mark.parametrize('storage', [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_seed_000_from_a_bag_is_exact(tmp_path, storage):
    """The issue's command on a bag of seed 000's measurements reproduces the seed."""
    bag, z = seed_000_bag(tmp_path / 'seed', storage)
    out = tmp_path / 'out.csv'
    assert replay(bag, '--output', out, *SEED_000) == 0
    header, rows = read_csv(out)
    assert header == ['t', 'position', 'velocity', 'var_position', 'var_velocity',
                      'predicted_position', 'predicted_velocity', 'var_predicted_position',
                      'var_predicted_velocity', 'nis']
    expected_x, expected_P = seed_000_matlab(z)
    assert len(rows) == 100
    np.testing.assert_array_equal(rows[:, 0], np.arange(1, 101) * PERIOD_NS / NS)
    # The same arithmetic in another order: each step's rounding (~1e-16 relative) is
    # carried by a contracting filter; 100 steps stay far below 1e-9 of the values
    # (positions up to ~100 m: absolute 1e-7 is 1e-9 relative).
    np.testing.assert_allclose(rows[:, 1:3], expected_x, rtol=1e-9, atol=1e-9 * 100)
    np.testing.assert_allclose(rows[:, 3], expected_P[:, 0, 0], rtol=1e-9)
    np.testing.assert_allclose(rows[:, 4], expected_P[:, 1, 1], rtol=1e-9)
    # The prediction 2 s ahead (the preset's horizon) of a Q = 0 model: F(2 s) x.
    np.testing.assert_allclose(rows[:, 5], rows[:, 1] + 2.0 * rows[:, 2], rtol=1e-12)
    assert np.all(rows[:, 9] >= 0.0)


def test_mcap_output_holds_the_node_topics(tmp_path):
    """--output X.mcap: estimate, prediction, innovation, /diagnostics, regimes (rail)."""
    bag, _ = seed_000_bag(tmp_path / 'seed')
    out = tmp_path / 'out.mcap'
    assert replay(bag, '--output', out, '-p', 'diagnostics_period_s:=1.0') == 0
    with Reader(out) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        kinds = {c.topic: c.msgtype for c in reader.connections}
        estimates = [TYPESTORE.deserialize_cdr(raw, c.msgtype)
                     for c, _, raw in reader.messages() if c.topic == '/estimate']
    assert kinds == {'/estimate': 'nav_msgs/msg/Odometry',
                     '/prediction': 'nav_msgs/msg/Odometry',
                     '/innovation': 'geometry_msgs/msg/Vector3Stamped',
                     '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
                     '/regime_probabilities': 'std_msgs/msg/Float64MultiArray'}
    # Default initialization (first measurement): 100 estimates, 99 innovations; record
    # times span 9.9 s, so /diagnostics at 1, 2, ..., 9 s after the first message.
    assert counts == {'/estimate': 100, '/prediction': 100, '/innovation': 99,
                      '/diagnostics': 9, '/regime_probabilities': 100}
    assert estimates[-1].header.stamp.sec == 10 and estimates[-1].header.stamp.nanosec == 0


def test_csv_equals_mcap(tmp_path):
    """The two outputs of one replay carry the same numbers, bit for bit."""
    bag, _ = seed_000_bag(tmp_path / 'seed')
    assert replay(bag, '--output', tmp_path / 'o.csv') == 0
    assert replay(bag, '--output', tmp_path / 'o.mcap') == 0
    header, rows = read_csv(tmp_path / 'o.csv')
    with Reader(tmp_path / 'o.mcap') as reader:
        estimates = [TYPESTORE.deserialize_cdr(raw, c.msgtype)
                     for c, _, raw in reader.messages() if c.topic == '/estimate']
    # The defaults: the rail preset, whose six states are all in the CSV.
    column = {name: rows[:, header.index(name)].tolist() for name in header}
    assert 'acceleration' in column and len(estimates) == len(rows)
    assert [m.pose.pose.position.x for m in estimates] == column['position']
    assert [m.twist.twist.linear.x for m in estimates] == column['velocity']
    assert [m.pose.covariance[0] for m in estimates] == column['var_position']
    assert [m.twist.covariance[0] for m in estimates] == column['var_velocity']
    # The rail preset's regimes: the CSV's p_<regime> are the bag's regime_probabilities.
    with Reader(tmp_path / 'o.mcap') as reader:
        regimes = [TYPESTORE.deserialize_cdr(raw, c.msgtype).data.tolist()
                   for c, _, raw in reader.messages() if c.topic == '/regime_probabilities']
        nis = [TYPESTORE.deserialize_cdr(raw, c.msgtype)
               for c, _, raw in reader.messages() if c.topic == '/innovation']
    names = [name for name in header if name.startswith('p_')]
    assert names == ['p_stand', 'p_accelerate', 'p_cruise', 'p_brake']
    assert header[-5:] == names + ['nis']
    assert rows[:, [header.index(name) for name in names]].tolist() == regimes
    assert math.isnan(rows[0, -1]) and [m.vector.z for m in nis] == rows[1:, -1].tolist()


def test_params_file_and_overrides(tmp_path):
    """--params-file (node estimator) then -p, as the node reads them."""
    bag, _ = seed_000_bag(tmp_path / 'seed')
    params = tmp_path / 'p.yaml'
    params.write_text('estimator:\n  ros__parameters:\n    preset: train\n'
                      '    initialization: prior\n    gate_probability: 1.0\n'
                      '    horizon_s: 5.0\n')
    assert replay(bag, '--output', tmp_path / 'a.csv', '--params-file', params,
                  '-p', 'horizon_s:=2.0') == 0
    assert replay(bag, '--output', tmp_path / 'b.csv', *SEED_000) == 0
    assert (tmp_path / 'a.csv').read_text() == (tmp_path / 'b.csv').read_text()


def test_topic_option(tmp_path):
    """--topic picks the measurement topic among several of the type."""
    z = TrainSimulation(seed=0).generate(20).measured_position_m
    records = []
    for k, v in enumerate(z, 1):
        message = pose_message(k * PERIOD_NS, float(v))
        records.append(('/a/measurement', POSE, k * PERIOD_NS, message))
        records.append(('/b/measurement', POSE, k * PERIOD_NS + 1,
                        pose_message(k * PERIOD_NS, float(v) + 100.0)))
    bag = write_bag(tmp_path / 'two', records)
    assert replay(bag, '--output', tmp_path / 'x.csv') == 1
    assert replay(bag, '--output', tmp_path / 'a.csv', '--topic', '/a/measurement') == 0
    assert replay(bag, '--output', tmp_path / 'b.csv', '--topic', '/b/measurement') == 0
    a, b = read_csv(tmp_path / 'a.csv')[1], read_csv(tmp_path / 'b.csv')[1]
    assert len(a) == len(b) == 20 and abs(b[0, 1] - a[0, 1] - 100.0) < 1e-9


def _bad(tmp_path, case):
    """Return (bag path, extra argv) of a bad input."""
    good, _ = seed_000_bag(tmp_path / 'good')
    if case == 'missing-path':
        return tmp_path / 'nothing', []
    if case == 'not-a-bag':
        (tmp_path / 'notes.mcap').write_text('not a bag\n')
        return tmp_path / 'notes.mcap', []
    if case == 'truncated':
        (mcap,) = good.glob('*.mcap')
        data = mcap.read_bytes()
        (tmp_path / 'cut.mcap').write_bytes(data[:int(len(data) * 0.6)])
        return tmp_path / 'cut.mcap', []
    if case == 'missing-topic':
        accel = T[ACCEL](header=T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=0, nanosec=1), frame_id='x'),
            accel=T['geometry_msgs/msg/Accel'](
                linear=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0),
                angular=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0)))
        return write_bag(tmp_path / 'other', [('/gps', ACCEL, 1, accel)]), []
    if case == 'missing-control':
        return good, ['-p', 'preset:=car']
    if case == 'explicit-topic':
        return good, ['--topic', '/gnss']
    if case == 'bad-parameter':
        return good, ['-p', 'no_such_parameter:=1']
    raise AssertionError(case)


BAD = {'missing-path': 'no such file', 'not-a-bag': 'not a readable bag',
       'truncated': 'truncated', 'missing-topic': 'no measurement topic',
       'missing-control': 'no control topic', 'explicit-topic': "'/gnss'",
       'bad-parameter': 'no_such_parameter'}


@pytest.mark.parametrize('output', ['out.csv', 'out.mcap', 'outdir'])
@pytest.mark.parametrize('case', sorted(BAD))
def test_bad_input_one_line_and_no_output(tmp_path, capsys, case, output):
    """A bad bag or parameter: exit 1, one line naming the problem, nothing written."""
    bag, extra = _bad(tmp_path, case)
    out_dir = tmp_path / 'out'
    out_dir.mkdir()
    assert replay(bag, '--output', out_dir / output, *extra) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('kf-train replay: error: ')
    assert BAD[case] in err
    assert os.listdir(out_dir) == []


def test_unwritable_output_is_one_line(tmp_path, capsys):
    """An output in a missing directory: one line, not a traceback."""
    bag, _ = seed_000_bag(tmp_path / 'seed')
    for out in (tmp_path / 'no' / 'x.csv', tmp_path / 'no' / 'x.mcap'):
        assert replay(bag, '--output', out) == 1
        err = capsys.readouterr().err
        assert err.count('\n') == 1 and 'does not exist' in err
