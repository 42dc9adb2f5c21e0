"""
The managed nodes and the QoS overrides through the real ``ros2`` command line.

``ros2 run ... --ros-args -p managed:=true`` starts each node ``unconfigured``;
``ros2 lifecycle set`` drives it through every transition, ``ros2 lifecycle get``
shows each state, and ``shutdown`` ends the process with code 0. ``ros2 param
describe`` shows rclpy's QoS override parameters. The environment, the skips and the
clean-up are test_ros2_cli.py's (its ``ros2`` fixture): a colcon install, an isolated
domain on localhost, bounded polls.
"""

import itertools
import re

from ros_helpers import wait_until
from test_ros2_cli import check_odometry, DISCOVERY_TIMEOUT_S, ros2  # noqa: F401 (fixture)

_ATTEMPTS = itertools.count()


def _run_node(ros2, executable, *parameters):  # noqa: F811
    """Start ``ros2 run kf_train EXECUTABLE --ros-args -p ...`` in the background."""
    arguments = []
    for parameter in parameters:
        arguments += ['-p', parameter]
    return ros2.start('run', 'kf_train', executable, '--ros-args', *arguments,
                      name=executable)


def _state(ros2, node):  # noqa: F811
    """Return the state label ``ros2 lifecycle get`` prints."""
    return ros2.check('lifecycle', 'get', node).split()[0]


def _transition(ros2, node, transition, succeeds=True):  # noqa: F811
    """Run ``ros2 lifecycle set NODE TRANSITION``; check that it succeeded (or failed)."""
    done = ros2.run_found('lifecycle', 'set', node, transition)
    text = done.stdout + done.stderr
    assert 'Traceback' not in text, text
    assert ('Transitioning successful' in text) == succeeds, (transition, text)


def _shut_down(ros2, node, process):  # noqa: F811
    """``ros2 lifecycle set NODE shutdown`` succeeds and the node's process exits 0."""
    # Once the node it called has gone, the CLI can hang in its own teardown after it
    # printed its result (seen in CI: 'Transitioning successful', then no exit in 60 s).
    # What is checked here is the result and the node's exit, so the CLI runs in the
    # background and whatever is left of it is killed with the test's clean-up.
    def answered():
        cli = ros2.start('lifecycle', 'set', node, 'shutdown',
                         name=f'shutdown{next(_ATTEMPTS)}')
        found = cli.wait_for_output(
            'Transitioning successful|Transitioning failed|Node not found|Exception while')
        answers.append(found[0])
        return answers[-1] != 'Node not found'  # a new CLI may not see it yet: again

    answers = []
    wait_until(answered, DISCOVERY_TIMEOUT_S, poll_s=0.2)
    assert answers[-1] == 'Transitioning successful', answers
    assert process.wait() == 0, process.report('did not exit on shutdown')
    assert 'Traceback' not in process.output(), process.report('printed a traceback')


def test_lifecycle_cli_drives_both_nodes_through_every_transition(ros2):  # noqa: F811
    """configure, activate (estimates flow), deactivate, cleanup, configure, shutdown."""
    simulator = _run_node(ros2, 'simulator', 'managed:=true')
    estimator = _run_node(ros2, 'estimator', 'managed:=true', 'preset:=train')
    ros2.wait_for_nodes('/simulator', '/estimator', watch=(simulator, estimator))
    for node in ('/simulator', '/estimator'):
        assert _state(ros2, node) == 'unconfigured'
        _transition(ros2, node, 'configure')
        assert _state(ros2, node) == 'inactive'
    text = ros2.check('param', 'describe', '/estimator',
                      'qos_overrides./measurement.subscription.reliability')
    assert 'Type: string' in text and 'Read only: true' in text, text
    assert ros2.check('param', 'get', '/estimator',
                      'qos_overrides./measurement.subscription.reliability').split()[-1] \
        == 'best_effort'
    for node in ('/simulator', '/estimator'):
        _transition(ros2, node, 'activate')
        assert _state(ros2, node) == 'active'
    check_odometry(ros2.echo_once('/estimate', 'nav_msgs/msg/Odometry'))
    for transition, state in (('deactivate', 'inactive'), ('cleanup', 'unconfigured'),
                              ('configure', 'inactive'), ('activate', 'active')):
        _transition(ros2, '/estimator', transition)
        assert _state(ros2, '/estimator') == state
    check_odometry(ros2.echo_once('/estimate', 'nav_msgs/msg/Odometry'))
    for node, process in (('/estimator', estimator), ('/simulator', simulator)):
        _shut_down(ros2, node, process)


def test_lifecycle_configure_fails_on_an_invalid_parameter(ros2):  # noqa: F811
    """An invalid parameter: configure fails, the node logs its reason in one line."""
    estimator = _run_node(ros2, 'estimator', 'managed:=true', 'stale_warn_periods:=20.0')
    ros2.wait_for_nodes('/estimator', watch=(estimator,))
    _transition(ros2, '/estimator', 'configure', succeeds=False)
    assert _state(ros2, '/estimator') == 'unconfigured'
    line = estimator.wait_for_output(r'\[estimator\]: configure failed: (.*)')
    assert 'stale_error_periods' in line[1] and 'stale_warn_periods' in line[1], line[0]
    assert len(re.findall('configure failed', estimator.output())) == 1
    _shut_down(ros2, '/estimator', estimator)


def test_launch_managed_argument(ros2):  # noqa: F811
    """``managed:=true`` on the launch file starts both nodes unconfigured."""
    text = ros2.check('launch', 'kf_train', 'kf_train.launch.py', '--show-args')
    assert "'managed':" in text, text
    launch = ros2.start('launch', 'kf_train', 'kf_train.launch.py', 'managed:=true',
                        name='launch')
    ros2.wait_for_nodes('/simulator', '/estimator', watch=(launch,))
    assert _state(ros2, '/estimator') == 'unconfigured'
    assert _state(ros2, '/simulator') == 'unconfigured'
