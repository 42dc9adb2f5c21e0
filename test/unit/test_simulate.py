"""Tests of ``kf-train simulate``: a simulated run written to a bag or a CSV, no DDS."""

import csv
from pathlib import Path

from kf_train.cli import main as kf_train_main
from kf_train.io.bagio_types import ACCEL, ODOMETRY, POSE, TWIST, TYPESTORE
from kf_train.sim import make_stream
from kf_train.sim.simulation import TrainSimulation
import numpy as np
import pytest
from rosbags.rosbag2 import Reader

NS = 1_000_000_000


def simulate(*args):
    """Run ``kf-train simulate ARGS``; return the exit code."""
    return kf_train_main(['simulate'] + [str(a) for a in args])


def read_bag(path):
    """Return {topic: (type, [(record_ns, message)])} of a bag."""
    topics = {}
    with Reader(path) as reader:
        for connection, record_ns, raw in reader.messages():
            kind = connection.msgtype
            entry = topics.setdefault(connection.topic, (kind, []))
            entry[1].append((record_ns, TYPESTORE.deserialize_cdr(raw, kind)))
    return topics


def read_csv(path):
    """Return the rows of a CSV as dicts."""
    with open(path, newline='') as stream:
        return list(csv.DictReader(stream))


def test_train_bag_holds_the_seed_measurements_and_the_truth(tmp_path):
    """Seed 0's train: measurements are seed 000's, the truth is x = 10 t, types the node's."""
    bag = tmp_path / 'run.mcap'
    assert simulate('--scenario', 'train', '--duration', 10, '--output', bag) == 0
    topics = read_bag(bag)
    assert set(topics) == {'/measurement', '/ground_truth'}
    kind, measurements = topics['/measurement']
    assert kind == POSE and len(measurements) == 100
    z = TrainSimulation(seed=0).generate(100).measured_position_m
    stamps = [m.header.stamp.sec * NS + m.header.stamp.nanosec for _, m in measurements]
    assert stamps == [round(k * NS / 10) for k in range(1, 101)]
    assert [record for record, _ in measurements] == stamps
    assert [m.pose.pose.position.x for _, m in measurements] == list(z)
    assert all(m.pose.covariance[0] == 1.0 and m.pose.covariance[7] == 1e9
               and m.pose.pose.orientation.w == 1.0 and m.header.frame_id == 'odom'
               for _, m in measurements)
    kind, truth = topics['/ground_truth']
    assert kind == ODOMETRY and len(truth) == 100
    assert [(m.pose.pose.position.x, m.twist.twist.linear.x) for _, m in truth] == [
        (10.0 * k / 10, 10.0) for k in range(1, 101)]
    assert all(m.child_frame_id == 'base_link' for _, m in truth)


@pytest.mark.parametrize('scenario,kind', [('car', ACCEL), ('robot-exact', TWIST)])
def test_control_scenarios_write_the_control_and_the_streams_numbers(tmp_path, scenario,
                                                                     kind):
    """Car and robot scenarios write control; every value is the node's stream's, seeded."""
    bag = tmp_path / 'run'
    assert simulate('--scenario', scenario, '--duration', 3, '--seed', 7, '--output', bag) == 0
    topics = read_bag(bag)
    assert set(topics) == {'/measurement', '/ground_truth', '/control'}
    stream = make_stream(scenario, 10.0, 7)
    expected = [stream.next_sample() for _ in range(30)]
    controls = [m for _, m in topics['/control'][1]]
    assert topics['/control'][0] == kind
    values = [m.accel.linear.x if kind == ACCEL else m.twist.linear.x for m in controls]
    assert values == [s.control for s in expected]
    assert all(m.header.frame_id == 'base_link' for m in controls)
    assert [m.pose.pose.position.x for _, m in topics['/measurement'][1]] == [
        s.measured_position_m for s in expected]
    assert [m.pose.pose.position.x for _, m in topics['/ground_truth'][1]] == [
        s.true_position_m for s in expected]


def test_the_bag_replays_and_the_csv_replays(tmp_path):
    """The bag replays with kf-train replay BAG, the CSV with --preset, with equal numbers."""
    assert simulate('--scenario', 'car', '--duration', 5, '--output', tmp_path / 'run.mcap') == 0
    assert simulate('--scenario', 'car', '--duration', 5, '--output', tmp_path / 'run.csv') == 0
    rows = read_csv(tmp_path / 'run.csv')
    assert list(rows[0]) == ['t', 'z_position', 'u', 'true_position', 'true_velocity']
    topics = read_bag(tmp_path / 'run.mcap')
    assert [float(r['z_position']) for r in rows] == [
        m.pose.pose.position.x for _, m in topics['/measurement'][1]]
    assert [float(r['true_position']) for r in rows] == [
        m.pose.pose.position.x for _, m in topics['/ground_truth'][1]]
    assert [float(r['t']) for r in rows] == [k / 10 for k in range(1, 51)]
    assert kf_train_main(['replay', str(tmp_path / 'run.mcap'), '--output',
                          str(tmp_path / 'bag_out.csv'), '-p', 'preset:=car']) == 0
    assert kf_train_main(['replay', str(tmp_path / 'run.csv'), '--preset', 'car',
                          '--output', str(tmp_path / 'csv_out.csv')]) == 0
    bag_out, csv_out = read_csv(tmp_path / 'bag_out.csv'), read_csv(tmp_path / 'csv_out.csv')
    assert len(bag_out) == len(csv_out) == 50
    # Same measurements, controls and model: the filters see the same numbers; the
    # node's initialisation (first measurement) and the preset's (its prior) differ,
    # so only the estimates' closeness to the truth is compared, not their bits.
    truth = np.array([float(r['true_position']) for r in rows])
    for out in (bag_out, csv_out):
        error = np.array([float(r['position']) for r in out]) - truth
        # σ = 1 m measurements: a converged estimate is within a few σ of the truth.
        assert np.all(np.abs(error[20:]) < 5.0)


def test_seeded_runs_are_identical_and_seeds_differ(tmp_path):
    """The same seed gives the same bytes; another seed other numbers."""
    for name, seed in (('a.csv', 3), ('b.csv', 3), ('c.csv', 4)):
        assert simulate('--duration', 2, '--seed', seed, '-p', 'outlier_probability:=0.2',
                        '--output', tmp_path / name) == 0
    a, b, c = ((tmp_path / n).read_bytes() for n in ('a.csv', 'b.csv', 'c.csv'))
    assert a == b and a != c
    for name in ('a.mcap', 'b.mcap'):
        assert simulate('--duration', 2, '--seed', 3, '--output', tmp_path / name) == 0
    first, second = read_bag(tmp_path / 'a.mcap'), read_bag(tmp_path / 'b.mcap')
    assert {t: [(r, TYPESTORE.serialize_cdr(m, k)) for r, m in v] for t, (k, v) in
            first.items()} == {t: [(r, TYPESTORE.serialize_cdr(m, k)) for r, m in v]
                               for t, (k, v) in second.items()}


def test_faults_use_the_nodes_parameter_names(tmp_path):
    """Dropouts leave empty cells (truth kept); bias and noise_std apply; delay records later."""
    out = tmp_path / 'run.csv'
    assert simulate('--duration', 20, '-p', 'dropout_probability:=0.3', '-p',
                    'measurement_bias_m:=100.0', '-p', 'noise_std:=0.0', '--output', out) == 0
    rows = read_csv(out)
    assert len(rows) == 200 and all(r['true_position'] for r in rows)
    lost = [r for r in rows if r['z_position'] == '']
    assert 30 < len(lost) < 90          # 60 expected; binomial σ ≈ 6.5
    assert all(float(r['z_position']) == float(r['true_position']) + 100.0
               for r in rows if r['z_position'])
    bag = tmp_path / 'delayed.mcap'
    assert simulate('--duration', 2, '-p', 'delay_s:=0.25', '--output', bag) == 0
    for record_ns, m in read_bag(bag)['/measurement'][1]:
        assert record_ns == m.header.stamp.sec * NS + m.header.stamp.nanosec + NS // 4


def test_params_file_sets_the_simulator(tmp_path):
    """A params file's simulator section applies, and -p overrides it."""
    params = tmp_path / 'p.yaml'
    params.write_text('simulator:\n  ros__parameters:\n    rate_hz: 5.0\n    seed: 2\n')
    out = tmp_path / 'run.csv'
    assert simulate('--duration', 2, '--params-file', params, '-p', 'rate_hz:=2.0',
                    '--output', out) == 0
    assert [float(r['t']) for r in read_csv(out)] == [0.5, 1.0, 1.5, 2.0]


@pytest.mark.parametrize('args,message', [
    (['--scenario', 'bus'], 'scenario must be one of'),
    (['-p', 'dropout_probability:=2.0'], 'dropout_probability'),
    (['-p', 'no_such:=1'], 'no_such'),
    (['--duration', '0'], '--duration'),
    (['--duration', 'nan'], '--duration'),
])
def test_bad_arguments_are_one_line(tmp_path, capsys, args, message):
    """A bad parameter or duration: exit 1, one line naming it, no output."""
    argv = ['--duration', 1] + args + ['--output', tmp_path / 'run.mcap']
    assert simulate(*argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith('kf-train simulate: error:') and '\n' not in err
    assert message in err
    assert list(Path(tmp_path).iterdir()) == []


@pytest.mark.parametrize('name', ['run.csv', 'run.mcap', 'bagdir'])
def test_unwritable_output_is_one_line(tmp_path, capsys, name):
    """A missing directory: one line, exit 1."""
    assert simulate('--duration', 1, '--output', tmp_path / 'missing' / name) == 1
    err = capsys.readouterr().err.strip()
    assert 'does not exist' in err and '\n' not in err
