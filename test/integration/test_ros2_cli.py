"""
The real ``ros2`` command line and ``ros2 launch`` against the colcon-built package.

These tests run what a ROS user types: ``ros2 pkg``, ``ros2 run``, ``ros2 launch``,
``ros2 topic echo/hz``, ``ros2 param``, ``ros2 service call`` and ``ros2 node info``,
each as a process of its own, in an environment made as a user makes theirs: the
colcon workspace's ``install/setup.bash`` sourced (``make colcon`` builds it in
``$COLCON_WS``), with the venv's prefix on ``AMENT_PREFIX_PATH``.

They need ``ros2`` (from the venv, ``make ros2cli``, or a sourced ROS) and the colcon
install; without either they skip, with the reason. With
``KF_TRAIN_REQUIRE_ROS2_CLI=1`` (set by ``.ci/run``) a missing one fails instead, so
CI cannot pass with them skipped.

Every test has its own ROS_DOMAIN_ID on localhost, its own ROS_LOG_DIR and TMPDIR
(launch_ros's parameter files) under tmp_path, stops the ``ros2 daemon`` the first
``ros2`` call starts, and kills what it started, process group by process group. Every
wait is a bounded poll.
"""

import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest
from ros_helpers import isolated_env, wait_until
import yaml

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
VENV_BIN = os.path.dirname(sys.executable)
COLCON_WS = os.environ.get('COLCON_WS', os.path.join(REPO, 'build', 'colcon_ws'))
COLCON_INSTALL = os.path.join(COLCON_WS, 'install')
REQUIRE_VARIABLE = 'KF_TRAIN_REQUIRE_ROS2_CLI'
NODES = ('simulator', 'estimator')
DISCOVERY_TIMEOUT_S = 30.0
COMMAND_TIMEOUT_S = 60.0
EXIT_TIMEOUT_S = 20.0
HZ_BOUND_S = 40.0
TRUE_VELOCITY_MPS = 10.0  # the train scenario's
HORIZON_S = 2.0  # the train preset's


def ros2_executable():
    """Return the ``ros2`` to test: the venv's, else the one on PATH, else None."""
    return shutil.which('ros2', path=VENV_BIN + os.pathsep + os.environ.get('PATH', ''))


def missing_requirement():
    """Return why these tests cannot run here, or None."""
    ros2 = ros2_executable()
    if ros2 is None:
        return ('no ros2 command: run `make ros2cli` (needs ../shared/ros2cli-wheels) or '
                'source a ROS 2 Jazzy installation')
    setup = os.path.join(COLCON_INSTALL, 'setup.bash')
    if not os.path.isfile(setup):
        return f'no colcon install in {COLCON_WS} (run make colcon)'
    source = os.path.join(COLCON_WS, 'src', 'kf_train')
    if os.path.realpath(source) != os.path.realpath(REPO):
        return f'{COLCON_WS} was built from {os.path.realpath(source)}, not from {REPO}'
    return None


@pytest.fixture
def ros2(domain_id, tmp_path):
    """Yield a Ros2 runner for the test's domain; stop its daemon and children after."""
    problem = missing_requirement()
    if problem is not None:
        if os.environ.get(REQUIRE_VARIABLE) == '1':
            pytest.fail(f'{REQUIRE_VARIABLE}=1 but the ros2 CLI tests cannot run: {problem}')
        pytest.skip(problem)
    runner = Ros2(domain_id, tmp_path)
    try:
        yield runner
    finally:
        runner.close()


def sourced_environment(domain_id, tmp_path):
    """Return the environment of a shell that sourced the colcon install, on our domain."""
    env = isolated_env(domain_id)
    bin_dir = os.path.dirname(ros2_executable())
    env['PATH'] = bin_dir + os.pathsep + env.get('PATH', '')
    prefixes = [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    if os.path.isdir(os.path.join(sys.prefix, 'share', 'ament_index')):
        prefixes.insert(0, sys.prefix)  # the venv's ROS wheels (see ros2cli-wheels README)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(prefixes)
    # colcon's scripts fail under `set -u`; -0 keeps values with newlines intact.
    dump = subprocess.run(
        ['bash', '-c', 'set +u; . "$1" >/dev/null && env -0', 'bash',
         os.path.join(COLCON_INSTALL, 'setup.bash')],
        env=env, stdout=subprocess.PIPE, check=True, timeout=COMMAND_TIMEOUT_S).stdout
    env = dict(item.split('=', 1) for item in dump.decode().split('\0') if '=' in item)
    for name in ('ROS_LOG_DIR', 'TMPDIR'):
        directory = tmp_path / name.lower()
        directory.mkdir()
        env[name] = str(directory)
    return env


class Ros2:
    """Runs ros2 commands in one test's environment and cleans up after them."""

    def __init__(self, domain_id, tmp_path):
        """Make the environment; nothing is started yet."""
        self.env = sourced_environment(domain_id, tmp_path)
        self.directory = tmp_path
        self.background = []

    def run(self, *args, timeout_s=COMMAND_TIMEOUT_S):
        """Run ``ros2 ARGS`` to its end; return the CompletedProcess (text output)."""
        return subprocess.run(['ros2'] + list(args), env=self.env, stdin=subprocess.DEVNULL,
                              capture_output=True, text=True, timeout=timeout_s)

    def run_found(self, *args, timeout_s=COMMAND_TIMEOUT_S):
        """Run ``ros2 ARGS`` on a node, again while it says 'Node not found' (bounded)."""
        runs = []

        def found():
            # A node that `ros2 node list` shows can still be unknown for a moment to a
            # new CLI process, which discovers the graph afresh (slower on a loaded
            # machine): only that is retried, within the discovery bound.
            runs.append(self.run(*args, timeout_s=timeout_s))
            return 'Node not found' not in runs[-1].stderr

        wait_until(found, DISCOVERY_TIMEOUT_S, poll_s=0.2)
        return runs[-1]

    def check(self, *args, timeout_s=COMMAND_TIMEOUT_S):
        """Run ``ros2 ARGS`` (:meth:`run_found`); fail unless it exits 0; return its stdout."""
        done = self.run_found(*args, timeout_s=timeout_s)
        assert done.returncode == 0, (args, done.stdout, done.stderr)
        assert 'Traceback' not in done.stdout + done.stderr, (args, done.stderr)
        return done.stdout

    def start(self, *args, name):
        """Start ``ros2 ARGS`` in a session (process group) of its own."""
        return self.start_command(['ros2'] + list(args), name=name)

    def start_command(self, command, name):
        """Start ``command`` in a session (process group) of its own."""
        process = Background(command, self.env, self.directory, name)
        self.background.append(process)
        return process

    def node_names(self):
        """Return the node names ``ros2 node list`` shows now."""
        done = self.run('node', 'list')
        return set(done.stdout.split()) if done.returncode == 0 else set()

    def wait_for_nodes(self, *names, watch=()):
        """Poll ``ros2 node list`` until it shows ``names``; fail if one of ``watch`` ends."""
        def ready():
            for process in watch:
                assert process.poll() is None, process.report('ended early')
            return set(names) <= self.node_names()

        assert wait_until(ready, DISCOVERY_TIMEOUT_S, poll_s=0.2), (
            f'{names} not discovered; ros2 node list shows {sorted(self.node_names())}')

    def echo_once(self, topic, kind):
        """Return the first message on ``topic`` as ``ros2 topic echo --once`` prints it."""
        text = self.check('topic', 'echo', '--once', topic, kind)
        return next(yaml.safe_load_all(text))

    def close(self):
        """Kill what is still running (by process group), then stop the domain's daemon."""
        for process in self.background:
            process.kill_group()
        self.run('daemon', 'stop', timeout_s=COMMAND_TIMEOUT_S)


class Background:
    """A long-running command in its own session, its output in files."""

    def __init__(self, command, env, directory, name):
        """Start ``command``; stdout and stderr go to ``directory/name.{out,err}``."""
        self.name = name
        self.out_path = os.path.join(directory, f'{name}.out')
        self.err_path = os.path.join(directory, f'{name}.err')
        with open(self.out_path, 'w') as out, open(self.err_path, 'w') as err:
            # A session of its own, as a terminal gives a job: its group can be sent a
            # Ctrl-C (killpg), or its leader alone one (kill).
            self.popen = subprocess.Popen(command, env=env, stdin=subprocess.DEVNULL,
                                          stdout=out, stderr=err, start_new_session=True)

    def poll(self):
        """Return the exit code, or None while running."""
        return self.popen.poll()

    def output(self):
        """Return stdout and stderr so far, joined."""
        texts = []
        for path in (self.out_path, self.err_path):
            with open(path, errors='replace') as stream:
                texts.append(stream.read())
        return '\n'.join(texts)

    def report(self, what):
        """Return a failure text: ``what`` with the exit code and the output."""
        return f'{self.name} {what} (exit {self.poll()}):\n{self.output()[-6000:]}'

    def wait_for_output(self, pattern, timeout_s=DISCOVERY_TIMEOUT_S):
        """Poll the output until ``pattern`` (a regex) matches; return the match."""
        found = []

        def matched():
            match = re.search(pattern, self.output())
            if match:
                found.append(match)
            return bool(match)

        assert wait_until(matched, timeout_s, poll_s=0.1), self.report(f'never printed '
                                                                       f'{pattern!r}')
        return found[0]

    def interrupt(self, whole_group):
        """Send SIGINT: to the whole group (a terminal's Ctrl-C) or to the leader alone."""
        if whole_group:
            os.killpg(self.popen.pid, signal.SIGINT)
        else:
            self.popen.send_signal(signal.SIGINT)

    def wait(self, timeout_s=EXIT_TIMEOUT_S):
        """Return the exit code; fail if the process does not end in time."""
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            pytest.fail(self.report(f'did not exit within {timeout_s} s'))

    def kill_group(self):
        """Kill the process group if anything in it still runs."""
        try:
            os.killpg(self.popen.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.popen.wait()


def assert_clean_launch_exit(launch):
    """Check that ``ros2 launch`` and both nodes ended with code 0 and no traceback."""
    code = launch.wait()
    text = launch.output()
    assert code == 0, launch.report('failed')
    assert 'Traceback' not in text and 'process has died' not in text, text
    for node in NODES:
        if f'[{node}-' in text:
            assert re.search(rf'\[{node}-\d+\]: process has finished cleanly', text), text


def stamp_s(header):
    """Return a printed header's stamp in seconds."""
    return header['stamp']['sec'] + header['stamp']['nanosec'] * 1e-9


def check_odometry(message, frame_id='odom', child_frame_id='base_link'):
    """Check an estimate or prediction: frames, finite values, variances, the 1e9s."""
    assert message['header']['frame_id'] == frame_id
    assert message['child_frame_id'] == child_frame_id
    position = message['pose']['pose']['position']['x']
    velocity = message['twist']['twist']['linear']['x']
    var_position = message['pose']['covariance'][0]
    var_velocity = message['twist']['covariance'][0]
    assert math.isfinite(position) and math.isfinite(velocity)
    assert var_position > 0.0 and var_velocity > 0.0
    assert message['pose']['covariance'][7] == 1e9  # y: not estimated
    # The train runs at 10 m/s: within 6 σ of the filter's own variance (a chance of
    # 2e-9 for a consistent filter). Its first estimates have σ ~ 100 m/s.
    assert abs(velocity - TRUE_VELOCITY_MPS) <= 6.0 * math.sqrt(var_velocity), message


def ros2_run_node(ros2, name, *arguments):
    """Start ``ros2 run kf_train NAME`` with ``--ros-args ARGUMENTS``."""
    extra = ['--ros-args'] + list(arguments) if arguments else []
    return ros2.start('run', 'kf_train', name, *extra, name=name)


def test_pkg_executables_and_prefix(ros2):
    """``ros2 pkg executables kf_train`` lists both nodes from the colcon install."""
    lines = ros2.check('pkg', 'executables', 'kf_train').splitlines()
    assert {'kf_train simulator', 'kf_train estimator'} <= set(lines), lines
    prefix = ros2.check('pkg', 'prefix', 'kf_train').strip()
    assert os.path.realpath(prefix) == os.path.realpath(os.path.join(COLCON_INSTALL,
                                                                     'kf_train'))
    share = ros2.check('pkg', 'prefix', '--share', 'kf_train').strip()
    for launch_file in ('kf_train.launch.py', 'estimator.launch.py'):
        assert os.path.isfile(os.path.join(share, 'launch', launch_file)), launch_file


def test_launch_files_show_their_arguments(ros2):
    """``--show-args`` lists every argument docs/ros.md documents, with defaults."""
    text = ros2.check('launch', 'kf_train', 'kf_train.launch.py', '--show-args')
    for argument in ('params_file', 'namespace', 'use_sim_time', 'scenario', 'preset'):
        assert f"'{argument}':" in text, text
    assert 'kf_train.yaml' in text  # the installed parameter file by default
    text = ros2.check('launch', 'kf_train', 'estimator.launch.py', '--show-args')
    for argument in ('params_file', 'namespace', 'use_sim_time', 'preset',
                     'measurement_topic', 'control_topic'):
        assert f"'{argument}':" in text, text


@pytest.mark.parametrize('arguments, words', [
    (['params_file:=/nonexistent/kf.yaml'], ['/nonexistent/kf.yaml', 'does not exist']),
    (['use_sim_time:=maybe'], ['use_sim_time', 'maybe']),
], ids=['missing-params-file', 'bad-use-sim-time'])
def test_launch_refuses_bad_arguments_in_one_line(ros2, arguments, words):
    """A bad launch argument: non-zero exit, an error naming it, no traceback, no nodes."""
    done = ros2.run('launch', 'kf_train', 'kf_train.launch.py', *arguments)
    text = done.stdout + done.stderr
    assert done.returncode != 0, text
    errors = [line for line in text.splitlines() if 'ERROR' in line or 'rror:' in line]
    assert errors and all(word in errors[0] for word in words), text
    assert 'Traceback' not in text and 'process started' not in text, text


def test_ros2_run_echo_hz_node_info_and_ctrl_c(ros2):
    """
    ``ros2 run`` both nodes; topic echo, hz and node info; Ctrl-C ends each with code 0.

    The estimator is started from the installed params file, as the README shows.
    """
    config = os.path.join(ros2.check('pkg', 'prefix', '--share', 'kf_train').strip(),
                          'config', 'kf_train.yaml')
    simulator = ros2_run_node(ros2, 'simulator')
    estimator = ros2_run_node(ros2, 'estimator', '--params-file', config)
    ros2.wait_for_nodes('/simulator', '/estimator', watch=(simulator, estimator))

    check_odometry(ros2.echo_once('/estimate', 'nav_msgs/msg/Odometry'))
    before_s = time.time()
    prediction = ros2.echo_once('/prediction', 'nav_msgs/msg/Odometry')
    after_s = time.time()
    check_odometry(prediction)
    # Stamped measurement stamp + horizon_s. A measurement is stamped on the wall clock,
    # at most one period (0.1 s) before its timer fires and never after; the one echoed
    # was taken after the echo started (it subscribes first): 1 s of slack below.
    assert before_s - 1.0 <= stamp_s(prediction['header']) - HORIZON_S <= after_s + 0.01

    check_topic_hz(ros2, '/measurement', expected_hz=10.0)
    check_node_info(ros2)

    for process in (simulator, estimator):
        process.interrupt(whole_group=True)  # what Ctrl-C in its terminal sends
    for process in (simulator, estimator):
        assert process.wait() == 0, process.report('failed on Ctrl-C')
        assert 'Traceback' not in process.output(), process.report('printed a traceback')


def check_topic_hz(ros2, topic, expected_hz):
    """``ros2 topic hz`` (bounded by ``timeout -s INT``) reports about ``expected_hz``."""
    # It runs until stopped: timeout -s INT is the hard bound, the SIGINT below (passed
    # on by timeout) the usual stop, once two reports are out.
    hz = ros2.start_command(['timeout', '-s', 'INT', str(int(HZ_BOUND_S)), 'ros2', 'topic',
                             'hz', topic], name='hz')
    pattern = r'average rate: (\S+)\n\s+min: \S+ max: \S+ std dev: \S+ window: (\d+)'
    try:
        hz.wait_for_output(pattern + r'[\s\S]*' + pattern)
    finally:
        hz.interrupt(whole_group=False)
    # ros2cli's main() returns signal.SIGINT (2) when a verb is interrupted.
    assert hz.wait() == signal.SIGINT, hz.report('did not end as interrupted')
    assert 'Traceback' not in hz.output(), hz.report('printed a traceback')
    rates = [float(rate) for rate, _ in re.findall(pattern, hz.output())]
    # Rates from arrival times over a window of >= 10 messages: the publisher's timer is
    # exact on average, arrival jitter on a loaded machine shifts a 1-s window by tens
    # of ms; +-25 % leaves a wide margin and still tells 10 Hz from 5 or 20.
    assert all(0.75 * expected_hz <= rate <= 1.25 * expected_hz for rate in rates), rates


def check_node_info(ros2):
    """``ros2 node info /estimator`` shows its topics, types and the reset service."""
    text = ros2.check('node', 'info', '/estimator')
    sections = dict(re.findall(r'^  (\w[\w ]*):\n((?:    .*\n?)*)', text, re.M))
    assert '/measurement: geometry_msgs/msg/PoseWithCovarianceStamped' in \
        sections['Subscribers'], text
    for line in ('/estimate: nav_msgs/msg/Odometry', '/prediction: nav_msgs/msg/Odometry',
                 '/innovation: geometry_msgs/msg/Vector3Stamped',
                 '/diagnostics: diagnostic_msgs/msg/DiagnosticArray'):
        assert line in sections['Publishers'], text
    assert '/estimator/reset: std_srvs/srv/Trigger' in sections['Service Servers'], text


def test_launch_params_reset_service_and_ctrl_c_to_launch(ros2):
    """
    ``ros2 launch``: param describe/set/get, the reset service, SIGINT to launch alone.

    A refused set keeps the old value; SIGINT to ros2 launch alone (as ``kill -INT``
    sends it) ends it and both nodes with code 0 and no traceback.
    """
    launch = ros2.start('launch', 'kf_train', 'kf_train.launch.py', name='launch')
    ros2.wait_for_nodes('/simulator', '/estimator', watch=(launch,))
    check_odometry(ros2.echo_once('/estimate', 'nav_msgs/msg/Odometry'))

    text = ros2.check('param', 'describe', '/estimator', 'process_noise_density', 'preset')
    described = text.split('Parameter name: ')
    noise = next(d for d in described if d.startswith('process_noise_density'))
    assert 'Type: double' in noise and 'Min value: 0.0' in noise, text
    assert 'White-noise acceleration density' in noise and 'Read only' not in noise, text
    preset = next(d for d in described if d.startswith('preset'))
    assert 'Type: string' in preset and 'Read only: true' in preset, text

    refused = [('process_noise_density', '-1.0', 'out of range'),
               ('preset', 'car', 'read-only')]
    for name, value, reason in refused:
        old = ros2.check('param', 'get', '/estimator', name)
        done = ros2.run('param', 'set', '/estimator', name, value)
        assert 'Setting parameter failed' in done.stderr and reason in done.stderr, done
        assert ros2.check('param', 'get', '/estimator', name) == old
    # The default preset (rail) has no white-noise q of its own to add to: refused too.
    done = ros2.run('param', 'set', '/estimator', 'process_noise_density', '0.5')
    assert 'Setting parameter failed' in done.stderr and 'rail' in done.stderr, done
    # The CLI can set what is valid: the refusals above are the node's.
    assert 'Set parameter successful' in ros2.check(
        'param', 'set', '/estimator', 'gate_probability', '0.999')
    assert ros2.check('param', 'get', '/estimator', 'gate_probability').split() == [
        'Double', 'value', 'is:', '0.999']

    text = ros2.check('service', 'call', '/estimator/reset', 'std_srvs/srv/Trigger')
    assert re.search(r'Trigger_Response\(success=True, message=.filter reset', text), text
    launch.wait_for_output(r'\[estimator\]: filter reset \(manual\)')

    launch.interrupt(whole_group=False)
    assert_clean_launch_exit(launch)


def test_launch_arguments_and_ctrl_c_in_a_terminal(ros2):
    """
    Launch arguments reach the nodes; a terminal's Ctrl-C ends everything cleanly.

    Namespace, scenario (the preset follows it) and use_sim_time; the train's preset
    values in the default params file are left out for the car. The Ctrl-C is SIGINT to
    launch and its nodes at once (one process group).
    """
    launch = ros2.start('launch', 'kf_train', 'kf_train.launch.py', 'namespace:=/line1',
                        'scenario:=car', name='launch')
    ros2.wait_for_nodes('/line1/simulator', '/line1/estimator', watch=(launch,))

    def parameter(node, name):
        return ros2.check('param', 'get', f'/line1/{node}', name).strip()

    assert parameter('simulator', 'scenario') == 'String value is: car'
    assert parameter('estimator', 'preset') == 'String value is: car'
    # seed 001: x0 = 0, P0 = Q = diag(0, 0.05), not the train's [0, 5] and I
    assert parameter('estimator', 'initial_state') == 'Double values are: [0.0, 0.0]'
    assert parameter('simulator', 'initial_position') == 'Double value is: 0.2'
    assert parameter('estimator', 'use_sim_time') == 'Boolean value is: False'
    # The rest of the default file still applies.
    assert parameter('estimator', 'history_s') == 'Double value is: 1.0'

    estimate = ros2.echo_once('/line1/estimate', 'nav_msgs/msg/Odometry')
    assert estimate['header']['frame_id'] == 'odom'
    text = ros2.check('node', 'info', '/line1/estimator')
    assert '/line1/control: geometry_msgs/msg/AccelStamped' in text, text

    launch.interrupt(whole_group=True)
    assert_clean_launch_exit(launch)


def test_estimator_launch_on_recorded_style_data(ros2):
    """
    ``estimator.launch.py`` alone follows /clock on a remapped measurement topic.

    Both as a bag played with ``ros2 bag play --clock`` would give them (the simulator
    stands in for the bag: ros2 bag is not among the wheels).
    """
    simulator = ros2_run_node(ros2, 'simulator', '-r', 'measurement:=/recorded/pose',
                              '-p', 'publish_clock:=true')
    launch = ros2.start('launch', 'kf_train', 'estimator.launch.py',
                        'measurement_topic:=/recorded/pose', name='launch')
    ros2.wait_for_nodes('/simulator', '/estimator', watch=(simulator, launch))
    assert ros2.check('param', 'get', '/estimator', 'use_sim_time').strip() == \
        'Boolean value is: True'
    check_odometry(ros2.echo_once('/estimate', 'nav_msgs/msg/Odometry'))
    text = ros2.check('node', 'info', '/estimator')
    assert '/recorded/pose: geometry_msgs/msg/PoseWithCovarianceStamped' in text, text
    assert '/clock: rosgraph_msgs/msg/Clock' in text, text

    launch.interrupt(whole_group=False)
    assert_clean_launch_exit(launch)
    simulator.interrupt(whole_group=True)
    assert simulator.wait() == 0, simulator.report('failed on Ctrl-C')


def test_node_ignores_the_second_sigint_of_a_terminal_ctrl_c(domain_id, tmp_path):
    """
    A node ends with code 0 and no traceback however many SIGINTs it gets.

    A Ctrl-C in a terminal running ``ros2 launch`` reaches each node twice: from the
    terminal, then from launch. Here SIGINTs go over and over until the node has
    exited (no ros2 CLI needed).
    """
    env = isolated_env(domain_id)
    env['ROS_LOG_DIR'] = str(tmp_path)
    err_path = tmp_path / 'estimator.err'
    with open(err_path, 'w') as err:
        # A tiny timeout_s makes the spinning node log once: then its handlers are in.
        popen = subprocess.Popen(
            [os.path.join(VENV_BIN, 'estimator'), '--ros-args', '-p', 'timeout_s:=0.001',
             '-p', 'diagnostics_period_s:=0.05'],
            env=env, stdin=subprocess.DEVNULL, stdout=err, stderr=err)
    try:
        assert wait_until(lambda: 'no measurement fused yet' in err_path.read_text(),
                          DISCOVERY_TIMEOUT_S), err_path.read_text()
        deadline = time.monotonic() + EXIT_TIMEOUT_S
        while popen.poll() is None and time.monotonic() < deadline:
            popen.send_signal(signal.SIGINT)
            time.sleep(0.001)  # pacing the burst, not waiting for anything
        assert popen.wait(timeout=EXIT_TIMEOUT_S) == 0, err_path.read_text()
        assert 'Traceback' not in err_path.read_text(), err_path.read_text()
    finally:
        if popen.poll() is None:
            popen.kill()
            popen.wait()
