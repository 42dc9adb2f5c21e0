"""
The estimator as a process: invalid parameters at start-up, and SIGINT/SIGTERM while it works.

Each test has its own ROS domain; children are always killed in a ``finally``.
"""

import signal
import subprocess
import sys
import time

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.ros import messages
from nav_msgs.msg import Odometry
import pytest
import rclpy
from ros_helpers import isolated_env, spin_until

COMMAND = [sys.executable, '-m', 'kf_train.ros.estimator_node']


def _start(domain_id, *ros_args):
    """Start the estimator with ``--ros-args`` ros_args in the test's domain."""
    arguments = ['--ros-args', *ros_args] if ros_args else []
    return subprocess.Popen(COMMAND + arguments, env=isolated_env(domain_id),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _stop(process):
    """Kill the process if it still runs and return its (stdout, stderr)."""
    if process.poll() is None:
        process.kill()
    return process.communicate(timeout=10)


@pytest.mark.parametrize('assignment, words', [
    ('gate_probability:=0.2', ['gate_probability', '0.5', '1']),
    ('history_s:=-1.0', ['history_s', '0', '60']),
    ('max_consecutive_outliers:=0', ['max_consecutive_outliers', '1']),
    ('restart_after_stale:=1', ['restart_after_stale', '2']),
    ('max_future_s:=-0.5', ['max_future_s', '0']),
    ('timeout_s:=0.0', ['timeout_s', '0.001']),
    ('nis_window:=0', ['nis_window', '1']),
    ('diagnostics_period_s:=1e9', ['diagnostics_period_s', '3600']),
    ('initial_covariance:=[1.0,2.0,3.0]', ['initial_covariance', '6', '36']),  # rail: 6 states
    ('reset_on_clock_jump:=maybe', ['reset_on_clock_jump']),
])
def test_invalid_parameter_at_startup(domain_id, assignment, words):
    """An invalid parameter: one line naming it and its range, exit code 2, no traceback."""
    process = _start(domain_id, '-p', assignment)
    try:
        process.wait(timeout=30)
    finally:
        stdout, stderr = _stop(process)
    assert process.returncode == 2, (stdout, stderr)
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: '), stderr
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert 'Traceback' not in stderr + stdout


@pytest.mark.parametrize('signal_number', [signal.SIGINT, signal.SIGTERM])
def test_signal_during_operation_exits_cleanly(ros_context, executor, domain_id,
                                               signal_number):
    """While fusing measurements, SIGINT or SIGTERM end the node with exit 0, no traceback."""
    process = _start(domain_id, '-p', 'diagnostics_period_s:=0.1')
    probe = rclpy.create_node('probe', context=ros_context)
    try:
        publisher = probe.create_publisher(PoseWithCovarianceStamped, 'measurement', 10)
        estimates = []
        probe.create_subscription(Odometry, 'estimate', estimates.append, 10)
        executor.add_node(probe)
        sent = [0]

        def publish_and_check():
            """Publish the next measurement (stamped now); return whether estimates came."""
            sent[0] += 1
            publisher.publish(messages.to_measurement_msg(
                time.time_ns(), 'odom', 10.0 * sent[0], 1.0))
            return len(estimates) >= 3

        assert spin_until(executor, publish_and_check, 30.0), 'no estimates from the node'
        process.send_signal(signal_number)
        process.wait(timeout=20)
    finally:
        stdout, stderr = _stop(process)
        executor.remove_node(probe)
        probe.destroy_node()
    assert process.returncode == 0, (stdout, stderr)
    assert 'Traceback' not in stderr + stdout, stderr
