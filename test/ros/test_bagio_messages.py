"""Bag outputs (kf_train.io.bagio_output) carry what the estimator node publishes."""

from kf_train.io.bagio_output import OutputBag
from kf_train.io.bagio_types import (
    DIAGNOSTIC_LEVELS, DIAGNOSTICS, ODOMETRY, TYPESTORE, UNESTIMATED_VARIANCE, VECTOR3)
from kf_train.ros import messages
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader

NS = 1_000_000_000


def normalised(raw: bytes, kind: str) -> bytes:
    """Return ``raw`` read and rewritten by rosbags: zero padding, every field kept."""
    # rclpy (Fast CDR) leaves alignment padding uninitialised, so its bytes are compared
    # after this round trip, which keeps every field's bits and zeroes the padding.
    return bytes(TYPESTORE.serialize_cdr(TYPESTORE.deserialize_cdr(raw, kind), kind))


def test_the_conventions_are_the_nodes():
    """The 1e9 of unestimated dimensions and the diagnostic levels match messages.py."""
    assert UNESTIMATED_VARIANCE == messages.UNESTIMATED_VARIANCE
    assert {name: int.from_bytes(level, 'little') if isinstance(level, bytes) else int(level)
            for name, level in messages.DIAGNOSTIC_LEVELS.items()} == DIAGNOSTIC_LEVELS


@pytest.mark.parametrize('dim_x', [1, 2])
def test_bag_messages_equal_the_nodes_messages(tmp_path, dim_x):
    """Every output, written from plain values, holds the fields the node would publish."""
    rng = np.random.default_rng(dim_x)
    estimate_writer = messages.EstimateWriter('map', 'train', dim_x)
    innovation_writer = messages.InnovationWriter('map')
    expected = []
    with OutputBag(tmp_path / 'out.mcap', frame_id='map', child_frame_id='train') as out:
        for k in range(40):
            stamp = int(rng.integers(0, 2 ** 31)) * NS + int(rng.integers(0, NS))
            x = rng.normal(0, 1e3, dim_x)
            P = np.diag(rng.uniform(0, 10, dim_x))
            y, S = float(rng.normal()), float(rng.uniform(0.5, 2))
            out.write_estimate(k, stamp, x, P)
            expected.append(serialize_message(estimate_writer.fill(stamp, x, P)))
            out.write_innovation(k, stamp, y, S, y * y / S)
            expected.append(serialize_message(innovation_writer.fill(stamp, y, S, y * y / S)))
        values = [('received', '40'), ('fused', '39')]
        out.write_diagnostics(99, 5 * NS, 'estimator: filter', 'kf_train', 'OK', 'ok', values)
        expected.append(serialize_message(messages.to_diagnostics_msg(
            5 * NS, 'estimator: filter', 'kf_train', 'OK', 'ok', values)))
    with Reader(tmp_path / 'out.mcap') as reader:
        written = [(c.msgtype, bytes(raw)) for c, _, raw in reader.messages()]
    assert [kind for kind, _ in written] == [ODOMETRY, VECTOR3] * 40 + [DIAGNOSTICS]
    for (kind, raw), node in zip(written, expected):
        assert raw == normalised(node, kind)
