"""Tests of the estimator's input contract, time handling and gating (kf_train.estimator)."""

import dataclasses
import math

from kf_train.estimator import (
    EstimatorSettings, NS_PER_S, Rejected, REJECTION_REASONS, RESET_REASONS, StreamEstimator)
from kf_train.filters import chi2_quantile, constant_velocity_F, WhiteNoiseAcceleration
import numpy as np
import pytest

PERIOD_NS = 100_000_000
EPOCH_NS = 1_700_000_000 * NS_PER_S
# The train's constant-velocity KF with noise (the rail default's contract:
# test_estimator_rail.test_hostile_inputs_are_rejected_counted_and_change_nothing_...).
ROBUST = EstimatorSettings(preset='train', process_noise_density=0.5, history_s=1.0,
                           gate_probability=0.9999, expected_frame_id='odom', max_future_s=1.0)


def _stream(n, seed=0, velocity=10.0, start_ns=EPOCH_NS):
    """Return (stamps, positions) of a 10 Hz train with σ = 1 m noise."""
    rng = np.random.default_rng(seed)
    stamps = [start_ns + (k + 1) * PERIOD_NS for k in range(n)]
    positions = velocity * 0.1 * np.arange(1, n + 1) + rng.standard_normal(n)
    return stamps, positions.tolist()


def _snapshot(estimator):
    """Return everything that makes up the filter state, as bytes, for exact comparison."""
    state = estimator.state
    x, P = (None, None) if state is None else (state[0].tobytes(), state[1].tobytes())
    history = tuple((e.stamp_ns, e.x.tobytes(), e.P.tobytes(), e.kind)
                    for e in estimator._history)
    return x, P, estimator.last_stamp_ns, history


def _fed(settings, stamps, positions, variance=1.0):
    """Return an estimator that fused the given measurements in order."""
    estimator = StreamEstimator(settings)
    for stamp, z in zip(stamps, positions):
        estimator.process(stamp, z, variance, frame_id='odom')
    return estimator


def _only(counts, reason):
    """Return whether counts has exactly one entry, for reason."""
    return counts[reason] == 1 and sum(counts.values()) == 1


BAD_INPUTS = {
    # name: (reason, kwargs changing a valid next measurement)
    'wrong frame': ('wrong_frame', {'frame_id': 'map'}),
    'NaN position': ('non_finite', {'position': math.nan}),
    '+Inf position': ('non_finite', {'position': math.inf}),
    '-Inf position': ('non_finite', {'position': -math.inf}),
    'NaN variance': ('non_finite', {'variance': math.nan}),
    'Inf variance': ('non_finite', {'variance': math.inf}),
    'zero variance': ('bad_variance', {'variance': 0.0}),
    'negative variance': ('bad_variance', {'variance': -1.0}),
    'zero stamp': ('zero_stamp', {'stamp': 0}),
    'negative stamp': ('zero_stamp', {'stamp': -5}),
    'future stamp': ('future_stamp', {'stamp_offset': int(1.5 * NS_PER_S)}),
    'duplicate of the newest': ('duplicate_stamp', {'stamp_offset': -PERIOD_NS}),
    'duplicate in the history': ('duplicate_stamp', {'stamp_offset': -4 * PERIOD_NS}),
    'stale': ('stale_stamp', {'stamp_offset': -12 * PERIOD_NS}),
    'outlier': ('outlier', {'position_offset': 50.0}),
    'overflowing position': ('numerical', {'position': 1e300}),
}


@pytest.mark.parametrize('name', BAD_INPUTS)
def test_bad_input_is_rejected_counted_and_changes_nothing(name):
    """Each bad input raises Rejected(reason), is counted once, and leaves the state exact."""
    reason, change = BAD_INPUTS[name]
    stamps, positions = _stream(31)
    estimator = _fed(ROBUST, stamps[:30], positions[:30])
    twin = _fed(ROBUST, stamps[:30], positions[:30])
    before = _snapshot(estimator)
    now_ns = stamps[29]
    stamp = change.get('stamp', stamps[30] + change.get('stamp_offset', 0))
    position = change.get('position', positions[30] + change.get('position_offset', 0.0))
    with pytest.raises(Rejected) as raised:
        estimator.process(stamp, position, change.get('variance', 1.0),
                          frame_id=change.get('frame_id', 'odom'), now_ns=now_ns)
    assert raised.value.reason == reason
    assert isinstance(raised.value, ValueError)
    assert raised.value.reset is None
    assert _only(estimator.stats().rejections, reason)
    assert sum(estimator.stats().resets.values()) == 0
    assert _snapshot(estimator) == before
    # It keeps running, exactly as if the bad input had never come.
    step = estimator.process(stamps[30], positions[30], 1.0, frame_id='odom', now_ns=now_ns)
    assert np.array_equal(step.x, twin.process(stamps[30], positions[30], 1.0).x)
    assert np.all(np.isfinite(step.x)) and np.all(np.isfinite(step.P))


@pytest.mark.parametrize('name', ['NaN position', 'zero variance', 'zero stamp', 'wrong frame'])
def test_bad_first_input_leaves_the_filter_uninitialised(name):
    """A bad measurement before the first good one does not initialise the filter."""
    reason, change = BAD_INPUTS[name]
    estimator = StreamEstimator(ROBUST)
    with pytest.raises(Rejected) as raised:
        estimator.process(change.get('stamp', EPOCH_NS), change.get('position', 1.0),
                          change.get('variance', 1.0), frame_id=change.get('frame_id', 'odom'))
    assert raised.value.reason == reason
    assert not estimator.initialized and estimator.last_stamp_ns is None


def test_checks_that_need_context_are_skipped_without_it():
    """No frame given, no expected frame, or no clock (None or 0) skip those checks."""
    estimator = StreamEstimator(ROBUST)
    estimator.process(EPOCH_NS, 1.0, 1.0)  # frame unknown
    estimator.process(EPOCH_NS + PERIOD_NS, 2.0, 1.0, now_ns=0)  # clock not started
    anything = StreamEstimator(dataclasses.replace(ROBUST, expected_frame_id=''))
    anything.process(EPOCH_NS, 1.0, 1.0, frame_id='whatever', now_ns=EPOCH_NS - NS_PER_S)
    assert estimator.stats().fused == 2 and anything.stats().fused == 1


def test_variance_override_still_rejects_a_broken_message():
    """With measurement_variance set, a 0 message variance is fine but a NaN one is not."""
    estimator = StreamEstimator(dataclasses.replace(ROBUST, measurement_variance=2.0))
    estimator.process(EPOCH_NS, 1.0, 0.0)
    with pytest.raises(Rejected, match='variance') as raised:
        estimator.process(EPOCH_NS + PERIOD_NS, 1.0, math.nan)
    assert raised.value.reason == 'non_finite'


@pytest.mark.parametrize('mode', ['prior', 'first_measurement'])
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_out_of_sequence_replay_equals_in_order(mode, seed):
    """Measurements shuffled within history_s give the in-order result to 1e-9 (exactly)."""
    rng = np.random.default_rng(seed)
    n = 200
    gaps = rng.integers(PERIOD_NS // 2, 2 * PERIOD_NS, n)
    stamps = (EPOCH_NS + np.cumsum(gaps)).tolist()
    positions = (10.0 * (np.array(stamps) - EPOCH_NS) / NS_PER_S
                 + rng.standard_normal(n)).tolist()
    settings = dataclasses.replace(ROBUST, initialization=mode, gate_probability=1.0)
    in_order = _fed(settings, stamps, positions)
    # Each arrival comes at most 5 places late: always younger than history_s = 1 s.
    order = sorted(range(n), key=lambda k: k + rng.uniform(0.0, 5.0))
    order.remove(0)
    order.insert(3, 0)  # the first one comes late too: in order it initialised the filter
    shuffled = StreamEstimator(settings)
    for k in order:
        step = shuffled.process(stamps[k], positions[k], 1.0, frame_id='odom')
        assert step.measurement_stamp_ns == stamps[k]
        assert step.stamp_ns == shuffled.last_stamp_ns
        assert step.replayed == sum(1 for j in order[:order.index(k)] if j > k)
    assert shuffled.stats().out_of_sequence > 50
    x, P = shuffled.state
    np.testing.assert_allclose(x, in_order.state[0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(P, in_order.state[1], rtol=1e-9, atol=1e-12)
    assert np.array_equal(x, in_order.state[0]) and np.array_equal(P, in_order.state[1])
    assert shuffled.last_stamp_ns == in_order.last_stamp_ns == stamps[-1]
    assert sum(shuffled.stats().rejections.values()) == 0


def test_replay_uses_the_settings_each_measurement_was_fused_with():
    """Measurements replayed after a noise change keep their own Q and R, as in order."""
    stamps, positions = _stream(40, seed=5)
    settings = dataclasses.replace(ROBUST, history_s=2.0)
    louder = dataclasses.replace(settings, process_noise_density=5.0, measurement_variance=3.0)
    in_order = _fed(settings, stamps[:30], positions[:30])
    in_order.reconfigure(louder)
    for k in range(30, 40):
        in_order.process(stamps[k], positions[k], 1.0)
    late = _fed(settings, stamps[:25], positions[:25])
    for k in range(26, 30):
        late.process(stamps[k], positions[k], 1.0)
    late.reconfigure(louder)
    for k in range(30, 40):
        late.process(stamps[k], positions[k], 1.0)
    # Sample 25 comes last; in order it was fused with the old settings.
    late.reconfigure(settings)
    step = late.process(stamps[25], positions[25], 1.0)
    assert step.replayed == 14
    np.testing.assert_allclose(late.state[0], in_order.state[0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(late.state[1], in_order.state[1], rtol=1e-9, atol=1e-12)


def test_out_of_sequence_outlier_is_gated_against_its_own_time():
    """A late outlier is rejected against the rewound state; nothing changes."""
    stamps, positions = _stream(20)
    estimator = _fed(ROBUST, stamps, positions)
    before = _snapshot(estimator)
    with pytest.raises(Rejected) as raised:
        estimator.process(stamps[15] - PERIOD_NS // 2, positions[15] + 30.0, 1.0)
    assert raised.value.reason == 'outlier' and raised.value.update.nis > 100.0
    assert _snapshot(estimator) == before


def test_history_is_bounded_by_history_s():
    """The replay history keeps history_s of states plus one to rewind to."""
    settings = dataclasses.replace(ROBUST, gate_probability=1.0)
    stamps, positions = _stream(500)
    estimator = _fed(settings, stamps, positions)
    assert estimator.stats().history_length == 11  # 1 s at 10 Hz, plus the anchor
    estimator.reconfigure(dataclasses.replace(settings, history_s=0.0))
    assert estimator.stats().history_length == 0
    with pytest.raises(Rejected, match='not newer') as raised:
        estimator.process(stamps[-1] - 1, 0.0, 1.0)
    assert raised.value.reason == 'stale_stamp'


def test_a_single_stale_measurement_is_rejected_and_a_restarted_stream_is_followed():
    """One stale stamp is rejected; restart_after_stale in a row reset and re-initialise."""
    stamps, positions = _stream(30)
    estimator = _fed(ROBUST, stamps[:20], positions[:20])
    restarted = [stamps[0] - 100 * NS_PER_S + k * PERIOD_NS for k in range(3)]
    # Interleaved with good data, stale stamps never add up to a restart.
    for k in range(20, 30):
        with pytest.raises(Rejected):
            estimator.process(restarted[0], 0.0, 1.0)
        estimator.process(stamps[k], positions[k], 1.0)
    assert estimator.stats().rejections['stale_stamp'] == 10
    # restart_after_stale = 3 in a row: the third resets and initialises from itself.
    for k in range(2):
        with pytest.raises(Rejected) as raised:
            estimator.process(restarted[k], 5.0 + k, 1.0)
        assert raised.value.reason == 'stale_stamp'
    step = estimator.process(restarted[2], 7.0, 1.0)
    assert step.reset == 'stream_restart'
    assert estimator.stats().resets['stream_restart'] == 1
    fresh = StreamEstimator(ROBUST).process(restarted[2], 7.0, 1.0)
    assert np.array_equal(step.x, fresh.x) and np.array_equal(step.P, fresh.P)
    assert estimator.last_stamp_ns == restarted[2]


def _three_rejected_after_a_jump(mode: str, lockout: str):
    """Return (estimator, stamps, positions): a train that jumped 500 m, 3 fixes gated."""
    settings = dataclasses.replace(ROBUST, initialization=mode, max_consecutive_outliers=4,
                                   process_noise_density=0.0, initial_state=(0.0, 10.0),
                                   lockout=lockout)
    stamps, positions = _stream(40)
    estimator = _fed(settings, stamps[:20], positions[:20])
    jumped = [z + 500.0 for z in positions]
    for k in range(20, 23):
        with pytest.raises(Rejected) as raised:
            estimator.process(stamps[k], jumped[k], 1.0)
        assert raised.value.reason == 'outlier' and raised.value.reset is None
    return estimator, stamps, jumped


@pytest.mark.parametrize('mode', ['first_measurement', 'prior'])
def test_consecutive_outliers_reinitialise_instead_of_locking_out(mode):
    """With lockout reset, a 500-m jump is gated N times, then the filter re-initialises."""
    estimator, stamps, jumped = _three_rejected_after_a_jump(mode, 'reset')
    with pytest.raises(Rejected) as raised:
        estimator.process(stamps[23], jumped[23], 1.0)
    assert raised.value.reset == 'outlier_lockout'
    assert not estimator.initialized
    assert estimator.stats().resets['outlier_lockout'] == 1
    assert estimator.stats().rejections['outlier'] == 4
    step = estimator.process(stamps[24], jumped[24], 1.0)  # initialises, never gated
    for k in range(25, 40):
        step = estimator.process(stamps[k], jumped[k], 1.0)
    # Back on the train (500 m further than before), also in prior mode: the lock-out
    # re-initialises from the measurement, not from the prior the data contradicted.
    assert abs(step.x[0] - (500.0 + 10.0 * 0.1 * 40)) < 4.0 * math.sqrt(step.P[0, 0])
    assert estimator.stats().rejections['outlier'] == 4
    assert estimator.stats().reacquisitions == 0


@pytest.mark.parametrize('mode', ['first_measurement', 'prior'])
def test_a_lockout_reacquires_the_track_by_default(mode):
    """With lockout reacquire, the N-th agreeing outlier is fused with the group; no reset."""
    assert EstimatorSettings().lockout == 'reacquire'
    estimator, stamps, jumped = _three_rejected_after_a_jump(mode, 'reacquire')
    step = estimator.process(stamps[23], jumped[23], 1.0)     # the fourth: re-acquired
    stats = estimator.stats()
    assert estimator.initialized and step.reset is None
    assert sum(stats.resets.values()) == 0 and stats.reacquisitions == 1
    assert stats.rejections['outlier'] == 3 and stats.fused == 21
    # The track now runs through the group: within a few σ of the jumped line, whose
    # four fixes (σ = 1 m) pin it to about 1 m; the velocity is the line's, 10 m/s.
    assert abs(step.x[0] - jumped[23]) < 4.0
    assert abs(step.x[1] - 10.0) < 4.0 * math.sqrt(step.P[1, 1]) + 1.0
    for k in range(24, 40):
        step = estimator.process(stamps[k], jumped[k], 1.0)    # fused: back on the train
    assert abs(step.x[0] - (500.0 + 10.0 * 0.1 * 40)) < 4.0 * math.sqrt(step.P[0, 0])
    assert estimator.stats().rejections['outlier'] == 3
    # Nothing rewinds past the widening: an older fix than it is stale.
    with pytest.raises(Rejected) as raised:
        estimator.process(stamps[19] + 1, jumped[19], 1.0)
    assert raised.value.reason == 'stale_stamp'


def test_scattered_outliers_never_reacquire():
    """Gross fixes that no line fits are rejected however many; the track coasts on."""
    settings = dataclasses.replace(ROBUST, max_consecutive_outliers=4)
    stamps, positions = _stream(40)
    estimator = _fed(settings, stamps[:20], positions[:20])
    for k in range(20, 32):
        with pytest.raises(Rejected):
            estimator.process(stamps[k], positions[k] + (-1) ** k * 300.0, 1.0)
    stats = estimator.stats()
    assert stats.reacquisitions == 0 and sum(stats.resets.values()) == 0
    assert estimator.initialized and stats.rejections['outlier'] == 12


def test_gate_threshold_comes_from_the_chi2_quantile_and_changes_live():
    """gate_threshold is the χ²(1) quantile of gate_probability; 1 disables the gate."""
    strict = dataclasses.replace(ROBUST, gate_probability=0.999)
    assert StreamEstimator(strict).gate_threshold == chi2_quantile(0.999, 1)
    assert StreamEstimator(EstimatorSettings(gate_probability=1.0)).gate_threshold == math.inf
    stamps, positions = _stream(21)
    estimator = _fed(strict, stamps[:20], positions[:20])
    x, P = estimator.state
    F = constant_velocity_F(0.1)
    x_prior = F @ x
    S = (F @ P @ F.T + WhiteNoiseAcceleration(0.5)(0.1))[0, 0] + 1.0
    # An innovation whose NIS is 12: above the 0.999 gate (10.83), below 0.9999 (15.14).
    z = x_prior[0] + math.sqrt(12.0 * S)
    with pytest.raises(Rejected) as raised:
        estimator.process(stamps[20], z, 1.0)
    assert raised.value.update.nis == pytest.approx(12.0, rel=1e-9)
    estimator.reconfigure(dataclasses.replace(ROBUST, gate_probability=0.9999))
    assert estimator.process(stamps[20], z, 1.0).update.nis == pytest.approx(12.0, rel=1e-9)


def test_numerical_failures_count_towards_the_lockout():
    """An update that overflows is rejected as numerical; enough in a row reset the filter."""
    settings = dataclasses.replace(ROBUST, max_consecutive_outliers=2)
    stamps, positions = _stream(5)
    estimator = _fed(settings, stamps[:3], positions[:3])
    with pytest.raises(Rejected) as raised:
        estimator.process(stamps[3], 1e300, 1.0)
    assert raised.value.reason == 'numerical' and estimator.initialized
    with pytest.raises(Rejected) as raised:
        estimator.process(stamps[3], -1e300, 1.0)
    assert raised.value.reset == 'outlier_lockout' and not estimator.initialized


def test_set_state():
    """set_state replaces the state (counted); invalid input is refused without change."""
    stamps, positions = _stream(10)
    estimator = _fed(ROBUST, stamps[:5], positions[:5])
    before = _snapshot(estimator)
    for args in [(stamps[5], [1.0], np.eye(2)), (stamps[5], [1.0, math.nan], np.eye(2)),
                 (stamps[5], [1.0, 2.0], [[1.0, 2.0], [2.0, 1.0]]),
                 (0, [1.0, 2.0], np.eye(2)), (1.5, [1.0, 2.0], np.eye(2))]:
        with pytest.raises(ValueError):
            estimator.set_state(*args)
        assert _snapshot(estimator) == before
    estimator.set_state(stamps[5], [6.0, 10.0], np.diag([0.5, 0.25]))
    assert estimator.stats().resets['set_state'] == 1
    assert estimator.last_stamp_ns == stamps[5]
    with pytest.raises(Rejected) as raised:  # before the set state: nothing to rewind to
        estimator.process(stamps[4], positions[4], 1.0)
    assert raised.value.reason == 'stale_stamp'
    step = estimator.process(stamps[6], positions[6], 1.0)
    F = constant_velocity_F(0.1)
    P_prior = F @ np.diag([0.5, 0.25]) @ F.T + WhiteNoiseAcceleration(0.5)(0.1)
    assert step.update.innovation[0] == pytest.approx(positions[6] - (6.0 + 1.0), rel=1e-12)
    assert step.update.innovation_covariance[0, 0] == pytest.approx(P_prior[0, 0] + 1.0,
                                                                    rel=1e-12)


def test_reset_reasons_are_counted_and_checked():
    """reset(reason) counts by reason; an unknown reason is refused."""
    estimator = StreamEstimator(ROBUST)
    for reason in RESET_REASONS:
        estimator.reset(reason)
    estimator.reset()
    assert estimator.stats().resets == {**dict.fromkeys(RESET_REASONS, 1), 'manual': 2}
    with pytest.raises(ValueError, match='reason'):
        estimator.reset('bogus')
    assert set(estimator.stats().rejections) == set(REJECTION_REASONS)


@pytest.mark.parametrize('kwargs, name', [
    ({'history_s': -1.0}, 'history_s'),
    ({'history_s': 61.0}, 'history_s'),
    ({'history_s': math.nan}, 'history_s'),
    ({'gate_probability': 0.4}, 'gate_probability'),
    ({'gate_probability': 1.01}, 'gate_probability'),
    ({'max_future_s': -0.1}, 'max_future_s'),
    ({'max_consecutive_outliers': 0}, 'max_consecutive_outliers'),
    ({'max_consecutive_outliers': 2.0}, 'max_consecutive_outliers'),
    ({'max_consecutive_outliers': True}, 'max_consecutive_outliers'),
    ({'restart_after_stale': 1}, 'restart_after_stale'),
    ({'expected_frame_id': None}, 'expected_frame_id'),
])
def test_new_settings_are_validated(kwargs, name):
    """Each bad robustness setting raises ValueError naming it (and its range)."""
    with pytest.raises(ValueError, match=rf'^{name} must'):
        StreamEstimator(EstimatorSettings(**kwargs))
    estimator = StreamEstimator(ROBUST)
    with pytest.raises(ValueError, match=rf'^{name} must'):
        estimator.reconfigure(EstimatorSettings(**kwargs))
    assert estimator.settings == ROBUST
