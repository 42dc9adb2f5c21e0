"""
The estimator's fast paths equal the plain ones.

* The train's closed-form KF inside StreamEstimator (``_FastTrainModel``) against the
  generic LinearModel path, on one stream with out-of-sequence measurements, gated
  outliers, a lock-out reset, duplicates, stale stamps, set_state and process noise:
  every step, every rejection and every counter agree, the numbers to 1e-9.
* The reused, partly refilled messages (messages.EstimateWriter, InnovationWriter)
  equal freshly built ones in every field.
* The subscription QoS parameters reach the subscriptions; a bad one stops start-up.
"""

import math

from kf_train.estimator import EstimatorSettings, Rejected, StreamEstimator
from kf_train.ros import messages
from kf_train.ros.estimator_node import EstimatorNode
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from rclpy.serialization import serialize_message
from ros_helpers import assert_startup_refused

EPOCH_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000


class _GenericEstimator(StreamEstimator):
    """The estimator with the train's generic (numpy matrix) model."""

    fast_path = False


def _events(n: int, seed: int):
    """Return a seeded list of (kind, args) events exercising every path."""
    rng = np.random.default_rng(seed)
    events = []
    stamps = [EPOCH_NS + (i + 1) * PERIOD_NS for i in range(n)]
    order = list(range(n))
    for i in range(4, n - 2, 9):
        order[i], order[i + 2] = order[i + 2], order[i]     # out of sequence
    for i in order:
        z = 10.0 * (i + 1) * PERIOD_NS / 1e9 + rng.standard_normal()
        if i % 23 == 11:
            z += 50.0                                        # an outlier for the gate
        events.append(('measure', stamps[i], z, 1.0 + 0.5 * (i % 3)))
        if i % 31 == 7:
            events.append(('measure', stamps[i], z, 1.0))    # a duplicate
    events.append(('measure', stamps[10], 0.0, 1.0))         # stale
    events += [('measure', stamps[-1] + k * PERIOD_NS, 1e4, 1.0) for k in range(1, 4)]
    P_set = [[2.0, 0.1], [0.1, 1.0]]
    events.append(('set_state', stamps[-1] + 5 * PERIOD_NS, [1e3, 9.0], P_set))
    events += [('measure', stamps[-1] + k * PERIOD_NS, 1e3 + 0.9 * (k - 5), 1.0)
               for k in range(6, 20)]
    return events


def _run(cls, settings: EstimatorSettings, events):
    """Return every outcome of the events, and the final counters."""
    estimator = cls(settings)
    outcomes = []
    for kind, stamp_ns, *args in events:
        if kind == 'set_state':
            estimator.set_state(stamp_ns, *args)
            outcomes.append('set')
            continue
        try:
            outcomes.append(estimator.process(stamp_ns, args[0], args[1]))
        except Rejected as rejection:
            outcomes.append((rejection.reason, rejection.reset,
                             None if rejection.update is None else rejection.update.nis))
    stats = estimator.stats()
    counters = (stats.rejections, stats.resets, stats.fused, stats.out_of_sequence,
                stats.reacquisitions)
    return estimator, outcomes, counters


def _close(a, b, what):
    """Assert arrays equal to 1e-9 (relative to their size, at least 1)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = max(1.0, float(np.abs(a).max(initial=0.0)))
    assert a.shape == b.shape and np.all(np.abs(a - b) <= 1e-9 * scale), (what, a, b)


@pytest.mark.parametrize('q, initialization, lockout', [
    (0.0, 'prior', 'reset'), (0.0, 'first_measurement', 'reacquire'),
    (0.5, 'first_measurement', 'reset'), (0.5, 'first_measurement', 'reacquire')])
def test_fast_train_path_equals_the_generic_path(q, initialization, lockout):
    """Closed form vs generic matrices: same steps, rejections and counters; 1e-9."""
    settings = EstimatorSettings(preset='train', history_s=1.0, gate_probability=0.999,
                                 max_consecutive_outliers=3, process_noise_density=q,
                                 initialization=initialization, lockout=lockout)
    events = _events(200, 1)
    fast, fast_out, fast_counts = _run(StreamEstimator, settings, events)
    generic, generic_out, generic_counts = _run(_GenericEstimator, settings, events)
    assert type(fast.model).__name__ == '_FastTrainModel'
    assert type(generic.model).__name__ != '_FastTrainModel'
    assert fast_counts == generic_counts
    rejections, resets, _, oos, reacquisitions = fast_counts
    # The stream reaches every path it is meant to.
    assert oos > 0 and rejections['outlier'] > 0 and rejections['duplicate_stamp'] > 0
    assert rejections['stale_stamp'] > 0
    if lockout == 'reset':
        assert resets['outlier_lockout'] > 0 and reacquisitions == 0
    else:
        assert resets['outlier_lockout'] == 0 and reacquisitions > 0
    assert resets['set_state'] == 1
    for i, (a, b) in enumerate(zip(fast_out, generic_out)):
        if isinstance(a, tuple) and not hasattr(a, 'x'):
            assert a[:2] == b[:2], i
            if a[2] is not None:
                assert a[2] == pytest.approx(b[2], rel=1e-9, abs=1e-12), i
            continue
        if a == 'set':
            assert b == 'set'
            continue
        assert (a.stamp_ns, a.prediction_stamp_ns, a.replayed, a.reset) == (
            b.stamp_ns, b.prediction_stamp_ns, b.replayed, b.reset), i
        for field in ('x', 'P', 'predicted_x', 'predicted_P'):
            _close(getattr(a, field), getattr(b, field), (i, field))
        assert (a.update is None) == (b.update is None), i
        if a.update is not None:
            for field in ('innovation', 'innovation_covariance', 'gain'):
                _close(getattr(a.update, field), getattr(b.update, field), (i, field))
            assert a.update.nis == pytest.approx(b.update.nis, rel=1e-9, abs=1e-12), i
    _close(fast.state[0], generic.state[0], 'final x')
    _close(fast.state[1], generic.state[1], 'final P')


def test_fast_train_path_rejects_what_the_generic_path_rejects():
    """Overflow and a singular S: a numerical rejection on both, the state unchanged."""
    for cls in (StreamEstimator, _GenericEstimator):
        estimator = cls(EstimatorSettings(preset='train', history_s=1.0))
        estimator.set_state(EPOCH_NS, [0.0, 1e300], [[0.0, 0.0], [0.0, 0.0]])
        before = estimator.state
        with pytest.raises(Rejected) as caught:
            estimator.process(EPOCH_NS + 10 ** 12, 0.0, 1.0)
        assert caught.value.reason == 'numerical', cls
        assert np.array_equal(estimator.state[0], before[0])


def _fields(msg):
    """Return every field of a message, recursively, as plain values."""
    if hasattr(msg, 'get_fields_and_field_types'):
        return {name: _fields(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    return msg


@pytest.mark.parametrize('dim_x', [1, 2])
def test_estimate_writer_equals_a_fresh_message(dim_x):
    """Refilling one message gives, field by field, what to_estimate_msg builds."""
    writer = messages.EstimateWriter('odom', 'base_link', dim_x)
    rng = np.random.default_rng(dim_x)
    for k in range(5):
        if k == 3:
            writer.set_frames('map', 'train')
        frames = ('map', 'train') if k >= 3 else ('odom', 'base_link')
        x = rng.standard_normal(dim_x) * 100.0
        A = rng.standard_normal((dim_x, dim_x))
        P = A @ A.T + np.eye(dim_x)
        stamp_ns = EPOCH_NS + k * 123_456_789
        expected = messages.to_estimate_msg(stamp_ns, *frames, x, P)
        assert _fields(writer.fill(stamp_ns, x, P)) == _fields(expected)


def test_innovation_writer_equals_a_fresh_message():
    """Refilling the innovation record gives what to_innovation_msg builds."""
    writer = messages.InnovationWriter('odom')
    for k in range(3):
        if k == 2:
            writer.set_frame('map')
        frame = 'map' if k == 2 else 'odom'
        values = (0.5 * k - 1.0, 1.0 + k, 0.25 * k)
        expected = messages.to_innovation_msg(EPOCH_NS + k, frame, *values)
        assert _fields(writer.fill(EPOCH_NS + k, *values)) == _fields(expected)


@pytest.mark.parametrize('frame_id', ['', 'o', 'odom', 'seven77', 'eight888', 'ninenine9',
                                      'gare_du_nord_é'])
def test_measurement_read_from_cdr_bytes_equals_the_deserialised_one(frame_id):
    """Reading the four fields from the bytes gives what deserialising gives."""
    rng = np.random.default_rng(len(frame_id))
    values = [(1, 0.0, 1.0), (EPOCH_NS + 123_456_789, -12.5, 0.25),
              ((2 ** 31 - 1) * 10 ** 9 + 999_999_999, 1e300, 1e-300),
              (EPOCH_NS, float('nan'), float('inf'))]
    largest_ns = (2 ** 31 - 1) * 10 ** 9  # stamp.sec is an int32
    values += [(int(rng.integers(1, largest_ns)), float(rng.standard_normal() * 1e4),
                float(rng.random())) for _ in range(20)]
    for stamp_ns, position, variance in values:
        msg = messages.to_measurement_msg(stamp_ns, frame_id, position, variance)
        fast = messages.measurement_from_serialized(serialize_message(msg))
        plain = messages.from_measurement_msg(msg)
        assert fast[:2] == plain[:2]
        for a, b in zip(fast[2:], plain[2:]):
            assert a == b or (math.isnan(a) and math.isnan(b))


def test_node_publishes_what_the_core_computes_after_a_frame_change(ros_context):
    """The node's reused messages carry the step's numbers and the new frame_id."""
    node = EstimatorNode(context=ros_context, parameter_overrides=[
        Parameter('qos_reliability', value='reliable'), Parameter('qos_depth', value=500)])
    try:
        qos = node.subscription.qos_profile
        assert qos.reliability == ReliabilityPolicy.RELIABLE and qos.depth == 500
        published = []
        node.estimate_pub.publish = lambda msg: published.append(_fields(msg))
        # Without a subscriber nothing is published; with one, every estimate is.
        node._on_measurement(messages.to_measurement_msg(EPOCH_NS, 'odom', 0.0, 1.0))
        assert published == [] and node.fused == 1
        node.estimate_pub.get_subscription_count = lambda: 1
        for k in range(1, 4):
            if k == 3:
                node.set_parameters([Parameter('frame_id', value='map')])
            msg = messages.to_measurement_msg(EPOCH_NS + k * PERIOD_NS, 'odom', 1.0 * k, 1.0)
            # As the raw subscription delivers it, and as a message object.
            node._on_measurement(serialize_message(msg) if k % 2 else msg)
            x, P = node.estimator.state
            expected = messages.to_estimate_msg(node.estimator.last_stamp_ns,
                                                node.frame_id, 'base_link', x, P)
            assert published[-1] == _fields(expected)
        assert published[-1]['header']['frame_id'] == 'map'
    finally:
        node.destroy_node()


@pytest.mark.parametrize('assignment, words', [
    ('qos_reliability:=sometimes', ['qos_reliability', 'best_effort', 'reliable']),
    ('qos_depth:=0', ['qos_depth', '1', '100000']),
])
def test_invalid_qos_parameter_at_startup(domain_id, assignment, words):
    """A bad QoS parameter: one line naming it, exit 2, no traceback."""
    assert_startup_refused(domain_id, 'kf_train.ros.estimator_node', assignment, words)
