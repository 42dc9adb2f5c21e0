"""The clean-up deadline after a signal (kf_train.ros.runner.exit_if_stuck), in subprocesses."""

import subprocess
import sys
import textwrap
import time

from kf_train.ros import runner

WAIT_S = 60.0       # bounds each child; a loaded machine starts Python + rclpy in seconds


def _child(body: str) -> subprocess.CompletedProcess:
    """Run ``body`` (after importing runner) in a fresh interpreter; return its result."""
    code = 'import sys, time\nfrom kf_train.ros.runner import exit_if_stuck\n' + \
        textwrap.dedent(body)
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=WAIT_S)


def test_a_clean_up_that_hangs_ends_the_process_with_exit_0_and_one_line():
    started = time.monotonic()
    result = _child("""
        print('stopped', flush=True)
        with exit_if_stuck(0.5):
            time.sleep(WAIT)                      # a teardown that does not return
        print('never')
    """.replace('WAIT', str(WAIT_S)))
    assert result.returncode == 0
    assert time.monotonic() - started < WAIT_S / 2
    assert result.stdout == 'stopped\n'             # flushed before it, nothing after
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith('warning: the clean-up after the signal')
    assert 'within 0.5 s' in lines[0]


def test_a_clean_up_in_time_or_not_armed_runs_to_its_end():
    result = _child("""
        with exit_if_stuck(30.0):
            time.sleep(0.1)
        with exit_if_stuck(0.2, armed=False):
            time.sleep(0.6)                       # past the deadline, but not armed
        print('done')
        sys.exit(3)
    """)
    assert (result.returncode, result.stdout, result.stderr) == (3, 'done\n', '')


def test_the_deadline_fits_launch_s_escalation():
    # ros2 launch sends SIGTERM 5 s after its SIGINT: a node should be gone by then.
    assert 0.0 < runner.CLEANUP_TIMEOUT_S <= 5.0
