"""docs/ros.md documents every parameter the nodes declare; the README has the quick start."""

import os
import re

from kf_train.ros.estimator_node import EstimatorNode
from kf_train.ros.param_spec import QOS_OVERRIDES_PREFIX
from kf_train.ros.simulator_node import SimulatorNode
import pytest

REPO = os.path.join(os.path.dirname(__file__), '..', '..')
README = os.path.join(REPO, 'README.md')
REFERENCE = os.path.join(REPO, 'docs', 'ros.md')
INTERNAL = {'use_sim_time', 'start_type_description_service'}


def _read(path: str) -> str:
    """Return a file's text."""
    with open(path, encoding='utf-8') as stream:
        return stream.read()


@pytest.mark.parametrize('node_class', [SimulatorNode, EstimatorNode])
def test_every_declared_parameter_is_documented(ros_context, node_class):
    """Each declared parameter has a row in docs/ros.md's tables, with its default."""
    node = node_class(context=ros_context)
    try:
        text = _read(REFERENCE)
        missing = []
        for name in sorted(name for name in set(node._parameters) - INTERNAL
                           if not name.startswith(QOS_OVERRIDES_PREFIX)):
            row = re.search(r'^\| `' + re.escape(name) + r'` \| `([^`]*)` \|', text, re.M)
            if row is None:
                missing.append(name)
        assert not missing, f'docs/ros.md lacks parameter rows for {missing}'
    finally:
        node.destroy_node()


def test_quick_start_gives_both_commands():
    """The quick start names make demo and make test; no placeholder is left anywhere."""
    text = _read(README)
    assert 'make demo' in text and 'make test' in text
    for path in (README, REFERENCE, os.path.join(REPO, 'docs', 'performance.md')):
        text = _read(path)
        assert 'PARAMETER_TABLES' not in text and 'BENCH_SECTION' not in text, path
