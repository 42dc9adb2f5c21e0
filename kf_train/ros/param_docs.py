"""
Documents generated from the parameter tables: the reference's tables and a params file.

Pure (no rclpy). tools/parameter_tables.py writes docs/ros.md's parameter tables and
config/kf_train.yaml with these functions, and a unit test keeps both equal to what
they return; ``kf-train tune`` can write a params file with :func:`params_file`.
"""

import textwrap
from typing import Any, Mapping, Optional, Sequence, Tuple

from kf_train.ros.param_spec import ParamTable, yaml_scalar

CONFIG_HEADER = """\
# Every parameter of kf_train's two nodes with its default, in ROS 2 params-file format.
# Generated from the parameter tables (kf_train/ros/simulator_params.py and
# estimator_params.py) by `python tools/parameter_tables.py --write`: edit the tables,
# not this file (test/unit/test_param_tables.py keeps the two equal).
#
#   simulator --ros-args --params-file config/kf_train.yaml
#   estimator --ros-args --params-file config/kf_train.yaml
#   (or: ros2 run kf_train estimator --ros-args --params-file ...)
#
# Copy it and edit what you need. The nodes enforce the ranges; `ros2 param describe
# <node> <name>` prints the same descriptions. A line marked "the train's" holds the
# default of the default preset (scenario): for another one, delete the line, and the
# node takes that preset's (scenario's) own.
"""
_WIDTH = 92


def markdown_table(table: ParamTable) -> str:
    """Return the Markdown table of a node's parameters, sorted by name."""
    defaults = table.defaults()
    lines = ['| parameter | default | unit | range | live | description |',
             '|---|---|---|---|---|---|']
    for spec in sorted(table.specs, key=lambda spec: spec.name):
        text = ' '.join(spec.description.split()).replace('|', '\\|')
        live = 'yes' if spec.live else 'no (restart)'
        lines.append(f'| `{spec.name}` | `{yaml_scalar(defaults[spec.name])}` | {spec.unit} | '
                     f'{spec.accepts} | {live} | {text} |')
    return '\n'.join(lines) + '\n'


def reference_tables(tables: Sequence[ParamTable]) -> str:
    """Return docs/ros.md's parameter section body: one headed table per node."""
    return '\n'.join(f'### `{table.node}`\n\n{markdown_table(table)}' for table in tables)


def params_file(sections: Sequence[Tuple[ParamTable, Optional[Mapping[str, Any]]]],
                header: str = '', comments: bool = True) -> str:
    """
    Return a ROS params file with one section per (table, values) pair.

    ``values`` None lists every parameter with its default; otherwise the given ones
    only, in table order. With ``comments`` each parameter is preceded by its
    description and what it accepts, under its group's heading.
    """
    lines = [header] if header else []
    for table, values in sections:
        defaults = table.defaults()
        listed = defaults if values is None else values
        lines += [f'{table.node}:', '  ros__parameters:']
        group = None
        for spec in table.specs:
            if spec.name not in listed:
                continue
            if comments and spec.group != group:
                lines += [''] if group is not None else []
                group = spec.group
                lines.append(f'    # --- {group} ---')
            if comments:
                lines.append('')
                lines += _comment(table, spec)
            lines.append(f'    {spec.name}: {yaml_scalar(listed[spec.name])}')
        lines.append('')
    return '\n'.join(lines).rstrip('\n') + '\n'


def _comment(table: ParamTable, spec) -> list:
    """Return the comment lines above a parameter in a params file."""
    accepts = spec.accepts
    if spec.unit:
        accepts += f' {spec.unit}' if spec.range is not None else f' ({spec.unit})'
    if spec.derived:
        accepts += f"; listed: the {table.spec(table.key).default}'s"
    lines = textwrap.wrap(' '.join(spec.description.split()), _WIDTH, break_on_hyphens=False,
                          initial_indent='    # ', subsequent_indent='    # ')
    return lines + textwrap.wrap(accepts, _WIDTH, break_on_hyphens=False,
                                 initial_indent='    # ', subsequent_indent='    #   ')
