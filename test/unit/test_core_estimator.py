"""Tests of kf_train.estimator.estimator: the stamped train estimator and its settings."""

from kf_train.estimator import (
    covariance_from_list, EstimatorSettings, NS_PER_S, seconds_to_ns, StreamEstimator)
from kf_train.filters import constant_velocity_F, WhiteNoiseAcceleration
import numpy as np
import pytest

# The train's constant-velocity KF without a gate: the defaults before issue 11 (the
# defaults are now the rail preset with the gate on; test_estimator_rail.py).
TRAIN = {'preset': 'train', 'gate_probability': 1.0}
PERIOD_NS = 100_000_000  # seed 000's dt = 0.1 s


def _seed_000_matlab(measurements, dt=0.1):
    """Return the estimates and covariances of a literal transcription of seed 000's loop."""
    inv = np.linalg.inv
    Xk_prev = np.array([[0.0], [5.0]])
    Phi = np.array([[1.0, dt], [0.0, 1.0]])
    P = np.eye(2)
    Q = np.zeros((2, 2))
    M = np.array([[1.0, 0.0]])
    R = 1.0
    states, covariances = [], []
    for Z in measurements:
        P1 = Phi @ P @ Phi.T + Q
        S = M @ P1 @ M.T + R
        K = P1 @ M.T @ inv(S)
        P = P1 - K @ M @ P1
        Xk = Phi @ Xk_prev + K @ (Z - M @ Phi @ Xk_prev)
        states.append(Xk.ravel())
        covariances.append(P)
        Xk_prev = Xk
    return states, covariances


def _train(n, start_s=0.0, velocity=10.0, seed=0):
    """Return n positions of a train sampled at 10 Hz from start_s + 0.1 s, σ = 1 m."""
    rng = np.random.default_rng(seed)
    t = start_s + 0.1 * np.arange(1, n + 1)
    return velocity * t + rng.standard_normal(n)


def _state(estimator):
    """Return the estimator's (x, P, last stamp) as bytes, for exact comparison."""
    state = estimator.state
    if state is None:
        return None, None, estimator.last_stamp_ns
    return state[0].tobytes(), state[1].tobytes(), estimator.last_stamp_ns


def test_prior_mode_is_seed_000():
    """Prior mode fed stamps k·0.1 s reproduces the seed's MATLAB loop."""
    z = _train(100)
    expected_x, expected_P = _seed_000_matlab(z)
    estimator = StreamEstimator(EstimatorSettings(**TRAIN, initialization='prior'))
    for k in range(100):
        step = estimator.process((k + 1) * PERIOD_NS, z[k], 1.0)
        # Rounding only (the seed's textbook P = P1 − K M P1 against the closed-form
        # Joseph update): <= 2.4e-11 in x (|x| <= 100) and 4e-14 in P by the bound of
        # test_presets.ATOL for this seed; 1e-9 has a margin of >= 40.
        np.testing.assert_allclose(step.x, expected_x[k], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(step.P, expected_P[k], rtol=1e-9, atol=1e-12)
        assert step.update is not None
    assert estimator.last_stamp_ns == 100 * PERIOD_NS


def test_first_measurement_mode_initialises_from_the_measurement():
    """The first output is [z1, v0] with variances [R, first_velocity_std²]."""
    settings = EstimatorSettings(**TRAIN, initial_state=(-7.0, 3.0),
                                 first_velocity_std_mps=20.0)
    step = StreamEstimator(settings).process(5 * NS_PER_S, 123.25, 0.5)
    assert step.update is None
    assert np.array_equal(step.x, [123.25, 3.0])
    assert np.array_equal(step.P, np.diag([0.5, 400.0]))
    assert step.stamp_ns == 5 * NS_PER_S
    assert EstimatorSettings(**TRAIN).initialization == 'first_measurement'


def test_first_measurement_mode_joins_a_moving_train():
    """
    Joining a train 6000 m down the track converges; the seed's prior does not.

    The seed's prior (x = 0, v = 5, P = I) with Q = 0 says the train is within metres of
    the origin, so the first measurement at 6000 m is explained mostly by a huge velocity,
    and the confident, noise-free model then takes hundreds of samples to unlearn it.
    """
    z = _train(200, start_s=599.9)  # first sample at t = 600 s, x = 6000 m
    stamps = [600 * NS_PER_S + k * PERIOD_NS for k in range(200)]

    estimator = StreamEstimator(EstimatorSettings(**TRAIN))
    for k in range(5):
        step = estimator.process(stamps[k], z[k], 1.0)
    sigma_v = np.sqrt(step.P[1, 1])
    assert abs(step.x[1] - 10.0) < 4.0 * sigma_v
    assert sigma_v < 5.0

    prior = StreamEstimator(EstimatorSettings(**TRAIN, initialization='prior'))
    for k in range(5):
        step = prior.process(stamps[k], z[k], 1.0)
    sigma_v = np.sqrt(step.P[1, 1])
    assert abs(step.x[1] - 10.0) > 100.0 * sigma_v  # confidently, absurdly wrong
    assert abs(step.x[1] - 10.0) > 100.0            # by more than 100 m/s
    for k in range(5, 200):
        step = prior.process(stamps[k], z[k], 1.0)
    # Still inconsistent after 20 s of data.
    assert abs(step.x[1] - 10.0) > 10.0 * np.sqrt(step.P[1, 1])


@pytest.mark.parametrize('horizon_s, horizon_ns', [
    (0.0, 0), (0.3, 300_000_000), (1.025, 1_025_000_000), (2.0, 2_000_000_000),
    (7.123456789, 7_123_456_789)])  # 1.025e9 is 1024999999.99… in floats: round, not cut
def test_prediction(horizon_s, horizon_ns):
    """The prediction is stamped stamp + horizon in ns and equals F(h) x, F P Fᵀ + Q(h)."""
    settings = EstimatorSettings(**TRAIN, horizon_s=horizon_s, process_noise_density=0.2)
    estimator = StreamEstimator(settings)
    z = _train(10)
    stamp = 1_700_000_000_123_456_789
    for k in range(10):
        step = estimator.process(stamp + k * PERIOD_NS, z[k], 1.0)
        assert step.prediction_stamp_ns == stamp + k * PERIOD_NS + horizon_ns
        assert isinstance(step.prediction_stamp_ns, int)
        F = constant_velocity_F(horizon_s)
        Q = WhiteNoiseAcceleration(0.2)(horizon_s)
        # Two float64 evaluations of F x and F P Fᵀ + Q (any summation order, with or
        # without FMA) each lie within γ_k|F||x| and γ_4(|F||P||F|ᵀ + Q) of the exact
        # values (γ_k ≈ k·u, u = eps/2): they differ by <= 2γ_2 = 2·eps and 2γ_4 = 4·eps
        # of those terms; twice that is allowed. The bound is relative to the size of
        # the terms, so a cancellation cannot hide in it.
        eps = np.finfo(float).eps
        np.testing.assert_allclose(step.predicted_x, F @ step.x, rtol=0.0,
                                   atol=4 * eps * np.max(np.abs(F) @ np.abs(step.x)))
        expected_P = F @ step.P @ F.T + Q
        terms = np.abs(F) @ np.abs(step.P) @ np.abs(F).T + Q
        assert np.all(np.abs(step.predicted_P - expected_P) <= 8 * eps * terms)
    assert seconds_to_ns(2.0) == 2 * NS_PER_S


@pytest.mark.parametrize('mode', ['prior', 'first_measurement'])
@pytest.mark.parametrize('delta_ns', [0, -1, -PERIOD_NS])
def test_non_increasing_stamp_rejected(mode, delta_ns):
    """A stamp not newer than the last raises ValueError and leaves the state unchanged."""
    estimator = StreamEstimator(EstimatorSettings(**TRAIN, initialization=mode))
    z = _train(3)
    for k in range(3):
        estimator.process((k + 1) * PERIOD_NS, z[k], 1.0)
    before = _state(estimator)
    with pytest.raises(ValueError, match='not newer'):
        estimator.process(3 * PERIOD_NS + delta_ns, 0.4, 1.0)
    assert _state(estimator) == before
    # The estimator still works, and gives what an untouched twin gives.
    twin = StreamEstimator(EstimatorSettings(**TRAIN, initialization=mode))
    for k in range(3):
        twin.process((k + 1) * PERIOD_NS, z[k], 1.0)
    assert np.array_equal(estimator.process(4 * PERIOD_NS, 4.0, 1.0).x,
                          twin.process(4 * PERIOD_NS, 4.0, 1.0).x)


@pytest.mark.parametrize('position, variance, pattern', [
    (float('nan'), 1.0, 'position'),
    (float('inf'), 1.0, 'position'),
    (1.0, 0.0, 'variance'),
    (1.0, -1.0, 'variance'),
    (1.0, float('nan'), 'variance'),
    (1.0, float('inf'), 'variance'),
])
@pytest.mark.parametrize('initialised', [False, True])
def test_bad_measurement_rejected(position, variance, pattern, initialised):
    """A non-finite position or a non-positive variance is rejected without change."""
    estimator = StreamEstimator(EstimatorSettings(**TRAIN))
    if initialised:
        estimator.process(PERIOD_NS, 1.0, 1.0)
    before = _state(estimator)
    with pytest.raises(ValueError, match=pattern):
        estimator.process(2 * PERIOD_NS, position, variance)
    assert _state(estimator) == before
    assert estimator.initialized == initialised


@pytest.mark.parametrize('stamp', [1.5e8, '100', None])
def test_non_integer_stamp_rejected(stamp):
    """A stamp that is not an integer number of nanoseconds is rejected."""
    estimator = StreamEstimator(EstimatorSettings(**TRAIN))
    with pytest.raises(ValueError, match='stamp_ns'):
        estimator.process(stamp, 1.0, 1.0)
    assert not estimator.initialized


def test_measurement_variance_override():
    """measurement_variance > 0 replaces the message's variance, even an invalid one."""
    estimator = StreamEstimator(EstimatorSettings(**TRAIN, measurement_variance=4.0))
    assert estimator.measurement_variance(0.25) == 4.0
    assert StreamEstimator(EstimatorSettings(**TRAIN)).measurement_variance(0.25) == 0.25
    step = estimator.process(PERIOD_NS, 10.0, 0.0)
    assert step.P[0, 0] == 4.0
    step = estimator.process(2 * PERIOD_NS, 11.0, 0.25)
    prior_P = constant_velocity_F(0.1) @ np.diag([4.0, 100.0 ** 2]) @ constant_velocity_F(0.1).T
    assert step.update.innovation_covariance[0, 0] == pytest.approx(prior_P[0, 0] + 4.0,
                                                                    rel=1e-14)


def test_reset():
    """reset() forgets everything; the next measurement initialises afresh, any stamp."""
    estimator = StreamEstimator(EstimatorSettings(**TRAIN))
    estimator.process(10 * PERIOD_NS, 5.0, 1.0)
    estimator.process(11 * PERIOD_NS, 6.0, 1.0)
    estimator.reset()
    assert not estimator.initialized
    assert estimator.state is None and estimator.last_stamp_ns is None
    step = estimator.process(PERIOD_NS, -3.0, 2.0)  # older than before: accepted
    fresh = StreamEstimator(EstimatorSettings(**TRAIN)).process(PERIOD_NS, -3.0, 2.0)
    assert np.array_equal(step.x, fresh.x) and np.array_equal(step.P, fresh.P)
    assert estimator.last_stamp_ns == PERIOD_NS


def test_state_accessors():
    """The state is None before the first measurement and copies afterwards."""
    estimator = StreamEstimator(EstimatorSettings(**TRAIN))
    assert estimator.state is None and not estimator.initialized
    estimator.process(PERIOD_NS, 1.0, 1.0)
    x, P = estimator.state
    x[0], P[0, 0] = 99.0, 99.0
    assert estimator.state[0][0] == 1.0 and estimator.state[1][0, 0] == 1.0


@pytest.mark.parametrize('kwargs, name', [
    ({'initial_state': (0.0, 1.0, 2.0)}, 'initial_state'),
    ({'initial_state': (0.0, float('nan'))}, 'initial_state'),
    ({'initial_covariance': (1.0, 1.0, 1.0)}, 'initial_covariance'),
    ({'initial_covariance': (-1.0, 1.0)}, 'initial_covariance'),
    ({'initial_covariance': (1.0, 0.5, 0.0, 1.0)}, 'initial_covariance'),
    ({'initial_covariance': (1.0, float('inf'))}, 'initial_covariance'),
    ({'process_noise_density': -1.0}, 'process_noise_density'),
    ({'process_noise_density': float('nan')}, 'process_noise_density'),
    ({'process_noise_density': 'a'}, 'process_noise_density'),
    ({'measurement_variance': -1.0}, 'measurement_variance'),
    ({'measurement_variance': float('inf')}, 'measurement_variance'),
    ({'horizon_s': -2.0}, 'horizon_s'),
    ({'horizon_s': (1.0, 2.0)}, 'horizon_s'),
    ({'initialization': 'bogus'}, 'initialization'),
    ({'initialization': None}, 'initialization'),
    ({'nominal_period_s': 0.0}, 'nominal_period_s'),
    ({'nominal_period_s': -0.1}, 'nominal_period_s'),
    ({'first_velocity_std_mps': 0.0}, 'first_velocity_std_mps'),
    ({'first_velocity_std_mps': float('nan')}, 'first_velocity_std_mps'),
])
def test_settings_validation(kwargs, name):
    """Each bad settings field raises ValueError naming the field, also from the estimator."""
    settings = EstimatorSettings(**TRAIN, **kwargs)
    with pytest.raises(ValueError, match=rf'^{name} must'):
        settings.validated()
    with pytest.raises(ValueError, match=rf'^{name} must'):
        StreamEstimator(settings)


def test_covariance_from_list():
    """A covariance is given by its diagonal or its row-major entries."""
    assert np.array_equal(covariance_from_list('c', [1.0, 2.0], 2), np.diag([1.0, 2.0]))
    assert np.array_equal(covariance_from_list('c', [2.0, 0.5, 0.5, 1.0], 2),
                          [[2.0, 0.5], [0.5, 1.0]])
    settings = EstimatorSettings(**TRAIN, initialization='prior',
                                 initial_covariance=(2.0, 0.5, 0.5, 1.0))
    step = StreamEstimator(settings).process(PERIOD_NS, 0.0, 1.0)
    np.testing.assert_allclose(step.update.innovation_covariance,
                               [[2.0 + 2 * 0.1 * 0.5 + 0.01 * 1.0 + 1.0]], rtol=1e-14)


@pytest.mark.parametrize('settings', [
    EstimatorSettings(**TRAIN, initialization='prior'),
    EstimatorSettings(**TRAIN),
    EstimatorSettings(**TRAIN, process_noise_density=0.5, horizon_s=1.0),
])
def test_nanosecond_epoch_offset(settings):
    """Stamps at an epoch of 1.7e18 ns give the same estimates as stamps from 0."""
    rng = np.random.default_rng(11)
    gaps = rng.integers(1, 3 * PERIOD_NS, 300)  # irregular, to the nanosecond
    stamps = np.cumsum(gaps).tolist()
    positions = 10.0 * np.array(stamps) / NS_PER_S + rng.standard_normal(300)
    epoch = 1_700_000_000_000_000_000
    near, far = StreamEstimator(settings), StreamEstimator(settings)
    for stamp, z in zip(stamps, positions):
        a = near.process(stamp, z, 1.0)
        b = far.process(epoch + stamp, z, 1.0)
        np.testing.assert_allclose(b.x, a.x, rtol=1e-12, atol=0.0)
        np.testing.assert_allclose(b.P, a.P, rtol=1e-12, atol=0.0)
        np.testing.assert_allclose(b.predicted_x, a.predicted_x, rtol=1e-12, atol=0.0)
        assert b.stamp_ns - a.stamp_ns == epoch
        assert b.prediction_stamp_ns - a.prediction_stamp_ns == epoch
    # A float of epoch seconds could not have done this: its spacing there is ~0.2 µs.
    assert np.spacing(epoch / NS_PER_S) > 1e-7
