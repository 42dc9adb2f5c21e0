"""
Integration tests across processes: the node executables, signals, bad parameters, the demo.

The executables under test are chosen explicitly: the venv console scripts next to
this Python are always tested; the colcon-installed ones (what ``ros2 run kf_train
...`` runs) too when ``make colcon`` has built them from this tree, else that variant
is skipped with the reason. Every test has its own ROS domain; children are killed in
the fixture's teardown whatever happens.
"""

import csv
import math
import os
import re
import selectors
import signal
import subprocess
import sys
import time

from kf_train.ros import messages
from kf_train.ros.demo_nodes import fetch_parameters, Probe
import pytest
from ros_helpers import isolated_env, spin_until, wait_until
from test_integration_inprocess import check_covariance, check_pose, k_sigma
import yaml

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CONFIG = os.path.join(REPO, 'config', 'kf_train.yaml')
VENV_BIN = os.path.dirname(sys.executable)
COLCON_WS = os.environ.get('COLCON_WS', '/tmp/kf_train_colcon_ws')
COLCON_BIN = os.path.join(COLCON_WS, 'install', 'kf_train', 'lib', 'kf_train')
NODES = ('simulator', 'estimator')
DISCOVERY_TIMEOUT_S = 20.0
EXIT_TIMEOUT_S = 15.0
RUN_TIMEOUT_S = 30.0


def colcon_problem():
    """Return why the colcon-installed executables cannot be tested here, or None."""
    source = os.path.join(COLCON_WS, 'src', 'kf_train')
    if not os.path.isdir(COLCON_BIN):
        return f'no colcon install in {COLCON_WS} (run make colcon)'
    if os.path.realpath(source) != os.path.realpath(REPO):
        return f'{COLCON_WS} was built from {os.path.realpath(source)}, not from {REPO}'
    missing = [n for n in NODES if not os.access(os.path.join(COLCON_BIN, n), os.X_OK)]
    if missing:
        return f'{COLCON_BIN} lacks {", ".join(missing)}'
    return None


VARIANTS = [
    pytest.param(VENV_BIN, id='venv-console-scripts'),
    pytest.param(COLCON_BIN, id='colcon-install', marks=pytest.mark.skipif(
        colcon_problem() is not None, reason=str(colcon_problem()))),
]


class Child:
    """A child process with its stdout and stderr in files."""

    def __init__(self, command, env, directory, name):
        """Start ``command``; its output goes to ``directory/name.{out,err}``."""
        self.name = name
        self.out_path = os.path.join(directory, f'{name}.out')
        self.err_path = os.path.join(directory, f'{name}.err')
        with open(self.out_path, 'w') as out, open(self.err_path, 'w') as err:
            self.popen = subprocess.Popen(command, env=env, stdin=subprocess.DEVNULL,
                                          stdout=out, stderr=err)

    def wait(self, timeout_s=EXIT_TIMEOUT_S):
        """Return the exit code, failing the test if the child does not exit in time."""
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            # PYTHONFAULTHANDLER (see spawn) makes SIGABRT dump every thread's stack.
            self.popen.send_signal(signal.SIGABRT)
            try:
                self.popen.wait(timeout=EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                pass
            pytest.fail(f'{self.name} did not exit within {timeout_s} s; its stacks:\n'
                        f'{self.stderr()[-8000:]}')

    def stderr(self):
        """Return everything the child wrote to stderr."""
        with open(self.err_path, errors='replace') as stream:
            return stream.read()

    def stdout(self):
        """Return everything the child wrote to stdout."""
        with open(self.out_path, errors='replace') as stream:
            return stream.read()


@pytest.fixture
def spawn(domain_id, tmp_path):
    """Yield a function starting children in the test's domain; kill them afterwards."""
    children = []

    env = isolated_env(domain_id)
    env['PYTHONFAULTHANDLER'] = '1'  # a hung child's stacks can be dumped

    def start(command, name):
        child = Child(command, env, str(tmp_path), name)
        children.append(child)
        return child

    try:
        yield start
    finally:
        for child in children:
            if child.popen.poll() is None:
                child.popen.kill()
                child.popen.wait()


def node(bin_dir, name, *parameters, extra=()):
    """Return the command running node ``name`` from ``bin_dir`` with ``-p`` parameters."""
    command = [os.path.join(bin_dir, name)] + list(extra)
    if parameters or not extra:
        command.append('--ros-args')
    for parameter in parameters:
        command += ['-p', parameter]
    return command


def discover(executor, probe, children):
    """
    Spin until the probe sees both nodes and the estimator has matched its topics.

    The estimator answering a service call shows it has discovered the probe; its
    /diagnostics then show its measurement input and its outputs matched on its side
    (Probe.estimator_connected). Fails early if a child dies.
    """
    def ready():
        for child in children:
            code = child.popen.poll()
            assert code is None, f'{child.name} exited with {code}: {child.stderr()}'
        return probe.sees_nodes()
    assert spin_until(executor, ready, DISCOVERY_TIMEOUT_S), 'discovery timed out'
    assert fetch_parameters(executor, probe, 'estimator', ['horizon_s'],
                            DISCOVERY_TIMEOUT_S) is not None, 'the estimator does not answer'
    # Each end of a topic is matched on its own; the estimator's status counts its ends.
    assert spin_until(executor, lambda: ready() and probe.estimator_connected(),
                      DISCOVERY_TIMEOUT_S), \
        f'the estimator has not matched its topics: {probe.estimator_status()}'


def missing(probe):
    """Return a failure message: counts, and which samples lack an estimate."""
    stamps = sorted(messages.stamp_to_ns(m.header.stamp) for m in probe.received['measurement'])
    estimated = {messages.stamp_to_ns(m.header.stamp) for m in probe.received['estimate']}
    lacking = [k for k, stamp in enumerate(stamps) if stamp not in estimated]
    return f'{probe.counts()}; samples without an estimate: {lacking}'


def assert_clean_exit(child):
    """Assert exit code 0 and no traceback."""
    assert child.wait() == 0, child.stderr()
    assert 'Traceback' not in child.stderr(), (child.name, child.stderr())


@pytest.mark.parametrize('bin_dir', VARIANTS)
def test_node_processes_converge_and_fill_every_message(ros_context, executor, spawn,
                                                        bin_dir):
    """Both executables over DDS: consistent estimates, every field as documented."""
    samples = 50
    probe = Probe(context=ros_context, subscribe_measurement=False)
    executor.add_node(probe)
    estimator = spawn(node(bin_dir, 'estimator', 'frame_id:=map',
                           'child_frame_id:=train'), 'estimator')
    simulator = spawn(node(bin_dir, 'simulator', 'rate_hz:=50.0', f'max_samples:={samples}',
                           'min_subscribers:=2', 'frame_id:=map', 'child_frame_id:=train'),
                      'simulator')
    discover(executor, probe, [estimator, simulator])
    probe.subscribe_measurement()
    assert spin_until(executor, lambda: min(probe.counts().values()) >= samples,
                      RUN_TIMEOUT_S), missing(probe)
    assert_clean_exit(simulator)  # max_samples reached: it ends by itself
    estimator.popen.send_signal(signal.SIGINT)
    assert_clean_exit(estimator)

    truth = {messages.stamp_to_ns(m.header.stamp): messages.from_odometry_msg(m)
             for m in probe.received['ground_truth']}
    k = k_sigma(checks=2 * samples)
    for msg in probe.received['estimate']:
        s = messages.from_odometry_msg(msg)
        assert abs(s.position_m - truth[s.stamp_ns].position_m) <= k * math.sqrt(
            s.position_variance_m2)
        assert abs(s.velocity_mps - truth[s.stamp_ns].velocity_mps) <= k * math.sqrt(
            s.velocity_variance_m2s2)
    horizon_ns = 2 * 1_000_000_000
    assert sorted(messages.stamp_to_ns(m.header.stamp) for m in probe.received['prediction']) \
        == sorted(s + horizon_ns for s in truth)
    for msg in probe.received['measurement']:
        assert msg.header.frame_id == 'map' and messages.stamp_to_ns(msg.header.stamp) in truth
        check_pose(msg.pose, first_variance=1.0)
    for topic in ('ground_truth', 'estimate', 'prediction'):
        for msg in probe.received[topic]:
            assert (msg.header.frame_id, msg.child_frame_id) == ('map', 'train')
            assert messages.stamp_to_ns(msg.header.stamp) > 0
            check_pose(msg.pose, first_variance=0.0 if topic == 'ground_truth' else None)
            check_covariance(msg.twist.covariance,
                             0.0 if topic == 'ground_truth' else None)


def test_signals_end_nodes_started_from_a_params_file_cleanly(ros_context, executor, spawn,
                                                              tmp_path):
    """
    Nodes started from an edited params file run with its values; signals end them cleanly.

    Two copies of the pair run side by side in namespaces /a and /b (one discovery for
    both): SIGINT goes to both nodes in /a, SIGTERM to both in /b, once estimates flow
    (so every node is inside spin()). Each must exit 0 without a traceback.
    """
    with open(CONFIG) as stream:
        config = yaml.safe_load(stream)
    simulator = config['simulator']['ros__parameters']
    estimator = config['estimator']['ros__parameters']
    simulator.update(initial_position=500.0, rate_hz=20.0, frame_id='map')
    estimator.update(horizon_s=1.5, frame_id='map')
    path = str(tmp_path / 'edited.yaml')
    with open(path, 'w') as stream:
        # '/**/name' matches the node in any namespace.
        yaml.safe_dump({'/**/simulator': {'ros__parameters': simulator},
                        '/**/estimator': {'ros__parameters': estimator}}, stream)
    signals = {'a': signal.SIGINT, 'b': signal.SIGTERM}
    probes, children = {}, {}
    for namespace in signals:
        probes[namespace] = Probe(context=ros_context, namespace=namespace,
                                  node_name=f'probe_{namespace}')
        executor.add_node(probes[namespace])
        for name in NODES:
            children[namespace, name] = spawn(node(VENV_BIN, name, extra=[
                '--ros-args', '--params-file', path, '-r', f'__ns:=/{namespace}']),
                f'{name}_{namespace}')
    assert spin_until(executor, lambda: all(
        len(probe.received['prediction']) >= 3 and len(probe.received['ground_truth']) >= 3
        for probe in probes.values()), DISCOVERY_TIMEOUT_S + RUN_TIMEOUT_S), \
        {namespace: probe.counts() for namespace, probe in probes.items()}

    for probe in probes.values():
        truth = [messages.from_odometry_msg(m) for m in probe.received['ground_truth']]
        assert all(t.position_m > 500.0 and t.frame_id == 'map' for t in truth)
        for msg in probe.received['prediction']:
            assert msg.header.frame_id == 'map'
            # stamp = a sample's stamp + 1.5 s; samples are 50 ms apart (20 Hz)
            offset_ns = messages.stamp_to_ns(msg.header.stamp) - 1_500_000_000 - \
                truth[0].stamp_ns
            assert offset_ns % 50_000_000 == 0, offset_ns
    for (namespace, _), child in children.items():
        child.popen.send_signal(signals[namespace])
    for child in children.values():
        assert_clean_exit(child)


@pytest.mark.parametrize('name, parameter, expected', [
    ('simulator', 'rate_hz:=-1.0', ['rate_hz', '[0.01, 10000.0]']),
    ('estimator', 'horizon_s:=-3.0', ['horizon_s', '[0.0, 86400.0]']),
    ('simulator', 'rate_hz:=10', ['rate_hz', 'DOUBLE', 'INTEGER']),
    ('simulator', 'max_samples:=-5', ['max_samples', '[0, 2147483647]']),
    ('estimator', 'initialization:=bogus', ['initialization', 'first_measurement', 'prior']),
    ('estimator', 'initial_covariance:=[1.0,-1.0]', ['initial_covariance']),
])
def test_invalid_parameter_at_startup_is_one_clear_line(spawn, name, parameter, expected):
    """A bad -p: exit code 2, one line naming the parameter and what it accepts."""
    child = spawn(node(VENV_BIN, name, parameter), name)
    assert child.wait() == 2
    lines = child.stderr().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: '), lines
    for fragment in expected:
        assert fragment in lines[0]


def test_demo_end_to_end(spawn, tmp_path):
    """``kf-train demo``: exit 0, the report's key lines, DDS equal to the offline core."""
    output_dir = tmp_path / 'demo'
    demo = spawn([os.path.join(VENV_BIN, 'kf-train'), 'demo', '--output-dir',
                  str(output_dir)], 'demo')
    assert demo.wait(timeout_s=180.0) == 0, demo.stderr()
    stdout = demo.stdout()
    rail_at = stdout.index('kf-train demo: a rail run over DDS')  # after seed 000's report
    report, rail_report = stdout[:rail_at], stdout[rail_at:]
    for key in ('final position [m] (t = 10.0 s)', 'final velocity [m/s] (t = 10.0 s)',
                'position at t = 12.0 s [m]: Kalman', 'running average (5 samples) baseline',
                'raw difference baseline', 'DDS vs offline core'):
        assert key in report, key
    assert float(re.search(r'core .*max \|difference\| = (\S+)', report)[1]) <= 1e-9
    assert float(re.search(r'simulation: max \|difference\| = (\S+)', report)[1]) == 0.0
    assert (output_dir / 'report.txt').read_text() + '\n' == report
    assert 'Traceback' not in demo.stderr()
    assert 'figures: ' in demo.stderr()  # drawn, or 'not available' without kf_train.plots
    # The rail run: the defaults against tuned KFs, DDS equal to the offline core.
    for key in ('a rail run over DDS', 'estimator defaults, over DDS', 'constant-velocity KF',
                'constant-acceleration KF', 'best tuned KF', 'figure: '):
        assert key in rail_report, key
    assert float(re.search(r'core .*max \|difference\| = (\S+)', rail_report)[1]) <= 1e-9
    assert float(re.search(r'simulation: max \|difference\| = (\S+)', report)[1]) == 0.0
    assert float(re.search(r'offline run: max \|difference\| = (\S+)', rail_report)[1]) == 0.0
    assert (output_dir / 'rail' / 'report.txt').read_text() == rail_report
    assert (output_dir / 'rail' / 'rail.png').is_file()
    with open(output_dir / 'series.csv') as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == 100
    last = rows[-1]
    assert float(last['t_s']) == pytest.approx(10.0)
    # The 2-s prediction for t = 12 s against the true 120 m, within the filter's own σ.
    assert abs(float(last['predicted_position_m']) - 120.0) <= k_sigma(1) * math.sqrt(
        float(last['var_predicted_position_m2']))


def read_until(popen, pattern, timeout_s):
    """Read ``popen``'s stderr until ``pattern`` matches; return the match, or None in time."""
    selector = selectors.DefaultSelector()
    selector.register(popen.stderr, selectors.EVENT_READ)
    text = b''
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if not selector.select(timeout=max(0.0, deadline - time.monotonic())):
                continue
            chunk = os.read(popen.stderr.fileno(), 4096)
            if not chunk:
                return None
            text += chunk
            match = re.search(pattern, text.decode(errors='replace'))
            if match:
                return match
    finally:
        selector.close()
    return None


@pytest.mark.parametrize('signum, when', [
    (signal.SIGINT, 'sampling'), (signal.SIGTERM, 'started')], ids=['SIGINT', 'SIGTERM'])
def test_interrupted_demo_stops_its_nodes(domain_id, tmp_path, signum, when):
    """A signal to the demo alone, while sampling or starting: exit 130, its nodes gone."""
    demo = subprocess.Popen([os.path.join(VENV_BIN, 'kf-train'), 'demo', '--output-dir',
                             str(tmp_path)], env=isolated_env(domain_id),
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    pids = []
    try:
        match = read_until(
            demo, r'estimator \(pid (\d+)\) and the simulator \(pid (\d+)\)',
            DISCOVERY_TIMEOUT_S)
        assert match, 'the demo did not report its nodes'
        pids = [int(match[1]), int(match[2])]
        if when == 'sampling':
            assert read_until(demo, r'both nodes up; sampling', DISCOVERY_TIMEOUT_S + 10.0)
        demo.send_signal(signum)
        assert demo.wait(timeout=EXIT_TIMEOUT_S) == 130
        assert b'interrupted' in demo.stderr.read()
        assert wait_until(lambda: not any(alive(pid) for pid in pids), EXIT_TIMEOUT_S)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
        for pid in pids:  # the demo's children, should it have failed to stop them
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
        demo.stderr.close()


def alive(pid):
    """Return whether process ``pid`` exists (and is not a zombie)."""
    try:
        with open(f'/proc/{pid}/stat') as stream:
            return stream.read().split(')')[-1].split()[0] != 'Z'
    except OSError:
        return False
