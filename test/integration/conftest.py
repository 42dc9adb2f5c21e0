"""ROS fixtures for this folder: an isolated domain and an rclpy Context per test."""

from ros_fixtures import domain_id, executor, owned_nodes, ros_context  # noqa: F401
