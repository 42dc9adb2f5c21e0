"""Helpers for ROS tests: isolated domains, per-test contexts, bounded waits."""

import itertools
import os
import subprocess
import sys
import time
from typing import Callable, Dict, Sequence, Tuple

import rclpy
from rclpy.context import Context
from rclpy.executors import Executor

# Fast DDS derives ports from the domain id; 1..100 stays in the valid range.
_DOMAIN_COUNT = 100
_counter = itertools.count()
_base = (os.getpid() * 7919 + int(time.time())) % _DOMAIN_COUNT


# Nodes a test created outside an executor fixture; destroy_owned_nodes() (an autouse
# fixture of ros_fixtures.py) destroys them after each test, so no DDS participant
# outlives the test that made it.
_OWNED_NODES = []


def own_node(node):
    """Register ``node`` to be destroyed after the test; return it."""
    _OWNED_NODES.append(node)
    return node


def destroy_owned_nodes() -> None:
    """Destroy the nodes registered by own_node(), newest first."""
    while _OWNED_NODES:
        _OWNED_NODES.pop().destroy_node()


def next_domain_id() -> int:
    """Return a domain id unlikely to be used by another test or a parallel run."""
    return 1 + (_base + next(_counter)) % _DOMAIN_COUNT


def isolated_env(domain_id: int) -> Dict[str, str]:
    """Return os.environ for a subprocess confined to ``domain_id`` on this host."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_STATIC_PEERS', None)
    env['PYTHONUNBUFFERED'] = '1'
    return env


def make_context(domain_id: int) -> Context:
    """Return an initialised rclpy Context on ``domain_id``."""
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    return context


def spin_until(executor: Executor, condition: Callable[[], bool],
               timeout_s: float = 10.0) -> bool:
    """Spin until ``condition()`` holds or ``timeout_s`` passes; return whether it held."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def wait_until(condition: Callable[[], bool], timeout_s: float = 10.0,
               poll_s: float = 0.05) -> bool:
    """Poll ``condition()`` without spinning until it holds or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll_s)
    return True


def assert_startup_refused(domain_id: int, module: str, assignment: str,
                           words: Sequence[str]) -> None:
    """Start ``module`` with ``-p assignment``: one error line naming ``words``, exit 2."""
    process = subprocess.Popen([sys.executable, '-m', module, '--ros-args', '-p', assignment],
                               env=isolated_env(domain_id), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
        stdout, stderr = process.communicate(timeout=10)
    assert process.returncode == 2, (stdout, stderr)
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: '), stderr
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert 'Traceback' not in stdout + stderr


def estimator_and_probe(context: Context, executor: Executor, parameters: dict,
                        inputs: Dict[str, type], outputs: Dict[str, type]):
    """
    Start an in-process estimator and a probe; return (node, probe's publishers, received).

    The probe publishes each of ``inputs`` (topic: message type) and records each of
    ``outputs`` in ``received[topic]``. It returns once DDS has matched every end. Both
    nodes are destroyed after the test.
    """
    from kf_train.ros.estimator_node import EstimatorNode
    from rclpy.parameter import Parameter
    node = own_node(EstimatorNode(context=context, parameter_overrides=[
        Parameter(name, value=value) for name, value in parameters.items()]))
    probe = own_node(rclpy.create_node('probe', context=context))
    executor.add_node(node)
    executor.add_node(probe)
    publishers = {topic: probe.create_publisher(kind, topic, 10)
                  for topic, kind in inputs.items()}
    received = {topic: [] for topic in outputs}
    for topic, kind in outputs.items():
        probe.create_subscription(kind, topic, received[topic].append, 1000)
    # The node publishes only to subscribers its own side has matched (DDS matches each
    # end on its own): wait for the node's publishers, not the probe's view.
    node_publishers = [p for p in node.publishers if p.topic_name.rsplit('/', 1)[-1] in outputs]
    assert len(node_publishers) == len(outputs)
    assert spin_until(executor, lambda: all(
        p.get_subscription_count() == 1 for p in publishers.values()) and all(
        p.get_subscription_count() == 1 for p in node_publishers), 10.0)
    return node, publishers, received


def live_estimator_outputs(context: Context, executor: Executor, sequence, parameters: dict,
                           topics: Dict[str, Tuple[type, Callable]]):
    """
    Send measurements one by one to an in-process estimator; return (node, outputs).

    ``sequence`` holds (stamp_ns, position_m) pairs, sent with σ = 1 m in frame odom.
    ``topics`` maps each output topic to (message type, the node's count of what it has
    published there); after each measurement the probe waits until it has them all.
    """
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from kf_train.ros import messages
    node, publishers, outputs = estimator_and_probe(
        context, executor, parameters, {'measurement': PoseWithCovarianceStamped},
        {topic: kind for topic, (kind, _) in topics.items()})
    for stamp_ns, position_m in sequence:
        received = node.received
        publishers['measurement'].publish(
            messages.to_measurement_msg(stamp_ns, 'odom', position_m, 1.0))
        assert spin_until(executor, lambda: node.received == received + 1, 5.0)
        assert spin_until(executor, lambda: all(
            len(outputs[topic]) == count(node) for topic, (_, count) in topics.items()), 5.0)
    return node, outputs
