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
    """
    Assert |a − b| <= tol · max(1, |b|) elementwise.

    1e-9 against the KF on the linear presets: the deviation form's only extra rounding
    is the sum of the ±√c F L_i deviations, amplified by 1/(2c): γ_2n·Σ|F L_j|/√c per
    step. Carried through the closed loop with the actual products (every linear preset,
    seed 3), that first-order bound is <= 3e-11 relative at α = 1e-3, <= 2.5e-10 at
    α = 1e-4 (κ = 1) and 3.4e-10 for the car at α = 1e-4, κ = −1.9, the corner of
    the hypothesis test. Against filterpy on range-bearing (α >= 0.3, n/c <= 11):
    h's rounding amplified by n/c is ~1e-12 per step. 1e-9 leaves a margin of >= 3.
    """
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
    eps = np.finfo(float).eps
    # Plain float arithmetic (no BLAS): 0.5 / c is computed as such, exactly.
    np.testing.assert_allclose(points.Wm[1:], 0.5 / c, rtol=1e-15)
    # λ/c = (c − n)/c against 1 − n/c: each rounds twice, by <= u·(n/c) + u·|1 − n/c|
    # + u·|λ/c| in all, < 2·eps·max(1, n/c) (u = eps/2).
    np.testing.assert_allclose(points.Wm[0], 1.0 - n / c, rtol=0.0,
                               atol=2.0 * eps * max(1.0, n / c))
    # filterpy forms n + λ from λ = c − n, a rounding of ε·n relative to c.
    tolerance = 4.0 * eps * max(1.0, n / c)
    np.testing.assert_allclose(points.Wm, reference.Wm, rtol=tolerance)
    np.testing.assert_allclose(points.Wc, reference.Wc, rtol=tolerance)
    # fsum adds exactly: what is left is the weights' own rounding, <= u·(3n/c + 2)
    # (Wm_0 rounds twice), < 4u/α² for these κ (n/(n + κ) <= 8/7): inside 1e-15/α².
    assert math.fsum(points.Wm) == pytest.approx(1.0, abs=1e-15 / alpha ** 2)
    moments = unscented_predict(x, P, points, np.zeros((n, n)), F=np.eye(n))
    # With F = I the deviations are s_i = ±√c L_i exactly (products by 1 and 0), so
    # the mean x + Σ s_i / (2c) is off only by the rounding of the sum of 2n terms,
    # <= γ_2n Σ|s_i| / (2c) = γ_2n Σ_j |L_j| / √c (γ_k ≈ k·u, any order or FMA),
    # and of x + δ (u|x|). At α = 1e-4 that is ~2e-11: small α amplifies it by 1/α.
    L = np.abs(np.linalg.cholesky(P))
    mean_bound = eps * np.abs(x) + 2 * n * eps * L.sum(axis=1) / math.sqrt(c)
    assert np.all(np.abs(moments[0] - x) <= mean_bound)
    # The covariance Σ W s_i s_iᵀ = L Lᵀ rounds by <= γ_2n |L||L|ᵀ, Cholesky's
    # backward error adds γ_{n+1} |L||L|ᵀ: ~15u·|P| in all, well inside 1e-12.
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
    for a, b in zip(got[:4], expected[:4]):
        _close(a, b, 1e-12)
    assert got.gate_nis is None and expected.gate_nis is None


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
    """
    Run the textbook (direct-form) angle-aware UKF in long double.

    Return the posterior means (N, 4) and, per step, what the rounding bound of
    test_small_alpha_stays_within_the_rounding_floor_of_h needs: the prior mean, the
    gain K and the largest |h(χ_i)| of each measurement component.
    """
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
    means, priors, gains, z_abs = [], [], [], []
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
        priors.append(x)
        gains.append(K)
        z_abs.append(np.max(np.abs(Z), axis=0))
        x = x + K @ (z.astype(ld) - zp)
        P = P - K @ S @ K.T
        P = (P + P.T) / 2
        means.append(x)
    return tuple(np.array(a).astype(float) for a in (means, priors, gains, z_abs))


def _range_bearing_jacobian(x):
    """Return ∂[atan2(y, x), √(x² + y²)] / ∂[x, vx, y, vy] at state x (sensor at 0)."""
    r2 = x[0] ** 2 + x[2] ** 2
    r = math.sqrt(r2)
    return np.array([[-x[2] / r2, 0.0, x[0] / r2, 0.0], [x[0] / r, 0.0, x[2] / r, 0.0]])


def _ukf_rounding_bound(preset, scenario, alpha, priors, gains, z_abs):
    """
    Return a bound (N, 4) on |float64 UKF − exact| for the range-bearing run.

    Derivation, to first order in the unit roundoffs u (float64) and u_ld (long double):

    * One float64 h(χ_i) is off by <= 8u·|h| (numpy's arctan2 and hypot are within
      4 ulp: numpy's accuracy tests allow up to 4 ulp for its float64 SIMD functions),
      plus the effect of rounding χ_i = x + s_i (<= u|χ_i| per component), which moves
      the bearing by <= u·|χ|/r = u and the range by <= u·r.
    * The measurement mean is Y_0 + Σ_{i>=1} d_i / (2c), d_i = h(χ_i) ⊖ h(χ_0), so these
      errors reach it as <= (2n / 2c)·(e_0 + max_i e_i) = (n/c)·2·max e. This is the
      floor of any float64 UKF: 1/(2c) = 1.25e5 at α = 1e-3. (The sum of the d_i and
      the division add ~2n·u·Σ|d_i| / 2c, below 1e-4 of it: d_i ~ √c·σ.)
    * The reference (direct form, long double) rounds 2n + 1 terms as large as
      (n/c)·|h| each: <= (2n + 1)·2·(n/c)·u_ld·|h|, about 1e-3 of ours.
    * The errors of S, P_xz and K are relative ~ e/|d_i| < 1e-9 and multiply an
      innovation of a few σ: below 1e-3 of the above, as is the rounding of x itself.
    * An error η_j in the predicted measurement at step j moves the state by −K_j η_j;
      the filter carries a state error e forward as (I − K J) F e (J the measurement
      Jacobian), so e_k = −Σ_j Φ_k⋯Φ_{j+1} K_j η_j and |e_k| <= Σ_j |Φ_k⋯Φ_{j+1} K_j| η_j
      elementwise. (Bounding factor by factor, |Φ_k|⋯|Φ_{j+1}|, grows without limit.)

    The products are taken from the long-double run; a factor 2 covers the neglected
    second-order terms.
    """
    n = 4
    c = alpha ** 2 * n
    u = float(np.finfo(float).eps) / 2.0
    u_ld = float(np.finfo(np.longdouble).eps) / 2.0
    bearing, radius = z_abs[:, 0], z_abs[:, 1]
    e_h = np.column_stack([8.0 * u * bearing + u, 8.0 * u * radius + u * radius])
    eta = (n / c) * 2.0 * e_h + (2 * n + 1) * 2.0 * (n / c) * u_ld * z_abs
    bound = np.empty_like(priors)
    carried = []  # Φ_k⋯Φ_{j+1} K_j for every earlier step j
    for k, dt in enumerate(time_steps_s(scenario.t_s)):
        Phi = (np.eye(n) - gains[k] @ _range_bearing_jacobian(priors[k])) @ preset.dynamics.F(dt)
        carried = [Phi @ M for M in carried] + [gains[k]]
        bound[k] = sum(np.abs(M) @ eta[j] for j, M in enumerate(carried))
    return 2.0 * bound


@pytest.mark.skipif(np.finfo(np.longdouble).eps > 1e-18,
                    reason='the reference needs an extended-precision long double')
@pytest.mark.parametrize('alpha', [1e-2, 1e-3])
def test_small_alpha_stays_within_the_rounding_floor_of_h(alpha):
    """
    At small alpha the UKF's error is the rounding of h, amplified by n/c, and no more.

    Against a long-double transcription of the textbook UKF, every step's state error
    is within the first-order bound of :func:`_ukf_rounding_bound`: the float64
    rounding of h(χ_i), which the sigma-point mean amplifies by n/c = 1/α² (10⁶ at
    MATLAB's α = 1e-3), carried through the filter. Nothing else may add to it: the
    deviation form does not round Wm_0·Y_0 (|Wm_0| ≈ n/c) against the other terms,
    and it computes the linear prediction exactly (that part is held to the KF at
    1e-9 down to α = 1e-4 by test_ukf_equals_the_kf_for_any_parameters).
    """
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 0)
    exact, priors, gains, z_abs = _textbook_ukf_ld(preset, scenario, alpha, 2.0, 0.0)
    ours = run_filter_series(make_filter(preset, 'ukf', alpha=alpha), scenario.t_s,
                             scenario.z).x
    bound = _ukf_rounding_bound(preset, scenario, alpha, priors, gains, z_abs)
    error = np.abs(ours - exact)
    assert np.all(error <= bound), float(np.max(error / bound))
    # The bound is not vacuous: ~3e-12/α² (3e-8 at α = 1e-2, 3e-6 at 1e-3, m and m/s).
    assert np.max(bound) < 1e-11 / alpha ** 2


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
