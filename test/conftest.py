"""
Pytest configuration shared by the whole kf_train suite.

It imports no ROS package, so that ``test/unit`` runs in a venv without ROS wheels. The
suite is split by what a test needs:

* ``unit/``: neither ROS nor node processes (marker ``unit``; ``make test-core``);
* ``ros/``: rclpy nodes in this process (marker ``ros``);
* ``integration/``: nodes in other processes, console scripts, DDS (marker ``integration``);
* ``lint/``: ament flake8 and pep257 (marker ``linter``).

The ROS fixtures (a domain and a Context per test) live in ``ros_fixtures.py``, which only
the ``ros/`` and ``integration/`` conftests import.
"""

import os
import sys

import pytest

TEST_DIR = os.path.dirname(os.path.abspath(__file__))
# ros_helpers.py and ros_fixtures.py sit here, beside the folders that use them.
sys.path.insert(0, TEST_DIR)

LAYERS = {
    'unit': 'needs neither ROS nor node processes (runs without ROS wheels)',
    'ros': 'runs rclpy nodes in the test process',
    'integration': 'runs nodes or console scripts in other processes, over DDS',
}


def pytest_configure(config):
    """Register the markers used by the test suite."""
    for marker in (
        'flake8: marks tests checking for flake8 compliance',
        'linter: marks tests running a code linter',
        'slow: marks tests that take long to run',
        *(f'{name}: {text}' for name, text in LAYERS.items()),
    ):
        config.addinivalue_line('markers', marker)


def _layer(item) -> str:
    """Return the top folder below test/ that holds ``item``."""
    relative = os.path.relpath(str(item.path), TEST_DIR)
    return relative.split(os.sep, 1)[0]


def pytest_collection_modifyitems(config, items):
    """
    Mark every test with its layer, and run the linters first.

    flake8 forks worker processes; forking a process that still holds DDS threads from
    earlier ROS tests can deadlock the child, so the linters go before any ROS test.
    """
    for item in items:
        layer = _layer(item)
        if layer in LAYERS:
            item.add_marker(getattr(pytest.mark, layer))
    items.sort(key=lambda item: 0 if item.get_closest_marker('linter') else 1)
