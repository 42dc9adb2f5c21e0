"""
Tests of kf_train.presets.loader: every preset against its seed, filterpy and its YAML.

Each ``_seedNNN`` function below is a literal transcription of the seed's MATLAB loop
(same matrices, same initial values, same order, same covariance formula), kept in
this file on purpose: the presets must reproduce these to 1e-9 on the seed's data.
Replay inputs follow the seeds' convention (docs/presets.md): row k holds the control of
the interval ending at t_k.
"""

import os
import textwrap

from filterpy.kalman import KalmanFilter as FilterpyKF
from kf_train.batch import run_linear_series, run_series
from kf_train.cli.replay import main as replay_main
from kf_train.io import read_table
from kf_train.presets.loader import (
    available_presets, ControlMatrix, DtExpression, Dynamics, load_preset,
    load_preset_file, per_step_weights, preset_from_mapping, PRESET_NAMES)
from kf_train.sim import robot_scenario
import numpy as np
import pytest
from scipy import integrate, stats
import yaml

# The seed loops and the presets evaluate the same recursion in float64 and differ only
# by rounding (textbook against Joseph form, BLAS order and FMA). A step rounds by
# <= ~16u of terms of size |F||x|, |x|, |K y| (|F||P||F|ᵀ, ... for P), times κ(S) <=
# 2.4 (scaled) for the 2-D measurements; the closed loop (I − K H) F carries it on.
# Summed with the actual products over each seed's 100 rows this first-order bound is
# <= 1e-10 m for x (|x| <= 270) and <= 3.4e-11 for P (range-bearing: 4.4e-12 of
# max|P|, hence its relative atol): 1e-9 leaves a margin of >= 10.
ATOL = 1e-9
SEEDS = [0, 1, 2]


def _run_both(preset, t, z, u=None):
    """Return the generic and the vectorised results (linear presets) for the same rows."""
    generic = run_series(preset, t, z, u)
    fast = run_linear_series(preset, t, z, u) if preset.linear else None
    return generic, fast


def _assert_close(actual, expected, atol=ATOL):
    """Assert elementwise |actual − expected| <= atol."""
    np.testing.assert_allclose(actual, expected, rtol=0.0, atol=atol)


# ---------------------------------------------------------------------------
# Seed transcriptions
# ---------------------------------------------------------------------------

def _seed000(Z, dt=0.1):
    """Seed 000 (kalmanfilterintuitivtutorial.m), its Kalman iteration line by line."""
    Xk_prev = np.array([[0.0], [0.5 * 10.0]])
    Phi = np.array([[1.0, dt], [0.0, 1.0]])
    P = np.array([[1.0, 0.0], [0.0, 1.0]])
    Q = np.zeros((2, 2))
    M = np.array([[1.0, 0.0]])
    R = 1.0 ** 2
    X, Ps = [], []
    for Zk in Z:
        P1 = Phi @ P @ Phi.T + Q
        S = M @ P1 @ M.T + R
        K = P1 @ M.T @ np.linalg.inv(S)
        P = P1 - K @ M @ P1
        Xk = Phi @ Xk_prev + K @ (Zk - M @ Phi @ Xk_prev)
        X.append(Xk[:, 0])
        Ps.append(P)
        Xk_prev = Xk
    return np.array(X), np.array(Ps)


def _seed000_data(seed, n=100, dt=0.1):
    """Return seed 000's t (1..N samples) and Z = Xtrue(k+1) + randn."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, n + 1) * dt
    Xtrue = 0.0 + 10.0 * t
    return t[1:], Xtrue[1:] + 1.0 * rng.standard_normal(n)


def _seed001(seed, N=100, dt=0.1):
    """Seed 001's simulation and filter; return (yv measurements, xh estimates, P)."""
    rng = np.random.default_rng(seed)
    Q = np.diag([0.0, 0.05])
    R = 1.0
    A = np.array([[1.0, dt], [0.0, 1.0]])
    B = np.array([[0.0], [dt]])
    C = np.array([[1.0, 0.0]])
    P = Q
    I2 = np.eye(2)
    x0 = np.array([[0.2], [0.0]])
    xh0 = np.array([[0.0], [0.0]])
    u = np.ones(N)
    w = np.sqrt(Q) @ rng.standard_normal((2, N))
    v = np.sqrt(R) * rng.standard_normal(N)
    yv_list, xh_list, P_list = [], [], []
    for i in range(N):
        xreal = A @ x0 + B * u[i]
        yreal = C @ x0
        x1 = xreal + w[:, [i]]
        yv = yreal + v[i]
        xfe = A @ xh0 + B * u[i]
        Pfe = A @ P @ A.T + Q
        K = Pfe @ C.T / (C @ Pfe @ C.T + R)
        xh1 = xfe + K @ (yv - C @ xfe)
        P = (I2 - K @ C) @ Pfe
        x0 = x1
        xh0 = xh1
        yv_list.append(yv[0, 0])
        xh_list.append(xh1[:, 0])
        P_list.append(P)
    return np.array(yv_list), np.array(xh_list), np.array(P_list)


def _seed002(seed, dt=0.1, SensorStd=0.03, SpeedStd=0.2):
    """Seed 002's simulation and filter; return (t, u, z, x_hat, P), all n long."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 101) * dt
    n = t.shape[0]
    x = 0.05 * t * np.cos(2 * t)
    u = np.concatenate([[0.0], np.diff(x) / dt]) + SpeedStd * rng.standard_normal(n)
    z = x - SensorStd * rng.standard_normal(n)
    B, F, Q, H, R = dt, 1.0, SpeedStd ** 2, 1.0, SensorStd ** 2
    x_hat = np.zeros(n)
    P = np.zeros(n)
    for i in range(1, n):
        x_hat[i] = F * x_hat[i - 1] + B * u[i - 1]
        P[i] = F * P[i - 1] * F + Q
        y_hat = z[i] - H * x_hat[i]
        S = H * P[i] * H + R
        K = P[i] * H / S
        x_hat[i] = x_hat[i] + K * y_hat
        P[i] = (1 - K * H) * P[i]
    return t, u, z, x_hat, P


def _seed003_example1(seed):
    """Seed 003 example 1; return (T, Z, X estimates, P)."""
    rng = np.random.default_rng(seed)
    T = np.arange(1, 101, dtype=float)
    trueX = np.arange(1, 200, 2, dtype=float)
    Z = trueX + 1 * rng.standard_normal(100)
    X = np.array([[110.0], [110.0]])
    P = np.array([[100.0, 0.0], [0.0, 100.0]])
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = np.array([[0.0001, 0.0], [0.0, 0.0001]])
    H = np.array([[1.0, 0.0]])
    R = 1.0
    out, Ps = [], []
    for i in range(100):
        X_ = F @ X
        P_ = F @ P @ F.T + Q
        K = P_ @ H.T / (H @ P_ @ H.T + R)
        X = X_ + K * (Z[i] - H @ X_)
        P = (np.eye(2) - K @ H) @ P_
        out.append(X[:, 0])
        Ps.append(P)
    return T, Z, np.array(out), np.array(Ps)


def _seed003_variant(seed):
    """Seed 003 example 1 variant (Z(:,1) left at zero, as in the seed)."""
    rng = np.random.default_rng(seed)
    T = np.arange(1, 101, dtype=float)
    trueX = np.zeros((2, 100))
    trueX[:, 0] = [1.0, 2.0]
    processNoise = np.diag([0.01, 0.01])
    Z = np.zeros((2, 100))
    measureNoise = np.diag([100.0, 100.0])
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    for i in range(1, 100):
        trueX[:, i] = F @ trueX[:, i - 1] + np.sqrt(processNoise) @ rng.standard_normal(2)
        Z[:, i] = trueX[:, i] + np.sqrt(measureNoise) @ rng.standard_normal(2)
    X = np.array([[50.0], [1.0]])
    P = np.array([[100.0, 0.0], [0.0, 100.0]])
    Q = processNoise
    H = np.diag([1.0, 1.0])
    R = measureNoise
    out, Ps = [], []
    for i in range(100):
        X_ = F @ X
        P_ = F @ P @ F.T + Q
        K = P_ @ H.T @ np.linalg.inv(H @ P_ @ H.T + R)
        X = X_ + K @ (Z[:, [i]] - H @ X_)
        P = (np.eye(2) - K @ H) @ P_
        out.append(X[:, 0])
        Ps.append(P)
    return T, Z.T, np.array(out), np.array(Ps)


def _measure_model(state):
    """Seed 003's measureModel: [atan(y/x); norm([x y])]."""
    return np.array([np.arctan(state[2] / state[0]), np.linalg.norm([state[0], state[2]])])


def _jacobian_h(x, vx, y, vy):
    """Seed 003's jacobian([atan(y/x); norm([x y])], [x, vx, y, vy]) written out."""
    r2 = x * x + y * y
    r = np.sqrt(r2)
    return np.array([[-y / r2, 0.0, x / r2, 0.0], [x / r, 0.0, y / r, 0.0]])


def _seed003_example3(seed):
    """Seed 003 example 3, the hand-written EKF; return (tspan, measurements, estimates)."""
    rng = np.random.default_rng(seed)
    dt = 0.2
    tspan = np.arange(0, 101) * dt
    F = np.array([[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, dt], [0, 0, 0, 1]], dtype=float)
    processNoise = np.diag([0.0, 1e-2, 0.0, 1e-2])
    measureNoise = np.diag([2e-6, 1.0])
    trueStates = np.full((4, 101), np.nan)
    trueStates[:, 0] = [30.0, 1.0, 40.0, 1.0]
    measurements = np.full((2, 101), np.nan)
    for i in range(1, 101):
        trueStates[:, i] = F @ trueStates[:, i - 1] + np.sqrt(processNoise) @ \
            rng.standard_normal(4)
        measurements[:, i] = _measure_model(trueStates[:, i]) + np.sqrt(measureNoise) @ \
            rng.standard_normal(2)
    X = np.array([35.0, 0.0, 45.0, 0.0])
    P = np.diag([100.0, 1e3, 100.0, 1e3])
    Q = processNoise
    R = measureNoise
    est, Ps = [], []
    for i in range(1, 101):
        X_ = F @ X
        P_ = F @ P @ F.T + Q
        H = _jacobian_h(*X_)
        K = P_ @ H.T @ np.linalg.inv(H @ P_ @ H.T + R)
        X = X_ + K @ (measurements[:, i] - _measure_model(X_))
        P = (np.eye(4) - K @ H) @ P_
        est.append(X)
        Ps.append(P)
    return tspan[1:], measurements[:, 1:].T, np.array(est), np.array(Ps)


# ---------------------------------------------------------------------------
# Every preset against its seed
# ---------------------------------------------------------------------------

@pytest.mark.parametrize('seed', SEEDS)
def test_train_reproduces_seed000(seed):
    """The train preset equals seed 000's loop, and its 2-s prediction the seed's."""
    t, Z = _seed000_data(seed)
    X, P = _seed000(Z)
    preset = load_preset('train')
    for result in _run_both(preset, t, Z):
        _assert_close(result.x, X)
        _assert_close(result.P, P)
        # The seed extrapolates the last sample 20 samples of 0.1 s ahead: x + 2 s · v.
        _assert_close(result.predicted_x[-1, 0], X[-1, 0] + 20 * 0.1 * X[-1, 1])
        _assert_close(result.predicted_x[:, 0], X[:, 0] + 2.0 * X[:, 1])


@pytest.mark.parametrize('seed', SEEDS)
def test_car_reproduces_seed001(seed):
    """The car preset (B = [0, dt], P0 = Q) equals seed 001's loop with u = 1."""
    yv, xh, P = _seed001(seed)
    t = np.arange(1, 101) * 0.1
    for result in _run_both(load_preset('car'), t, yv, np.ones(100)):
        _assert_close(result.x, xh)
        _assert_close(result.P, P)


def test_car_exact_differs_only_by_B():
    """car-exact uses B = [dt²/2, dt]; with zero control it equals car."""
    car, exact = load_preset('car'), load_preset('car-exact')
    np.testing.assert_array_equal(car.dynamics.control(0.1), [[0.0], [0.1]])
    # dt**2/2 goes through numpy's power (within 4 ulp = 8u on SIMD paths, u = eps/2,
    # 1 ulp on others: it differs by CPU) and 0.1, 0.005 are rounded decimals: 8·eps.
    np.testing.assert_allclose(exact.dynamics.control(0.1), [[0.005], [0.1]],
                               rtol=8 * np.finfo(float).eps, atol=0.0)
    yv, _, _ = _seed001(0)
    t = np.arange(1, 101) * 0.1
    a = run_series(car, t, yv, np.zeros(100))
    b = run_series(exact, t, yv, np.zeros(100))
    np.testing.assert_array_equal(a.x, b.x)


@pytest.mark.parametrize('seed', SEEDS)
def test_robot_reproduces_seed002(seed):
    """The robot preset equals seed 002's loop; row i carries the seed's u(i-1)."""
    t, u, z, x_hat, P = _seed002(seed)
    for result in _run_both(load_preset('robot'), t[1:], z[1:], u[:-1]):
        _assert_close(result.x[:, 0], x_hat[1:])
        _assert_close(result.P[:, 0, 0], P[1:])


def test_robot_exact_process_noise():
    """robot-exact's Q is the speed noise propagated: (dt·SpeedStd)², not SpeedStd²."""
    exact, seed = load_preset('robot-exact'), load_preset('robot')
    for dt in (0.05, 0.1, 0.3):
        # (dt·0.2)² however it is grouped: <= 3 roundings each side, 4·eps = 8u apart.
        np.testing.assert_allclose(exact.dynamics.Q(dt), [[(dt * 0.2) ** 2]],
                                   rtol=4 * np.finfo(float).eps, atol=0.0)
    _assert_close(seed.dynamics.Q(0.1), [[0.04]], atol=0.0)


def test_robot_exact_is_consistent_with_its_scenario():
    """Over M independent runs the final NEES sums to χ²(M): robot-exact is honest."""
    preset = load_preset('robot-exact')
    M = 200
    total = 0.0
    for seed in range(M):
        s = robot_scenario(seed, seed_lag=False)
        r = run_linear_series(preset, s.t_s, s.z, s.u)
        e = r.x[-1, 0] - s.truth[-1, 0]
        total += e * e / r.P[-1, 0, 0]
    # Two-sided test at level 1e-3 from the exact χ²(M) distribution.
    assert stats.chi2.ppf(0.0005, M) < total < stats.chi2.ppf(0.9995, M)


@pytest.mark.parametrize('seed', SEEDS)
def test_cv_position_reproduces_seed003(seed):
    """cv-position equals seed 003 example 1 (dt = 1 s, rows at T = 1..100)."""
    T, Z, X, P = _seed003_example1(seed)
    for result in _run_both(load_preset('cv-position'), T, Z):
        _assert_close(result.x, X)
        _assert_close(result.P, P)


@pytest.mark.parametrize('seed', SEEDS)
def test_cv_position_velocity_reproduces_seed003(seed):
    """cv-position-velocity equals the variant, including its zero first measurement."""
    T, Z, X, P = _seed003_variant(seed)
    for result in _run_both(load_preset('cv-position-velocity'), T, Z):
        _assert_close(result.x, X)
        _assert_close(result.P, P)


@pytest.mark.parametrize('seed', SEEDS)
def test_range_bearing_reproduces_seed003(seed):
    """range-bearing equals seed 003 example 3's hand-written EKF (atan = atan2, x > 0)."""
    t, z, X, P = _seed003_example3(seed)
    assert np.all(X[:, 0] > 0)
    result = run_series(load_preset('range-bearing'), t, z)
    _assert_close(result.x, X)
    _assert_close(result.P, P, atol=1e-9 * np.max(np.abs(P)))


def _write_csv(path, columns):
    """Write a CSV with the given {name: values} columns, numbers as repr."""
    names = list(columns)
    rows = zip(*[np.asarray(columns[n], dtype=float).tolist() for n in names])
    with open(path, 'w') as stream:
        stream.write(','.join(names) + '\n')
        stream.writelines(','.join(map(repr, row)) + '\n' for row in rows)


def _replay(tmp_path, preset, columns, *extra):
    """Run ``kf-train replay`` on the columns; return the output table's columns."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _write_csv(source, columns)
    assert replay_main(['--preset', preset, str(source), '--output', str(target),
                        *extra]) == 0
    with open(target) as stream:
        header = stream.readline().strip().split(',')
    return read_table(str(target), [(h,) for h in header]).columns


def test_every_seed_through_replay_csv(tmp_path):
    """The seeds' numbers come out of the CSV replay too (text round trip included)."""
    t, Z = _seed000_data(5)
    X, P = _seed000(Z)
    out = _replay(tmp_path, 'train', {'t': t, 'z_position': Z})
    _assert_close(out['position'], X[:, 0])
    _assert_close(out['var_velocity'], P[:, 1, 1])
    _assert_close(out['predicted_position'], X[:, 0] + 2.0 * X[:, 1])

    yv, xh, _ = _seed001(5)
    out = _replay(tmp_path, 'car', {'t': np.arange(1, 101) * 0.1, 'z_position': yv,
                                    'u': np.ones(100)})
    _assert_close(out['velocity'], xh[:, 1])

    tr, u, z, x_hat, Pr = _seed002(5)
    out = _replay(tmp_path, 'robot', {'t': tr[1:], 'z_range': z[1:], 'u': u[:-1]})
    _assert_close(out['position'], x_hat[1:])
    _assert_close(out['var_position'], Pr[1:])

    T, Z1, X1, _ = _seed003_example1(5)
    out = _replay(tmp_path, 'cv-position', {'t': T, 'z_position': Z1})
    _assert_close(out['velocity'], X1[:, 1])

    T, Z2, X2, _ = _seed003_variant(5)
    out = _replay(tmp_path, 'cv-position-velocity',
                  {'t': T, 'z_position': Z2[:, 0], 'z_velocity': Z2[:, 1]})
    _assert_close(out['position'], X2[:, 0])

    t3, z3, X3, _ = _seed003_example3(5)
    out = _replay(tmp_path, 'range-bearing', {'t': t3, 'z_bearing': z3[:, 0],
                                              'z_range': z3[:, 1]})
    _assert_close(np.column_stack([out[s] for s in ('x', 'vx', 'y', 'vy')]), X3)


# ---------------------------------------------------------------------------
# filterpy
# ---------------------------------------------------------------------------

@pytest.mark.parametrize('name', ['train', 'car', 'car-exact', 'robot', 'robot-exact',
                                  'cv-position', 'cv-position-velocity'])
def test_linear_presets_match_filterpy(name):
    """Every linear preset equals filterpy's KalmanFilter with the same matrices."""
    preset = load_preset(name)
    rng = np.random.default_rng(11)
    N, dt = 150, preset.nominal_period_s
    t = np.arange(1, N + 1) * dt
    z = 3.0 * t[:, None] + rng.standard_normal((N, preset.dim_z))
    u = rng.standard_normal((N, preset.dim_u)) if preset.dim_u else None
    kf = FilterpyKF(dim_x=preset.dim_x, dim_z=preset.dim_z,
                    dim_u=max(preset.dim_u, 1))
    kf.x = preset.initial_state.reshape(-1, 1).copy()
    kf.P = preset.initial_covariance.copy()
    kf.F, kf.Q = preset.dynamics.F(dt), preset.dynamics.Q(dt)
    kf.H, kf.R = preset.model.H, preset.model.R
    if preset.dim_u:
        kf.B = preset.dynamics.control(dt)
    xs, Ps = [], []
    for k in range(N):
        kf.predict(u=None if u is None else u[k].reshape(-1, 1))
        kf.update(z[k].reshape(-1, 1))
        xs.append(kf.x[:, 0].copy())
        Ps.append(kf.P.copy())
    for result in _run_both(preset, t, z, u):
        _assert_close(result.x, np.array(xs))
        _assert_close(result.P, np.array(Ps))


# ---------------------------------------------------------------------------
# The preset files and their validation
# ---------------------------------------------------------------------------

def test_shipped_presets():
    """All eight presets load, with the seeds' names, dimensions and columns."""
    assert available_presets() == list(PRESET_NAMES)
    expected = {
        'train': (('position', 'velocity'), ('position',), ()),
        'car': (('position', 'velocity'), ('position',), ('acceleration',)),
        'car-exact': (('position', 'velocity'), ('position',), ('acceleration',)),
        'robot': (('position',), ('position',), ('velocity',)),
        'robot-exact': (('position',), ('position',), ('velocity',)),
        'cv-position': (('position', 'velocity'), ('position',), ()),
        'cv-position-velocity': (('position', 'velocity'), ('position', 'velocity'), ()),
        'range-bearing': (('x', 'vx', 'y', 'vy'), ('bearing', 'range'), ()),
    }
    for name in PRESET_NAMES:
        preset = load_preset(name)
        assert preset.name == name
        assert (preset.state_names, preset.measurement_names,
                preset.control_names) == expected[name]
        assert preset.linear == (name != 'range-bearing')
        assert os.path.basename(preset.source) == name + '.yaml'
    assert load_preset('train').horizon_s == 2.0
    assert load_preset('robot').measurement_columns() == (('z_position', 'z_range'),)
    assert load_preset('car').control_columns() == ('u',)


@pytest.mark.parametrize('name', PRESET_NAMES)
def test_per_step_noise_is_the_seed_matrix_at_the_nominal_period(name):
    """Q(T) is bit for bit the YAML's per-step matrix; Q(0) = 0."""
    preset = load_preset(name)
    with open(preset.source) as stream:
        data = yaml.safe_load(stream)
    T = preset.nominal_period_s
    if 'per_step' in data['process_noise']:
        per_step = np.array(data['process_noise']['per_step'], dtype=float)
        if per_step.ndim == 1:
            per_step = np.diag(per_step)
        np.testing.assert_array_equal(preset.dynamics.Q(T), per_step)
    np.testing.assert_array_equal(preset.dynamics.Q(0.0), np.zeros((preset.dim_x,) * 2))


def test_per_step_noise_accumulates_like_repeated_steps():
    """Q(3T) equals three seed steps P ← F P Fᵀ + Q from P = 0; fractions scale."""
    dyn = load_preset('range-bearing').dynamics
    T = dyn.period_s
    F, Q = dyn.F(T), dyn.Q(T)
    P = np.zeros((4, 4))
    for _ in range(3):
        P = F @ P @ F.T + Q
    _assert_close(dyn.Q(3 * T), P, atol=1e-15)
    _assert_close(dyn.Q(0.25 * T), 0.25 * Q, atol=1e-17)
    s0, s1, s2 = per_step_weights(np.array([T, 2 * T]), T)
    np.testing.assert_array_equal(s0, [1.0, 2.0])
    np.testing.assert_array_equal(s1[0], 0.0)
    np.testing.assert_array_equal(s2[0], 0.0)


def test_continuous_noise_is_integrated_exactly():
    """Continuous noise equals ∫₀^dt F(s) Qc F(s)ᵀ ds by quadrature."""
    Qc = np.array([[0.3, 0.1], [0.1, 2.0]])
    dyn = Dynamics([[0.0, 1.0], [0.0, 0.0]], period_s=0.1, continuous=Qc)
    for dt in (0.01, 0.5, 3.0):
        expected = np.empty((2, 2))
        for i in range(2):
            for j in range(2):
                def f(s, i=i, j=j):
                    F = np.array([[1.0, s], [0.0, 1.0]])
                    return (F @ Qc @ F.T)[i, j]
                expected[i, j] = integrate.quad(f, 0.0, dt, epsabs=0.0, epsrel=1e-13)[0]
        np.testing.assert_allclose(dyn.Q(dt), expected, rtol=1e-12, atol=0.0)


def test_dt_expressions():
    """B entries accept arithmetic in dt and reject anything else, naming the entry."""
    # numpy's power: within 4 ulp (8u) on SIMD paths, and 0.2, 0.02 are rounded: 8·eps.
    assert DtExpression('dt**2/2')(np.array([0.2]))[0] == pytest.approx(
        0.02, rel=8 * np.finfo(float).eps, abs=0.0)
    assert DtExpression('-(dt + 1) * 2')(np.array([1.0]))[0] == -4.0
    assert DtExpression(3)(np.array([5.0]))[0] == 3.0
    for bad in ('__import__("os")', 'dt.real', 'x', 'lambda: 1', 'dt if 1 else 2', '1/0',
                'dt +', True, None):
        with pytest.raises(ValueError, match='B\\[1\\]\\[0\\]'):
            ControlMatrix([['0'], [bad]], 2, 1)


def _train_mapping():
    """Return the train preset's YAML as a mapping to modify."""
    with open(load_preset('train').source) as stream:
        return yaml.safe_load(stream)


@pytest.mark.parametrize('change, message', [
    ({'R': [[1.0, 0.0]]}, 'R must have shape \\(1, 1\\)'),
    ({'R': [[0.0]]}, 'R must be positive definite'),
    ({'Rx': 1}, "unknown key 'Rx'"),
    ({'states': ['position']}, "'motion' constant_velocity has 2 states"),
    ({'states': ['position', 'position']}, "'states' has repeated names"),
    ({'nominal_period_s': 0}, 'nominal_period_s must be > 0'),
    ({'nominal_period_s': 'fast'}, 'nominal_period_s must be numeric'),
    ({'process_noise': {'per_step': [[1, 2], [3, 4]]}}, 'process_noise.per_step must be '
                                                        'symmetric'),
    ({'process_noise': {'sometimes': 1}}, "unknown key 'process_noise.sometimes'"),
    ({'process_noise': None}, "'process_noise' must be a mapping"),
    ({'initial_state': [0.0]}, 'initial_state must have length 2'),
    ({'initial_covariance': [[1, 0], [0, -1]]}, 'initial_covariance must be positive'),
    ({'horizon_s': -1}, 'horizon_s must be > 0'),
    ({'B': [['0'], ['dt']]}, "'B' is given but 'controls' is not"),
    ({'controls': ['a']}, "'B' is required"),
    ({'motion': 'teleport'}, "'motion' must be one of"),
    ({'measurements': ['speed'], 'H': None}, "'H' is required: measurement 'speed'"),
    ({'measurement_model': 'sonar'}, "'measurement_model' must be linear or range_bearing"),
])
def test_invalid_preset_names_the_key(change, message):
    """Every invalid field is reported with the file name and the key."""
    data = _train_mapping()
    data.update(change)
    with pytest.raises(ValueError, match=message) as error:
        preset_from_mapping(data, source='my.yaml')
    assert str(error.value).startswith('my.yaml: ')


def test_user_config_file(tmp_path):
    """A user's YAML loads, H defaults to selecting measured states, errors name the file."""
    path = tmp_path / 'mine.yaml'
    path.write_text(textwrap.dedent("""\
        name: mine
        motion: constant_velocity
        states: [position, velocity]
        measurements: [velocity]
        R: [0.25]
        controls: [acceleration]
        B: [['dt**2/2'], ['dt']]
        process_noise: {continuous: [0, 0.5], control_std: [0.1]}
        nominal_period_s: 0.5
        initial_state: [1, 2]
        initial_covariance: [4, 9]
        """))
    preset = load_preset_file(str(path))
    np.testing.assert_array_equal(preset.model.H, [[0.0, 1.0]])
    np.testing.assert_array_equal(preset.initial_covariance, np.diag([4.0, 9.0]))
    dt = 0.5
    B = np.array([[dt ** 2 / 2], [dt]])
    expected = (0.5 * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
                + 0.01 * B @ B.T)
    np.testing.assert_allclose(preset.dynamics.Q(dt), expected, rtol=1e-15, atol=0.0)
    (tmp_path / 'broken.yaml').write_text('name: [unclosed\n')
    with pytest.raises(ValueError, match='broken.yaml: not valid YAML'):
        load_preset_file(str(tmp_path / 'broken.yaml'))
    with pytest.raises(ValueError, match='missing.yaml: cannot read'):
        load_preset_file(str(tmp_path / 'missing.yaml'))
    with pytest.raises(ValueError, match="unknown preset 'bus'"):
        load_preset('bus')
