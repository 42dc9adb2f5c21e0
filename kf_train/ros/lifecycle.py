"""
Managed (lifecycle) variants of kf_train's nodes: ``-p managed:=true``.

:func:`managed_class` turns a node class into a ``rclpy.lifecycle`` node that starts
``unconfigured``. The node class provides what the variant needs:

* ``NODE_NAME``;
* ``configure()``: declares and checks the parameters and creates everything the node
  uses (its plain ``__init__`` calls it too);
* ``GATED_CALLBACKS``: the names of the callbacks that only run while ``active``
  (subscriptions and timers: an inactive node neither takes input nor publishes).

The transitions (``ros2 lifecycle set /estimator configure`` ...):

* ``configure``: ``configure()``; an invalid parameter fails the transition (back to
  ``unconfigured``) with the node's one-line reason in the log (level ERROR);
* ``activate`` / ``deactivate``: the gated callbacks run / return at once;
* ``cleanup``: every publisher, subscription, timer and service made by ``configure()``
  is destroyed and the parameter-change callbacks removed; the parameters stay
  declared (rclpy cannot undeclare read-only ones), so the next ``configure`` reads
  their current values;
* ``shutdown`` (from any state): as cleanup, then the node's ``done`` future completes
  and the process exits with code 0 (kf_train.ros.runner).

Whether a node is managed is decided before it exists, so :func:`managed_requested`
reads ``managed`` from the command line (``-p``/``--param``, ``--params-file``) as
rcl would give it to the node; the node then declares it like any parameter.
"""

import sys
from typing import Callable, List, Optional

from kf_train.ros.param_spec import (
    node_parameters, ParameterError, parse_override, read_params_file)
from kf_train.ros.runner import one_line, StartupError
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.lifecycle import LifecycleNodeMixin, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.task import Future

CONFIGURE_ERRORS = (ParameterError, StartupError, InvalidParameterValueException,
                    InvalidParameterTypeException, ValueError)
"""What an invalid parameter raises while a node configures."""
SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE


def managed_requested(args: Optional[List[str]], node_name: str) -> bool:
    """Return the ``managed`` parameter the command line gives ``node_name`` (False)."""
    argv = list(sys.argv if args is None else args)
    files, overrides, in_ros = [], {}, False
    for i, arg in enumerate(argv):
        value = argv[i + 1] if i + 1 < len(argv) else ''
        if arg == '--ros-args':
            in_ros = True
        elif arg == '--':
            in_ros = False
        elif in_ros and arg in ('-p', '--param') and value.startswith('managed:='):
            overrides.update([parse_override(value)])
        elif in_ros and arg == '--params-file' and value:
            try:
                files.append(node_parameters(read_params_file(value), node_name))
            except (OSError, ParameterError):
                pass  # rcl reports an unreadable file itself
    values = {}
    for section in files + [overrides]:  # the command line's -p over the files, as rcl
        values.update(section)
    return values.get('managed') is True


def node_factory(node_class: type, args: Optional[List[str]]) -> Callable[[], Node]:
    """Return what makes the node the command line asks for: managed or not."""
    return managed_class(node_class) if managed_requested(
        args, node_class.NODE_NAME) else node_class


def managed_class(node_class: type) -> type:
    """Return the managed (lifecycle) variant of ``node_class`` (see the module doc)."""
    class Managed(LifecycleNodeMixin, node_class):
        __doc__ = f'{node_class.__name__}, managed: starts unconfigured.'

        def __init__(self, **kwargs):
            Node.__init__(self, node_class.NODE_NAME, **kwargs)
            LifecycleNodeMixin.__init__(self)
            self.active = False
            self.done = Future()
            self._before_configure = None
            self._unwatch = None

        def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
            self._before_configure = _entities(self)
            try:
                self.configure()
            except CONFIGURE_ERRORS as error:
                self.get_logger().error(f'configure failed: {one_line(error)}')
                self._teardown()
                return FAILURE
            return SUCCESS

        def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
            self.active = True
            return SUCCESS

        def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
            self.active = False
            return SUCCESS

        def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
            self._teardown()
            return SUCCESS

        def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
            self.active = False
            self._teardown()
            if not self.done.done():
                self.done.set_result(None)
            return SUCCESS

        def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
            self.active = False
            self._teardown()
            return SUCCESS

        def _teardown(self) -> None:
            """Destroy what configure() made; keep the parameters and lifecycle services."""
            if self._before_configure is None:
                return
            if self._unwatch is not None:
                self._unwatch()
                self._unwatch = None
            kept = self._before_configure
            self._before_configure = None
            for entity in _entities(self) - kept:
                _destroy(self, entity)

    for name in node_class.GATED_CALLBACKS:
        setattr(Managed, name, _gated(getattr(node_class, name)))
    Managed.__name__ = Managed.__qualname__ = 'Managed' + node_class.__name__
    return Managed


def _gated(callback: Callable) -> Callable:
    """Return ``callback`` running only while the node is active."""
    def gated(self, *args):
        if self.active:
            return callback(self, *args)
        return None
    gated.__doc__ = callback.__doc__
    return gated


def _entities(node: Node) -> frozenset:
    """Return the node's publishers, subscriptions, timers, services and clients."""
    return frozenset(node.publishers) | frozenset(node.subscriptions) | frozenset(
        node.timers) | frozenset(node.services) | frozenset(node.clients)


def _destroy(node: Node, entity) -> None:
    """Destroy one entity of the node."""
    for kind, destroy in (('publishers', node.destroy_publisher),
                          ('subscriptions', node.destroy_subscription),
                          ('timers', node.destroy_timer), ('services', node.destroy_service),
                          ('clients', node.destroy_client)):
        if entity in getattr(node, kind):
            destroy(entity)
            return
