"""
The demos' node processes: started, watched, asked for their settings, stopped.

``kf-train demo`` (:mod:`kf_train.cli.demo`, seed 000) and its rail run
(:mod:`kf_train.cli.demo_rail`) start the ``estimator`` and the ``simulator`` as
processes of their own (:func:`start`), spin a probe node until a condition holds
while watching them (:func:`spin_until`), and stop them (:func:`stop`). A failure is a
:class:`DemoError`: one line, exit code 1.
"""

import dataclasses
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import Callable, Dict, List, NamedTuple

from kf_train.estimator import EstimatorSettings
from kf_train.ros import demo_nodes, diagnostics

MAX_DOMAIN_ID = 232
HOLD_SUBSCRIBERS = 1000
"""The simulator's largest min_subscribers: it holds the first sample until released."""
DISCOVERY_TIMEOUT_S = 20.0
EXIT_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0


class Child(NamedTuple):
    """A node process and the file its output goes to."""

    process: subprocess.Popen
    log_path: Path


class DemoError(Exception):
    """A failure the demo reports as one line and exit code 1."""


class Terminated(Exception):
    """SIGTERM reached the demo."""


def wait_connected(executor, probe: demo_nodes.Probe, children: Dict[str, Child],
                   prefix: str = '') -> None:
    """Spin until the estimator reports its input and outputs matched (or raise DemoError)."""
    # The probe's own view cannot show it: DDS matches each end of a topic separately,
    # and the estimator's best-effort reader drops samples from a writer it has not
    # matched yet. Its /diagnostics (every diagnostics_period_s) counts its own ends.
    if not spin_until(executor, probe.estimator_connected, DISCOVERY_TIMEOUT_S, children):
        status = probe.estimator_status()
        seen = ('no /diagnostics from it' if status is None else ', '.join(
            f'{key} {status.get(key, "?")}' for key in diagnostics.MATCHED_KEYS))
        raise DemoError(f'{prefix}the estimator has not matched its topics after '
                        f'{DISCOVERY_TIMEOUT_S:g} s: {seen}')
    check_children(children)


def demo_environment(environ) -> Dict[str, str]:
    """Return the children's environment: the user's domain if set, else one of this run."""
    env = dict(environ)
    if not env.get('ROS_DOMAIN_ID', '').strip():
        # 1..100 keeps Fast DDS's port arithmetic valid; the pid spreads concurrent runs.
        env['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 100)
        env.pop('ROS_STATIC_PEERS', None)
    try:
        domain_id = int(env['ROS_DOMAIN_ID'])
    except ValueError:
        domain_id = -1
    # Fast DDS cannot map larger ids to ports, and exits the process if asked to.
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise DemoError(f'ROS_DOMAIN_ID must be an integer in [0, {MAX_DOMAIN_ID}], '
                        f'got {env["ROS_DOMAIN_ID"]!r}')
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env['PYTHONUNBUFFERED'] = '1'
    return env


def node_command(name: str) -> List[str]:
    """Return the command starting node ``name``: the console script beside Python, or -m."""
    script = Path(sys.executable).parent / name
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    return [sys.executable, '-m', f'kf_train.ros.{name}_node']


def start(name: str, ros_args: List[str], env: Dict[str, str], output_dir: Path) -> Child:
    """Start node ``name`` with its output in ``output_dir/<name>.log``."""
    command = node_command(name) + ['--ros-args'] + ros_args
    log_path = output_dir / f'{name}.log'
    try:
        with open(log_path, 'w') as log:
            return Child(subprocess.Popen(command, env=env, stdin=subprocess.DEVNULL,
                                          stdout=log, stderr=subprocess.STDOUT), log_path)
    except OSError as error:
        raise DemoError(f'cannot start the {name} ({command[0]}): {error.strerror}') from None


def spin_until(executor, condition: Callable[[], bool], timeout_s: float,
               children: Dict[str, Child],
               simulator_may_finish: bool = False) -> bool:
    """Spin until ``condition()``; raise DemoError as soon as a node exits unexpectedly."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        check_children(children, simulator_may_finish)
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def check_children(children: Dict[str, Child], simulator_may_finish: bool = False) -> None:
    """Raise DemoError if a node has exited (the simulator may, once it is done)."""
    for name, child in children.items():
        code = child.process.poll()
        if code is None or (code == 0 and name == 'simulator' and simulator_may_finish):
            continue
        raise DemoError(f'the {name} exited early with code {code}: {last_line(child)}')


def settings_from_parameters(values: Dict[str, object]) -> EstimatorSettings:
    """Return the EstimatorSettings of an estimator node with these parameter values."""
    fields = {field.name for field in dataclasses.fields(EstimatorSettings)}
    settings = {}
    for name, value in values.items():
        if name in fields:
            # Array parameters arrive as lists or array.array; the settings keep tuples.
            is_array = isinstance(value, (list, tuple)) or hasattr(value, 'typecode')
            settings[name] = tuple(float(v) for v in value) if is_array else value
    return EstimatorSettings(**settings)


def estimator_settings(executor, probe: demo_nodes.Probe) -> EstimatorSettings:
    """Ask the estimator node for its parameters; return the settings it runs with."""
    names = sorted(field.name for field in dataclasses.fields(EstimatorSettings))
    values = demo_nodes.fetch_parameters(executor, probe, 'estimator', names,
                                         DISCOVERY_TIMEOUT_S)
    if values is None:
        raise DemoError(f'the estimator did not answer get_parameters within '
                        f'{DISCOVERY_TIMEOUT_S:g} s')
    # Parameters the node does not declare come back NOT_SET (None): defaults apply.
    return settings_from_parameters({n: v for n, v in values.items() if v is not None})


def expect_exit(children: Dict[str, Child], name: str, timeout_s: float) -> None:
    """Wait for node ``name`` to exit; raise DemoError unless it exits 0 in time."""
    try:
        code = children[name].process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise DemoError(f'the {name} did not exit within {timeout_s:g} s') from None
    if code != 0:
        raise DemoError(f'the {name} exited with code {code}: {last_line(children[name])}')


def stop(children: Dict[str, Child]) -> None:
    """Stop every child still running: SIGINT, then SIGKILL after STOP_TIMEOUT_S."""
    running = [child.process for child in children.values() if child.process.poll() is None]
    for child in running:
        child.send_signal(signal.SIGINT)
    for child in running:
        try:
            child.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


def last_line(child: Child) -> str:
    """Return the last non-empty line a child logged, for a one-line error."""
    try:
        with open(child.log_path, errors='replace') as log:
            lines = [line.strip() for line in log if line.strip()]
    except OSError:
        return '(no output)'
    return lines[-1] if lines else '(no output)'


def progress(text: str) -> None:
    """Print a progress line to stderr, keeping stdout for the report."""
    print(f'kf-train demo: {text}', file=sys.stderr, flush=True)


def raise_on_sigterm():
    """Turn SIGTERM into an exception so the children are stopped; return the old handler."""
    def handler(signum, frame):
        raise Terminated()
    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        return None
