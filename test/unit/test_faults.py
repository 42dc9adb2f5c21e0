"""
Tests of fault injection (core.faults) and the estimator core's handling of it.

They feed :class:`FaultInjector` output straight into :class:`StreamEstimator`; the node
versions are in test/ros/test_simulator_faults.py.
"""

import dataclasses
import math

from kf_train.estimator import EstimatorSettings, NS_PER_S, Rejected, StreamEstimator
from kf_train.filters import chi2_quantile
from kf_train.sim import Delivery, FaultInjector, FaultSettings, TrainSimulation
import numpy as np
import pytest

START_NS = 1_700_000_000 * NS_PER_S
RATE_HZ = 10.0
ROBUST = EstimatorSettings(preset='train', process_noise_density=0.1, history_s=1.0,
                           gate_probability=0.9999)


def _faulty_stream(settings, n=2000, seed=7):
    """Return (clean samples, stamps, deliveries, injector) for n samples at 10 Hz."""
    simulation = TrainSimulation(noise_std_m=1.0, rate_hz=RATE_HZ, seed=seed)
    injector = FaultInjector(settings, seed)
    samples, stamps, deliveries = [], [], []
    for _ in range(n):
        sample = simulation.next_sample()
        stamp = START_NS + round(sample.index * NS_PER_S / RATE_HZ)
        samples.append(sample)
        stamps.append(stamp)
        deliveries += injector.apply(sample.index, sample.t_s, stamp,
                                     sample.measured_position_m)
    return samples, stamps, deliveries + injector.flush(), injector


def _binomial_ok(count, n, p):
    """Return whether count successes of n trials fit probability p at the 99.9% level."""
    # (count - np)² / (np(1-p)) is asymptotically χ²(1).
    return (count - n * p) ** 2 / (n * p * (1.0 - p)) <= chi2_quantile(0.999, 1)


def _run(settings, deliveries):
    """Return the estimator after processing the deliveries, and its rejections."""
    estimator = StreamEstimator(settings)
    rejected = []
    for d in deliveries:
        try:
            estimator.process(d.stamp_ns, d.position_m, 1.0)
        except Rejected as rejection:
            rejected.append((d, rejection.reason))
    return estimator, rejected


def test_defaults_inject_nothing_and_leave_the_noise_alone():
    """Default settings deliver every sample unchanged; faults never touch the noise."""
    samples, stamps, deliveries, _ = _faulty_stream(FaultSettings(), n=50)
    assert deliveries == [Delivery(s.index, t, s.measured_position_m, False)
                          for s, t in zip(samples, stamps)]
    faulty, _, _, _ = _faulty_stream(FaultSettings(dropout_probability=0.5,
                                                   outlier_probability=0.5), n=50)
    assert [s.measured_position_m for s in faulty] == [s.measured_position_m for s in samples]


def test_faults_are_reproducible_from_the_seed():
    """The same seed gives the same faults; another seed other ones."""
    settings = FaultSettings(dropout_probability=0.3, outlier_probability=0.2,
                             reorder_probability=0.2)
    assert _faulty_stream(settings, 300)[2] == _faulty_stream(settings, 300)[2]
    assert _faulty_stream(settings, 300)[2] != _faulty_stream(settings, 300, seed=8)[2]


def test_dropouts_are_survived():
    """Dropped samples: the rate fits the probability, and the rest is fused without complaint."""
    settings = FaultSettings(dropout_probability=0.3)
    samples, _, deliveries, injector = _faulty_stream(settings)
    assert injector.dropped + len(deliveries) == len(samples)
    assert _binomial_ok(injector.dropped, len(samples), 0.3)
    estimator, rejected = _run(ROBUST, deliveries)
    assert rejected == [] and estimator.stats().fused == len(deliveries)
    x, P = estimator.state
    error = np.array([samples[-1].true_position_m, samples[-1].true_velocity_mps]) - x
    assert error @ np.linalg.solve(P, error) < chi2_quantile(0.9999, 2)


def test_outliers_are_gated_exactly():
    """20σ outliers are all rejected, nothing else is, and the estimate equals a clean run."""
    settings = FaultSettings(outlier_probability=0.05, outlier_size_m=20.0)
    samples, _, deliveries, injector = _faulty_stream(settings)
    assert _binomial_ok(injector.outliers, len(samples), 0.05)
    clean = {s.index: s.measured_position_m for s in samples}
    for d in deliveries:
        assert d.position_m - clean[d.index] == (pytest.approx(20.0, abs=1e-9) if d.outlier
                                                 and d.position_m > clean[d.index] else
                                                 pytest.approx(-20.0, abs=1e-9) if d.outlier
                                                 else 0.0)
    estimator, rejected = _run(ROBUST, deliveries)
    assert [d for d, _ in rejected] == [d for d in deliveries if d.outlier]
    assert {reason for _, reason in rejected} == {'outlier'}
    reference, _ = _run(ROBUST, [d for d in deliveries if not d.outlier])
    assert np.array_equal(estimator.state[0], reference.state[0])
    assert np.array_equal(estimator.state[1], reference.state[1])


def test_reordered_samples_are_fused_as_if_in_order():
    """A sample arriving after the next one is fused by replay: the in-order result, exactly."""
    settings = FaultSettings(reorder_probability=0.2, dropout_probability=0.1)
    samples, _, deliveries, injector = _faulty_stream(settings)
    late = sum(1 for a, b in zip(deliveries, deliveries[1:]) if b.stamp_ns < a.stamp_ns)
    assert late == injector.reordered > 0
    # A kept sample is held with 0.9·0.2 = 0.18 unless the one before is held; a held
    # one comes late if the next is kept (0.9). Held fraction h = 0.18 (1 - h).
    held = 0.18 / 1.18
    assert _binomial_ok(late, len(samples), held * 0.9)
    estimator, rejected = _run(ROBUST, deliveries)
    assert rejected == [] and estimator.stats().out_of_sequence == late
    in_order, _ = _run(ROBUST, sorted(deliveries, key=lambda d: d.stamp_ns))
    np.testing.assert_allclose(estimator.state[0], in_order.state[0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(estimator.state[1], in_order.state[1], rtol=1e-9, atol=1e-12)
    # Without an out-of-sequence window the late ones are rejected as stale instead.
    strict, rejected = _run(dataclasses.replace(ROBUST, history_s=0.0), deliveries)
    assert len(rejected) == late and {r for _, r in rejected} == {'stale_stamp'}


def test_a_bias_passes_through_one_to_one():
    """
    A constant bias shifts the position estimate by exactly the bias.

    It is unobservable from the measurements alone (the innovations stay white), so
    only a comparison with ground truth reveals it.
    """
    _, _, clean, _ = _faulty_stream(FaultSettings(), n=300)
    _, _, biased, _ = _faulty_stream(FaultSettings(bias_m=2.5), n=300)
    a, _ = _run(ROBUST, clean)
    b, _ = _run(ROBUST, biased)
    np.testing.assert_allclose(b.state[0] - a.state[0], [2.5, 0.0], atol=1e-9)
    np.testing.assert_allclose(b.state[1], a.state[1], rtol=1e-12)


def test_a_stamp_jump_back_is_followed_as_a_restarted_stream():
    """Stamps jumping 100 s back: restart_after_stale - 1 stale rejections, then one reset."""
    settings = FaultSettings(clock_jump_at_s=5.0, clock_jump_s=-100.0)
    samples, stamps, deliveries, _ = _faulty_stream(settings, n=200)
    # Sample k is taken at t = k / 10 s: sample 50 (index 49 here) is the first to jump.
    assert deliveries[48].stamp_ns == stamps[48] and deliveries[49].stamp_ns == (
        stamps[49] - 100 * NS_PER_S)
    estimator, rejected = _run(ROBUST, deliveries)
    assert [r for _, r in rejected] == ['stale_stamp'] * (ROBUST.restart_after_stale - 1)
    assert estimator.stats().resets['stream_restart'] == 1
    x, P = estimator.state
    error = np.array([samples[-1].true_position_m, samples[-1].true_velocity_mps]) - x
    assert error @ np.linalg.solve(P, error) < chi2_quantile(0.9999, 2)
    assert estimator.last_stamp_ns == deliveries[-1].stamp_ns


@pytest.mark.parametrize('kwargs, name', [
    ({'dropout_probability': 1.5}, 'dropout_probability'),
    ({'outlier_probability': -0.1}, 'outlier_probability'),
    ({'reorder_probability': math.nan}, 'reorder_probability'),
    ({'outlier_size_m': -1.0}, 'outlier_size_m'),
    ({'delay_s': -0.5}, 'delay_s'),
    ({'clock_jump_at_s': math.inf}, 'clock_jump_at_s'),
    ({'bias_m': math.nan}, 'bias_m'),
    ({'clock_jump_s': '1'}, 'clock_jump_s'),
])
def test_fault_settings_are_validated(kwargs, name):
    """A bad fault setting raises ValueError naming it."""
    with pytest.raises(ValueError, match=rf'^{name} must'):
        FaultInjector(FaultSettings(**kwargs))
