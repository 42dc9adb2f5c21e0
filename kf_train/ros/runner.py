"""
The shared ``main()`` of kf_train's nodes: clean exits on Ctrl-C, SIGTERM and bad input.

Ctrl-C and SIGTERM shut the context down (rclpy's signal handler), and a shutdown
from elsewhere does too: ``spin()`` ends with ``ExternalShutdownException``. A Ctrl-C
before ``rclpy.init`` arrives as ``KeyboardInterrupt``. Each ends the node with exit
code 0 and no traceback. An invalid parameter at start-up prints one line naming
the parameter and what it accepts, and exits with code 2.

After a signal, the clean-up (the node's and the context's DDS teardown) gets
CLEANUP_TIMEOUT_S: a teardown that has not returned by then (seen in rclpy's
``destroy_node`` after SIGTERM, rarely, on loaded machines; ros2/rclpy#456 and related)
ends the process with code 0 and one warning line, instead of leaving a stopped node
hanging until it is killed (:func:`exit_if_stuck`).
"""

import contextlib
import os
import re
import signal
import sys
import threading
from typing import Callable, List, Optional, Tuple

from kf_train.ros.param_spec import out_of_range_line, ParameterError, wrong_type_line
import rclpy
from rclpy.exceptions import (
    InvalidParameterTypeException, InvalidParameterValueException)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future

RCLError = rclpy_implementation.RCLError
EXIT_OK = 0
EXIT_BAD_PARAMETER = 2
CLEANUP_TIMEOUT_S = 5.0
"""How long the clean-up after a signal may take; within ``ros2 launch``'s 5 s before it
escalates SIGINT to SIGTERM, a normal one takes well under a second."""


class StartupError(Exception):
    """A configuration problem found while a node starts; its text is the whole message."""


def run(make_node: Callable[[], Node], args: Optional[List[str]] = None,
        executor: str = 'single_threaded') -> int:
    """
    Create a node, spin it until shutdown or until it says it is done, and exit cleanly.

    A node may offer a ``done`` future (rclpy.task.Future); spinning stops when it
    completes, e.g. a simulator that has published its last sample. ``executor`` is
    one of :data:`EXECUTORS` (see :func:`executor_option`).
    """
    if executor != 'single_threaded':
        return _run_other_executor(make_node, args, executor)
    sigint = _InterruptOnce()
    rclpy.init(args=args)
    sigint.context_shut_down_first = True   # rclpy's handler (init's) comes before it
    node = None
    signalled = False
    try:
        node = make_node()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        done = getattr(node, 'done', None)
        if done is not None:
            executor.spin_until_future_complete(done)
        else:
            executor.spin()
        return EXIT_OK
    except (KeyboardInterrupt, ExternalShutdownException):
        signalled = True
        return EXIT_OK
    except RCLError:
        # SIGTERM shuts the context down from rclpy's signal handler; if that lands
        # between spin()'s shutdown check and its wait set, rcl raises instead.
        if rclpy.ok():
            raise
        signalled = True
        return EXIT_OK
    except (InvalidParameterValueException, InvalidParameterTypeException,
            ParameterError, StartupError) as error:
        print(f'error: {one_line(error)}', file=sys.stderr)
        return EXIT_BAD_PARAMETER
    finally:
        with exit_if_stuck(CLEANUP_TIMEOUT_S, armed=signalled):
            if isinstance(executor, SingleThreadedExecutor):
                # Explicitly, not in Executor.__del__ at exit: that prints "Exception
                # ignored ... InvalidHandle" with a traceback after a SIGINT.
                executor.shutdown(timeout_sec=0)
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
        sigint.restore()


@contextlib.contextmanager
def exit_if_stuck(timeout_s: float, armed: bool = True):
    """
    Run the block; if it has not finished after timeout_s, end the process with exit 0.

    For the clean-up after a signal only (``armed``): the node has stopped as asked,
    and a DDS teardown that never returns must not keep it alive. A daemon timer
    thread flushes the standard streams, prints one warning line and calls os._exit.
    """
    if not armed:
        yield
        return
    timer = threading.Timer(timeout_s, _exit_stuck, (timeout_s,))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def _exit_stuck(timeout_s: float) -> None:
    """End the process with EXIT_OK after a clean-up that did not return (exit_if_stuck)."""
    try:
        sys.stdout.flush()
        print(f'warning: the clean-up after the signal did not finish within {timeout_s:g} s '
              '(a DDS teardown that did not return); exiting', file=sys.stderr, flush=True)
    finally:
        os._exit(EXIT_OK)


class _InterruptOnce:
    """
    A node process's SIGINT handler: the first ends the spin, later ones do nothing.

    A Ctrl-C in a terminal running ``ros2 launch`` reaches launch and its nodes (one
    process group), and launch then sends each node a SIGINT of its own: without this,
    that second one lands in the clean-up and prints a KeyboardInterrupt traceback
    (exit -2). rclpy's handler, installed by ``rclpy.init`` after this one, still shuts
    the context down first and then calls it. Off the main thread, where handlers
    cannot be set, it changes nothing.
    """

    def __init__(self):
        """Install the handler (main thread only), remembering the one it replaces."""
        self.interrupted = False
        self.previous = None
        # True once rclpy.init has put its handler before this one (see _on_sigint).
        self.context_shut_down_first = False
        if threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGINT, self._on_sigint)
            # None: a handler set outside Python; Python's own is the best stand-in.
            self.previous = signal.default_int_handler if previous is None else previous

    def _on_sigint(self, signum, frame) -> None:
        if self.interrupted:
            return
        self.interrupted = True
        # After rclpy.init, rclpy's handler has shut the context down before it calls
        # this one, and spin() ends at its next wait (ExternalShutdownException). A
        # KeyboardInterrupt on top of that lands wherever Python is: once (CI) inside
        # rclpy's Task.__init__ before its fields were set, whose __del__ then printed a
        # traceback. So it is raised only while the context is still running (before
        # rclpy.init, or if its handler did not act), as Python's own handler would.
        if not (self.context_shut_down_first and not rclpy.ok()):
            raise KeyboardInterrupt

    def restore(self) -> None:
        """
        Put the previous handler back, unless a SIGINT came: then ignore SIGINT.

        Ignored to the end of the process, because while Python finalises it resets a
        handler of its own to the default, fatal action, and one more SIGINT would then
        end the process with -2 after it had shut down cleanly.
        """
        if self.previous is not None:
            signal.signal(signal.SIGINT,
                          signal.SIG_IGN if self.interrupted else self.previous)


# rclpy's texts (Jazzy), e.g. "Invalid parameter value (-1.0) for parameter. Reason:
# Parameter rate_hz out of range Min: 0.01, Max: 10000.0, value: -1.0: rate_hz" and
# "Trying to set parameter 'rate_hz' to '10' of type 'INTEGER', expecting type 'DOUBLE':
# rate_hz"; anything else is passed on as it is.
_OUT_OF_RANGE = re.compile(r'Parameter (?P<name>\S+) out of range\.? Min: (?P<low>[^,]+), '
                           r'Max: (?P<high>[^,]+), value: (?P<value>.+?): (?P=name)$')
_WRONG_TYPE = re.compile(r"Trying to set parameter '(?P<name>[^']+)' to '(?P<value>.*)' of "
                         r"type '(?P<got>\w+)', expecting type '(?P<want>\w+)'")


def one_line(error: Exception) -> str:
    """Return an exception's text on one line, naming the parameter and what it accepts."""
    text = ' '.join(str(error).split())
    match = _OUT_OF_RANGE.search(text)
    if match:
        return out_of_range_line(match['name'], match['value'], match['low'], match['high'],
                                 integer=match['low'].lstrip('-').isdigit())
    match = _WRONG_TYPE.search(text)
    if match:
        return wrong_type_line(match['name'], match['value'], match['want'], match['got'])
    return text


# -- optional executors ---------------------------------------------------------------
#
# rclpy.experimental.EventsExecutor delivers several times the message rate of the
# SingleThreadedExecutor, but in this rclpy its spin() never returns on SIGINT or a
# shutdown from elsewhere and ignores SIGTERM: while it spins, the main thread never
# runs the Python signal handlers, rclpy's included. Its
# spin_until_future_complete() with a timeout does run them whenever one of its
# callbacks runs. So in 'events' mode the runner installs its own SIGINT and SIGTERM
# handlers, which complete a stop future, and gives the node a heartbeat timer so that
# a callback runs at least every HEARTBEAT_S even when no message arrives; the spin
# then returns within about HEARTBEAT_S of the signal.
# test/integration/test_events_executor.py proves the exit (code 0, no traceback,
# bounded time) at high message rates.

EXECUTORS = ('single_threaded', 'events')
"""Values of ``--executor``: rclpy's SingleThreadedExecutor (the default) or its
experimental EventsExecutor."""
HEARTBEAT_S = 0.1
SPIN_SLICE_S = 1.0


def executor_option(args: Optional[List[str]]) -> Tuple[Optional[List[str]], str]:
    """
    Take ``--executor KIND`` (or ``--executor=KIND``) out of a node's command line.

    Returns the remaining arguments (for rclpy.init) and KIND, 'single_threaded' when
    the option is absent; only arguments before ``--ros-args`` are looked at. An
    unknown or missing KIND is returned as it is for :func:`run` to refuse.
    """
    argv = list(sys.argv if args is None else args)
    end = argv.index('--ros-args') if '--ros-args' in argv else len(argv)
    kind = 'single_threaded'
    for i in range(1, end):
        if argv[i] == '--executor':
            kind = argv[i + 1] if i + 1 < end else ''
            del argv[i:i + 2]
            break
        if argv[i].startswith('--executor='):
            kind = argv[i].partition('=')[2]
            del argv[i]
            break
    else:
        return args, kind
    return argv, kind


def _run_other_executor(make_node: Callable[[], Node], args: Optional[List[str]],
                        kind: str) -> int:
    """Do :func:`run` with the EventsExecutor and the shutdown path described above."""
    if kind not in EXECUTORS:
        print(f'error: invalid --executor {kind!r}: must be one of '
              f'{", ".join(EXECUTORS)}', file=sys.stderr)
        return EXIT_BAD_PARAMETER
    if threading.current_thread() is not threading.main_thread():
        print('error: --executor events needs the main thread (its shutdown path uses '
              'signal handlers)', file=sys.stderr)
        return EXIT_BAD_PARAMETER
    stop = Future()

    def on_signal(signum, frame) -> None:
        if not stop.done():
            stop.set_result(signum)

    previous = {signum: signal.signal(signum, on_signal)
                for signum in (signal.SIGINT, signal.SIGTERM)}
    node = executor = None
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        node = make_node()
        node.create_timer(HEARTBEAT_S, _heartbeat)
        done = getattr(node, 'done', None)
        if done is not None:
            done.add_done_callback(lambda _: None if stop.done() else stop.set_result(0))
        executor = EventsExecutor()
        executor.add_node(node)
        while not stop.done():
            executor.spin_until_future_complete(stop, timeout_sec=SPIN_SLICE_S)
        return EXIT_OK
    except (KeyboardInterrupt, ExternalShutdownException):
        return EXIT_OK
    except (InvalidParameterValueException, InvalidParameterTypeException,
            ParameterError, StartupError) as error:
        print(f'error: {one_line(error)}', file=sys.stderr)
        return EXIT_BAD_PARAMETER
    finally:
        # A signal completes ``stop`` with its number; the node's own end with 0.
        signalled = stop.done() and stop.result() in previous
        with exit_if_stuck(SPIN_SLICE_S + CLEANUP_TIMEOUT_S, armed=signalled):
            if executor is not None:
                executor.shutdown(timeout_sec=SPIN_SLICE_S)
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _heartbeat() -> None:
    """Do nothing: running any callback lets the main thread run pending signal handlers."""
