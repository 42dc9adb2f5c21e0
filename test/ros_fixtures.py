"""Fixtures for tests that run ROS: their own domain on this host, a Context per test."""

import pytest
import ros_helpers


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


@pytest.fixture(autouse=True)
def owned_nodes():
    """Destroy the nodes the test registered with ros_helpers.own_node, afterwards."""
    yield
    ros_helpers.destroy_owned_nodes()
