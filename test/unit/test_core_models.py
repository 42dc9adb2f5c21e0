"""Tests of kf_train.filters.models: transition matrix and the two process-noise models."""

from fractions import Fraction
import math

from kf_train.filters import (
    constant_velocity_F, ConstantVelocityModel, PerStepNoise, POSITION_H, WhiteNoiseAcceleration)
import numpy as np
import pytest
from scipy import integrate

DTS = [0.0, 1e-9, 1e-3, 0.05, 0.1, 0.25, 1.0 / 3.0, 0.7, 1.0, 2.0, 3.7, 10.0, 1234.5]


def _wna_integral(q, dt):
    """Return the integral over [0, dt] of F(s) G Gᵀ F(s)ᵀ q ds, G = [0, 1]ᵀ, by quad."""
    def integrand(s, i, j):
        FG = np.array([s, 1.0])  # F(s) G
        return q * FG[i] * FG[j]
    Q = np.empty((2, 2))
    for i in range(2):
        for j in range(2):
            Q[i, j] = integrate.quad(integrand, 0.0, dt, args=(i, j),
                                     epsabs=0.0, epsrel=1e-13)[0]
    return Q


def test_constant_velocity_F():
    """F(dt) is [[1, dt], [0, 1]] and F(a) F(b) == F(a + b)."""
    assert np.array_equal(constant_velocity_F(0.3), np.array([[1.0, 0.3], [0.0, 1.0]]))
    assert np.array_equal(constant_velocity_F(0.0), np.eye(2))
    assert np.allclose(constant_velocity_F(0.2) @ constant_velocity_F(1.3),
                       constant_velocity_F(1.5), rtol=0.0, atol=1e-15)


@pytest.mark.parametrize('q', [0.0, 1e-3, 0.5, 1.0, 42.0, 1e3])
@pytest.mark.parametrize('dt', DTS)
def test_white_noise_acceleration_formula(q, dt):
    """Q(dt) is q · [[dt³/3, dt²/2], [dt²/2, dt]]."""
    expected = q * np.array([[dt ** 3 / 3.0, dt ** 2 / 2.0], [dt ** 2 / 2.0, dt]])
    np.testing.assert_allclose(WhiteNoiseAcceleration(q)(dt), expected, rtol=1e-15, atol=0.0)


@pytest.mark.parametrize('q', [1e-3, 1.0, 42.0])
@pytest.mark.parametrize('dt', [1e-3, 0.1, 0.7, 1.0, 2.0, 10.0, 1234.5])
def test_white_noise_acceleration_matches_integral(q, dt):
    """Q(dt) equals the numerically integrated continuous noise."""
    np.testing.assert_allclose(WhiteNoiseAcceleration(q)(dt), _wna_integral(q, dt),
                               rtol=1e-10, atol=0.0)


def test_white_noise_acceleration_matches_trapezoid():
    """Q(dt) equals a fine trapezoid integration (an independent second quadrature)."""
    q, dt = 3.0, 2.5
    s = np.linspace(0.0, dt, 200_001)
    FG = np.stack([s, np.ones_like(s)])  # F(s) G for every s, shape (2, len(s))
    integrand = q * FG[:, None, :] * FG[None, :, :]
    Q = integrate.trapezoid(integrand, s, axis=-1)
    # The trapezoid error is dt h² max|f''| / 12 with f'' = 2q for the (0, 0) entry.
    h = dt / (len(s) - 1)
    np.testing.assert_allclose(WhiteNoiseAcceleration(q)(dt), Q, rtol=0.0,
                               atol=dt * h ** 2 * 2.0 * q / 12.0 + 1e-12)


def test_white_noise_acceleration_zero_dt_and_properties():
    """Q(0) is exactly zero; Q(dt) is symmetric and positive semi-definite."""
    assert np.array_equal(WhiteNoiseAcceleration(7.0)(0.0), np.zeros((2, 2)))
    for dt in DTS:
        Q = WhiteNoiseAcceleration(7.0)(dt)
        assert np.array_equal(Q, Q.T)
        assert np.min(np.linalg.eigvalsh(Q)) >= -1e-12 * np.max(np.abs(Q))


@pytest.mark.parametrize('Q_step', [
    [[0.0, 0.0], [0.0, 0.05]],
    [[1e-4, 0.0], [0.0, 1e-4]],
    [[1.0, 0.3], [0.3, 2.0]],
    [[2.0, -0.5], [-0.5, 1.0]],
])
@pytest.mark.parametrize('period', [0.1, 0.3, 1.0 / 3.0, 0.7, 1.0, 2.5, 1e-3])
def test_per_step_noise_one_period_is_q_step_exactly(Q_step, period):
    """Q(period) is Q_step bit for bit, and Q(0) is exactly zero."""
    noise = PerStepNoise(Q_step, period)
    assert np.array_equal(noise(period), np.array(Q_step))
    assert np.array_equal(noise(0.0), np.zeros((2, 2)))


def _brute_force_per_step(Q_step, period, dt):
    """
    Return Q(dt) by stepping: n full periods, then the remainder, in exact arithmetic.

    Every float input is converted to the rational number it exactly represents, so the
    only rounding is the final conversion back to float: the loop itself accumulates no
    error however many steps it takes.
    """
    T = Fraction(period)
    d = Fraction(dt)
    n = math.floor(d / T)
    r = d - n * T
    Qs = [[Fraction(v) for v in row] for row in Q_step]

    def step(Q, s, weight):
        # Q <- F(s) Q F(s)ᵀ + weight · Q_step, written out for F(s) = [[1, s], [0, 1]].
        a, c, b = Q[0][0], Q[0][1], Q[1][1]
        a, c = a + 2 * s * c + s * s * b, c + s * b
        return [[a + weight * Qs[0][0], c + weight * Qs[0][1]],
                [c + weight * Qs[1][0], b + weight * Qs[1][1]]]

    Q = [[Fraction(0), Fraction(0)], [Fraction(0), Fraction(0)]]
    for _ in range(n):
        Q = step(Q, T, 1)
    Q = step(Q, r, r / T)
    return np.array([[float(v) for v in row] for row in Q])


@pytest.mark.parametrize('Q_step', [
    [[0.0, 0.0], [0.0, 0.05]],
    [[1.0, 0.3], [0.3, 2.0]],
])
@pytest.mark.parametrize('dt', [0.0, 0.01, 0.05, 0.1, 0.15, 0.2, 0.3, 0.99, 2.0, 2.05,
                                7.77, 123.4, 1234.5])
def test_per_step_noise_matches_stepping(Q_step, dt):
    """Q(n·T + r) equals n full steps then a remainder step weighted r/T."""
    noise = PerStepNoise(Q_step, 0.1)
    expected = _brute_force_per_step(Q_step, 0.1, dt)
    np.testing.assert_allclose(noise(dt), expected, rtol=1e-12,
                               atol=1e-12 * np.max(np.abs(expected)))


@pytest.mark.parametrize('dt', [0.0, 0.4, 1.0, 1.3, 2.0, 2.9, 60.0])
def test_per_step_noise_other_period(dt):
    """The stepping identity holds for a period that is not a decimal fraction."""
    Q_step = [[0.5, 0.1], [0.1, 0.25]]
    noise = PerStepNoise(Q_step, 1.0 / 3.0)
    expected = _brute_force_per_step(Q_step, 1.0 / 3.0, dt)
    np.testing.assert_allclose(noise(dt), expected, rtol=1e-12,
                               atol=1e-12 * np.max(np.abs(expected)))


def test_per_step_noise_seed_two_seconds_is_twenty_steps():
    """A 2-s prediction with the seed period is as uncertain as 20 seed steps in floats."""
    Q_step = np.diag([0.0, 0.05])
    F = constant_velocity_F(0.1)
    Q = np.zeros((2, 2))
    for _ in range(20):
        Q = F @ Q @ F.T + Q_step
    np.testing.assert_allclose(PerStepNoise(Q_step, 0.1)(2.0), Q, rtol=1e-12, atol=0.0)


def test_per_step_noise_is_symmetric_psd_and_continuous():
    """Q(dt) is symmetric PSD and has no jump at a whole number of periods."""
    noise = PerStepNoise([[1.0, 0.3], [0.3, 2.0]], 0.1)
    for dt in np.linspace(0.0, 5.0, 501):
        Q = noise(dt)
        assert np.array_equal(Q, Q.T)
        assert np.min(np.linalg.eigvalsh(Q)) >= -1e-12 * np.max(np.abs(Q))
    for k in (1, 2, 10, 37):
        below, above = noise(k * 0.1 - 1e-12), noise(k * 0.1 + 1e-12)
        np.testing.assert_allclose(below, above, rtol=1e-9, atol=0.0)


def test_constant_velocity_model_delegates():
    """The model's F and Q are constant_velocity_F and the noise callable."""
    noise = WhiteNoiseAcceleration(2.0)
    model = ConstantVelocityModel(noise)
    assert model.dim_x == 2
    assert np.array_equal(model.F(0.7), constant_velocity_F(0.7))
    assert np.array_equal(model.Q(0.7), noise(0.7))
    assert np.array_equal(POSITION_H, np.array([[1.0, 0.0]]))
    assert 'WhiteNoiseAcceleration(q=2.0)' in repr(model)


@pytest.mark.parametrize('call', [
    lambda: constant_velocity_F(-0.1),
    lambda: constant_velocity_F(float('nan')),
    lambda: WhiteNoiseAcceleration(1.0)(-1e-9),
    lambda: WhiteNoiseAcceleration(1.0)(float('inf')),
    lambda: PerStepNoise(np.eye(2), 0.1)(-0.1),
    lambda: PerStepNoise(np.eye(2), 0.1)([0.1, 0.2]),
])
def test_models_reject_bad_dt(call):
    """A negative, non-finite or non-scalar dt raises ValueError naming dt."""
    with pytest.raises(ValueError, match=r'^dt must'):
        call()


@pytest.mark.parametrize('call, name', [
    (lambda: WhiteNoiseAcceleration(-1.0), 'q'),
    (lambda: WhiteNoiseAcceleration(float('nan')), 'q'),
    (lambda: PerStepNoise(np.eye(2), 0.0), 'period_s'),
    (lambda: PerStepNoise(np.eye(2), -0.1), 'period_s'),
    (lambda: PerStepNoise(np.eye(3), 0.1), 'Q_step'),
    (lambda: PerStepNoise(-np.eye(2), 0.1), 'Q_step'),
    (lambda: PerStepNoise([[1.0, 0.5], [0.0, 1.0]], 0.1), 'Q_step'),
    (lambda: PerStepNoise([[1.0, np.nan], [np.nan, 1.0]], 0.1), 'Q_step'),
])
def test_models_reject_bad_parameters(call, name):
    """Bad noise parameters raise ValueError naming the parameter."""
    with pytest.raises(ValueError, match=rf'^{name} must'):
        call()


@pytest.mark.parametrize('noise', [WhiteNoiseAcceleration(1.0),
                                   PerStepNoise([[1.0, 0.0], [0.0, 1.0]], 0.1)])
def test_an_overflowing_dt_is_a_value_error(noise):
    """A dt so large that Q overflows raises ValueError naming dt, not OverflowError."""
    with pytest.raises(ValueError, match='dt'):
        noise(1e300)
