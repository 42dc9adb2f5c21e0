"""
QoS by parameter and QoS mismatches reported: the rclpy side of both.

Every publisher and subscription of kf_train's nodes is created with
:data:`OVERRIDES` (rclpy's standard QoS overrides): rclpy declares
``qos_overrides.<topic>.<publisher|subscription>.<policy>`` (history, depth and
reliability; read-only, so given at start-up with ``-p`` or a params
file) starting from the profile the node passes, and applies them. For the
estimator's inputs that profile is made of ``qos_reliability`` and ``qos_depth``, so
those parameters keep working and are the overrides' defaults.

:func:`subscription_events` / :func:`publisher_events` replace rclpy's default
incompatible-QoS callbacks (a warning per event) with one warning per topic and
policy, recorded in an :class:`kf_train.ros.input_watch.InputWatch` for
``/diagnostics``.
"""

from typing import Callable

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import qos_policy_name_from_kind
from rclpy.qos_overriding_options import QoSOverridingOptions

OVERRIDES = QoSOverridingOptions.with_default_policies()
"""Overrides of history, depth and reliability, for every topic."""


def _on_incompatible(node: Node, topic: str, other: str, record) -> Callable:
    """Return the incompatible-QoS callback of one topic (``other``: who is incompatible)."""
    name = node.resolve_topic_name(topic)

    def callback(info) -> None:
        policy = qos_policy_name_from_kind(info.last_policy_kind)
        if record(name, policy, max(int(info.total_count_change), 1)):
            node.get_logger().warning(
                f'{other} on {name} has an incompatible QoS: {policy} (nothing it sends '
                'or asks for gets through; see the qos_overrides parameters)')
    return callback


def subscription_events(node: Node, topic: str, record) -> SubscriptionEventCallbacks:
    """Return event callbacks for a subscription to ``topic``: mismatches to ``record``."""
    return SubscriptionEventCallbacks(
        incompatible_qos=_on_incompatible(node, topic, 'a publisher', record))


def publisher_events(node: Node, topic: str, record) -> PublisherEventCallbacks:
    """Return event callbacks for a publisher on ``topic``: mismatches to ``record``."""
    return PublisherEventCallbacks(
        incompatible_qos=_on_incompatible(node, topic, 'a subscription', record))
