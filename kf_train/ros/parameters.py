"""Parameter declaration helpers: every parameter gets a descriptor with a range."""

from typing import Any, Optional, Tuple

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

# Largest double range bound we advertise; rclpy compares with it inclusively.
BIG = 1e12


def declare(node: Node, name: str, default: Any, description: str, *,
            float_range: Optional[Tuple[float, float]] = None,
            int_range: Optional[Tuple[int, int]] = None,
            constraints: str = '', read_only: bool = False) -> Any:
    """Declare ``name`` with a descriptor and return its (possibly overridden) value."""
    descriptor = ParameterDescriptor(description=description,
                                     additional_constraints=constraints,
                                     read_only=read_only)
    if float_range is not None:
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=float(float_range[0]), to_value=float(float_range[1]), step=0.0)]
    if int_range is not None:
        descriptor.integer_range = [IntegerRange(
            from_value=int(int_range[0]), to_value=int(int_range[1]), step=0)]
    return node.declare_parameter(name, default, descriptor).value


def allowed(node: Node, name: str) -> str:
    """Return a short text of what ``name`` accepts, from its descriptor."""
    descriptor = node.describe_parameter(name)
    if descriptor.floating_point_range:
        r = descriptor.floating_point_range[0]
        return f'a double in [{r.from_value:g}, {r.to_value:g}]'
    if descriptor.integer_range:
        r = descriptor.integer_range[0]
        return f'an integer in [{r.from_value}, {r.to_value}]'
    return descriptor.additional_constraints or 'see the parameter description'
