"""
The runner's optional EventsExecutor mode: its shutdown path, proven under load.

rclpy's EventsExecutor never returns from spin() on SIGINT and ignores SIGTERM, so
kf_train.ros.runner spins it with a stop future completed by its own signal handlers (see
runner.py). These tests start the estimator in that mode in a subprocess, keep it busy
with a stream of measurements published as fast as this process can, signal it in
the middle of the stream, and require exit code 0, no traceback, and an exit within
EXIT_TIMEOUT_S. The default executor is held to the same.
"""

import os
import signal
import subprocess
import sys
import tempfile
import time

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.ros import estimator_node, messages
from kf_train.ros.runner import executor_option
from nav_msgs.msg import Odometry
import pytest
from rclpy.node import Node
from rclpy.qos import QoSProfile
from ros_helpers import isolated_env, spin_until, wait_until

DISCOVERY_TIMEOUT_S = 20.0
EXIT_TIMEOUT_S = 10.0
NS_PER_S = 1_000_000_000


def _start(argv, domain_id):
    """Start a child with stdout and stderr in temporary files; return (process, stderr)."""
    stderr = tempfile.TemporaryFile(mode='w+')
    process = subprocess.Popen(argv, env=isolated_env(domain_id), stdout=subprocess.DEVNULL,
                               stderr=stderr, text=True)
    return process, stderr


def _stderr(stderr) -> str:
    """Return what a child wrote to stderr."""
    stderr.flush()
    stderr.seek(0)
    return stderr.read()


def _stop(process, signum):
    """Send ``signum``; return the exit code, or fail if the process does not end in time."""
    process.send_signal(signum)
    try:
        return process.wait(timeout=EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        pytest.fail(f'no exit within {EXIT_TIMEOUT_S} s of {signal.Signals(signum).name}')


@pytest.mark.parametrize('executor_kind', ['events', 'single_threaded'])
@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_exit_is_clean_under_a_stream_of_measurements(domain_id, ros_context, executor,
                                                      executor_kind, signum):
    """SIGINT or SIGTERM in the middle of a flat-out stream: exit 0, no traceback."""
    argv = [sys.executable, '-m', 'kf_train.ros.estimator_node', '--executor', executor_kind]
    process, stderr = _start(argv, domain_id)
    try:
        node = Node('stream', context=ros_context)
        publisher = node.create_publisher(PoseWithCovarianceStamped, 'measurement', 10)
        estimates = []
        node.create_subscription(Odometry, 'estimate', estimates.append, QoSProfile(depth=100))
        executor.add_node(node)
        assert wait_until(lambda: publisher.get_subscription_count() >= 1 or
                          process.poll() is not None, DISCOVERY_TIMEOUT_S), _stderr(stderr)
        assert process.poll() is None, _stderr(stderr)
        start_ns = last_ns = time.time_ns()
        sent = 0

        def publish_burst(count):
            nonlocal sent, last_ns
            for _ in range(count):
                sent += 1
                last_ns = max(time.time_ns(), last_ns + 1)
                publisher.publish(messages.to_measurement_msg(
                    last_ns, 'odom', 10.0 * (last_ns - start_ns) / NS_PER_S, 1.0))
            executor.spin_once(timeout_sec=0.0)
            return bool(estimates)

        # Keep publishing until the estimator is visibly busy, then signal it while the
        # stream goes on, and keep the stream going until it has exited.
        assert spin_until(executor, lambda: publish_burst(200), DISCOVERY_TIMEOUT_S), (
            f'no estimate after {sent} measurements; {_stderr(stderr)}')
        process.send_signal(signum)
        deadline = time.monotonic() + EXIT_TIMEOUT_S
        while process.poll() is None and time.monotonic() < deadline:
            publish_burst(200)
        code = _stop(process, signum)
        text = _stderr(stderr)
        assert code == 0, text
        assert 'Traceback' not in text, text
        assert len(estimates) > 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_events_executor_exits_when_idle(domain_id, ros_context, signum):
    """With no message at all the heartbeat still lets the signal through: exit 0."""
    argv = [sys.executable, '-m', 'kf_train.ros.estimator_node', '--executor', 'events',
            '--ros-args', '-p', 'diagnostics_period_s:=3600.0']
    process, stderr = _start(argv, domain_id)
    try:
        # Its subscription shows that the node is up (the runner's handlers were
        # installed before rclpy.init); it never receives a message.
        node = Node('watcher', context=ros_context)
        publisher = node.create_publisher(PoseWithCovarianceStamped, 'measurement', 10)
        assert wait_until(lambda: publisher.get_subscription_count() >= 1 or
                          process.poll() is not None, DISCOVERY_TIMEOUT_S), _stderr(stderr)
        assert process.poll() is None, _stderr(stderr)
        code = _stop(process, signum)
        text = _stderr(stderr)
        assert code == 0 and 'Traceback' not in text, text
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_done_future_ends_the_events_executor(domain_id):
    """A node's done future (the simulator's max_samples) ends the events spin: exit 0."""
    code = ('import sys\n'
            'from kf_train.ros.runner import run\n'
            'from kf_train.ros.simulator_node import SimulatorNode\n'
            'sys.exit(run(SimulatorNode, ["simulator", "--ros-args", "-p", '
            '"max_samples:=30", "-p", "rate_hz:=300.0"], executor="events"))\n')
    process, stderr = _start([sys.executable, '-c', code], domain_id)
    try:
        assert process.wait(timeout=30.0) == 0, _stderr(stderr)
        assert 'Traceback' not in _stderr(stderr)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


@pytest.mark.parametrize('value', ['fast', ''])
def test_unknown_executor_is_a_one_line_error(value, capsys):
    """--executor with an unknown or missing value exits 2 with one line, before rclpy."""
    args = ['estimator', '--executor'] + ([value] if value else [])
    assert estimator_node.main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('error: invalid --executor') and '\n' not in err
    assert 'single_threaded, events' in err


@pytest.mark.parametrize('argv, rest, kind', [
    (['estimator'], ['estimator'], 'single_threaded'),
    (['estimator', '--executor', 'events'], ['estimator'], 'events'),
    (['estimator', '--executor=events', '--ros-args', '-p', 'horizon_s:=1.0'],
     ['estimator', '--ros-args', '-p', 'horizon_s:=1.0'], 'events'),
    (['estimator', '--ros-args', '--executor', 'events'],
     ['estimator', '--ros-args', '--executor', 'events'], 'single_threaded'),
    (['estimator', '--executor'], ['estimator'], ''),
])
def test_executor_option_parsing(argv, rest, kind):
    """--executor KIND is taken out before --ros-args only; the rest is left for rclpy."""
    assert executor_option(argv) == (rest, kind)
    assert argv[0] == 'estimator'  # the caller's list is not modified


def test_executor_option_reads_sys_argv(monkeypatch):
    """Without arguments the option is looked for in sys.argv."""
    monkeypatch.setattr(sys, 'argv', ['estimator', '--executor', 'events'])
    assert executor_option(None) == (['estimator'], 'events')
    monkeypatch.setattr(sys, 'argv', ['estimator'])
    assert executor_option(None) == (None, 'single_threaded')


def test_console_script_accepts_the_option(domain_id):
    """The installed estimator script takes --executor events too (not just -m)."""
    script = os.path.join(os.path.dirname(sys.executable), 'estimator')
    if not os.access(script, os.X_OK):
        pytest.skip(f'no console script at {script}')
    process, stderr = _start([script, '--executor', 'nonsense'], domain_id)
    assert process.wait(timeout=30.0) == 2
    assert 'invalid --executor' in _stderr(stderr)
