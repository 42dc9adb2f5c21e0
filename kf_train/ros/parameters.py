"""
A node's parameter table in rclpy: descriptors, declaration, and validate-then-apply changes.

The tables themselves are pure (:mod:`kf_train.ros.param_spec`); this is the only
parameter code that needs rclpy. A runtime change goes the way rclpy's design (and
demo_nodes_py's set_parameters_callback) lays out: rclpy checks each value against its
descriptor (type, range, read-only), the on-set callback validates the change as a
whole without side effects, and the post-set callback applies it.
"""

from typing import Any, Callable, Dict

from kf_train.ros.param_spec import is_implicit, ParameterError, ParamSpec, ParamTable
from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult)
from rclpy.node import Node


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """Return the ParameterDescriptor of a spec: what ``ros2 param describe`` shows."""
    result = ParameterDescriptor(description=spec.description,
                                 additional_constraints=spec.additional_constraints
                                 if spec.range is None else '',
                                 read_only=not spec.live)
    if spec.range is not None and spec.type == 'double':
        result.floating_point_range = [FloatingPointRange(
            from_value=float(spec.range[0]), to_value=float(spec.range[1]), step=0.0)]
    elif spec.range is not None:
        result.integer_range = [IntegerRange(
            from_value=int(spec.range[0]), to_value=int(spec.range[1]), step=0)]
    return result


def declare_table(node: Node, table: ParamTable) -> Dict[str, Any]:
    """
    Declare every parameter of ``table`` on ``node``; return their values.

    The key parameter (the preset, the scenario) goes first: the defaults of the
    derived ones depend on its value (a bad one raises ParameterError). rclpy checks
    each override against its descriptor and raises with its own text, which
    kf_train.ros.runner turns into the same line the table gives.
    """
    values = {}
    if table.key:
        key_spec = table.spec(table.key)
        values[table.key] = _declare(node, key_spec, key_spec.default)
    defaults = table.defaults(values.get(table.key))
    for spec in table.specs:
        if spec.name not in values:
            values[spec.name] = _declare(node, spec, defaults[spec.name])
    return values


def _declare(node: Node, spec: ParamSpec, default) -> Any:
    """Declare one parameter (a managed node's re-configure: read it); return its value."""
    if node.has_parameter(spec.name):
        value = node.get_parameter(spec.name).value
    else:
        value = node.declare_parameter(spec.name, default, descriptor(spec)).value
    return list(value) if spec.type == 'double_array' else value


def watch_changes(node: Node, validate: Callable[[Dict[str, Any]], Any],
                  apply: Callable[[Dict[str, Any]], None]) -> Callable[[], None]:
    """
    Validate parameter changes with ``validate`` and apply them with ``apply``.

    ``validate(changes)`` must have no side effects and raise ParameterError for an
    invalid change (its reason is the answer; the old values stay); ``apply(changes)``
    runs once rclpy has stored the new values. ``changes`` maps name to new value.
    Returns a function that removes both callbacks again (a managed node's cleanup).
    """
    def on_set(parameters) -> SetParametersResult:
        try:
            validate(_changes(parameters))
        except ParameterError as error:
            return SetParametersResult(successful=False, reason=error.reason)
        return SetParametersResult(successful=True)

    def on_post_set(parameters) -> None:
        apply(_changes(parameters))

    node.add_on_set_parameters_callback(on_set)
    node.add_post_set_parameters_callback(on_post_set)

    def unwatch() -> None:
        node.remove_on_set_parameters_callback(on_set)
        node.remove_post_set_parameters_callback(on_post_set)
    return unwatch


def _changes(parameters) -> Dict[str, Any]:
    """Return {name: value} of a parameter list (arrays as lists; rclpy's own left out)."""
    return {parameter.name: list(parameter.value) if type(parameter.value).__name__ in (
        'array', 'tuple') else parameter.value for parameter in parameters
        if not is_implicit(parameter.name)}
