"""
The ROS side of ``kf-train demo``: its probe node, parameter calls, and their context.

:class:`Probe` records every message on the simulator's and the estimator's topics;
:func:`fetch_parameters` and :func:`set_parameter` talk to a node's parameter
services; :func:`start_probe` brings a probe up in a context of its own. The demo
itself (processes, checks, report) is :mod:`kf_train.cli.demo`.
"""

import time
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import AccelStamped, PoseWithCovarianceStamped
from kf_train.ros.diagnostics import MATCHED_KEYS, STATUS_SUFFIX
from nav_msgs.msg import Odometry
import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Float64MultiArray

__all__ = ['Context', 'ExternalShutdownException', 'fetch_parameters', 'Probe', 'PROBE_DEPTH',
           'RAIL_TOPICS', 'set_parameter', 'start_probe', 'TOPICS']

PROBE_DEPTH = 1000
"""Keep-last depth of the probe's subscriptions: never the bottleneck."""


TOPICS = {
    'measurement': PoseWithCovarianceStamped,
    'ground_truth': Odometry,
    'estimate': Odometry,
    'prediction': Odometry,
}
"""The topics the probe records, with their message types."""
RAIL_TOPICS = {**TOPICS, 'ground_truth_accel': AccelStamped,
               'regime_probabilities': Float64MultiArray, '/diagnostics': DiagnosticArray}
"""What the probe records of a rail run: the true acceleration, the regimes, the status."""


class Probe(Node):
    """Records every message on the simulator's and the estimator's topics."""

    def __init__(self, *, context: Optional[Context] = None,
                 node_name: str = 'kf_train_probe', namespace: str = '',
                 depth: int = PROBE_DEPTH, subscribe_measurement: bool = True,
                 topics: Mapping[str, type] = TOPICS, estimator_name: str = 'estimator'):
        """
        Subscribe to ``topics`` (TOPICS: ground_truth, estimate, prediction), measurement last.

        The topics are relative: in ``namespace`` they are the nodes' of that namespace.
        Subscribing to ``measurement`` late (:meth:`subscribe_measurement`) lets a
        simulator with ``min_subscribers`` wait until the probe listens everywhere.
        """
        super().__init__(node_name, context=context, namespace=namespace)
        self.qos = QoSProfile(depth=depth)
        self.topics = dict(topics)
        self.received: Dict[str, List] = {topic: [] for topic in self.topics}
        self._estimator_status: Optional[Dict[str, str]] = None
        self._status_name = f'{estimator_name}: {STATUS_SUFFIX}'
        self._topic_subscriptions = {}
        for topic in self.topics:
            if topic != 'measurement':
                self._subscribe(topic)
        if '/diagnostics' not in self.topics:
            # Not recorded, only read: the estimator's status tells what it has matched.
            self._status_subscription = self.create_subscription(
                DiagnosticArray, '/diagnostics', self._on_diagnostics, self.qos)
        if subscribe_measurement:
            self.subscribe_measurement()

    def _subscribe(self, topic: str) -> None:
        """Record ``topic`` into ``self.received[topic]``."""
        record = self.received[topic].append
        if topic == '/diagnostics':
            def record(msg, append=record):
                append(msg)
                self._on_diagnostics(msg)
        self._topic_subscriptions[topic] = self.create_subscription(
            self.topics[topic], topic, record, self.qos)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        """Keep the values of the estimator's newest status."""
        for status in msg.status:
            if status.name == self._status_name:
                self._estimator_status = {value.key: value.value for value in status.values}

    def estimator_status(self) -> Optional[Dict[str, str]]:
        """Return the values of the estimator's newest /diagnostics status, or None."""
        return self._estimator_status

    def estimator_connected(self) -> bool:
        """
        Return whether the estimator's newest status shows its input and outputs matched.

        DDS matches each end of a topic on its own: the simulator (``min_subscribers``)
        and the probe see only their own ends. A best-effort reader drops what arrives
        from a writer it has not matched yet, so before the first sample goes out the
        estimator must report a matched measurement publisher, and estimate and
        prediction subscribers.
        """
        status = self._estimator_status or {}
        return all(int(status.get(key, '0')) >= 1 for key in MATCHED_KEYS)

    def subscribe_measurement(self) -> None:
        """Start recording ``measurement`` (idempotent)."""
        if 'measurement' not in self._topic_subscriptions:
            self._subscribe('measurement')

    def counts(self) -> Dict[str, int]:
        """Return how many messages each topic has delivered so far."""
        return {topic: len(msgs) for topic, msgs in self.received.items()}

    def sees_nodes(self) -> bool:
        """Return whether both nodes' publishers are matched and the estimator listens."""
        # The graph (count_publishers) learns of an endpoint before DDS matches it; a
        # message sent in between is lost (and the estimator publishes only to matched
        # subscribers), so the probe's own subscriptions must report a matched publisher.
        return (all(self.count_publishers(topic) >= 1 for topic in self.topics)
                and all(subscription.get_publisher_count() >= 1
                        for subscription in self._topic_subscriptions.values())
                and self.count_subscribers('measurement') >= 1)


def start_probe(context: Context, domain_id: int, topics: Mapping[str, type] = TOPICS,
                events: bool = False) -> Tuple[SingleThreadedExecutor, Probe]:
    """
    Initialise ``context`` in ``domain_id`` and return (executor, probe) spinning in it.

    The probe does not record ``measurement`` yet (:meth:`Probe.subscribe_measurement`).
    rclpy's signal handlers stay off: the demo handles SIGINT and SIGTERM itself.
    """
    rclpy.init(context=context, domain_id=domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    probe = Probe(context=context, subscribe_measurement=False, topics=topics)
    # rclpy's EventsExecutor takes several times the message rate of the default one:
    # for a probe of hundreds of messages a second (a run played faster).
    executor = (EventsExecutor if events else SingleThreadedExecutor)(context=context)
    executor.add_node(probe)
    return executor, probe


def fetch_parameters(executor, node: Node, target: str, names: Sequence[str],
                     timeout_s: float, attempt_s: float = 2.0) -> Optional[Dict[str, object]]:
    """
    Return parameters of node ``target`` by a service round trip, or None after timeout_s.

    A call is repeated every ``attempt_s``: one made while discovery is still going on
    may be lost. Undeclared parameters come back as None.
    """
    names = list(names)
    response = _call_until_answered(
        executor, AsyncParameterClient(node, target),
        lambda client: client.get_parameters(names), timeout_s, attempt_s)
    if response is None:
        return None
    return {name: parameter_value_to_python(value)
            for name, value in zip(names, response.values)}


def set_parameter(executor, node: Node, target: str, name: str, value,
                  timeout_s: float, attempt_s: float = 2.0) -> Optional[str]:
    """Set one parameter of node ``target``; return None on success, else the reason."""
    response = _call_until_answered(
        executor, AsyncParameterClient(node, target),
        lambda client: client.set_parameters([Parameter(name, value=value)]),
        timeout_s, attempt_s)
    if response is None:
        return f'{target} did not answer within {timeout_s:g} s'
    result = response.results[0]
    return None if result.successful else result.reason


def _call_until_answered(executor, client: AsyncParameterClient, call, timeout_s: float,
                         attempt_s: float):
    """Return the response of ``call(client)``, repeated every attempt_s; None on timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not client.wait_for_services(
                timeout_sec=max(0.0, min(attempt_s, deadline - time.monotonic()))):
            continue
        future = call(client)
        executor.spin_until_future_complete(
            future, timeout_sec=max(0.0, min(attempt_s, deadline - time.monotonic())))
        if future.done() and future.result() is not None:
            return future.result()
    return None
