"""Pytest configuration shared by the kf_train test suite."""

import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(__file__))
import ros_helpers  # noqa: E402, I100


def pytest_configure(config):
    """Register the markers used by the test suite."""
    for marker in (
        'flake8: marks tests checking for flake8 compliance',
        'linter: marks tests running a code linter',
        'slow: marks tests that take long to run',
    ):
        config.addinivalue_line('markers', marker)


def pytest_collection_modifyitems(config, items):
    """
    Run the linters first.

    flake8 forks worker processes; forking a process that still holds DDS threads from
    earlier ROS tests can deadlock the child, so the linters go before any ROS test.
    """
    items.sort(key=lambda item: 0 if item.get_closest_marker('linter') else 1)


@pytest.fixture
def domain_id(monkeypatch):
    """Give the test its own ROS domain, confined to this host."""
    domain = ros_helpers.next_domain_id()
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return domain


@pytest.fixture
def ros_context(domain_id):
    """Yield an rclpy Context of the test's own, shut down afterwards."""
    context = ros_helpers.make_context(domain_id)
    yield context
    context.try_shutdown()


@pytest.fixture
def executor(ros_context):
    """Yield a SingleThreadedExecutor bound to the test's context."""
    from rclpy.executors import SingleThreadedExecutor
    executor = SingleThreadedExecutor(context=ros_context)
    yield executor
    nodes = executor.get_nodes()
    executor.shutdown()
    for node in nodes:
        node.destroy_node()
