"""Tests of the ``kf-train`` umbrella command and of the demo's command line and report."""

import os
import subprocess
import sys

from kf_train import cli
from kf_train.cli import demo, demo_processes
from kf_train.estimator import EstimatorSettings, NS_PER_S, StreamEstimator
from kf_train.ros import messages
from kf_train.sim import TrainSimulation
import numpy as np
import pytest
from ros_helpers import isolated_env

VENV_BIN = os.path.dirname(sys.executable)
KF_TRAIN = os.path.join(VENV_BIN, 'kf-train')
SEED000_SETTINGS = EstimatorSettings(preset='train', initialization='prior', gate_probability=1.0)
"""The demo's seed 000 estimator: the train preset, the seed's prior, the gate off."""


def test_usage_lists_every_command(capsys):
    """No arguments, -h and --help print the usage with every command, exit 0."""
    for argv in ([], ['-h'], ['--help']):
        assert cli.main(argv) == 0
        out = capsys.readouterr().out
        assert out.startswith('usage: kf-train <command>')
        for name in cli.COMMANDS:
            assert f'  {name}  ' in out


def test_unknown_command_exits_2(capsys):
    """An unknown command: exit 2, the error and the usage on stderr."""
    assert cli.main(['bogus']) == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert "unknown command 'bogus'" in captured.err
    assert 'usage: kf-train' in captured.err


def test_demo_help(capsys):
    """``kf-train demo --help`` documents its options and exits 0."""
    assert cli.main(['demo', '--help']) == 0
    out = capsys.readouterr().out
    for option in ('--seed', '--output-dir', '--timeout-s', 'usage: kf-train demo'):
        assert option in out


@pytest.mark.parametrize('argv', [['--seed', '-1'], ['--seed', 'x'], ['--bogus'],
                                  ['--timeout-s', '0'], ['--timeout-s', 'nan']])
def test_demo_rejects_a_bad_command_line(capsys, argv):
    """Bad demo options: exit 2 with a message, before any node starts."""
    assert demo.main(argv) == 2
    assert 'kf-train demo' in capsys.readouterr().err


def test_console_script_and_node_dispatch(domain_id):
    """The installed ``kf-train`` runs; ``kf-train simulator`` passes ROS arguments on."""
    env = isolated_env(domain_id)
    usage = subprocess.run([KF_TRAIN], capture_output=True, text=True, timeout=60, env=env)
    assert usage.returncode == 0 and 'demo' in usage.stdout
    unknown = subprocess.run([KF_TRAIN, 'nope'], capture_output=True, text=True, timeout=60,
                             env=env)
    assert unknown.returncode == 2
    bad = subprocess.run([KF_TRAIN, 'simulator', '--ros-args', '-p', 'rate_hz:=-1.0'],
                         capture_output=True, text=True, timeout=60, env=env)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == [
        'error: invalid parameter rate_hz:=-1.0: must be a double in [0.01, 10000.0]']


def test_demo_environment_keeps_a_user_domain_and_picks_one_otherwise():
    """A user's ROS_DOMAIN_ID is kept; otherwise one in 1..100 is picked; bad ones refused."""
    env = demo.demo_environment({'ROS_DOMAIN_ID': '42', 'PATH': '/bin'})
    assert env['ROS_DOMAIN_ID'] == '42' and env['PATH'] == '/bin'
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    env = demo.demo_environment({'ROS_STATIC_PEERS': 'elsewhere'})
    assert 1 <= int(env['ROS_DOMAIN_ID']) <= 100 and 'ROS_STATIC_PEERS' not in env
    env = demo.demo_environment({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'})
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
    for bad in ('abc', '-1', '233'):
        with pytest.raises(demo.DemoError, match='ROS_DOMAIN_ID'):
            demo.demo_environment({'ROS_DOMAIN_ID': bad})


def test_node_command_falls_back_to_python_m(monkeypatch, tmp_path, domain_id):
    """Without console scripts beside Python the nodes run as ``python -m``, and that works."""
    assert demo_processes.node_command('simulator') == [os.path.join(VENV_BIN, 'simulator')]
    with monkeypatch.context() as patch:
        patch.setattr(sys, 'executable', str(tmp_path / 'python3'))
        assert demo_processes.node_command('estimator') == [
            str(tmp_path / 'python3'), '-m', 'kf_train.ros.estimator_node']
    command = [sys.executable, '-m', 'kf_train.ros.simulator_node', '--ros-args', '-p',
               'max_samples:=-1']
    result = subprocess.run(command, capture_output=True, text=True, timeout=60,
                            env=isolated_env(domain_id))
    assert result.returncode == 2 and 'max_samples' in result.stderr


class FakeProbe:
    """Recorded messages as a Probe holds them, built offline."""

    def __init__(self, seed, samples=demo.SAMPLES, start_ns=1_700_000_000 * NS_PER_S):
        """Simulate seed 000 and run the core filter as the nodes would."""
        series = TrainSimulation(seed=seed).generate(samples)
        estimator = StreamEstimator(SEED000_SETTINGS)
        self.received = {topic: [] for topic in demo.TOPICS}
        for k in range(samples):
            stamp_ns = start_ns + (k + 1) * NS_PER_S // 10
            z = series.measured_position_m[k]
            step = estimator.process(stamp_ns, z, 1.0)
            self.received['measurement'].append(
                messages.to_measurement_msg(stamp_ns, 'odom', z, 1.0))
            self.received['ground_truth'].append(messages.to_odometry_msg(
                stamp_ns, 'odom', 'base_link', series.true_position_m[k], 10.0, 0.0, 0.0))
            self.received['estimate'].append(messages.to_state_odometry_msg(
                stamp_ns, 'odom', 'base_link', step.x, step.P))
            self.received['prediction'].append(messages.to_state_odometry_msg(
                step.prediction_stamp_ns, 'odom', 'base_link', step.predicted_x,
                step.predicted_P))
        self.measured = series.measured_position_m
        self.last_x = step.x


def test_demo_report_numbers_follow_seed_000(tmp_path):
    """The report's baselines are the seed's formulas; the CSV reads back exactly."""
    probe = FakeProbe(seed=3)
    settings = SEED000_SETTINGS
    series = demo.build_series(probe, 3, settings)
    assert series.offline_max_abs_diff == 0.0 and series.simulation_max_abs_diff == 0.0
    np.testing.assert_allclose(series.t_s, 0.1 * np.arange(1, 101), rtol=0, atol=1e-12)
    # MATLAB: v = [0 diff(Z_buffer)/dt] with Z_buffer(1) = 0, filter(ones(1,5)/5, 1, v).
    z_buffer = np.concatenate(([0.0], probe.measured))
    v = np.concatenate(([0.0], np.diff(z_buffer) / 0.1))
    running = np.mean(v[-5:])
    report = demo.format_report(series, 7, 3, settings)
    kalman = probe.last_x[0] + 2.0 * probe.last_x[1]
    for label, value in (('[m]: Kalman', kalman),
                         ('running average (5 samples) baseline',
                          probe.last_x[0] + 2.0 * running),
                         ('raw difference baseline', probe.last_x[0] + 2.0 * v[-1])):
        [line] = [line for line in report.splitlines() if label in line]
        assert f'{value:.3f}' in line, (label, line)
    assert 'position at t = 12.0 s' in report and '120.000' in report
    demo._write_data(tmp_path, series)
    table = np.genfromtxt(tmp_path / 'series.csv', delimiter=',', names=True, dtype=None)
    assert len(table) == 100
    assert list(table.dtype.names) == list(demo.CSV_COLUMNS)
    np.testing.assert_array_equal(table['measured_m'], probe.measured)
    assert table['running_average_velocity_mps'][-1] == pytest.approx(running, rel=1e-12)
