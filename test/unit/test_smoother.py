"""Tests of kf_train.batch.smoother: RTS against filterpy and against the batch solution."""

import math

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
    """
    Smoothing a linear preset's output equals filterpy's rts_smoother and a long-double RTS.

    Ours is held to the long-double reference within twice its rounding bound
    (_rts_rounding_bounds): 1e-10 to 7e-9 over these 300 rows (P⁻ with κ <= 1.2e3);
    measured, the error is <= 6% of it. filterpy inverts P⁻ explicitly, whose worst
    case is ~κ times worse: the comparison with it allows both bounds (measured, the
    two agree to <= 5e-13).
    """
    preset = load_preset(name)
    rng = np.random.default_rng(4)
    N = 300
    t = np.arange(1, N + 1) * preset.nominal_period_s
    z = 2.0 * t[:, None] + rng.standard_normal((N, preset.dim_z))
    result = run_linear_series(preset, t, z)
    ours = smooth_series(result)
    Qs = np.array([preset.dynamics.Q(dt) for dt in _dts(t)])
    x_ref, P_ref = _long_double_rts(result, Qs)
    ours_x, ours_P = _rts_rounding_bounds(result, ours.gain, x_ref, P_ref)
    assert np.all(np.max(np.abs(ours.x - x_ref), axis=1) <= 2.0 * ours_x)
    assert np.all(np.max(np.abs(ours.P - P_ref), axis=(1, 2)) <= 2.0 * ours_P)
    assert np.max(ours_x) < 1e-9 and np.max(ours_P) < 1e-8  # bounds that mean something
    xs, Ps, _, _ = rts_smoother(result.x.copy(), result.P.copy(), result.F, Qs)
    theirs_x, theirs_P = _rts_rounding_bounds(result, ours.gain, x_ref, P_ref,
                                              inverted=True)
    assert np.all(np.max(np.abs(ours.x - xs), axis=1) <= 2.0 * (ours_x + theirs_x))
    assert np.all(np.max(np.abs(ours.P - Ps), axis=(1, 2)) <= 2.0 * (ours_P + theirs_P))
    # Ps <= P exactly; the diagonal's rounding is a few u of its terms (~|P|), far
    # inside 1e-12 relative.
    assert np.all(np.diagonal(ours.P, axis1=1, axis2=2)
                  <= np.diagonal(result.P, axis1=1, axis2=2) * (1 + 1e-12))


def _long_double_rts(result, Qs):
    """Return RTS means and covariances computed in long double (Gauss-Jordan): a reference."""
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

    x, P, F = result.x.astype(ld), result.P.astype(ld), result.F.astype(ld)
    xs, Ps = [x[-1]], [P[-1]]
    for k in range(P.shape[0] - 2, -1, -1):
        Pp = F[k + 1] @ P[k] @ F[k + 1].T + Qs[k + 1].astype(ld)
        G = P[k] @ F[k + 1].T @ inverse(Pp)
        xs.append(x[k] + G @ (xs[-1] - F[k + 1] @ x[k]))
        Ps.append(P[k] + G @ (Ps[-1] - Pp) @ G.T)
    return np.array(xs[::-1]).astype(float), np.array(Ps[::-1]).astype(float)


def _rts_rounding_bounds(result, gains, xs, Ps, inverted=False):
    """
    Return per-row bounds (N,) on |Δxs| and |ΔPs| of a float64 RTS pass (2-norms).

    First order in u = eps/2, n states. The gain is solved from P⁻ Gᵀ = F P_k: a
    backward-stable solve gives (P⁻ + E) Ĝᵀ = F P_k + e with |E| <= 6n·u·|P⁻| (LU with
    partial pivoting of a positive definite matrix, growth <= 2) and |e| <= n·u·|F||P_k|,
    so ΔG = −(G E − eᵀ)(P⁻)⁻¹ and

    * ΔG (Ps − P⁻) = −(G E − eᵀ)((P⁻)⁻¹ Ps − I): as Ps <= P⁻ (smoothed <= filtered
      <= predicted), |(P⁻)⁻¹ Ps| <= √κ (κ = cond P⁻), and <= |Ps|/λ_min anyway;
    * ΔG (xs − x⁻) = −(G E − eᵀ)(P⁻)⁻¹ (xs − x⁻), |(P⁻)⁻¹ v| <= √(vᵀ(P⁻)⁻¹v / λ_min).

    Each row adds that (twice for Ps: G and Gᵀ) and the rounding of its own sums,
    <= 2n·u·(|P_k| + |G|²|Ps − P⁻|) and 2n·u·(|x_k| + |G|(|xs| + |x⁻|)). An error at
    row j reaches row k through Π = G_k⋯G_{j−1}: as Π δ Πᵀ for Ps, Π δ for xs.

    ``inverted``: the pass forms G = P_k Fᵀ inv(P⁻) instead (filterpy). The inverse's
    forward error is <= 3n·u·κ·|(P⁻)⁻¹|, so |ΔG| <= 3n·u·κ·|P_k Fᵀ| / λ_min, with no
    cancellation against P⁻: that replaces the solve's terms above.
    """
    u = np.finfo(float).eps / 2.0
    norm = np.linalg.norm
    N, n = result.x.shape
    local_x, local_P = np.zeros(N), np.zeros(N)
    for k in range(N - 1):
        G, F, P_k, Pm = gains[k], result.F[k + 1], result.P[k], result.P_prior[k + 1]
        v, D = xs[k + 1] - result.x_prior[k + 1], Ps[k + 1] - Pm
        lam = np.linalg.eigvalsh(Pm)
        backward = 6 * n * u * norm(G, 2) * norm(Pm, 2) + n * u * norm(F, 2) * norm(P_k, 2)
        amplified = 1.0 + min(norm(Ps[k + 1], 2) / lam[0], np.sqrt(lam[-1] / lam[0]))
        if inverted:
            dG = 3 * n * u * (lam[-1] / lam[0]) * norm(P_k @ F.T, 2) / lam[0]
            gain_P, gain_x = 2 * dG * norm(D, 2) * norm(G, 2), dG * norm(v)
        else:
            gain_P = 2 * backward * amplified * norm(G, 2)
            gain_x = backward * np.sqrt(max(v @ np.linalg.solve(Pm, v), 0.0) / lam[0])
        local_P[k] = gain_P + 2 * n * u * (norm(P_k, 2) + norm(G, 2) ** 2 * norm(D, 2))
        local_x[k] = gain_x + 2 * n * u * (norm(result.x[k]) + norm(G, 2) * (
            norm(xs[k + 1]) + norm(v + xs[k + 1])))
    bound_x, bound_P = np.zeros(N), np.zeros(N)
    for k in range(N - 1):
        carry = np.eye(n)
        for j in range(k, N - 1):
            spread = math.sqrt(float(np.sum(carry * carry)))  # Frobenius >= 2-norm
            bound_x[k] += spread * local_x[j]
            bound_P[k] += spread ** 2 * local_P[j]
            carry = carry @ gains[j]
    return bound_x, bound_P


def test_range_bearing_smooths_to_a_long_double_reference():
    """
    The EKF's output (linear dynamics) smooths to a long-double RTS within its bound.

    P⁻ reaches condition numbers ~1.1e5 here (the first bearing makes position and
    velocity nearly collinear) and the smoothed covariances are ~1e4 times smaller
    than the filtered ones they are computed from, so the bound
    (:func:`_rts_rounding_bounds`, with a factor 2 of margin) is what the mathematics
    allows; measured, the error is ~1e-3 of it under every OpenBLAS kernel. The
    long-double reference adds ~κ·1e-19 relative: nothing at this scale.

    filterpy's rts_smoother inverts P⁻ explicitly and its covariances are off by 2e-9
    to 5e-9 of their scale here, depending on the BLAS kernel: comparing with it would
    test filterpy's rounding, not ours (the well-conditioned presets above are
    compared with filterpy).
    """
    preset = load_preset('range-bearing')
    s = range_bearing_scenario(7)
    result = run_series(preset, s.t_s, s.z)
    ours = smooth_series(result)
    Qs = np.array([preset.dynamics.Q(dt) for dt in _dts(s.t_s)])
    xs, Ps = _long_double_rts(result, Qs)
    bound_x, bound_P = _rts_rounding_bounds(result, ours.gain, xs, Ps)
    assert np.all(np.max(np.abs(ours.x - xs), axis=1) <= 2.0 * bound_x)
    assert np.all(np.max(np.abs(ours.P - Ps), axis=(1, 2)) <= 2.0 * bound_P)
    # The bound means something: below 1e-8 of the smoothed covariances' scale.
    assert np.max(bound_P) < 1e-8 * np.max(np.abs(Ps))
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
    # The batch system (122 unknowns) has κ(A) ≈ 320: its solve and inverse are good
    # to ~n·u·κ ≈ 4e-12 relative (|mean| <= 13, |cov| <= 0.5), RTS to less: 1e-9 is
    # a margin of >= 20.
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
    # A is tridiagonal with κ ≈ (1/R + 4/Q)/(1/R) ≈ 1.1: solve and inverse are good to
    # ~N·u·κ ≈ 1e-14 relative, |x| < 1 and P ≈ 9e-4, so 1e-9 and 1e-12 hold by >= 100.
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
    # The same recursion associated differently: each pass rounds a row by <= 2n·u of
    # its terms (|x| <= 65 and |G||xs|; |P|, |G|²|Ps| <= 1.3) and carries earlier errors
    # with gain products G_k⋯G_j, whose norms sum to <= 22 (squared: <= 52) on this
    # run: <= 3e-12 for x and 7e-14 for P per pass. 1e-9 and 1e-12 hold with margin.
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
