"""Print the README's parameter tables from the nodes' own declarations."""

import os
import sys

import rclpy


def rows(node):
    """Yield one Markdown table row per declared parameter of ``node``."""
    for name in sorted(node._parameters):
        if name in ('use_sim_time', 'start_type_description_service'):
            continue
        descriptor = node.describe_parameter(name)
        value = node.get_parameter(name).value
        if isinstance(value, (list, tuple)) or type(value).__name__ == 'array':
            value = '[' + ', '.join(f'{v:g}' for v in value) + ']'
        if descriptor.floating_point_range:
            r = descriptor.floating_point_range[0]
            allowed = f'[{r.from_value:g}, {r.to_value:g}]'
        elif descriptor.integer_range:
            r = descriptor.integer_range[0]
            allowed = f'[{r.from_value}, {r.to_value}]'
        else:
            allowed = descriptor.additional_constraints or ''
        live = 'no (restart)' if descriptor.read_only else 'yes'
        text = ' '.join(descriptor.description.split()).replace('|', '\\|')
        yield f'| `{name}` | `{value}` | {allowed} | {live} | {text} |'


def main() -> int:
    """Print both tables."""
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    from kf_train.ros.estimator_node import EstimatorNode
    from kf_train.ros.simulator_node import SimulatorNode
    rclpy.init()
    try:
        for title, cls in (('simulator', SimulatorNode), ('estimator', EstimatorNode)):
            node = cls()
            print(f'### `{title}`\n')
            print('| parameter | default | range | live | description |')
            print('|---|---|---|---|---|')
            for row in rows(node):
                print(row)
            print()
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
