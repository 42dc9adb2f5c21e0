"""Tests of kf_train.filters.kalman against filterpy, seed 000 and closed-form solutions."""

import filterpy.kalman
from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.filters import (
    constant_velocity_F, KalmanFilter, PerStepNoise, predict, update, WhiteNoiseAcceleration)
import numpy as np
import pytest

# Both filters evaluate the same equations in float64 and differ only by rounding
# (summation order, FMA, solve against inverse). These problems are well conditioned
# (S scalar or with κ <= 3, the prior at most ~100x the posterior), so a step rounds
# by <= ~16u·κ of its terms (u = eps/2); the closed loop (I − K H) F carries earlier
# errors with products whose norms sum to O(10) here: <= ~1e-11 relative over the
# 300-500 steps. 1e-9 leaves a margin of ~100; the Q = 0 least-squares tests below
# add their own bounds.
RTOL = 1e-9
# The train's constant-velocity KF without a gate: the defaults before issue 11 (the
# defaults are now the rail preset with the gate on; test_estimator_rail.py).
TRAIN = {'preset': 'train', 'gate_probability': 1.0}


def _close(actual, expected, scale=1.0):
    """Assert agreement to RTOL relative, with an absolute floor of RTOL times scale."""
    np.testing.assert_allclose(actual, expected, rtol=RTOL, atol=RTOL * scale)


def _run_against_filterpy(x0, P0, steps):
    """
    Run our filter and filterpy's side by side, comparing after every step.

    Each step is a dict with F, Q and optionally B and u (predict), then z, H and R
    (update). Returns our filter after the last step.
    """
    x0 = np.asarray(x0, dtype=float)
    P0 = np.asarray(P0, dtype=float)
    ours = KalmanFilter(x0, P0)
    dim_z = np.atleast_1d(steps[0]['z']).shape[0]
    oracle = filterpy.kalman.KalmanFilter(dim_x=x0.shape[0], dim_z=dim_z)
    oracle.x = x0.reshape(-1, 1).copy()
    oracle.P = P0.copy()
    for step in steps:
        B, u = step.get('B'), step.get('u')
        ours.predict(step['F'], step['Q'], B, u)
        if B is None:
            oracle.predict(F=step['F'], Q=step['Q'])
        else:
            oracle.predict(u=np.asarray(u, dtype=float).reshape(-1, 1),
                           B=np.asarray(B, dtype=float),
                           F=step['F'], Q=step['Q'])
        scale = max(1.0, np.max(np.abs(oracle.P)))
        _close(ours.x, oracle.x.ravel(), np.max(np.abs(oracle.x)))
        _close(ours.P, oracle.P, scale)

        result = ours.update(step['z'], step['H'], step['R'])
        oracle.update(np.asarray(step['z'], dtype=float).reshape(-1, 1),
                      R=np.asarray(step['R'], dtype=float), H=np.asarray(step['H'], dtype=float))
        scale = max(1.0, np.max(np.abs(oracle.P)))
        _close(ours.x, oracle.x.ravel(), max(1.0, np.max(np.abs(oracle.x))))
        _close(ours.P, oracle.P, scale)
        _close(result.innovation, oracle.y.ravel(), max(1.0, np.max(np.abs(oracle.y))))
        _close(result.innovation_covariance, oracle.S, np.max(np.abs(oracle.S)))
        _close(result.gain, oracle.K, max(1.0, np.max(np.abs(oracle.K))))
        y = result.innovation
        np.testing.assert_allclose(
            result.nis, float(y @ np.linalg.inv(result.innovation_covariance) @ y),
            rtol=RTOL, atol=1e-12)
        np.testing.assert_allclose(result.nis, oracle.mahalanobis ** 2, rtol=RTOL, atol=1e-12)
    return ours


def test_filterpy_seed_000_train():
    """Seed 000 (Q = 0, R = 1, x0 = [0, 5], P0 = I) matches filterpy over 500 steps."""
    rng = np.random.default_rng(1)
    dt = 0.1
    F = np.array([[1.0, dt], [0.0, 1.0]])
    steps = [{'F': F, 'Q': np.zeros((2, 2)), 'z': [10.0 * k * dt + rng.standard_normal()],
              'H': [[1.0, 0.0]], 'R': [[1.0]]} for k in range(1, 501)]
    kf = _run_against_filterpy([0.0, 5.0], np.eye(2), steps)
    assert abs(kf.x[1] - 10.0) < 0.5  # sanity: the velocity converged


def test_filterpy_process_noise_varying_dt():
    """Nonzero white-noise-acceleration Q with random dt (including 0) matches filterpy."""
    rng = np.random.default_rng(2)
    noise = WhiteNoiseAcceleration(0.5)
    dts = rng.uniform(0.0, 2.0, 400)
    dts[::37] = 0.0
    position, velocity, steps = 0.0, 3.0, []
    for dt in dts:
        velocity += rng.normal(0.0, np.sqrt(0.5 * dt))
        position += velocity * dt
        steps.append({'F': constant_velocity_F(dt), 'Q': noise(dt),
                      'z': [position + rng.normal(0.0, 2.0)], 'H': [[1.0, 0.0]],
                      'R': [[4.0]]})
    _run_against_filterpy([0.0, 0.0], np.diag([10.0, 10.0]), steps)


def test_filterpy_per_step_noise():
    """Per-step noise over irregular intervals matches filterpy."""
    rng = np.random.default_rng(3)
    noise = PerStepNoise([[0.01, 0.002], [0.002, 0.05]], 0.1)
    steps = []
    for k, dt in enumerate(rng.choice([0.05, 0.1, 0.2, 0.35, 1.0], 300)):
        steps.append({'F': constant_velocity_F(dt), 'Q': noise(dt), 'z': [2.0 * k],
                      'H': [[1.0, 0.0]], 'R': [[0.5]]})
    _run_against_filterpy([0.0, 1.0], np.eye(2), steps)


def test_filterpy_control_input():
    """The car of seed 001 (B = [0, dt], u = 1, P0 = Q) and a 2-input B match filterpy."""
    rng = np.random.default_rng(4)
    dt = 0.1
    Q = np.diag([0.0, 0.05])
    steps = [{'F': constant_velocity_F(dt), 'Q': Q, 'B': [[0.0], [dt]], 'u': [1.0],
              'z': [0.5 * (k * dt) ** 2 + rng.standard_normal()], 'H': [[1.0, 0.0]],
              'R': [[1.0]]} for k in range(1, 301)]
    _run_against_filterpy([0.0, 0.0], Q, steps)

    steps = [{'F': constant_velocity_F(dt), 'Q': Q, 'B': [[dt ** 2 / 2, 0.3], [dt, -0.1]],
              'u': rng.normal(size=2), 'z': [rng.normal(0.0, 5.0)], 'H': [[1.0, 0.0]],
              'R': [[2.0]]} for _ in range(300)]
    _run_against_filterpy([1.0, -1.0], np.eye(2), steps)


def test_filterpy_position_and_velocity_measured():
    """H = I2, R = diag(100, 100) (seed 003's variant) matches filterpy."""
    rng = np.random.default_rng(5)
    steps = [{'F': constant_velocity_F(1.0), 'Q': np.diag([0.01, 0.01]),
              'z': [50.0 + k + rng.normal(0.0, 10.0), 1.0 + rng.normal(0.0, 10.0)],
              'H': np.eye(2), 'R': np.diag([100.0, 100.0])} for k in range(1, 301)]
    _run_against_filterpy([50.0, 1.0], 100.0 * np.eye(2), steps)


def _seed_000_matlab(measurements, dt=0.1):
    """Return Xk_buffer (without the prior) and P after each step of seed 000's loop."""
    inv = np.linalg.inv
    Xk_prev = np.array([[0.0], [0.5 * 10.0]])
    Phi = np.array([[1.0, dt], [0.0, 1.0]])
    sigma_model = 1.0
    P = np.array([[sigma_model ** 2, 0.0], [0.0, sigma_model ** 2]])
    Q = np.array([[0.0, 0.0], [0.0, 0.0]])
    M = np.array([[1.0, 0.0]])
    sigma_meas = 1.0
    R = sigma_meas ** 2
    Xk_buffer, P_buffer = [], []
    for Z in measurements:
        P1 = Phi @ P @ Phi.T + Q
        S = M @ P1 @ M.T + R
        K = P1 @ M.T @ inv(S)
        P = P1 - K @ M @ P1
        Xk = Phi @ Xk_prev + K @ (Z - M @ Phi @ Xk_prev)
        Xk_buffer.append(Xk.ravel())
        P_buffer.append(P)
        Xk_prev = Xk
    return np.array(Xk_buffer), np.array(P_buffer)


def test_seed_000_transcription():
    """The filter and the prior-mode estimator reproduce seed 000's loop."""
    rng = np.random.default_rng(0)
    Nsamples, dt = 100, 0.1
    Z = 10.0 * dt * np.arange(1, Nsamples + 1) + 1.0 * rng.standard_normal(Nsamples)
    expected_x, expected_P = _seed_000_matlab(Z)

    kf = KalmanFilter([0.0, 5.0], np.eye(2))
    estimator = StreamEstimator(EstimatorSettings(**TRAIN, initialization='prior'))
    for k in range(Nsamples):
        kf.predict(constant_velocity_F(dt), np.zeros((2, 2)))
        kf.update([Z[k]], [[1.0, 0.0]], [[1.0]])
        _close(kf.x, expected_x[k], 100.0)
        _close(kf.P, expected_P[k])
        step = estimator.process((k + 1) * 100_000_000, Z[k], 1.0)
        _close(step.x, expected_x[k], 100.0)
        _close(step.P, expected_P[k])
    # The seed's goal: the position 2 s after the last sample (truth 120 m).
    assert abs(step.predicted_x[0] - 120.0) < 5.0 * np.sqrt(step.predicted_P[0, 0])


def _kalman_line_fit(z, dt, x0, P0_scale, R):
    """Filter positions z sampled at dt·(1..N) with Q = 0 from x0, P0 = P0_scale·I at t = 0."""
    kf = KalmanFilter(x0, P0_scale * np.eye(2))
    for zk in z:
        kf.predict(constant_velocity_F(dt), np.zeros((2, 2)))
        kf.update([zk], [[1.0, 0.0]], [[R]])
    return kf


def _line_fit_problem(N=100, dt=0.1, sigma=1.0):
    """Return times, measurements and the design matrix of a noisy 10 m/s train."""
    rng = np.random.default_rng(6)
    t = dt * np.arange(1, N + 1)
    z = 3.0 + 10.0 * t + sigma * rng.standard_normal(N)
    A = np.stack([np.ones(N), t], axis=1)  # parameters [position at t = 0, velocity]
    return t, z, A


@pytest.mark.parametrize('p', [1.0, 1e2, 1e4, 1e6])
def test_q0_equals_regularised_least_squares(p):
    """With Q = 0 the filter is the batch Bayesian line fit with the prior as pseudo-data."""
    sigma2, x0 = 1.0, np.array([0.0, 5.0])
    t, z, A = _line_fit_problem()
    kf = _kalman_line_fit(z, 0.1, x0, p, sigma2)
    information = A.T @ A / sigma2 + np.eye(2) / p
    C0 = np.linalg.inv(information)
    theta = C0 @ (A.T @ z / sigma2 + x0 / p)
    FN = constant_velocity_F(t[-1])
    _close(kf.x, FN @ theta, 100.0)
    _close(kf.P, FN @ C0 @ FN.T)


@pytest.mark.parametrize('p', [1e2, 1e4, 1e6, 1e8])
def test_q0_large_prior_is_ordinary_least_squares(p):
    """
    With Q = 0 and P0 = p·I the filter tends to the OLS line fit as p grows.

    The filter equals the fit with the prior as extra information J0 = I/p (test above),
    so in the t = 0 parameters θ_reg - θ_ols = (J + J0)⁻¹ J0 (x0 - θ_ols), J = AᵀA/σ².
    (J + J0)⁻¹ <= J⁻¹ = C_ols, so |θ_reg - θ_ols| <= |C_ols| |x0 - θ_ols| / p, and
    C_reg - C_ols = -(J + J0)⁻¹ J0 C_ols gives |C_reg - C_ols| <= |C_ols|² / p (spectral
    norms). Moving to the last time t_N multiplies by |F(t_N)| and |F(t_N)|². The bounds
    shrink as 1/p; 1e-9 of slack covers the rounding of the filter itself.
    """
    sigma2, x0 = 1.0, np.array([0.0, 5.0])
    t, z, A = _line_fit_problem()
    kf = _kalman_line_fit(z, 0.1, x0, p, sigma2)

    theta, *_ = np.linalg.lstsq(A, z, rcond=None)
    C_ols = sigma2 * np.linalg.inv(A.T @ A)
    FN = constant_velocity_F(t[-1])
    x_ols = FN @ theta  # [position at t_N, velocity = slope]
    P_ols = FN @ C_ols @ FN.T

    norm = np.linalg.norm
    x_bound = norm(FN, 2) * norm(C_ols, 2) * norm(x0 - theta) / p + 1e-9
    P_bound = norm(FN, 2) ** 2 * norm(C_ols, 2) ** 2 / p + 1e-9
    assert norm(kf.x - x_ols) <= x_bound
    assert norm(kf.P - P_ols, 2) <= P_bound
    # The bounds are tight enough to mean something at the largest p.
    if p >= 1e8:
        assert x_bound < 1e-7 and P_bound < 1e-8


def test_q0_huge_prior_is_ordinary_least_squares():
    """
    P0 = 1e12·I: the 1/p bias is ~1e-12; 1e-9 relative covers the rounding.

    With P0 = 1e12 the first update's 1 - K = 1/S is known to only ~4 digits, which costs
    ~1e-10 in the result. Beyond ~1e13 that difference loses all its digits.
    """
    t, z, A = _line_fit_problem()
    kf = _kalman_line_fit(z, 0.1, [0.0, 5.0], 1e12, 1.0)
    theta, *_ = np.linalg.lstsq(A, z, rcond=None)
    FN = constant_velocity_F(t[-1])
    _close(kf.x, FN @ theta, 100.0)
    _close(kf.P, FN @ np.linalg.inv(A.T @ A) @ FN.T)


@pytest.mark.parametrize('R', [1e-3, 1.0, 4.0, 1e3])
def test_random_constant_is_running_mean(R):
    """
    F = 1, Q = 0, H = 1, P0 = p: x_k is the running mean and P_k = R/k.

    Exactly, P_k = 1/(1/p + k/R) and x_k = P_k (x0/p + Σz/R), so
    |x_k - mean_k| = P_k |x0 - mean_k| / p <= R |x0 - mean_k| / (k p) and
    0 <= R/k - P_k <= (R/k)² / p.
    """
    p, x0 = 1e8, 3.0
    rng = np.random.default_rng(7)
    z = 42.0 + np.sqrt(R) * rng.standard_normal(1000)
    kf = KalmanFilter([x0], [[p]])
    for k in range(1, len(z) + 1):
        kf.predict([[1.0]], [[0.0]])
        kf.update([z[k - 1]], [[1.0]], [[R]])
        mean = np.mean(z[:k])
        # Rounding: each step adds <= ~2u·|x| (u = eps/2) and carries the old error by
        # 1 − K = (k − 1)/k, so after k steps <= Σ_j (j/k)·2u|x| <= k·u·|x| = 1.1e-13·|x|
        # at k = 1000; P_k's relative error grows likewise to <= ~k·3u/2. 1e-12 holds.
        assert abs(kf.x[0] - mean) <= R * abs(x0 - mean) / (k * p) + 1e-12 * abs(mean)
        assert abs(kf.P[0, 0] - R / k) <= (R / k) ** 2 / p + 1e-12 * R / k


def test_predict_ahead_leaves_state_untouched():
    """predict_ahead does not change x or P (bitwise) and equals predict on a copy."""
    kf = KalmanFilter([1.5, -2.0], [[2.0, 0.3], [0.3, 0.7]])
    kf.update([1.0], [[1.0, 0.0]], [[0.5]])
    x_before, P_before = kf.x.tobytes(), kf.P.tobytes()
    F, Q = constant_velocity_F(2.0), WhiteNoiseAcceleration(0.3)(2.0)
    for B, u in ((None, None), ([[0.0], [2.0]], [0.25])):
        x_ahead, P_ahead = kf.predict_ahead(F, Q, B, u)
        assert kf.x.tobytes() == x_before and kf.P.tobytes() == P_before
        twin = kf.copy()
        twin.predict(F, Q, B, u)
        assert np.array_equal(x_ahead, twin.x) and np.array_equal(P_ahead, twin.P)
        assert kf.x.tobytes() == x_before and kf.P.tobytes() == P_before
        assert not np.array_equal(x_ahead, kf.x)


def test_state_is_returned_as_copies():
    """Mutating the returned x, P or the caller's arrays does not reach the filter."""
    x0, P0 = np.array([1.0, 2.0]), np.eye(2)
    kf = KalmanFilter(x0, P0)
    x0[0], P0[0, 0] = 99.0, 99.0
    kf.x[0] = 7.0
    kf.P[0, 0] = 7.0
    assert np.array_equal(kf.x, [1.0, 2.0]) and np.array_equal(kf.P, np.eye(2))


def test_pure_functions_do_not_modify_inputs():
    """The pure predict and update return new arrays and leave their arguments alone."""
    x, P = np.array([1.0, 2.0]), np.array([[2.0, 0.5], [0.5, 1.0]])
    x_copy, P_copy = x.copy(), P.copy()
    predict(x, P, constant_velocity_F(1.0), np.eye(2))
    update(x, P, [3.0], [[1.0, 0.0]], [[1.0]])
    assert np.array_equal(x, x_copy) and np.array_equal(P, P_copy)


NAN, INF = float('nan'), float('inf')
ASYMMETRIC = [[1.0, 0.5], [0.0, 1.0]]
NEGATIVE = [[-1.0, 0.0], [0.0, -2.0]]
F_OK, Q_OK = constant_velocity_F(0.1), 0.01 * np.eye(2)


@pytest.mark.parametrize('x0, P0, name', [
    ([[1.0, 2.0], [3.0, 4.0]], np.eye(2), 'x0'),
    ([1.0, NAN], np.eye(2), 'x0'),
    ([INF, 1.0], np.eye(2), 'x0'),
    (['a', 'b'], np.eye(2), 'x0'),
    ([1.0, 2.0], np.eye(3), 'P0'),
    ([1.0, 2.0], [1.0, 2.0, 3.0], 'P0'),
    ([1.0, 2.0], [[1.0, NAN], [NAN, 1.0]], 'P0'),
    ([1.0, 2.0], [[INF, 0.0], [0.0, 1.0]], 'P0'),
    ([1.0, 2.0], NEGATIVE, 'P0'),
    ([1.0, 2.0], [[1.0, 2.0], [2.0, 1.0]], 'P0'),  # symmetric but indefinite
    ([1.0, 2.0], ASYMMETRIC, 'P0'),
])
def test_constructor_rejects(x0, P0, name):
    """A bad x0 or P0 raises ValueError naming it."""
    with pytest.raises(ValueError, match=rf'^{name} must'):
        KalmanFilter(x0, P0)


PREDICT_ERRORS = [
    ({'F': np.eye(3), 'Q': Q_OK}, r'^F must'),
    ({'F': [1.0, 0.1], 'Q': Q_OK}, r'^F must'),
    ({'F': [[1.0, NAN], [0.0, 1.0]], 'Q': Q_OK}, r'^F must'),
    ({'F': [[1.0, 0.1], [0.0, INF]], 'Q': Q_OK}, r'^F must'),
    ({'F': 'F', 'Q': Q_OK}, r'^F must'),
    ({'F': F_OK, 'Q': np.eye(3)}, r'^Q must'),
    ({'F': F_OK, 'Q': [[NAN, 0.0], [0.0, 1.0]]}, r'^Q must'),
    ({'F': F_OK, 'Q': [[1.0, 0.0], [0.0, INF]]}, r'^Q must'),
    ({'F': F_OK, 'Q': NEGATIVE}, r'^Q must be positive semi-definite'),
    ({'F': F_OK, 'Q': ASYMMETRIC}, r'^Q must be symmetric'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[0.0], [0.1]]}, r'^B and u must be given together'),
    ({'F': F_OK, 'Q': Q_OK, 'u': [1.0]}, r'^B and u must be given together'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[0.0], [0.1], [0.2]], 'u': [1.0]}, r'^B must'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[0.0, 1.0], [0.1, 1.0]], 'u': [1.0]}, r'^B must'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[NAN], [0.1]], 'u': [1.0]}, r'^B must'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[INF], [0.1]], 'u': [1.0]}, r'^B must'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[0.0], [0.1]], 'u': [[1.0, 2.0], [3.0, 4.0]]}, r'^u must'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[0.0], [0.1]], 'u': [NAN]}, r'^u must'),
    ({'F': F_OK, 'Q': Q_OK, 'B': [[0.0], [0.1]], 'u': [-INF]}, r'^u must'),
    ({'F': [[1e200, 0.0], [0.0, 1.0]], 'Q': Q_OK}, r'^prediction produced a non-finite'),
]


@pytest.mark.parametrize('kwargs, pattern', PREDICT_ERRORS)
def test_predict_rejects_and_keeps_state(kwargs, pattern):
    """A rejected predict (or predict_ahead) raises naming the input; x, P are unchanged."""
    kf = KalmanFilter([1.0, 2.0], [[2.0, 0.5], [0.5, 1.0]])
    x_before, P_before = kf.x.tobytes(), kf.P.tobytes()
    with np.errstate(over='ignore'):  # the overflow case warns before it is rejected
        with pytest.raises(ValueError, match=pattern):
            kf.predict(**kwargs)
        with pytest.raises(ValueError, match=pattern):
            kf.predict_ahead(**kwargs)
    assert kf.x.tobytes() == x_before and kf.P.tobytes() == P_before


UPDATE_ERRORS = [
    ({'z': [[1.0, 2.0], [3.0, 4.0]], 'H': [[1.0, 0.0]], 'R': [[1.0]]}, r'^z must'),
    ({'z': [NAN], 'H': [[1.0, 0.0]], 'R': [[1.0]]}, r'^z must'),
    ({'z': [INF], 'H': [[1.0, 0.0]], 'R': [[1.0]]}, r'^z must'),
    ({'z': 'z', 'H': [[1.0, 0.0]], 'R': [[1.0]]}, r'^z must'),
    ({'z': [1.0], 'H': [[1.0, 0.0, 0.0]], 'R': [[1.0]]}, r'^H must'),
    ({'z': [1.0, 2.0], 'H': [[1.0, 0.0]], 'R': np.eye(2)}, r'^H must'),
    ({'z': [1.0], 'H': [[NAN, 0.0]], 'R': [[1.0]]}, r'^H must'),
    ({'z': [1.0], 'H': [[1.0, INF]], 'R': [[1.0]]}, r'^H must'),
    ({'z': [1.0], 'H': [[1.0, 0.0]], 'R': np.eye(2)}, r'^R must'),
    ({'z': [1.0], 'H': [[1.0, 0.0]], 'R': [[NAN]]}, r'^R must'),
    ({'z': [1.0], 'H': [[1.0, 0.0]], 'R': [[INF]]}, r'^R must'),
    ({'z': [1.0], 'H': [[1.0, 0.0]], 'R': [[-1.0]]}, r'^R must be positive semi-definite'),
    ({'z': [1.0, 2.0], 'H': np.eye(2), 'R': NEGATIVE}, r'^R must be positive semi-definite'),
    ({'z': [1.0, 2.0], 'H': np.eye(2), 'R': ASYMMETRIC}, r'^R must be symmetric'),
]


@pytest.mark.parametrize('kwargs, pattern', UPDATE_ERRORS)
def test_update_rejects_and_keeps_state(kwargs, pattern):
    """A rejected update raises naming the input; x and P are bitwise unchanged."""
    kf = KalmanFilter([1.0, 2.0], [[2.0, 0.5], [0.5, 1.0]])
    x_before, P_before = kf.x.tobytes(), kf.P.tobytes()
    with pytest.raises(ValueError, match=pattern):
        kf.update(**kwargs)
    assert kf.x.tobytes() == x_before and kf.P.tobytes() == P_before


@pytest.mark.parametrize('P, z, H, R', [
    (np.zeros((2, 2)), [1.0], [[1.0, 0.0]], [[0.0]]),
    (np.zeros((2, 2)), [1.0, 2.0], np.eye(2), np.zeros((2, 2))),
    # P ≠ 0 but H P Hᵀ has rank 1: both rows of H see the same state.
    (np.diag([1.0, 0.0]), [1.0, 2.0], [[1.0, 0.0], [2.0, 0.0]], np.zeros((2, 2))),
])
def test_singular_innovation_covariance(P, z, H, R):
    """S = H P Hᵀ + R singular raises ValueError naming S; the state is unchanged."""
    kf = KalmanFilter([1.0, 2.0], P)
    x_before, P_before = kf.x.tobytes(), kf.P.tobytes()
    with pytest.raises(ValueError, match=r'innovation covariance S .* singular'):
        kf.update(z, H, R)
    assert kf.x.tobytes() == x_before and kf.P.tobytes() == P_before


@pytest.mark.parametrize('x, P, pattern', [
    ([1.0, 2.0, 3.0], np.eye(2), r'^x must'),
    ([1.0, NAN], np.eye(2), r'^x must'),
    ([1.0, 2.0], ASYMMETRIC, r'^P must be symmetric'),
    ([1.0, 2.0], NEGATIVE, r'^P must be positive semi-definite'),
    ([1.0, 2.0], np.eye(3), r'^P must'),
])
def test_set_state_rejects_and_keeps_state(x, P, pattern):
    """set_state validates like the constructor and keeps the old state on failure."""
    kf = KalmanFilter([1.0, 2.0], [[2.0, 0.5], [0.5, 1.0]])
    x_before, P_before = kf.x.tobytes(), kf.P.tobytes()
    with pytest.raises(ValueError, match=pattern):
        kf.set_state(x, P)
    assert kf.x.tobytes() == x_before and kf.P.tobytes() == P_before
