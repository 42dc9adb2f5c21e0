"""Pytest configuration shared by the kf_train test suite."""


def pytest_configure(config):
    """Register the markers used by the test suite."""
    for marker in (
        'flake8: marks tests checking for flake8 compliance',
        'linter: marks tests running a code linter',
        'slow: marks tests that take long to run',
    ):
        config.addinivalue_line('markers', marker)
