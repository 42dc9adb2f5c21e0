"""
Tests of kf_train.filters.regularised_pf: the particle filter that tracks range-bearing.

Every test is seeded. The accuracy tests would fail for a collapsed filter: the
bootstrap filter runs through the same checks and fails them.
"""

import math

from kf_train.batch import run_filter_series, time_steps_s
from kf_train.evaluate import anees_bounds, nees, run_comparison
from kf_train.filters import (
    FilterOptions, kernel_draws, make_filter, optimal_bandwidth, ParticleFilter,
    regularisation_jitter, RegularisedParticleFilter, tempering_step)
from kf_train.presets import load_preset, preset_from_mapping
from kf_train.sim import scenario_for_preset
import numpy as np
import pytest
from scipy import stats
import yaml

RMSE_FACTOR = 1.5
"""Issue 14's target: position RMSE at most 1.5 times the EKF's."""


def _pf(preset, n_particles=1000, seed=0, x0=None, P0=None, **kwargs):
    """Return a regularised PF at the preset's (or the given) initial estimate."""
    return RegularisedParticleFilter(
        preset.model, preset.initial_state if x0 is None else x0,
        preset.initial_covariance if P0 is None else P0, n_particles=n_particles,
        seed=seed, **kwargs)


def _run(pf, scenario, rows=None):
    """Predict and update over a scenario's rows; return the means and covariances."""
    means, covariances = [], []
    for k, dt in enumerate(time_steps_s(scenario.t_s)[:rows]):
        pf.predict(dt, None if scenario.u is None else scenario.u[k])
        pf.update(scenario.z[k])
        means.append(pf.mean)
        covariances.append(pf.covariance)
    return np.array(means), np.array(covariances)


def _position_rmse(x, truth):
    """Return the position RMSE of range-bearing estimates [m]."""
    return math.sqrt(np.mean((x[:, 0] - truth[:, 0]) ** 2 + (x[:, 2] - truth[:, 2]) ** 2))


# ---------------------------------------------------------------------------
# Accuracy and consistency on the range-bearing seed
# ---------------------------------------------------------------------------

def test_tracks_the_seeds_own_data_within_the_bound_of_the_ekf():
    """
    Seed scenario 0 from the preset's initial state: pf ≤ 1.5× the EKF's RMSE.

    Measured: EKF 0.50 m, pf ~0.5 m (ratio ~1), bootstrap ~10 m; the bound is the
    issue's target and sits far outside the seed-to-seed spread of the ratio (a few
    per cent over 100 rows). The bootstrap filter, run through the same check, fails.
    """
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 0)
    rmse = {}
    for kind in ('ekf', 'pf', 'bootstrap-pf'):
        result = run_filter_series(make_filter(preset, kind, particles=2000, seed=0),
                                   scenario.t_s, scenario.z, horizon_s=0.0)
        rmse[kind] = _position_rmse(result.x, scenario.truth)
    assert rmse['pf'] <= RMSE_FACTOR * rmse['ekf'], rmse
    assert rmse['bootstrap-pf'] > RMSE_FACTOR * rmse['ekf'], rmse


@pytest.mark.parametrize('initial', ['sampled', 'preset'])
def test_monte_carlo_rmse_and_anees_meet_the_targets(initial):
    """
    Ten seeded Monte-Carlo runs: RMSE ≤ 1.5× the EKF's, ANEES inside the χ² 99% band.

    ANEES: for a consistent filter each row's runs·ANEES_k is χ²(runs·n); the mean
    over the rows of identically distributed ANEES_k is less dispersed than any one
    of them (Jensen: it is smaller in the convex order), so the one-row band
    [χ²₀.₀₀₅(40), χ²₀.₉₉₅(40)] / 10 = [2.07, 6.68] is a conservative band for it.
    Only with ``sampled`` initial estimates (drawn from N(truth, P0)) is the NEES
    test valid from the first row; ``preset`` checks the RMSE only. Measured: pf
    ANEES ~4.2, RMSE 0.46 m against the EKF's 1.23 m (sampled) and 0.46 m (preset).
    The bootstrap filter fails both (hundreds of metres, infinite ANEES).
    """
    runs = 10
    comparison = run_comparison('range-bearing', runs=runs, seed=0, initial=initial,
                                kinds=['ekf', 'pf', 'bootstrap-pf'],
                                options=FilterOptions(particles=1000))
    ekf, pf, bootstrap = comparison.summaries
    assert pf.runs_ok == runs and pf.runs_failed == 0
    assert pf.rmse_position_m <= RMSE_FACTOR * ekf.rmse_position_m
    assert bootstrap.rmse_position_m > RMSE_FACTOR * ekf.rmse_position_m
    if initial == 'sampled':
        low, high = anees_bounds(runs, 4)
        assert low <= pf.mean_anees <= high, pf.mean_anees
        assert not low <= bootstrap.mean_anees <= high


def _grid_posterior(m, C, z, R, points=401, width=8.0):
    """
    Return the exact first posterior (mean, covariance) of range-bearing by quadrature.

    Prior N(m, C) on [x, vx, y, vy], measurement z = [bearing, range] with noise R
    (diagonal): p(p | z) ∝ N(z; h(p), R) N(p; m_p, C_pp) on a polar grid ±width σ
    around z (area element r dr dθ); the velocity is linear-Gaussian given the
    position: E[v | p] = m_v + K (p − m_p), K = C_vp C_pp⁻¹.
    """
    bearing = z[0] + np.linspace(-width, width, points) * math.sqrt(R[0, 0])
    distance = z[1] + np.linspace(-width, width, points) * math.sqrt(R[1, 1])
    T, D = np.meshgrid(bearing, distance, indexing='ij')
    p = np.column_stack([(D * np.cos(T)).ravel(), (D * np.sin(T)).ravel()])
    pos, vel = [0, 2], [1, 3]
    e = p - m[pos]
    log_w = (-0.5 * ((z[0] - T.ravel()) ** 2 / R[0, 0] + (z[1] - D.ravel()) ** 2 / R[1, 1])
             - 0.5 * np.einsum('ij,jk,ik->i', e, np.linalg.inv(C[np.ix_(pos, pos)]), e)
             + np.log(D.ravel()))
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    mp = w @ p
    Pp = ((p - mp) * w[:, None]).T @ (p - mp)
    K = np.linalg.solve(C[np.ix_(pos, pos)], C[np.ix_(pos, vel)]).T
    mean, P = np.empty(4), np.empty((4, 4))
    mean[pos], mean[vel] = mp, m[vel] + K @ (mp - m[pos])
    P[np.ix_(pos, pos)] = Pp
    P[np.ix_(vel, vel)] = C[np.ix_(vel, vel)] - K @ C[np.ix_(pos, vel)] + K @ Pp @ K.T
    P[np.ix_(vel, pos)] = K @ Pp
    P[np.ix_(pos, vel)] = (K @ Pp).T
    return mean, P


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_first_update_from_the_measurement_is_the_exact_posterior(seed):
    """
    The first update's particles are weighted draws of the exact posterior.

    Against quadrature of the same Gaussian prior (the predicted particles' moments):
    the weighted mean of N = 20000 independent weighted draws has standard error
    √(diag P / ESS) (delta method); k = 4.9 per component is a false-alarm probability
    of 1e-5 over 3 seeds × 4 states (Bonferroni, normal). Each variance is within
    k·√(2 / ESS) of the exact one (sample variance of near-Gaussian draws).
    """
    preset = load_preset('range-bearing')
    z = scenario_for_preset('range-bearing', seed).z[0]
    pf = _pf(preset, n_particles=20_000, seed=seed)
    pf.predict(0.2)
    reference, P = _grid_posterior(pf.mean, pf.covariance, z, np.asarray(preset.model.R))
    pf.update(z)
    assert pf.counters['measurement_initialisations'] == 1
    assert pf.ess > 0.9 * pf.n_particles          # prior weights vary slowly over the draws
    k = stats.norm.isf(1e-5 / (2 * 3 * 4))
    sd = np.sqrt(np.diag(P))
    assert np.all(np.abs(pf.mean - reference) <= k * sd / math.sqrt(pf.ess))
    assert np.all(np.abs(np.diag(pf.covariance) / sd ** 2 - 1.0) <= k * math.sqrt(2.0 / pf.ess))


def test_tempered_first_update_without_measurement_draws_also_reaches_the_posterior():
    """
    From the prior's particles, progressive correction walks them into the posterior.

    The bootstrap filter keeps a handful of particles (ESS ~20 of 20000); the tempered
    update resamples and moves in stages and lands on the quadrature posterior. Its
    particles are correlated by the moves, so the bound assumes only N_eff ≥ 400:
    |error| ≤ 5σ/√400 = 0.25σ per state.
    """
    preset = load_preset('range-bearing')
    z = scenario_for_preset('range-bearing', 0).z[0]
    bootstrap = ParticleFilter(preset.model, preset.initial_state, preset.initial_covariance,
                               n_particles=20_000, seed=0, resample_threshold=0.0)
    bootstrap.predict(0.2)
    bootstrap.update(z)
    assert bootstrap.ess < 100.0
    pf = _pf(preset, n_particles=20_000, seed=0, initialise_from_measurement=False)
    pf.predict(0.2)
    reference, P = _grid_posterior(pf.mean, pf.covariance, z, np.asarray(preset.model.R))
    pf.update(z)
    assert pf.counters['tempering_stages'] >= 3
    assert pf.counters['measurement_initialisations'] == 0
    assert np.all(np.abs(pf.mean - reference) <= 0.25 * np.sqrt(np.diag(P)))


def test_linear_first_update_draws_the_kalman_posterior():
    """
    On a linear preset the first update draws N(x⁺, P⁺), the KF update of the prior.

    Equal weights; the sample mean is within k·√(diag P⁺ / N) of x⁺ (k for 1e-6 over
    two states).
    """
    preset = load_preset('car')
    pf = _pf(preset, n_particles=5000, seed=3)
    pf.predict(0.1, [1.0])
    x_prior, P_prior = pf.mean, pf.covariance
    pf.update([0.7])
    H, R = np.asarray(preset.model.H), np.asarray(preset.model.R)
    S = H @ P_prior @ H.T + R
    K = P_prior @ H.T @ np.linalg.inv(S)
    x_post = x_prior + K @ (np.array([0.7]) - H @ x_prior)
    P_post = (np.eye(2) - K @ H) @ P_prior
    assert pf.counters['measurement_initialisations'] == 1
    np.testing.assert_allclose(pf.weights, 1.0 / pf.n_particles, rtol=1e-12)
    k = stats.norm.isf(1e-6 / 4)
    assert np.all(np.abs(pf.mean - x_post) <= k * np.sqrt(np.diag(P_post) / pf.n_particles))


def test_a_tight_prior_keeps_its_own_particles():
    """When the prior is tighter than the measurement, the measurement draw is skipped."""
    preset = load_preset('range-bearing')
    pf = _pf(preset, n_particles=2000, x0=[30.0, 1.0, 40.0, 1.0],
             P0=np.diag([1e-4, 1e-4, 1e-4, 1e-4]))
    pf.predict(0.2)
    pf.update([math.atan2(40.2, 30.2), 50.3])
    assert pf.counters['measurement_initialisations'] == 0
    assert pf.ess > 0.5 * pf.n_particles


# ---------------------------------------------------------------------------
# Why Gordon's roughening is not enough
# ---------------------------------------------------------------------------

def test_gordons_roughening_blows_up_the_thin_direction_the_kernel_does_not():
    """
    Roughening inflates the cloud across the likelihood's sliver; the kernel does not.

    On a converged range-bearing cloud, x and y are ~94% correlated (a sliver along the
    line of sight, 0.05 m thin across it): axis-aligned roughening adds the same
    σ_j² = (K·E_j·N^(−1/n))² to x and y, which multiplies the variance across the
    sliver by >2 while leaving the long axis almost unchanged; the covariance-shaped
    kernel multiplies every direction by the same 1 + h².

    The algebra is checked against the jitter functions: the sample variance of N
    jitters along a unit direction u is within k·√(2/N) of uᵀ Σ u (k for 1e-6 over
    the 2 kernels × 4 directions).
    """
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 0)
    pf = _pf(preset, n_particles=2000, seed=0)
    _run(pf, scenario, rows=30)
    X = pf.particles[pf.weights.argsort()[::-1]]  # any order; equal weights after moves
    C = np.cov(X.T, bias=True)
    N, n = X.shape
    eigenvalues, directions = np.linalg.eigh(C)
    gordon = np.diag((0.2 * np.ptp(X, axis=0) * N ** (-1.0 / n)) ** 2)
    h = optimal_bandwidth(N, n, 'gaussian')
    inflation = {'gordon': 1.0 + np.einsum('ji,jk,ki->i', directions, gordon, directions)
                 / eigenvalues,
                 'gaussian': np.full(n, 1.0 + h * h)}
    assert inflation['gordon'][0] > 2.0 and inflation['gordon'][-1] < 1.1
    assert inflation['gaussian'][0] < 1.2
    k = stats.norm.isf(1e-6 / (2 * 2 * 4))
    rng = np.random.default_rng(1)
    for kernel, expected in (('gordon', gordon), ('gaussian', h * h * C)):
        jitter = regularisation_jitter(rng, X, kernel)
        for u in directions.T:
            variance = float(np.mean((jitter @ u) ** 2))
            assert abs(variance / (u @ expected @ u) - 1.0) <= k * math.sqrt(2.0 / N)


def test_roughening_alone_fails_where_the_full_filter_tracks():
    """
    Measurement draw + roughening misses the targets; the regularised filter meets them.

    Without progressive correction and the Metropolis step, Gordon's roughening after
    the measurement draw loses the track in several of ten runs from N(truth, P0)
    (measured: 4 of 10 beyond 1 m, one at 84 m) and its ANEES is infinite; with the
    regularised filter's steps the same runs meet the RMSE target and the ANEES band
    (the conservative band of test_monte_carlo_rmse_and_anees_meet_the_targets).
    """
    preset = load_preset('range-bearing')
    G0 = np.linalg.cholesky(preset.initial_covariance)
    runs = 10
    variants = (('roughening', {'kernel': 'gordon', 'tempering': False, 'metropolis': False}),
                ('full', {}))
    squared = {'ekf': [], 'roughening': [], 'full': []}
    nees_rows = {'roughening': [], 'full': []}
    for run in range(runs):
        scenario = scenario_for_preset('range-bearing', run)
        x0 = scenario.truth0 + G0 @ np.random.default_rng(100 + run).standard_normal(4)
        result = run_filter_series(make_filter(preset, 'ekf'), scenario.t_s, scenario.z,
                                   x0=x0, horizon_s=0.0)
        squared['ekf'].append(_position_rmse(result.x, scenario.truth) ** 2)
        for name, kwargs in variants:
            x, P = _run(_pf(preset, n_particles=1000, seed=run, x0=x0, **kwargs), scenario)
            squared[name].append(_position_rmse(x, scenario.truth) ** 2)
            nees_rows[name].append(nees(x - scenario.truth, P))
    rmse = {name: math.sqrt(np.mean(values)) for name, values in squared.items()}
    anees = {name: float(np.mean(np.mean(rows, axis=0))) for name, rows in nees_rows.items()}
    low, high = anees_bounds(runs, 4)
    assert rmse['full'] <= RMSE_FACTOR * rmse['ekf'] and low <= anees['full'] <= high
    assert rmse['roughening'] > RMSE_FACTOR * rmse['ekf'], rmse
    assert not low <= anees['roughening'] <= high, anees


# ---------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------

def test_optimal_bandwidths_are_silvermans_in_one_dimension():
    """In 1-D: Gaussian h = 1.06·N^(−1/5), Epanechnikov 2.34·N^(−1/5) (Silverman 1986)."""
    for N in (100, 10_000):
        assert optimal_bandwidth(N, 1, 'gaussian') * N ** 0.2 == pytest.approx(1.06, abs=5e-3)
        assert optimal_bandwidth(N, 1, 'epanechnikov') * N ** 0.2 == pytest.approx(
            2.34, abs=5e-3)


def test_epanechnikov_draws_fill_the_unit_ball_with_covariance_over_d_plus_4():
    """|ε| ≤ 1, and Cov ε = I/(d + 4) within k·√(2/N) relative (k for 1e-6)."""
    N, d = 200_000, 4
    draws = kernel_draws(np.random.default_rng(0), N, d, 'epanechnikov')
    assert draws.shape == (N, d) and np.max(np.linalg.norm(draws, axis=1)) <= 1.0
    k = stats.norm.isf(1e-6 / (2 * d))
    variance = np.mean(draws ** 2, axis=0) * (d + 4)
    assert np.all(np.abs(variance - 1.0) <= k * math.sqrt(2.0 / N) * 1.5)  # kurtosis < 3


def test_tempering_step_keeps_the_target_ess():
    """λ keeps ESS ≥ target, and 1.06·λ (beyond the bisection's resolution) does not."""
    rng = np.random.default_rng(2)
    log_w = np.full(5000, -math.log(5000))
    log_likelihood = -0.5 * (rng.standard_normal(5000) * 30.0) ** 2
    power = tempering_step(log_w, log_likelihood, 1.0, 2500.0)

    def ess(p):
        a = np.exp(p * log_likelihood - np.max(p * log_likelihood))
        return a.sum() ** 2 / np.sum(a * a)
    assert 0.0 < power < 1.0
    assert ess(power) >= 2500.0 > ess(1.06 * power)


# ---------------------------------------------------------------------------
# Reproducibility, state handling, checks
# ---------------------------------------------------------------------------

def test_seeded_runs_are_reproducible_bit_for_bit():
    """Same seed: identical particles, estimates and counters; another seed differs."""
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 1)
    results = []
    for seed in (4, 4, 5):
        pf = _pf(preset, n_particles=300, seed=seed)
        results.append(_run(pf, scenario, rows=30) + (pf.particles, pf.counters))
    for a, b in zip(results[0][:3], results[1][:3]):
        np.testing.assert_array_equal(a, b)
    assert results[0][3] == results[1][3]
    assert not np.array_equal(results[0][0], results[2][0])


def test_snapshot_restore_and_reset_replay_exactly_from_before_the_first_update():
    """The first-update flag is part of the state: a restore or reset replays bit for bit."""
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 1)
    pf = _pf(preset, n_particles=300, seed=2)
    start = pf.snapshot()
    assert start.awaiting_first_update
    first = _run(pf, scenario, rows=10)
    assert not pf.snapshot().awaiting_first_update
    pf.restore(start)
    np.testing.assert_array_equal(_run(pf, scenario, rows=10)[0], first[0])
    pf.reset(preset.initial_state, preset.initial_covariance)
    np.testing.assert_array_equal(_run(pf, scenario, rows=10)[0], first[0])
    with pytest.raises(ValueError, match='RegularisedParticleFilter'):
        pf.restore(ParticleFilter(preset.model, preset.initial_state,
                                  preset.initial_covariance, n_particles=300).snapshot())


def test_predict_ahead_gives_exact_moments_and_changes_nothing():
    """predict_ahead = (F x̄, F P Fᵀ + Q); particles, weights, generator, flag untouched."""
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 2)
    pf = _pf(preset, n_particles=500, seed=1)
    _run(pf, scenario, rows=5)
    before = pf.snapshot()
    x, P = pf.predict_ahead(2.0)
    F = preset.dynamics.F(2.0)
    np.testing.assert_allclose(x, F @ pf.mean, rtol=1e-14)
    np.testing.assert_allclose(P, F @ pf.covariance @ F.T + preset.dynamics.Q(2.0),
                               rtol=1e-12)
    after = pf.snapshot()
    for a, b in zip(before, after):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b


def test_rejected_steps_leave_everything_unchanged():
    """Bad z, R or dt raise ValueError; particles, weights, generator, counters stay."""
    preset = load_preset('range-bearing')
    for updates in (0, 1):   # before the first update (measurement draw) and after
        pf = _pf(preset, n_particles=500, seed=3)
        pf.predict(0.2)
        for _ in range(updates):
            pf.update([0.93, 50.0])
            pf.predict(0.2)
        before = pf.snapshot()
        for call, message in [
                (lambda: pf.update([np.nan, 50.0]), 'z must be finite'),
                (lambda: pf.update([0.9]), 'z must have length 2'),
                (lambda: pf.update([0.9, 50.0], R=np.zeros((2, 2))),
                 'R must be positive definite'),
                (lambda: pf.update([0.9, 1e300], R=np.diag([1e-300, 1e-300])),
                 'every particle has zero likelihood'),
                (lambda: pf.predict(-0.1), 'dt must be >= 0')]:
            with pytest.raises(ValueError, match=message):
                call()
            after = pf.snapshot()
            for a, b in zip(before, after):
                if isinstance(a, np.ndarray):
                    np.testing.assert_array_equal(a, b)
                else:
                    assert a == b


def test_shapes_and_parameters_are_checked():
    """Estimates have the state's shapes; bad kernels, counts, seeds raise ValueError."""
    preset = load_preset('range-bearing')
    pf = _pf(preset, n_particles=200)
    pf.predict(0.2)
    result = pf.update([0.93, 50.0])
    assert pf.mean.shape == (4,) and pf.covariance.shape == (4, 4)
    assert pf.particles.shape == (200, 4) and pf.weights.shape == (200,)
    assert result.innovation.shape == (2,) and result.innovation_covariance.shape == (2, 2)
    assert result.gain.shape == (4, 2) and result.nis >= 0.0
    for kwargs, message in [({'kernel': 'box'}, 'kernel must be one of'),
                            ({'n_particles': 0}, 'n_particles must be an integer'),
                            ({'seed': -1}, 'seed must be a non-negative integer'),
                            ({'resample_threshold': 1.5}, 'resample_threshold must be in'),
                            ({'roughening': -0.1}, 'roughening must be a number >= 0')]:
        with pytest.raises(ValueError, match=message):
            _pf(preset, **kwargs)
    with pytest.raises(ValueError, match='P0 must be positive semi-definite'):
        _pf(preset, P0=-np.eye(4))


@pytest.mark.parametrize('P0,R', [
    ([0.0, 0.0, 0.0, 0.0], None),
    ([1e-30, 1e-30, 1e-30, 1e-30], None),
    (None, [[1e-20, 0.0], [0.0, 1e-12]]),
    ([1e-30, 1e3, 1e-30, 1e3], [[1e-20, 0.0], [0.0, 1e-12]]),
])
def test_degenerate_inputs_never_crash(P0, R):
    """
    Zero or near-singular P0, tiny R: every step succeeds and the state stays finite.

    (30 rows: a 1e-10-rad bearing makes every update use all the tempering stages.)
    """
    data = yaml.safe_load(open(load_preset('range-bearing').source, encoding='utf-8'))
    if P0 is not None:
        data['initial_covariance'] = P0
    if R is not None:
        data['R'] = R
    preset = preset_from_mapping(data)
    pf = _pf(preset, n_particles=300, seed=1)
    means, covariances = _run(pf, scenario_for_preset('range-bearing', 2), rows=30)
    assert np.all(np.isfinite(means)) and np.all(np.isfinite(covariances))
    for P in covariances:
        assert np.min(np.linalg.eigvalsh(P)) >= -1e-12 * max(1.0, np.max(np.abs(P)))


@pytest.mark.parametrize('kernel', ['epanechnikov', 'gordon'])
def test_other_kernels_run_and_are_reproducible(kernel):
    """The Epanechnikov and Gordon kernels run the seed, reproducibly."""
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 0)
    runs = [_run(_pf(preset, n_particles=300, seed=8, kernel=kernel), scenario, rows=20)[0]
            for _ in range(2)]
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.all(np.isfinite(runs[0]))
