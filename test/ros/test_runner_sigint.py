"""The nodes' SIGINT handler (kf_train.ros.runner._InterruptOnce), called directly."""

import signal

from kf_train.ros import runner
import pytest


@pytest.fixture
def handler():
    """Return a fresh _InterruptOnce; put the process's SIGINT handler back afterwards."""
    before = signal.getsignal(signal.SIGINT)
    try:
        yield runner._InterruptOnce()
    finally:
        signal.signal(signal.SIGINT, before)


def test_before_rclpy_init_the_first_sigint_raises_and_the_next_do_not(handler):
    with pytest.raises(KeyboardInterrupt):
        handler._on_sigint(signal.SIGINT, None)
    assert handler._on_sigint(signal.SIGINT, None) is None
    handler.restore()
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_after_rclpy_shut_the_context_down_spin_ends_it_alone(handler, monkeypatch):
    # rclpy's own handler ran first and shut the context down: no KeyboardInterrupt
    # (it could land inside rclpy's internals), spin() ends at its next wait.
    handler.context_shut_down_first = True
    monkeypatch.setattr(runner.rclpy, 'ok', lambda *args, **kwargs: False)
    assert handler._on_sigint(signal.SIGINT, None) is None
    assert handler.interrupted


def test_a_context_still_running_is_interrupted_as_before(handler, monkeypatch):
    handler.context_shut_down_first = True
    monkeypatch.setattr(runner.rclpy, 'ok', lambda *args, **kwargs: True)
    with pytest.raises(KeyboardInterrupt):
        handler._on_sigint(signal.SIGINT, None)
