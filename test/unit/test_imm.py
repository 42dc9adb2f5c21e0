"""The generic IMM (kf_train.filters.imm): filterpy's IMMEstimator, probabilities, purity."""

from filterpy.kalman import IMMEstimator, KalmanFilter
from hypothesis import given, settings, strategies as st
from kf_train.estimator.imm_model import IMMModel
from kf_train.filters import kalman
from kf_train.filters.imm import (
    check_transition_matrix, combine, FixedTransition, IMM, IMMFilter, make_state,
    RateTransition)
from kf_train.filters.models import LinearModel
import numpy as np
import pytest

DT = 0.1
H = np.array([[1.0, 0.0, 0.0]])


def _regimes():
    """Return three linear regimes in [p, v, a]: CV (a held at 0), quiet CA, agile CA."""
    ca = np.array([[1.0, DT, DT * DT / 2.0], [0.0, 1.0, DT], [0.0, 0.0, 1.0]])
    cv = ca.copy()
    cv[:, 2] = 0.0
    return [(cv, np.diag([0.0, 1e-3, 0.0]), 1.0),
            (ca, np.diag([1e-7, 1e-5, 1e-4]), 1.0),
            (ca, np.diag([1e-5, 1e-3, 5e-2]), 2.0)]  # its own R: filterpy allows it


def _ours(M, mu0, x0, P0):
    models = [LinearModel(lambda dt, F=F: F, lambda dt, Q=Q: Q, H, [[r]],
                          state_names=('p', 'v', 'a')) for F, Q, r in _regimes()]
    imm = IMM(models, FixedTransition(M))
    return imm, imm.initial_state(x0, P0, mu0)


def _filterpy(M, mu0, x0, P0):
    filters = []
    for F, Q, r in _regimes():
        f = KalmanFilter(dim_x=3, dim_z=1)
        f.F, f.Q, f.H, f.R = F, Q, H, np.array([[r]])
        f.x, f.P = np.array(x0, dtype=float)[:, None], np.array(P0, dtype=float)
        filters.append(f)
    return IMMEstimator(filters, mu0, M)


def _maneuvering_measurements(seed, n=400):
    """Return positions of a target that cruises, accelerates and brakes, with noise."""
    rng = np.random.default_rng(seed)
    a = np.where(np.arange(n) < 100, 0.0, np.where(np.arange(n) < 200, 1.0, -0.8))
    v = 10.0 + np.cumsum(a) * DT
    return np.cumsum(v) * DT + rng.standard_normal(n)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_equals_filterpy_imm_estimator(seed):
    # Both run the same arithmetic (mixing, F P Fᵀ + Q, Joseph update, Bayes rule on
    # the mode probabilities) in a different order: ours symmetrises P after each step,
    # sums the mixtures with einsum and normalises likelihoods in the log domain. Each
    # step therefore differs by a few ulps of the quantities (|x| <= 2e3, P <= 10, so
    # ~1e-12 absolute), and the filters are stable: an error in one step is damped, not
    # amplified, by the next (the Kalman recursion is contractive). 400 steps stay near
    # 1e-12; 1e-9 leaves three orders of magnitude for CPU-dependent rounding.
    M = np.array([[0.95, 0.03, 0.02], [0.02, 0.96, 0.02], [0.05, 0.05, 0.90]])
    mu0, x0, P0 = [0.5, 0.3, 0.2], [0.0, 9.0, 0.0], np.diag([1.0, 4.0, 1.0])
    imm, state = _ours(M, mu0, x0, P0)
    reference = _filterpy(M, mu0, x0, P0)
    for z in _maneuvering_measurements(seed):
        reference.predict()
        state = imm.predict(state, DT)
        for f, x, P in zip(reference.filters, state.means, state.covariances):
            np.testing.assert_allclose(x, f.x[:, 0], rtol=0, atol=1e-9)
            np.testing.assert_allclose(P, f.P, rtol=0, atol=1e-9)
        np.testing.assert_allclose(state.probabilities, reference.cbar, rtol=0, atol=1e-9)
        reference.update(z)
        state, _ = imm.update(state, z)
        x, P = imm.estimate(state)
        np.testing.assert_allclose(state.probabilities, reference.mu, rtol=0, atol=1e-9)
        np.testing.assert_allclose(x, reference.x[:, 0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(P, reference.P, rtol=0, atol=1e-9)
    # The run exercised the switching: each regime led at some point.
    assert reference.mu.max() < 1.0


def test_a_single_mode_imm_is_the_kalman_filter():
    F, Q, r = _regimes()[1]
    model = LinearModel(lambda dt: F, lambda dt: Q, H, [[r]], state_names=('p', 'v', 'a'))
    imm = IMM([model], FixedTransition([[1.0]]))
    state = imm.initial_state([0.0, 9.0, 0.0], np.eye(3))
    x, P = np.array([0.0, 9.0, 0.0]), np.eye(3)
    for z in _maneuvering_measurements(5, 50):
        state = imm.predict(state, DT)
        state, result = imm.update(state, z)
        x, P = kalman.predict(x, P, F, Q)
        x, P, expected = kalman.update(x, P, z, H, [[r]])
        np.testing.assert_array_equal(state.means[0], x)
        np.testing.assert_array_equal(state.covariances[0], P)
        # The mixture innovation of one mode is that mode's, to rounding.
        np.testing.assert_allclose(result.innovation, expected.innovation, rtol=1e-12)
        np.testing.assert_allclose(result.innovation_covariance,
                                   expected.innovation_covariance, rtol=1e-12)
        assert result.nis == pytest.approx(expected.nis, rel=1e-12)
        np.testing.assert_allclose(result.gain, expected.gain, rtol=1e-10, atol=1e-15)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1e7, 1e7), min_size=1, max_size=30),
       st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3))
def test_mode_probabilities_sum_to_one_even_when_likelihoods_underflow(zs, mu0):
    # Measurements up to 1e7 m away make every likelihood exp(-1e13) = 0 in floats;
    # the log-domain normalisation still gives finite probabilities summing to 1.
    if sum(mu0) == 0.0:
        mu0 = [1.0, 0.0, 0.0]
    M = np.array([[0.9, 0.05, 0.05], [0.05, 0.9, 0.05], [0.05, 0.05, 0.9]])
    imm, state = _ours(M, mu0, [0.0, 0.0, 0.0], np.eye(3))
    for z in zs:
        state = imm.predict(state, DT)
        assert state.probabilities.sum() == pytest.approx(1.0, abs=1e-12)
        state, _ = imm.update(state, z)
        assert np.all(np.isfinite(state.probabilities))
        assert np.all(state.probabilities >= 0.0)
        assert state.probabilities.sum() == pytest.approx(1.0, abs=1e-12)


def test_the_filter_rewinds_exactly_and_a_failed_step_changes_nothing():
    M = np.array([[0.97, 0.02, 0.01], [0.02, 0.97, 0.01], [0.05, 0.05, 0.9]])
    imm, _ = _ours(M, None, [0.0, 9.0, 0.0], np.eye(3))
    filt = IMMFilter(imm, [0.0, 9.0, 0.0], np.eye(3))
    zs = _maneuvering_measurements(3, 60)
    for z in zs[:30]:
        filt.predict(DT)
        filt.update(z)
    kept = filt.snapshot()
    ahead = filt.predict_ahead(2.0)
    np.testing.assert_array_equal(filt.predict_ahead(2.0)[0], ahead[0])  # nothing moved
    assert filt.snapshot() is kept
    first = []
    for z in zs[30:]:
        filt.predict(DT)
        filt.update(z)
        first.append(filt.mean)
    filt.restore(kept)
    for z, expected in zip(zs[30:], first):
        filt.predict(DT)
        filt.update(z)
        np.testing.assert_array_equal(filt.mean, expected)
    before = filt.snapshot()
    for bad in (float('nan'), [1.0, 2.0], 'x'):
        with pytest.raises(ValueError):
            filt.update(bad)
        assert filt.snapshot() is before
    with pytest.raises(ValueError):
        filt.predict(-0.1)
    assert filt.snapshot() is before
    with pytest.raises(ValueError):
        before.means[0, 0] = 1.0  # states are read-only: a snapshot cannot be altered
    copy = filt.copy()
    copy.predict(DT)
    assert filt.snapshot() is before
    filt.reset()
    np.testing.assert_array_equal(filt.mean, [0.0, 9.0, 0.0])
    np.testing.assert_allclose(filt.mode_probabilities, [1 / 3] * 3)


def test_rate_transitions_are_stochastic_for_every_dt():
    rates = RateTransition([[0.0, 0.5, 0.1], [0.2, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(rates.matrix(0.0), np.eye(3))
    for dt in (1e-6, 0.1, 2.0, 1e6):
        matrix = rates.matrix(dt)
        check_transition_matrix(matrix, 3)  # raises unless >= 0 with rows summing to 1
        # Leaving mode 0 at 0.6/s: e^(-0.6 dt) stays; the rest splits 5 : 1.
        assert matrix[0, 0] == pytest.approx(np.exp(-0.6 * dt))
        assert matrix[0, 1] == pytest.approx(5.0 * matrix[0, 2])
        assert matrix[2, 2] == 1.0  # absorbing
    with pytest.raises(ValueError, match='rates'):
        RateTransition([[0.0, -1.0], [0.0, 0.0]])
    with pytest.raises(ValueError, match='rows summing to 1'):
        FixedTransition([[0.5, 0.4], [0.0, 1.0]])


def test_combine_is_the_mixture_moments():
    rng = np.random.default_rng(4)
    means = rng.normal(size=(3, 2))
    covs = np.array([np.eye(2) * s for s in (0.5, 1.0, 2.0)])
    mu = np.array([0.2, 0.5, 0.3])
    x, P = combine(means, covs, mu)
    np.testing.assert_allclose(x, mu @ means)
    # E[xxᵀ] - x xᵀ of the mixture, written out.
    second = sum(m * (C + np.outer(a, a)) for m, a, C in zip(mu, means, covs))
    np.testing.assert_allclose(P, second - np.outer(x, x), atol=1e-14)


def test_states_are_checked():
    with pytest.raises(ValueError, match='covariances'):
        make_state(np.zeros((2, 2)), np.zeros((3, 2, 2)), [0.5, 0.5])
    with pytest.raises(ValueError, match='probabilities'):
        make_state(np.zeros((2, 2)), np.zeros((2, 2, 2)), [-0.5, 1.5])
    with pytest.raises(ValueError, match='mode_names'):
        IMM([object(), object()], FixedTransition(np.eye(2)), mode_names=('a', 'a'))


def test_the_pure_x_p_adapter_remembers_every_state_and_rewinds_exactly():
    M = np.array([[0.95, 0.03, 0.02], [0.02, 0.96, 0.02], [0.05, 0.05, 0.90]])
    imm, _ = _ours(M, None, [0.0, 9.0, 0.0], np.eye(3))
    model = IMMModel(imm, H, [[1.0]], ('p', 'v', 'a'))
    filt = IMMFilter(imm, [0.0, 9.0, 0.0], np.eye(3))
    zs = _maneuvering_measurements(7, 80)
    x, P = np.array([0.0, 9.0, 0.0]), np.eye(3)  # not one of the model's: a fresh start
    kept = []
    for z in zs:
        x, P = model.predict(x, P, DT)
        x, P, result = model.update(x, P, z)
        filt.predict(DT)
        expected = filt.update(z)
        np.testing.assert_array_equal(x, filt.mean)
        np.testing.assert_array_equal(P, filt.covariance)
        assert result.nis == expected.nis
        np.testing.assert_array_equal(model.mode_probabilities(x, P), filt.mode_probabilities)
        kept.append((x, P))
    # Rewind to step 40 and replay: the same numbers, because x remembers its state.
    x, P = kept[40]
    for z, (x_first, P_first) in zip(zs[41:], kept[41:]):
        x, P = model.predict(x, P, DT)
        x, P, _ = model.update(x, P, z)
        np.testing.assert_array_equal(x, x_first)
        np.testing.assert_array_equal(P, P_first)
    np.testing.assert_array_equal(model.predict_ahead(x, P, 2.0)[0], filt.predict_ahead(2.0)[0])
    # A copy of a mean is not the mean: it starts every mode afresh at (x, P).
    np.testing.assert_allclose(model.mode_probabilities(x.copy(), P), [1 / 3] * 3)
    # States of freed means are forgotten.
    count = len(model.states)
    del kept, x, P, x_first, P_first
    assert len(model.states) < count
