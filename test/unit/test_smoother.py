"""Tests of kf_train.batch.smoother: RTS against filterpy and against the batch solution."""

from filterpy.kalman import rts_smoother
from kf_train.batch import rts_smooth, run_linear_series, run_series, smooth_series
from kf_train.presets import load_preset, preset_from_mapping
from kf_train.sim import range_bearing_scenario, robot_scenario
import numpy as np
import pytest


def _dts(t, t0=0.0):
    """Return the time steps into each row."""
    return np.diff(np.concatenate([[t0], t]))


@pytest.mark.parametrize('name', ['train', 'cv-position', 'cv-position-velocity'])
def test_linear_presets_match_filterpy_rts(name):
    """Smoothing a linear preset's output equals filterpy's rts_smoother."""
    preset = load_preset(name)
    rng = np.random.default_rng(4)
    N = 300
    t = np.arange(1, N + 1) * preset.nominal_period_s
    z = 2.0 * t[:, None] + rng.standard_normal((N, preset.dim_z))
    result = run_linear_series(preset, t, z)
    ours = smooth_series(result)
    Qs = np.array([preset.dynamics.Q(dt) for dt in _dts(t)])
    xs, Ps, _, _ = rts_smoother(result.x.copy(), result.P.copy(), result.F, Qs)
    np.testing.assert_allclose(ours.x, xs, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(ours.P, Ps, rtol=0.0, atol=1e-9)
    assert np.all(np.diagonal(ours.P, axis1=1, axis2=2)
                  <= np.diagonal(result.P, axis1=1, axis2=2) * (1 + 1e-12))


def _long_double_rts_covariances(P, F, Qs):
    """Return RTS covariances computed in long double (Gauss-Jordan inverse): a reference."""
    ld = np.longdouble

    def inverse(A):
        n = A.shape[0]
        M = np.concatenate([A.copy(), np.eye(n, dtype=ld)], axis=1)
        for i in range(n):
            pivot = i + int(np.argmax(np.abs(M[i:, i])))
            M[[i, pivot]] = M[[pivot, i]]
            M[i] /= M[i, i]
            for j in range(n):
                if j != i:
                    M[j] -= M[j, i] * M[i]
        return M[:, n:]

    out = [P[-1].astype(ld)]
    for k in range(P.shape[0] - 2, -1, -1):
        Pk, Fk = P[k].astype(ld), F[k + 1].astype(ld)
        Pp = Fk @ Pk @ Fk.T + Qs[k + 1].astype(ld)
        G = Pk @ Fk.T @ inverse(Pp)
        out.append(Pk + G @ (out[-1] - Pp) @ G.T)
    return np.array(out[::-1]).astype(float)


def test_range_bearing_matches_filterpy_rts():
    """The EKF's output (linear dynamics) smooths as filterpy's rts_smoother does."""
    preset = load_preset('range-bearing')
    s = range_bearing_scenario(7)
    result = run_series(preset, s.t_s, s.z)
    ours = smooth_series(result)
    Qs = np.array([preset.dynamics.Q(dt) for dt in _dts(s.t_s)])
    xs, Ps, _, _ = rts_smoother(result.x.copy(), result.P.copy(), result.F, Qs)
    np.testing.assert_allclose(ours.x, xs, rtol=0.0, atol=1e-9)
    # P⁻ has condition numbers up to ~1e5 here, and filterpy inverts it: its covariances
    # are off by ~2e-9 of their scale near the start. Ours (solved, not inverted) match a
    # long-double reference to ~1e-12 of the scale (1e-11 allowed), so filterpy is held
    # to its own accuracy, 1e-8.
    reference = _long_double_rts_covariances(result.P, result.F, Qs)
    scale = np.max(np.abs(reference))
    np.testing.assert_allclose(ours.P, reference, rtol=0.0, atol=1e-11 * scale)
    np.testing.assert_allclose(ours.P, Ps, rtol=0.0, atol=1e-8 * scale)
    # Smoothing helps: the smoothed track is closer to the truth on average.
    err_f = np.linalg.norm((result.x - s.truth)[:, [0, 2]], axis=1)
    err_s = np.linalg.norm((ours.x - s.truth)[:, [0, 2]], axis=1)
    assert np.mean(err_s) < np.mean(err_f)


def _batch_smoother(F, Q, B, u, H, R, x0, P0, z):
    """Return the joint MAP means and marginal covariances of x_0 (at t0) … x_N."""
    N, n = z.shape[0], F.shape[0]
    dim = (N + 1) * n
    A = np.zeros((dim, dim))
    b = np.zeros(dim)
    Qi, Ri, P0i = np.linalg.inv(Q), np.linalg.inv(R), np.linalg.inv(P0)
    A[:n, :n] += P0i                                     # prior on x_0
    b[:n] += P0i @ x0
    for k in range(1, N + 1):
        i, j = slice((k - 1) * n, k * n), slice(k * n, (k + 1) * n)
        c = B @ u[k - 1]
        # (x_k − F x_{k−1} − c)ᵀ Q⁻¹ (…): quadratic in the stacked states
        A[j, j] += Qi
        A[i, i] += F.T @ Qi @ F
        A[i, j] -= F.T @ Qi
        A[j, i] -= Qi @ F
        b[j] += Qi @ c
        b[i] -= F.T @ Qi @ c
        A[j, j] += H.T @ Ri @ H                          # (z_k − H x_k)ᵀ R⁻¹ (…)
        b[j] += H.T @ Ri @ z[k - 1]
    cov = np.linalg.inv(A)
    mean = np.linalg.solve(A, b)
    return (mean.reshape(N + 1, n)[1:],
            np.array([cov[k * n:(k + 1) * n, k * n:(k + 1) * n] for k in range(1, N + 1)]))


def test_smoother_with_control_equals_the_batch_solution():
    """With a control input (which filterpy's rts_smoother ignores) RTS is the joint MAP."""
    mapping = {
        'name': 'controlled', 'motion': 'constant_velocity',
        'states': ['position', 'velocity'], 'measurements': ['position'], 'R': [0.5],
        'controls': ['acceleration'], 'B': [['dt**2/2'], ['dt']],
        'process_noise': {'continuous': [[0.1, 0.0], [0.0, 0.4]]}, 'nominal_period_s': 0.2,
        'initial_state': [1.0, -1.0], 'initial_covariance': [[2.0, 0.5], [0.5, 3.0]],
    }
    preset = preset_from_mapping(mapping)
    rng = np.random.default_rng(5)
    N, dt = 60, 0.2
    t = np.arange(1, N + 1) * dt
    u = rng.standard_normal((N, 1))
    z = rng.standard_normal((N, 1)) + t[:, None]
    result = run_linear_series(preset, t, z, u)
    ours = smooth_series(result)
    mean, cov = _batch_smoother(preset.dynamics.F(dt), preset.dynamics.Q(dt),
                                preset.dynamics.control(dt), u, preset.model.H,
                                preset.model.R, preset.initial_state,
                                preset.initial_covariance, z)
    np.testing.assert_allclose(ours.x, mean, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(ours.P, cov, rtol=0.0, atol=1e-9)


def test_robot_smoother_equals_the_batch_solution():
    """The robot preset (1 state, control, P0 = 0) smooths to the joint MAP too."""
    preset = load_preset('robot')
    s = robot_scenario(2)
    result = run_linear_series(preset, s.t_s, s.z, s.u)
    ours = smooth_series(result)
    # P0 = 0 pins x(t0) = 0: the first transition then starts from a known state.
    N = s.t_s.shape[0]
    Q, R, dt = 0.04, 0.0009, 0.1
    A = np.zeros((N, N))
    b = np.zeros(N)
    for k in range(N):
        A[k, k] += 1.0 / Q + 1.0 / R
        b[k] += s.z[k, 0] / R + dt * s.u[k, 0] / Q
        if k:
            A[k - 1, k - 1] += 1.0 / Q
            A[k - 1, k] -= 1.0 / Q
            A[k, k - 1] -= 1.0 / Q
            b[k - 1] -= dt * s.u[k, 0] / Q
    np.testing.assert_allclose(ours.x[:, 0], np.linalg.solve(A, b), rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(ours.P[:, 0, 0], np.diag(np.linalg.inv(A)), rtol=0.0,
                               atol=1e-12)


def test_vectorised_and_row_by_row_passes_agree(monkeypatch):
    """The affine-recursion pass equals the plain backward loop."""
    import kf_train.batch.smoother as smoother
    preset = load_preset('car')
    rng = np.random.default_rng(6)
    t = np.cumsum(rng.uniform(0.05, 0.2, 500))
    result = run_linear_series(preset, t, rng.standard_normal((500, 1)) + t[:, None],
                               rng.standard_normal((500, 1)))
    fast = smooth_series(result)
    monkeypatch.setattr(smoother, 'VECTORISED_MAX_STATES', 0)
    slow = smooth_series(result)
    np.testing.assert_allclose(fast.x, slow.x, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(fast.P, slow.P, rtol=0.0, atol=1e-12)


def test_edge_cases_and_errors():
    """One row is its own smoothing; bad shapes and singular priors are named."""
    x, P = np.array([[1.0, 2.0]]), np.eye(2)[None]
    one = rts_smooth(x, P, x, P, np.eye(2)[None])
    np.testing.assert_array_equal(one.x, x)
    assert one.gain.shape == (0, 2, 2)
    with pytest.raises(ValueError, match='P_prior must have shape'):
        rts_smooth(x, P, x, np.eye(3)[None], np.eye(2)[None])
    x2 = np.zeros((2, 2))
    P2 = np.stack([np.eye(2), np.eye(2)])
    with pytest.raises(ValueError, match=r'P_prior\[1\] is singular'):
        rts_smooth(x2, P2, x2, np.stack([np.eye(2), np.zeros((2, 2))]),
                   np.stack([np.eye(2)] * 2))
