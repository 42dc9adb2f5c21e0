"""
The shared ``main()`` of kf_train's nodes: clean exits on Ctrl-C, SIGTERM and bad input.

Ctrl-C reaches ``spin()`` as ``KeyboardInterrupt``; SIGTERM (rclpy's signal handler)
and a shutdown from elsewhere as ``ExternalShutdownException``. Both end the node with
exit code 0 and no traceback. An invalid parameter at start-up prints one line naming
the parameter and what it accepts, and exits with code 2.
"""

import sys
from typing import Callable, List, Optional

import rclpy
from rclpy.exceptions import (
    InvalidParameterTypeException, InvalidParameterValueException)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

EXIT_OK = 0
EXIT_BAD_PARAMETER = 2


class StartupError(Exception):
    """A configuration problem found while a node starts; its text is the whole message."""


def run(make_node: Callable[[], Node], args: Optional[List[str]] = None) -> int:
    """
    Create a node, spin it until shutdown or until it says it is done, and exit cleanly.

    A node may offer a ``done`` future (rclpy.task.Future); spinning stops when it
    completes, e.g. a simulator that has published its last sample.
    """
    rclpy.init(args=args)
    node = None
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
        return EXIT_OK
    except (InvalidParameterValueException, InvalidParameterTypeException,
            StartupError) as error:
        print(f'error: {_one_line(error)}', file=sys.stderr)
        return EXIT_BAD_PARAMETER
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


def _one_line(error: Exception) -> str:
    """Return an exception's text on one line."""
    return ' '.join(str(error).split())
