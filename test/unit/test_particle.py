"""Tests of kf_train.filters.particle: the bootstrap particle filter."""

import math

from kf_train.batch import run_series, time_steps_s
from kf_train.filters import log_normalise, ParticleFilter, psd_factor, systematic_resample
from kf_train.presets import load_preset, preset_from_mapping
from kf_train.sim import scenario_for_preset
import numpy as np
import pytest
from scipy import stats
import yaml


def _run(pf, t_s, z, u=None):
    """Run a particle filter over rows; return the means and covariances."""
    means, covariances = [], []
    for k, dt in enumerate(time_steps_s(t_s)):
        pf.predict(dt, None if u is None else u[k])
        pf.update(z[k])
        means.append(pf.mean)
        covariances.append(pf.covariance)
    return np.array(means), np.array(covariances)


def _importance_sampling_variance(prior_mean, prior_cov, mean, cov):
    """
    Return (V, K0): the asymptotic variance N·Var(μ̂) of self-normalised IS, and K0.

    Proposal q = N(prior_mean, prior_cov), target π = N(mean, cov):
    V = E_q[(π/q)² (x − μ)(x − μ)ᵀ] = K0 (B + a aᵀ) with, about μ = 0,
    C = 2 P⁻¹ − Σ⁻¹, B = C⁻¹, a = −B Σ⁻¹ m, K0 = √(det Σ det B) / det P · exp(E),
    E = ½ aᵀ C a + ½ mᵀ Σ⁻¹ m. K0 = ∫ π²/q ≥ 1 is the variance inflation: N/K0 is
    the effective sample size.
    """
    m = prior_mean - mean
    Sigma_inv = np.linalg.inv(prior_cov)
    C = 2.0 * np.linalg.inv(cov) - Sigma_inv
    B = np.linalg.inv(C)
    a = -B @ Sigma_inv @ m
    E = 0.5 * a @ C @ a + 0.5 * m @ Sigma_inv @ m
    K0 = math.sqrt(np.linalg.det(prior_cov) * np.linalg.det(B)) / np.linalg.det(cov) * math.exp(E)
    return K0 * (B + np.outer(a, a)), K0


def test_mean_approaches_the_kf_within_the_monte_carlo_bound():
    """
    On the train preset (Q = 0) without resampling, the PF mean is within k·σ of the KF's.

    With Q = 0 and no resampling the particles are x_i(t) = F(t) x_i(0), x_i(0) ~ N(x0, P0),
    weighted by the likelihood of every measurement: self-normalised importance sampling
    from q = N(F x0, F P0 Fᵀ) to the KF posterior π = N(μ, P). By the delta method
    √N (μ̂ − μ) → N(0, V) with V = E_q[(π/q)² (x − μ)(x − μ)ᵀ], in closed form for
    Gaussians (_importance_sampling_variance); V ≈ K0·P, i.e. σ ≈ √(P / N_eff) with
    N_eff = N / K0. The data are drawn from the prior (truth0 ~ N(x0, P0)), the rows
    tested keep N_eff >= 1000 so the normal approximation holds, and k is the normal
    quantile for a false-alarm probability of 1e-6 over all rows × components
    (Bonferroni).
    """
    preset = load_preset('train')
    rng = np.random.default_rng(11)
    truth0 = preset.initial_state + rng.standard_normal(2)
    rows = 50
    t = np.arange(1, rows + 1) * 0.1
    z = (truth0[0] + truth0[1] * t + rng.standard_normal(rows))[:, None]
    kf = run_series(preset, t, z)
    N = 100_000
    pf = ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                        n_particles=N, seed=5, resample_threshold=0.0)
    means, covariances = _run(pf, t, z)
    assert pf.resample_count == 0
    k = stats.norm.isf(1e-6 / (2 * rows * 2))
    for row in range(rows):
        Phi = preset.dynamics.F(t[row])
        V, K0 = _importance_sampling_variance(
            Phi @ preset.initial_state, Phi @ preset.initial_covariance @ Phi.T,
            kf.x[row], kf.P[row])
        assert N / K0 >= 1000
        sigma = np.sqrt(np.diag(V) / N)
        assert np.all(np.abs(means[row] - kf.x[row]) <= k * sigma), (row, means[row], kf.x[row])


def test_resampling_with_control_is_unbiased_across_seeds():
    """
    With resampling and a control input (car), the PF's error has mean zero across seeds.

    M independent seeds give errors e_r = μ̂_r − μ_KF at the last row; their mean over
    the seeds is within t·s/√M, t the Student quantile (M − 1 dof) for a false-alarm
    probability of 1e-4 over the two components. The PF's O(1/N) bias is far below.
    """
    preset = load_preset('car')
    scenario = scenario_for_preset('car', 2)
    kf = run_series(preset, scenario.t_s, scenario.z, scenario.u)
    M, N = 30, 2000
    errors = []
    for seed in range(M):
        pf = ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                            n_particles=N, seed=seed)
        means, _ = _run(pf, scenario.t_s, scenario.z, scenario.u)
        assert pf.resample_count > 0
        errors.append(means[-1] - kf.x[-1])
    errors = np.array(errors)
    t = stats.t.isf(1e-4 / (2 * 2), M - 1)
    s = errors.std(axis=0, ddof=1)
    assert np.all(np.abs(errors.mean(axis=0)) <= t * s / math.sqrt(M))
    # And the spread itself is a Monte-Carlo error, small against the KF's own σ.
    assert np.all(s < np.sqrt(np.diag(kf.P[-1])))


# ---------------------------------------------------------------------------
# Resampling and weights
# ---------------------------------------------------------------------------

def test_systematic_resampling_copies_floor_or_ceil_and_is_unbiased():
    """Particle i is copied ⌊N w_i⌋ or ⌈N w_i⌉ times; over u0 the mean count is N w_i."""
    rng = np.random.default_rng(3)
    N = 257
    w = rng.dirichlet(np.full(N, 0.3))
    grid = (np.arange(4000) + 0.5) / 4000
    mean_counts = np.zeros(N)
    for u0 in np.concatenate([[0.0, 1.0 - 1e-16], grid]):
        counts = np.bincount(systematic_resample(w, u0), minlength=N)
        assert counts.sum() == N
        assert np.all((counts == np.floor(N * w)) | (counts == np.ceil(N * w)))
        if 0.0 < u0 < 1.0 - 1e-9:
            mean_counts += counts / grid.size
    # Each count is a step function of u0; the midpoint rule errs by at most 1/grid.
    assert np.all(np.abs(mean_counts - N * w) <= 1.0 / grid.size + 1e-12)


def test_log_weights_survive_a_measurement_that_underflows_every_likelihood():
    """
    A measurement 10⁴ σ away: every likelihood is exp(−5·10⁷) = 0 in doubles.

    The log-weights still pick the particles nearest the measurement; the weights are
    finite and sum to one.
    """
    preset = load_preset('train')
    pf = ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                        n_particles=1000, seed=1, resample_threshold=0.0)
    pf.predict(0.1)
    before = pf.particles
    result = pf.update([1e4])
    w = pf.weights
    assert np.all(np.isfinite(w)) and math.isclose(w.sum(), 1.0, rel_tol=1e-12)
    assert int(np.argmax(w)) == int(np.argmax(before[:, 0]))  # the closest particle
    assert np.all(np.isfinite(pf.mean)) and np.all(np.isfinite(pf.covariance))
    assert result.nis > 1e7 and math.isfinite(result.nis)
    with pytest.raises(ValueError, match='every particle has zero likelihood'):
        log_normalise(np.full(3, -np.inf))


def test_psd_factor_is_exact_for_singular_and_diagonal_matrices():
    """G Gᵀ = M, with as many columns as M's rank (no noise drawn for a zero Q)."""
    assert psd_factor('Q', np.zeros((2, 2)), 2).shape == (2, 0)
    G = psd_factor('Q', np.diag([0.0, 0.01, 0.0, 0.01]), 4)
    assert G.shape == (4, 2)
    np.testing.assert_allclose(G @ G.T, np.diag([0.0, 0.01, 0.0, 0.01]), rtol=1e-15)
    assert np.all(G[[0, 2]] == 0.0)  # no noise at all on the noiseless states
    M = np.array([[2.0, 1.0], [1.0, 0.5]])  # rank 1
    G = psd_factor('M', M, 2)
    assert G.shape == (2, 1)
    np.testing.assert_allclose(G @ G.T, M, atol=1e-15)


# ---------------------------------------------------------------------------
# Reproducibility and state handling
# ---------------------------------------------------------------------------

def _range_bearing_pf(seed=4, **kwargs):
    """Return a PF on the range-bearing preset and the scenario's rows."""
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 1)
    pf = ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                        n_particles=500, seed=seed, **kwargs)
    return pf, scenario


def test_seeded_runs_are_reproducible_bit_for_bit():
    """Same seed: identical particles and estimates; another seed: different ones."""
    results = []
    for seed in (4, 4, 5):
        pf, scenario = _range_bearing_pf(seed, roughening=0.2)
        results.append(_run(pf, scenario.t_s, scenario.z) + (pf.particles,))
    for a, b in zip(results[0], results[1]):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(results[0][0], results[2][0])


def test_snapshot_restore_and_reset_replay_exactly():
    """After restore (or reset) the same steps give the same numbers, bit for bit."""
    pf, scenario = _range_bearing_pf()
    dt = time_steps_s(scenario.t_s)
    fresh = _run(pf, scenario.t_s[:20], scenario.z[:20])
    pf.reset(load_preset('range-bearing').initial_state,
             load_preset('range-bearing').initial_covariance)
    np.testing.assert_array_equal(_run(pf, scenario.t_s[:20], scenario.z[:20])[0], fresh[0])
    snapshot = pf.snapshot()
    first = []
    for k in range(20, 40):
        pf.predict(dt[k])
        pf.update(scenario.z[k])
        first.append((pf.mean, pf.particles))
    pf.restore(snapshot)
    for k, (mean, particles) in zip(range(20, 40), first):
        pf.predict(dt[k])
        pf.update(scenario.z[k])
        np.testing.assert_array_equal(pf.mean, mean)
        np.testing.assert_array_equal(pf.particles, particles)
    assert not snapshot.particles.flags.writeable


def test_rejected_steps_leave_everything_unchanged():
    """A bad z, R or dt raises ValueError; particles, weights and generator are untouched."""
    pf, _ = _range_bearing_pf()
    pf.predict(0.2)
    pf.update([0.93, 50.0])
    before = pf.snapshot()
    for call, message in [
            (lambda: pf.update([np.nan, 50.0]), 'z must be finite'),
            (lambda: pf.update([0.9]), 'z must have length 2'),
            (lambda: pf.update([0.9, 50.0], R=np.zeros((2, 2))), 'R must be positive definite'),
            (lambda: pf.update([0.9, 1e200], R=np.diag([1e-300, 1e-300])),
             'every particle has zero likelihood'),
            (lambda: pf.predict(-0.1), 'dt must be >= 0'),
            (lambda: pf.predict(0.1, u=[1.0]), 'u given to a model without control input')]:
        with pytest.raises(ValueError, match=message):
            call()
        after = pf.snapshot()
        np.testing.assert_array_equal(after.particles, before.particles)
        np.testing.assert_array_equal(after.log_weights, before.log_weights)
        assert after.rng_state == before.rng_state


def test_predict_ahead_gives_exact_moments_and_changes_nothing():
    """predict_ahead = (F x̄ + B u, F P Fᵀ + Q) of the particles; no draw, no change."""
    preset = load_preset('car-exact')
    pf = ParticleFilter(preset.model, [1.0, 2.0], np.diag([0.5, 0.2]), n_particles=300,
                        seed=2)
    pf.predict(0.1, [1.0])
    pf.update([1.3])
    before = pf.snapshot()
    x, P = pf.predict_ahead(2.0, [0.5])
    F, B = preset.dynamics.F(2.0), preset.dynamics.control(2.0)
    np.testing.assert_allclose(x, F @ pf.mean + B @ [0.5], rtol=1e-14)
    np.testing.assert_allclose(P, F @ pf.covariance @ F.T + preset.dynamics.Q(2.0), rtol=1e-13)
    after = pf.snapshot()
    np.testing.assert_array_equal(after.particles, before.particles)
    assert after.rng_state == before.rng_state


# ---------------------------------------------------------------------------
# Angles and degenerate inputs
# ---------------------------------------------------------------------------

def test_bearing_residual_is_wrapped_across_the_branch_cut():
    """Particles straddling bearing ±π and z = π − 0.001: small innovation, sane NIS."""
    data = yaml.safe_load(open(load_preset('range-bearing').source, encoding='utf-8'))
    preset = preset_from_mapping(data)
    pf = ParticleFilter(preset.model, [-50.0, 0.0, 0.0, 0.0], np.diag([1.0, 0.1, 1.0, 0.1]),
                        n_particles=2000, seed=0)
    pf.predict(0.2)
    bearings = np.arctan2(pf.particles[:, 2], pf.particles[:, 0])
    assert np.any(bearings > 3.0) and np.any(bearings < -3.0)
    result = pf.update([math.pi - 0.001, 50.0])
    assert abs(result.innovation[0]) < 0.05
    assert result.nis < stats.chi2.isf(1e-6, 2)
    assert pf.ess > 10.0


@pytest.mark.parametrize('P0,R', [
    ([0.0, 0.0, 0.0, 0.0], None),
    ([1e-30, 1e-30, 1e-30, 1e-30], None),
    (None, [[1e-20, 0.0], [0.0, 1e-12]]),
    ([1e-30, 1e3, 1e-30, 1e3], [[1e-20, 0.0], [0.0, 1e-12]]),
])
def test_degenerate_inputs_never_crash(P0, R):
    """Zero or near-singular P0, tiny R: every step succeeds and the state stays finite."""
    data = yaml.safe_load(open(load_preset('range-bearing').source, encoding='utf-8'))
    if P0 is not None:
        data['initial_covariance'] = P0
    if R is not None:
        data['R'] = R
    preset = preset_from_mapping(data)
    scenario = scenario_for_preset('range-bearing', 2)
    pf = ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                        n_particles=300, seed=1)
    means, covariances = _run(pf, scenario.t_s, scenario.z)
    assert np.all(np.isfinite(means)) and np.all(np.isfinite(covariances))
    for P in covariances:
        assert np.min(np.linalg.eigvalsh(P)) >= -1e-12 * max(1.0, np.max(np.abs(P)))


def test_robot_preset_with_zero_initial_covariance():
    """The robot seed (P0 = 0, control input) runs and tracks the range finder."""
    preset = load_preset('robot')
    scenario = scenario_for_preset('robot', 0)
    pf = ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                        n_particles=2000, seed=0)
    means, covariances = _run(pf, scenario.t_s, scenario.z, scenario.u)
    kf = run_series(preset, scenario.t_s, scenario.z, scenario.u)
    sigma = np.sqrt(kf.P[:, 0, 0])
    assert np.all(np.abs(means[:, 0] - kf.x[:, 0]) < sigma)


def test_roughening_makes_resampled_particles_distinct():
    """With roughening every resampled particle differs; without, duplicates remain."""
    for roughening, distinct in ((0.0, False), (0.2, True)):
        pf, scenario = _range_bearing_pf(roughening=roughening)
        pf.predict(0.2)
        pf.update(scenario.z[0])
        assert pf.resample_count == 1
        unique = np.unique(pf.particles, axis=0).shape[0]
        assert (unique == pf.n_particles) == distinct


def test_parameters_are_checked():
    """Bad particle counts, seeds, thresholds and roughening raise ValueError."""
    preset = load_preset('train')
    for kwargs, message in [({'n_particles': 0}, 'n_particles must be an integer'),
                            ({'n_particles': 2.5}, 'n_particles must be an integer'),
                            ({'seed': -1}, 'seed must be a non-negative integer'),
                            ({'resample_threshold': 1.5}, 'resample_threshold must be in'),
                            ({'roughening': -0.1}, 'roughening must be a number >= 0')]:
        with pytest.raises(ValueError, match=message):
            ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                           **kwargs)
    with pytest.raises(ValueError, match='P0 must be positive semi-definite'):
        ParticleFilter(preset.model, [0.0, 0.0], -np.eye(2))
