"""Tests of kf_train.sim.simulation and kf_train.sim.baselines."""

import math

from kf_train.sim import extrapolate, raw_difference_velocity, running_average, TrainSimulation
import numpy as np
import pytest


def _as_arrays(samples):
    """Return the fields of a list of TrainSample as a dict of arrays."""
    return {field: np.array([getattr(s, field) for s in samples])
            for field in samples[0]._fields}


def test_same_seed_same_sequence():
    """Two simulations with one seed produce identical samples, one by one and in bulk."""
    a, b = TrainSimulation(seed=123), TrainSimulation(seed=123)
    assert [a.next_sample() for _ in range(50)] == [b.next_sample() for _ in range(50)]
    first, second = a.generate(200), b.generate(200)
    for x, y in zip(first, second):
        assert x.tobytes() == y.tobytes()


def test_generate_equals_next_sample_bitwise():
    """generate(n) gives bit for bit what n calls of next_sample() give, and continues."""
    bulk = TrainSimulation(initial_position_m=-3.5, velocity_mps=7.25, noise_std_m=2.0,
                           rate_hz=10.0, seed=9)
    single = TrainSimulation(initial_position_m=-3.5, velocity_mps=7.25, noise_std_m=2.0,
                             rate_hz=10.0, seed=9)
    one_by_one = _as_arrays([single.next_sample() for _ in range(1000)])
    series = bulk.generate(400)
    rest = bulk.generate(600)
    for name in ('t_s', 'true_position_m', 'true_velocity_mps', 'measured_position_m'):
        joined = np.concatenate((getattr(series, name), getattr(rest, name)))
        assert joined.tobytes() == one_by_one[name].tobytes(), name
    assert np.array_equal(one_by_one['index'], np.arange(1, 1001))
    # Interleaving also continues the same stream.
    assert bulk.next_sample() == single.next_sample()
    assert bulk.generate(0).t_s.shape == (0,)


def test_different_seeds_differ():
    """Different seeds give different noise."""
    a = TrainSimulation(seed=1).generate(100).measured_position_m
    b = TrainSimulation(seed=2).generate(100).measured_position_m
    assert not np.any(a == b)


def test_truth_and_times():
    """t_k = k / rate, truth x0 + v·t, true velocity v, zero noise measures the truth."""
    sim = TrainSimulation(initial_position_m=6000.0, velocity_mps=-12.5, noise_std_m=0.0,
                          rate_hz=40.0, seed=0)
    series = sim.generate(1000)
    k = np.arange(1, 1001)
    assert np.array_equal(series.t_s, k / 40.0)
    assert np.array_equal(series.true_position_m, 6000.0 + -12.5 * (k / 40.0))
    assert np.array_equal(series.true_velocity_mps, np.full(1000, -12.5))
    assert np.array_equal(series.measured_position_m, series.true_position_m)
    assert sim.period_s == 1.0 / 40.0
    assert sim.sample_time(4) == 0.1
    assert sim.truth(2.0) == 6000.0 - 25.0


def test_noise_statistics():
    """Over 10⁵ samples the noise mean and std are within 5 standard errors."""
    n, sigma = 100_000, 2.5
    sim = TrainSimulation(initial_position_m=100.0, velocity_mps=10.0, noise_std_m=sigma,
                          seed=2024)
    series = sim.generate(n)
    noise = series.measured_position_m - series.true_position_m
    # Standard error of the mean σ/√n; of the sample std of a normal σ/√(2(n - 1)).
    assert abs(np.mean(noise)) < 5.0 * sigma / math.sqrt(n)
    assert abs(np.std(noise, ddof=1) - sigma) < 5.0 * sigma / math.sqrt(2.0 * (n - 1))
    # And the noise is not correlated from one sample to the next: the lag-1
    # correlation of independent samples has standard error 1/√n.
    correlation = np.corrcoef(noise[:-1], noise[1:])[0, 1]
    assert abs(correlation) < 5.0 / math.sqrt(n)


@pytest.mark.parametrize('kwargs, name', [
    ({'noise_std_m': -1.0}, 'noise_std_m'),
    ({'noise_std_m': float('nan')}, 'noise_std_m'),
    ({'rate_hz': 0.0}, 'rate_hz'),
    ({'rate_hz': -10.0}, 'rate_hz'),
    ({'rate_hz': float('inf')}, 'rate_hz'),
    ({'velocity_mps': float('nan')}, 'velocity_mps'),
    ({'initial_position_m': float('-inf')}, 'initial_position_m'),
    ({'initial_position_m': [1.0, 2.0]}, 'initial_position_m'),
    ({'seed': -1}, 'seed'),
    ({'seed': 1.5}, 'seed'),
    ({'seed': '42'}, 'seed'),
])
def test_simulation_rejects(kwargs, name):
    """Bad configuration raises ValueError naming the field."""
    with pytest.raises(ValueError, match=rf'^{name} must'):
        TrainSimulation(**kwargs)


@pytest.mark.parametrize('count', [-1, 2.0, '3'])
def test_generate_rejects_bad_count(count):
    """generate() needs a non-negative integer count and draws nothing otherwise."""
    sim, twin = TrainSimulation(seed=5), TrainSimulation(seed=5)
    with pytest.raises(ValueError, match=r'^count must'):
        sim.generate(count)
    assert sim.next_sample() == twin.next_sample()


def _matlab_instantaneous_velocity(Z, dt):
    """Transcribe InstantaneousVelocity = [0 (Z_buffer(2:N+1)-Z_buffer(1:N))/dt]."""
    N = len(Z)
    Z_buffer = np.zeros(N + 1)  # MATLAB's zeros(1, Nsamples + 1): Z_buffer(1) = 0
    Z_buffer[1:] = Z            # Z_buffer(k+1) = Z
    velocity = [0.0]
    for i in range(1, N + 1):   # MATLAB index i + 1 is Python index i
        velocity.append((Z_buffer[i] - Z_buffer[i - 1]) / dt)
    return np.array(velocity)


def _matlab_filter(b, v):
    """Transcribe filter(b, 1, v): y(n) = Σ_k b(k) v(n - k + 1), zero before the start."""
    y = np.zeros(len(v))
    for n in range(len(v)):
        for k in range(len(b)):
            if n - k >= 0:
                y[n] += b[k] * v[n - k]
    return y


def test_raw_difference_velocity_matches_seed():
    """raw_difference_velocity is the seed's InstantaneousVelocity bit for bit."""
    dt = 0.1
    Z = TrainSimulation(seed=0).generate(100).measured_position_m
    expected = _matlab_instantaneous_velocity(Z, dt)
    actual = raw_difference_velocity(Z, dt)
    assert actual.shape == (101,)
    assert actual.tobytes() == expected.tobytes()


def test_raw_difference_velocity_first_position():
    """A nonzero first_position_m replaces the seed's Z_buffer(1) = 0."""
    v = raw_difference_velocity([6001.0, 6002.0], 0.1, first_position_m=6000.0)
    np.testing.assert_allclose(v, [0.0, 10.0, 10.0], rtol=1e-12)


@pytest.mark.parametrize('window', [1, 2, 5, 7])
def test_running_average_matches_matlab_filter(window):
    """running_average is filter(ones(1, w)/w, 1, v) to rounding."""
    v = raw_difference_velocity(TrainSimulation(seed=3).generate(100).measured_position_m, 0.1)
    expected = _matlab_filter(np.ones(window) / window, v)
    actual = running_average(v, window)
    assert actual.shape == v.shape
    np.testing.assert_allclose(actual, expected, rtol=1e-12, atol=1e-12 * np.max(np.abs(v)))


def test_running_average_start_and_default_window():
    """The first outputs treat the values before the start as zero; default window 5."""
    np.testing.assert_allclose(running_average([5.0, 5.0, 5.0, 5.0, 5.0, 5.0]),
                               [1.0, 2.0, 3.0, 4.0, 5.0, 5.0], rtol=1e-15)
    assert running_average([]).shape == (0,)


def test_extrapolate():
    """Extrapolation is position + velocity·ahead, elementwise and broadcast."""
    assert extrapolate(99.0, 10.5, 2.0) == 120.0
    np.testing.assert_array_equal(
        extrapolate([0.0, 1.0, 2.0], [10.0, 20.0, 30.0], [2.0, 1.0, 0.0]),
        [20.0, 21.0, 2.0])
    np.testing.assert_array_equal(extrapolate([0.0, 1.0], 10.0, 2.0), [20.0, 21.0])


def test_seed_000_extrapolation_by_running_average():
    """The seed's running-average projection equals extrapolate on the baseline."""
    Nsamples, dt, ahead, Nlast = 100, 0.1, 20, 10
    Z = TrainSimulation(seed=0).generate(Nsamples).measured_position_m
    average = running_average(raw_difference_velocity(Z, dt))
    Z_buffer = np.concatenate(([0.0], Z))
    last = slice(Nsamples - Nlast, Nsamples + 1)
    steps = np.arange(ahead + Nlast, ahead - 1, -1)  # (SamplesIntoTheFuture+Nlast):-1:...
    expected = Z_buffer[last] + steps * dt * average[last]
    np.testing.assert_allclose(extrapolate(Z_buffer[last], average[last], steps * dt),
                               expected, rtol=1e-15)


@pytest.mark.parametrize('call, name', [
    (lambda: raw_difference_velocity([1.0, 2.0], 0.0), 'dt_s'),
    (lambda: raw_difference_velocity([1.0, 2.0], -0.1), 'dt_s'),
    (lambda: raw_difference_velocity([1.0, float('nan')], 0.1), 'measured_position_m'),
    (lambda: raw_difference_velocity([[1.0, 2.0], [3.0, 4.0]], 0.1), 'measured_position_m'),
    (lambda: running_average([1.0, float('inf')]), 'values'),
    (lambda: running_average([1.0, 2.0], 0), 'window'),
    (lambda: running_average([1.0, 2.0], 2.5), 'window'),
])
def test_baselines_reject(call, name):
    """Bad baseline inputs raise ValueError naming the input."""
    with pytest.raises(ValueError, match=rf'^{name} must'):
        call()
