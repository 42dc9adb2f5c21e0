"""Tests of kf_train.filters.ukf: sigma points, the angle-aware transform, the robust root."""

import math

from filterpy.kalman import MerweScaledSigmaPoints as FilterpyPoints
from filterpy.kalman import unscented_transform as filterpy_transform
from filterpy.kalman import UnscentedKalmanFilter as FilterpyUKF
from hypothesis import given, settings
from hypothesis import strategies as st
from kf_train.batch import run_filter_series, run_series, time_steps_s
from kf_train.filters import (
    make_filter, MerweScaledSigmaPoints, robust_cholesky, unscented_predict, unscented_update,
    UnscentedModel)
from kf_train.presets import load_preset, preset_from_mapping, PRESET_NAMES
from kf_train.sim import scenario_for_preset
import numpy as np
import pytest
import yaml

LINEAR = [name for name in PRESET_NAMES if name != 'range-bearing']
# (alpha, beta, kappa): MATLAB's default, Julier's kappa = 3 - n, extremes of each.
PARAMETERS = [(1e-3, 2.0, 0.0), (1.0, 2.0, 0.0), (0.5, 0.0, 1.5), (1e-4, 5.0, 1.0),
              (3.0, 2.0, 0.0), (1.0, 2.0, -0.5)]


def _close(a, b, tol=1e-9):
    """Assert |a − b| <= tol · max(1, |b|) elementwise."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape
    err = np.abs(a - b) / np.maximum(1.0, np.abs(b))
    assert np.all(err <= tol), float(np.max(err))


def _wrap(angle):
    """Return an angle wrapped to [−π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


# ---------------------------------------------------------------------------
# Sigma points and the transform
# ---------------------------------------------------------------------------

@pytest.mark.parametrize('alpha,beta,kappa', PARAMETERS)
def test_sigma_points_reproduce_mean_and_covariance(alpha, beta, kappa):
    """The weighted sigma points have the mean x and covariance P; weights as filterpy."""
    rng = np.random.default_rng(7)
    n = 4
    A = rng.standard_normal((n, n))
    P = A @ A.T + 0.1 * np.eye(n)
    x = rng.standard_normal(n) * 10
    points = MerweScaledSigmaPoints(n, alpha, beta, kappa)
    reference = FilterpyPoints(n, alpha, beta, kappa)
    c = alpha ** 2 * (n + kappa)
    np.testing.assert_allclose(points.Wm[1:], 0.5 / c, rtol=1e-15)
    np.testing.assert_allclose(points.Wm[0], 1.0 - n / c, rtol=1e-15)
    # filterpy forms n + λ from λ = c − n, a rounding of ε·n relative to c.
    tolerance = 4.0 * np.finfo(float).eps * max(1.0, n / c)
    np.testing.assert_allclose(points.Wm, reference.Wm, rtol=tolerance)
    np.testing.assert_allclose(points.Wc, reference.Wc, rtol=tolerance)
    assert math.fsum(points.Wm) == pytest.approx(1.0, abs=1e-15 / alpha ** 2)
    moments = unscented_predict(x, P, points, np.zeros((n, n)), F=np.eye(n))
    _close(moments[0], x, 1e-12)
    _close(moments[1], P, 1e-12)


def test_nonlinear_transform_matches_filterpy():
    """Through polar → Cartesian, the deviation form equals filterpy's transform."""
    x, P = np.array([10.0, 0.7]), np.array([[4.0, 0.3], [0.3, 0.2]])

    def polar(X):
        return np.column_stack([X[:, 0] * np.cos(X[:, 1]), X[:, 0] * np.sin(X[:, 1])])
    for alpha, beta, kappa in PARAMETERS[1:3] + PARAMETERS[4:]:
        points = MerweScaledSigmaPoints(2, alpha, beta, kappa)
        reference = FilterpyPoints(2, alpha, beta, kappa)
        sigmas = polar(reference.sigma_points(x, P))
        mean, cov = filterpy_transform(sigmas, reference.Wm, reference.Wc)
        ours = unscented_predict(x, P, points, np.zeros((2, 2)), fx=polar)
        _close(ours[0], mean, 1e-12)
        _close(ours[1], cov, 1e-12)


# ---------------------------------------------------------------------------
# UKF = KF on linear models
# ---------------------------------------------------------------------------

@pytest.mark.parametrize('alpha,beta,kappa', PARAMETERS)
@pytest.mark.parametrize('name', LINEAR)
def test_ukf_equals_the_kf_on_every_linear_preset(name, alpha, beta, kappa):
    """On a linear preset the UKF gives the KF's means, covariances and predictions."""
    preset = load_preset(name)
    scenario = scenario_for_preset(name, seed=3)
    expected = run_series(preset, scenario.t_s, scenario.z, scenario.u, horizon_s=1.5)
    ukf = make_filter(preset, 'ukf', alpha=alpha, beta=beta, kappa=kappa)
    got = run_filter_series(ukf, scenario.t_s, scenario.z, scenario.u, horizon_s=1.5)
    for field in ('x', 'P', 'x_prior', 'P_prior', 'predicted_x', 'predicted_P'):
        _close(getattr(got, field), getattr(expected, field))


@settings(max_examples=25, deadline=None)
@given(alpha=st.floats(1e-4, 3.0), beta=st.floats(0.0, 4.0), kappa=st.floats(-1.9, 5.0),
       seed=st.integers(0, 1000))
def test_ukf_equals_the_kf_for_any_parameters(alpha, beta, kappa, seed):
    """Any alpha > 0, beta, kappa > −n: the car (control input) UKF is the KF."""
    preset = load_preset('car')
    scenario = scenario_for_preset('car', seed)
    expected = run_series(preset, scenario.t_s, scenario.z, scenario.u)
    ukf = make_filter(preset, 'ukf', alpha=alpha, beta=beta, kappa=kappa)
    got = run_filter_series(ukf, scenario.t_s, scenario.z, scenario.u)
    _close(got.x, expected.x)
    _close(got.P, expected.P)


def test_update_statistics_equal_the_kf():
    """Innovation, its covariance, the NIS and the gain equal the KF's."""
    preset = load_preset('cv-position-velocity')
    ukf = UnscentedModel.from_model(preset.model, alpha=0.3)
    x, P = preset.model.predict(preset.initial_state, preset.initial_covariance, 1.0)
    z = np.array([60.0, -2.0])
    _, _, expected = preset.model.update(x, P, z)
    _, _, got = ukf.update(x, P, z)
    for a, b in zip(got, expected):
        _close(a, b, 1e-12)


# ---------------------------------------------------------------------------
# The range-bearing preset against filterpy and an extended-precision transcription
# ---------------------------------------------------------------------------

def _hx(x):
    """Return filterpy's range-bearing measurement of a state."""
    return np.array([math.atan2(x[2], x[0]), math.hypot(x[0], x[2])])


def _z_mean(sigmas, Wm):
    """Return the weighted circular mean of the bearing and the mean range."""
    return np.array([math.atan2(Wm @ np.sin(sigmas[:, 0]), Wm @ np.cos(sigmas[:, 0])),
                     Wm @ sigmas[:, 1]])


def _residual_z(a, b):
    """Return a − b with the bearing wrapped."""
    d = np.asarray(a, dtype=float) - b
    d[0] = _wrap(d[0])
    return d


def _filterpy_ukf(preset, alpha, beta, kappa):
    """Return filterpy's UKF set up as the preset, angle-aware."""
    ukf = FilterpyUKF(4, 2, preset.nominal_period_s, _hx,
                      lambda x, dt: preset.dynamics.F(dt) @ x,
                      FilterpyPoints(4, alpha, beta, kappa), z_mean_fn=_z_mean,
                      residual_z=_residual_z)
    ukf.x, ukf.P = preset.initial_state.copy(), preset.initial_covariance.copy()
    ukf.R = preset.model.R.copy()
    return ukf


@pytest.mark.parametrize('alpha,beta,kappa', [(1.0, 2.0, 0.0), (0.3, 2.0, 0.0),
                                              (0.5, 0.0, 1.0)])
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_range_bearing_matches_filterpy(seed, alpha, beta, kappa):
    """Every row's x, P, innovation and S equal filterpy's UKF (angle-aware) to 1e-9."""
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', seed)
    reference = _filterpy_ukf(preset, alpha, beta, kappa)
    ours = make_filter(preset, 'ukf', alpha=alpha, beta=beta, kappa=kappa)
    for dt, z in zip(time_steps_s(scenario.t_s), scenario.z):
        reference.Q = preset.dynamics.Q(dt)
        reference.predict(dt=dt)
        reference.update(z)
        ours.predict(dt)
        result = ours.update(z)
        _close(ours.mean, reference.x)
        _close(ours.covariance, reference.P)
        _close(result.innovation, reference.y)
        _close(result.innovation_covariance, reference.S)


def _cholesky_ld(A):
    """Return the lower Cholesky factor of A in long double."""
    n = A.shape[0]
    L = np.zeros_like(A)
    for i in range(n):
        for j in range(i + 1):
            s = A[i, j] - np.sum(L[i, :j] * L[j, :j])
            L[i, j] = np.sqrt(s) if i == j else s / L[j, j]
    return L


def _solve_ld(A, B):
    """Return A⁻¹ B by Gauss-Jordan elimination with partial pivoting, in long double."""
    n = A.shape[0]
    M = np.concatenate([A, B], axis=1)
    for c in range(n):
        p = c + int(np.argmax(np.abs(M[c:, c])))
        M[[c, p]] = M[[p, c]]
        M[c] /= M[c, c]
        for r in range(n):
            if r != c:
                M[r] -= M[r, c] * M[c]
    return M[:, n:]


def _textbook_ukf_ld(preset, scenario, alpha, beta, kappa):
    """Run the textbook (direct-form) angle-aware UKF in long double; return the means."""
    ld = np.longdouble
    n = 4
    lam = ld(alpha) ** 2 * (n + ld(kappa)) - n
    Wm = np.full(2 * n + 1, 1 / (2 * (n + lam)), dtype=ld)
    Wm[0] = lam / (n + lam)
    Wc = Wm.copy()
    Wc[0] += 1 - ld(alpha) ** 2 + ld(beta)
    x = preset.initial_state.astype(ld)
    P = preset.initial_covariance.astype(ld)
    R = preset.model.R.astype(ld)

    def sigmas(x, P):
        L = _cholesky_ld((n + lam) * P)
        return np.array([x] + [x + L[:, i] for i in range(n)] + [x - L[:, i] for i in range(n)])
    means = []
    for dt, z in zip(time_steps_s(scenario.t_s), scenario.z):
        F, Q = preset.dynamics.F(dt).astype(ld), preset.dynamics.Q(dt).astype(ld)
        Y = sigmas(x, P) @ F.T
        x = Wm @ Y
        D = Y - x
        P = (D * Wc[:, None]).T @ D + Q
        X = sigmas(x, P)
        Z = np.column_stack([np.arctan2(X[:, 2], X[:, 0]), np.hypot(X[:, 0], X[:, 2])])
        zp = np.array([np.arctan2(Wm @ np.sin(Z[:, 0]), Wm @ np.cos(Z[:, 0])), Wm @ Z[:, 1]])
        dZ = Z - zp
        S = (dZ * Wc[:, None]).T @ dZ + R
        Pxz = ((X - x) * Wc[:, None]).T @ dZ
        K = _solve_ld(S, Pxz.T).T
        x = x + K @ (z.astype(ld) - zp)
        P = P - K @ S @ K.T
        P = (P + P.T) / 2
        means.append(x)
    return np.array(means)


def _relative_error(x, exact):
    """Return the largest |x − exact| / max(1, |exact|)."""
    return float(np.max(np.abs(x - exact) / np.maximum(1.0, np.abs(exact))))


@pytest.mark.parametrize('alpha', [1e-2, 1e-3])
def test_small_alpha_is_accurate_where_the_direct_form_is_not(alpha):
    """
    At small alpha the UKF stays close to a long-double transcription; filterpy does not.

    The direct form sums Wm_0·Y_0 with Wm_0 = 1 − n/c (≈ −10⁶ at MATLAB's α = 1e-3)
    and loses ~log10(n/c) digits of |x|; the deviation form does not. What is left is
    the rounding of h(χ_i) itself, amplified by 1/(2c) in the second-order mean (the
    floor for any float64 evaluation of h): below 1e-9 at α = 1e-2, and at α = 1e-3
    (where that floor is ~1e-8) still ten times smaller than filterpy's error.
    """
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 0)
    exact = _textbook_ukf_ld(preset, scenario, alpha, 2.0, 0.0).astype(float)
    ours = run_filter_series(make_filter(preset, 'ukf', alpha=alpha), scenario.t_s,
                             scenario.z).x
    reference = _filterpy_ukf(preset, alpha, 2.0, 0.0)
    theirs = []
    for dt, z in zip(time_steps_s(scenario.t_s), scenario.z):
        reference.Q = preset.dynamics.Q(dt)
        reference.predict(dt=dt)
        reference.update(z)
        theirs.append(reference.x.copy())
    ours_error = _relative_error(ours, exact)
    if alpha >= 1e-2:
        assert ours_error <= 1e-9
    else:
        assert ours_error <= _relative_error(np.array(theirs), exact) / 10.0


def test_circular_mean_is_right_across_the_branch_cut():
    """
    A target crossing bearing ±π is tracked as the mirrored one crossing 0.

    Mirroring the whole scene through the sensor (x → −x, bearing → bearing + π) maps
    the sigma points onto themselves, so the UKF must give exactly the mirrored
    estimates; a plain weighted mean of bearings near ±π would average to ~0 instead.
    """
    data = yaml.safe_load(open(load_preset('range-bearing').source, encoding='utf-8'))
    data.update(initial_state=[50.0, 0.0, -0.3, 0.5],
                initial_covariance=[4.0, 1.0, 4.0, 1.0])
    preset = preset_from_mapping(data)
    mirrored = preset_from_mapping(dict(data, initial_state=[-50.0, 0.0, 0.3, -0.5]))
    t = np.arange(1, 31) * 0.2
    truth_y = -0.3 + 0.5 * t
    rng = np.random.default_rng(4)
    z = np.column_stack([np.arctan2(truth_y, 50.0) + 1e-3 * rng.standard_normal(t.size),
                         np.hypot(50.0, truth_y) + rng.standard_normal(t.size)])
    z_mirror = z.copy()
    z_mirror[:, 0] = _wrap(z[:, 0] + math.pi)
    assert np.any(z_mirror[:, 0] > 3.0) and np.any(z_mirror[:, 0] < -3.0)
    for kind in ('ukf', 'ekf'):
        a = run_filter_series(make_filter(preset, kind), t, z)
        b = run_filter_series(make_filter(mirrored, kind), t, z_mirror)
        _close(b.x, -a.x)
        _close(b.P, a.P)
        assert np.all(np.abs(a.x[:, 2] - truth_y) < 1.0)


# ---------------------------------------------------------------------------
# Never crash: degenerate covariances, where filterpy raises
# ---------------------------------------------------------------------------

def test_robust_cholesky_cases():
    """PD: plain Cholesky; PSD or slightly indefinite: jitter; far from PD: eigenvalues."""
    P = np.array([[4.0, 1.0], [1.0, 3.0]])
    root = robust_cholesky(P)
    assert root.method == 'cholesky' and root.jitter == 0.0
    np.testing.assert_array_equal(root.L, np.linalg.cholesky(P))
    for P, method in [(np.zeros((3, 3)), 'jitter'), (np.diag([0.0, 0.05]), 'jitter'),
                      (np.array([[1.0, 1.0], [1.0, 1.0 - 1e-13]]), 'jitter'),
                      (np.diag([1.0, -0.5]), 'eigen'),
                      (np.array([[1.0, 2.0], [2.0 + 1e-12, 1.0]]), 'eigen')]:
        root = robust_cholesky(P)
        assert root.method == method
        np.linalg.cholesky(root.P)  # the regularised matrix is positive definite
        np.testing.assert_allclose(root.L @ root.L.T, root.P, atol=1e-12 * max(1.0, np.max(
            np.abs(P))))
        scale = max(float(np.max(np.abs(np.diag(P)))), 1e-154)
        if method == 'jitter':
            assert 0.0 < root.jitter <= 1e-12 * scale
    with pytest.raises(ValueError, match='P must be finite'):
        robust_cholesky([[np.nan]])


def _filterpy_linear(preset, scenario, R=None):
    """Run filterpy's UKF on a linear preset; return the exception it raised, or None."""
    ukf = FilterpyUKF(preset.dim_x, preset.dim_z, preset.nominal_period_s,
                      lambda x: preset.model.H @ x, lambda x, dt: preset.dynamics.F(dt) @ x,
                      FilterpyPoints(preset.dim_x, 1.0, 2.0, 0.0))
    ukf.x, ukf.P = preset.initial_state.copy(), preset.initial_covariance.copy()
    ukf.R = preset.model.R if R is None else R
    try:
        for dt, z in zip(time_steps_s(scenario.t_s), scenario.z):
            ukf.Q = preset.dynamics.Q(dt)
            ukf.predict(dt=dt)
            ukf.update(z)
    except np.linalg.LinAlgError as error:
        return error
    return None


def test_singular_initial_covariance_filterpy_raises_ours_equals_the_kf():
    """
    The cv-position seed with P0 = diag(0, 100) (position known): filterpy's UKF raises.

    Its Cholesky of (λ + n)·P0 fails at the first predict (rlabbe/filterpy #62,
    #218); ours adds a 1e-14 jitter and follows the KF to 1e-9.
    """
    data = yaml.safe_load(open(load_preset('cv-position').source, encoding='utf-8'))
    preset = preset_from_mapping(dict(data, initial_covariance=[0.0, 100.0]))
    scenario = scenario_for_preset('cv-position', 0)
    assert isinstance(_filterpy_linear(preset, scenario), np.linalg.LinAlgError)
    ukf = make_filter(preset, 'ukf', alpha=1.0)
    got = run_filter_series(ukf, scenario.t_s, scenario.z)
    expected = run_series(preset, scenario.t_s, scenario.z)
    _close(got.x, expected.x)
    _close(got.P, expected.P)
    assert ukf.diagnostics()['regularisations'] >= 1


def test_tiny_r_filterpy_raises_ours_stays_finite_and_within_its_uncertainty():
    """
    R = 1e-14 m² with P0 = 10⁶·I: P − K S Kᵀ loses definiteness and filterpy raises.

    Ours keeps P positive definite (Joseph form for a linear H) and every estimate
    is within 3σ of the KF's own posterior, σ = √diag(P_KF).
    """
    data = yaml.safe_load(open(load_preset('cv-position').source, encoding='utf-8'))
    preset = preset_from_mapping(dict(data, R=[[1e-14]], initial_covariance=[1e6, 1e6]))
    scenario = scenario_for_preset('cv-position', 0)
    assert isinstance(_filterpy_linear(preset, scenario), np.linalg.LinAlgError)
    got = run_filter_series(make_filter(preset, 'ukf'), scenario.t_s, scenario.z)
    expected = run_series(preset, scenario.t_s, scenario.z)
    assert np.all(np.isfinite(got.x)) and np.all(np.isfinite(got.P))
    for P in got.P:
        np.linalg.cholesky(P)
    sigma = np.sqrt(np.diagonal(expected.P, axis1=1, axis2=2))
    assert np.all(np.abs(got.x - expected.x) <= 3.0 * sigma + 1e-12 * np.abs(expected.x))


@pytest.mark.parametrize('P0,R', [
    ([1e-30, 1e-30, 1e-30, 1e-30], [[2e-6, 0.0], [0.0, 1.0]]),
    ([0.0, 0.0, 0.0, 0.0], [[2e-6, 0.0], [0.0, 1.0]]),
    ([100.0, 1000.0, 100.0, 1000.0], [[1e-20, 0.0], [0.0, 1e-12]]),
    ([1e-30, 1e6, 1e-30, 1e6], [[1e-20, 0.0], [0.0, 1e-12]]),
])
def test_degenerate_range_bearing_never_crashes(P0, R):
    """Near-singular or zero P0, tiny R: every row finite, every P positive definite."""
    data = yaml.safe_load(open(load_preset('range-bearing').source, encoding='utf-8'))
    preset = preset_from_mapping(dict(data, initial_covariance=P0, R=R))
    scenario = scenario_for_preset('range-bearing', 5)
    for alpha in (1e-3, 1.0):
        got = run_filter_series(make_filter(preset, 'ukf', alpha=alpha), scenario.t_s,
                                scenario.z)
        assert np.all(np.isfinite(got.x)) and np.all(np.isfinite(got.P))
        for P in got.P:
            np.linalg.cholesky(P)


def test_pure_functions_leave_inputs_and_reject_bad_ones():
    """Inputs are not modified; bad shapes and parameters raise ValueError naming them."""
    points = MerweScaledSigmaPoints(2, 1.0)
    x, P = np.array([1.0, 2.0]), np.eye(2)
    x0, P0 = x.copy(), P.copy()
    unscented_update(x, P, [1.5], points, [[1.0]], H=np.array([[1.0, 0.0]]))
    unscented_predict(x, P, points, np.eye(2), F=np.eye(2))
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(P, P0)
    with pytest.raises(ValueError, match='P must be positive semi-definite'):
        unscented_predict(x, -np.eye(2), points, np.eye(2), F=np.eye(2))
    with pytest.raises(ValueError, match='x must have length 2'):
        unscented_predict([1.0], P, points, np.eye(2), F=np.eye(2))
    with pytest.raises(ValueError, match='R must have shape'):
        unscented_update(x, P, [1.5], points, np.eye(2), H=np.array([[1.0, 0.0]]))
    with pytest.raises(ValueError, match='fx must return shape'):
        unscented_predict(x, P, points, np.eye(2), fx=lambda X: X[:, :1])
    for kwargs, message in [({'alpha': 0.0}, 'alpha must be > 0'),
                            ({'alpha': float('nan')}, 'alpha must be finite'),
                            ({'kappa': -2.0}, 'kappa must be > -n = -2'),
                            ({'beta': float('inf')}, 'beta must be finite')]:
        with pytest.raises(ValueError, match=message):
            MerweScaledSigmaPoints(2, **kwargs)
    with pytest.raises(ValueError, match='n must be a positive integer'):
        MerweScaledSigmaPoints(0)
