"""
Tests of the noise estimation: likelihood, estimates, checks and the running suggestion.

The likelihood, checks and running suggestion are kf_train.batch's, the estimates
kf_train.tune.noise_fit's.

The likelihood is held to independent code: the streaming estimator's innovations
(the node's filter), pykalman's log-likelihood, and EM on the same model built from
pykalman's E-step (benchmarks/tune_vs_pykalman.py), whose fixed point is the
maximum-likelihood estimate. The intervals are held to their coverage over seeded
Monte-Carlo runs, and the estimates to a round trip through the estimator.
"""

import importlib.util
import math
import os
import subprocess
import sys

from kf_train.batch import (
    make_segment, nis_consistency, NoiseParameterisation, NoiseSetting, noisy_preset,
    prediction_errors, RunningNoiseEstimate, TuningProblem)
from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.filters import chi2_mean_bounds, NS_PER_S, WhiteNoiseAcceleration
from kf_train.presets import load_preset
from kf_train.sim import car_scenario, TrainSimulation, white_noise_acceleration_scenario
from kf_train.tune import estimate_noise
import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TRAIN = load_preset('train')


def _oracle():
    """Return benchmarks/tune_vs_pykalman.py as a module (the EM oracle lives there)."""
    path = os.path.join(REPO, 'benchmarks', 'tune_vs_pykalman.py')
    spec = importlib.util.spec_from_file_location('tune_vs_pykalman', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _wna_problem(q, R, rows, seed, **kwargs):
    """Return a tuning problem of the train preset on data with known q and R."""
    scenario = white_noise_acceleration_scenario(q, math.sqrt(R), rows, seed=seed)
    segment = make_segment(TRAIN, scenario.t_s, scenario.z, truth=scenario.truth)
    return TuningProblem(TRAIN, [segment], **kwargs)


# ---------------------------------------------------------------------------
# The model and the likelihood are the node's
# ---------------------------------------------------------------------------

def test_noisy_preset_adds_the_nodes_white_noise_acceleration():
    """Q(dt) = preset's + q·[[dt³/3, dt²/2], [dt²/2, dt]] bit for bit; R replaced; input kept."""
    car = load_preset('car-exact')
    for preset in (TRAIN, car):
        tuned = noisy_preset(preset, 0.37, [2.5])
        for dt in (0.1, 0.25, 3.0):
            expected = preset.dynamics.Q(dt) + WhiteNoiseAcceleration(0.37)(dt)
            assert np.allclose(tuned.dynamics.Q(dt), expected, rtol=1e-15, atol=0.0)
            assert np.array_equal(tuned.model.Q(dt), tuned.dynamics.Q(dt))
        assert tuned.model.R.tolist() == [[2.5]]
        assert preset.dynamics.continuous is None and preset.model.R.tolist() == [[1.0]]
    with pytest.raises(ValueError, match='process_noise_density must be 0'):
        noisy_preset(load_preset('robot'), 0.1)
    with pytest.raises(ValueError, match='measurement variances must be > 0'):
        noisy_preset(TRAIN, 0.1, [0.0])


def _estimator_innovations(settings, t_s, z, velocity=None):
    """Return the streaming estimator's (y, S) of every update, the first one skipped."""
    estimator = StreamEstimator(settings)
    ys, Ss = [], []
    for k, t in enumerate(t_s):
        extra = {} if velocity is None else {'velocity_mps': velocity[k],
                                             'velocity_variance_m2s2': 1.0}
        step = estimator.process(int(round(t * NS_PER_S)), z[k], 1.0, **extra)
        if step.update is not None:
            ys.append(step.update.innovation)
            Ss.append(step.update.innovation_covariance)
    return np.array(ys), np.array(Ss)


@pytest.mark.parametrize('initialization', ['first_measurement', 'prior'])
def test_innovations_are_the_streaming_estimators(initialization):
    """The likelihood's innovations equal StreamEstimator's (the node's filter) to 1e-9."""
    scenario = white_noise_acceleration_scenario(0.8, 0.7, 300, seed=3)
    problem = TuningProblem(TRAIN, [make_segment(TRAIN, scenario.t_s, scenario.z)],
                            initialization=initialization)
    setting = NoiseSetting(0.8, (0.49,))
    ours = problem.innovations(setting)
    y, S = _estimator_innovations(EstimatorSettings(
        preset='train', gate_probability=1.0,
        initialization=initialization, process_noise_density=0.8, measurement_variance=0.49),
        scenario.t_s, scenario.z[:, 0])
    # Both are the same arithmetic in another order: differences are rounding, ~1e-14
    # relative to the state's scale (positions up to ~300 m), far below 1e-9.
    assert ours.y.shape == y.shape and ours.S.shape == S.shape
    assert np.max(np.abs(ours.y - y)) <= 1e-9 * max(1.0, np.max(np.abs(scenario.z)))
    assert np.max(np.abs(ours.S - S) / S) <= 1e-9


def test_innovations_of_a_two_dimensional_measurement():
    """cv-position-velocity (position and velocity measured) matches the estimator too."""
    preset = load_preset('cv-position-velocity')
    rng = np.random.default_rng(5)
    t = np.arange(1, 201, dtype=float)
    z = np.column_stack([2.0 * t + 3.0 * rng.standard_normal(200),
                         2.0 + rng.standard_normal(200)])
    problem = TuningProblem(preset, [make_segment(preset, t, z)])
    ours = problem.innovations(NoiseSetting(0.05, (9.0, 1.0)))
    y, S = _estimator_innovations(EstimatorSettings(
        gate_probability=1.0,
        preset='cv-position-velocity', process_noise_density=0.05, measurement_variance=9.0,
        measurement_velocity_variance=1.0), t, z[:, 0], velocity=z[:, 1])
    assert np.max(np.abs(ours.y - y)) <= 1e-9 * 400.0
    assert np.max(np.abs(ours.S - S) / np.abs(S).max()) <= 1e-9


def test_log_likelihood_equals_pykalmans():
    """ℓ equals pykalman's KalmanFilter.loglikelihood on the same model, to 1e-9 relative."""
    oracle = _oracle()
    case = oracle.make_case(0.5, 1.0, 300, seed=2)
    for setting in (NoiseSetting(0.5, (1.0,)), NoiseSetting(3e-4, (0.2,)),
                    NoiseSetting(40.0, (5.0,))):
        ours = case.problem.log_likelihood(setting)
        theirs = oracle.pykalman_filter(case, setting).loglikelihood(case.z)
        # Two implementations of the same sum of ~300 terms of size ~1: they differ
        # by rounding, ~1e-13 relative.
        assert abs(ours - theirs) <= 1e-9 * abs(theirs), (setting, ours, theirs)


def test_segments_add_up():
    """Several objects share the noise: ℓ of the bank is the sum over the objects."""
    scenarios = [white_noise_acceleration_scenario(0.5, 1.0, n, seed=s)
                 for n, s in ((120, 1), (80, 2), (1, 3))]
    segments = [make_segment(TRAIN, s.t_s, s.z) for s in scenarios]
    setting = NoiseSetting(0.4, (1.1,))
    together = TuningProblem(TRAIN, segments)
    alone = [TuningProblem(TRAIN, [s]) for s in segments[:2]]
    assert together.rows == 119 + 79
    assert together.log_likelihood(setting) == pytest.approx(
        sum(p.log_likelihood(setting) for p in alone), rel=1e-12)


# ---------------------------------------------------------------------------
# The estimates
# ---------------------------------------------------------------------------

@pytest.mark.slow
def test_estimates_agree_with_em_on_the_same_model():
    """
    EM with pykalman's E-step converges to tune's estimate, inside tune's intervals.

    EM's fixed point is the maximum of ℓ. It stops when an iteration moves log q and
    log R by < 1e-5; at its linear rate λ (≈ 0.97 here) the distance left is about
    1e-5·λ/(1 − λ) ≈ 3e-4 in log, against interval widths of ~1 (q) and ~0.3 (R) in
    log: the two must agree to 1e-2 of the interval width, and tune's ℓ be no lower
    than EM's (beyond ℓ's rounding, 1e-8). (pykalman's E-step is slow: ~0.03 s an
    iteration here.)
    """
    oracle = _oracle()
    case = oracle.make_case(0.5, 1.0, 200, seed=4)
    result = oracle.tune(case)
    q_em, R_em, iterations = oracle.structured_em(case, 1.0, 1.0, tolerance=1e-5)
    (q, R) = result.estimates
    assert iterations < 5000
    assert q.low <= q_em <= q.high and R.low <= R_em <= R.high
    assert abs(q_em - q.value) <= 1e-2 * (q.high - q.low)
    assert abs(R_em - R.value) <= 1e-2 * (R.high - R.low)
    ll_em = case.problem.log_likelihood(NoiseSetting(q_em, (R_em,)))
    assert result.log_likelihood >= ll_em - 1e-8


RUNS = 200
# Coverage: if the 95 % intervals are right, the number of the RUNS seeded runs whose
# interval holds the truth is Binomial(RUNS, 0.95): mean 190, sd √(200·0.95·0.05) = 3.1.
# Accept the counts outside the two 0.05 % tails of Binomial(200, 0.95): [179, 198]
# (P(X <= 178) = 0.00048, P(X >= 199) = 0.0004; scipy.stats.binom, checked below).
# Right intervals fail it with probability < 0.1 % (the seed is fixed, so it passes or
# fails for good). Intervals 30 % too narrow (z = 1.37: coverage ≈ 85 %) fail it with
# probability 96 %, 50 % too wide (z = 2.94: ≈ 99.7 %) with probability 88 %.
# Measured (2026-11): these seeds give q 183, R 191; seeds 1000..1199 (the benchmark)
# q 189, R 188. Over the 400 runs q's log-Wald interval covers 93.0 %: slightly
# liberal at 300 rows (30 s of data), as an asymptotic interval may be.
COVERAGE_BOUNDS = (179, 198)


def test_coverage_bounds_are_the_binomial_tails():
    """The acceptance region is Binomial(200, 0.95)'s central 99.9 %."""
    from scipy import stats
    low, high = COVERAGE_BOUNDS
    assert stats.binom.cdf(low - 1, RUNS, 0.95) < 0.0005 <= stats.binom.cdf(low, RUNS, 0.95)
    assert stats.binom.sf(high, RUNS, 0.95) < 0.0005 <= stats.binom.sf(high - 1, RUNS, 0.95)
    # and they reject the mis-sized intervals named above
    assert stats.binom.sf(low - 1, RUNS, 0.85) < 0.05 and stats.binom.sf(high, RUNS, 0.997) > 0.85


@pytest.mark.slow
def test_intervals_cover_the_truth_95_percent_of_the_time():
    """Over 200 seeded runs with known q and R, the 95 % intervals hold them ~95 % of times."""
    hits = np.zeros(2, dtype=int)
    for run in range(RUNS):
        problem = _wna_problem(0.5, 1.0, 300, seed=10_000 + run)
        result = estimate_noise(problem, NoiseParameterisation(problem))
        for i, (estimate, truth) in enumerate(zip(result.estimates, (0.5, 1.0))):
            hits[i] += estimate.low <= truth <= estimate.high
    low, high = COVERAGE_BOUNDS
    assert low <= hits[0] <= high and low <= hits[1] <= high, hits


def test_no_process_noise_is_reported_as_compatible_with_zero():
    """Seed 000's constant-velocity train: q = 0 with a profile bound; R's interval holds σ²."""
    series = TrainSimulation(noise_std_m=0.5, seed=1).generate(400)
    problem = TuningProblem(TRAIN, [make_segment(TRAIN, series.t_s,
                                                 series.measured_position_m)])
    result = estimate_noise(problem, NoiseParameterisation(problem))
    q, R = result.estimates
    assert q.method == 'profile' and q.low == 0.0 and 0.0 < q.high < 1e-2
    assert result.setting.process_noise_density == q.value
    # R is determined although q sits at its boundary. With q = 0 its estimate is a
    # residual variance of N = 400 rows: sd ≈ R·√(2/N) = 0.0177. (Its 95 % interval
    # holds 0.25 in 27 of seeds 0..29; for seed 1 R̂ is 2.4 sd low, so check in sd.)
    sd = 0.25 * math.sqrt(2.0 / 400)
    assert R.method == 'wald-log' and abs(R.value - 0.25) <= 4.0 * sd
    assert R.std_error == pytest.approx(R.value * math.sqrt(2.0 / 400), rel=0.2)


def test_initial_state_is_estimated_in_prior_mode():
    """With the prior far off, the estimated initial state lies near the truth."""
    scenario = white_noise_acceleration_scenario(0.05, 1.0, 300, seed=8,
                                                 initial_state=(50.0, 20.0))
    problem = TuningProblem(TRAIN, [make_segment(TRAIN, scenario.t_s, scenario.z)],
                            initialization='prior', initial_covariance=np.eye(2) * 1e-4)
    parameterisation = NoiseParameterisation(problem, initial_state=True)
    result = estimate_noise(problem, parameterisation)
    by_symbol = {e.parameter.symbol: e for e in result.estimates}
    # The truth at t0 = t₁ − 0.1 s (the node's prior lead) is (50, 20).
    assert by_symbol['x0[position]'].low <= 50.0 <= by_symbol['x0[position]'].high
    assert by_symbol['x0[velocity]'].low <= 20.0 <= by_symbol['x0[velocity]'].high
    assert result.log_likelihood > problem.log_likelihood(NoiseSetting(0.05, (1.0,))) + 100


def test_parameterisation_refuses_what_cannot_be_estimated():
    """The q needs [position, velocity], the initial state prior mode; names are checked."""
    robot = load_preset('robot')
    rows = np.arange(1, 51) * 0.1
    problem = TuningProblem(robot, [make_segment(robot, rows, np.sin(rows), np.cos(rows))])
    with pytest.raises(ValueError, match='q cannot be estimated for preset'):
        NoiseParameterisation(problem)
    assert [p.name for p in NoiseParameterisation(problem, process_noise=False).parameters] \
        == ['measurement_variance']
    train = _wna_problem(0.5, 1.0, 50, seed=1)
    with pytest.raises(ValueError, match='only with the prior'):
        NoiseParameterisation(train, initial_state=True)
    with pytest.raises(ValueError, match="'speed' is not a measurement"):
        NoiseParameterisation(train, measurement_noise=['speed'])
    with pytest.raises(ValueError, match='nothing to estimate'):
        NoiseParameterisation(train, process_noise=False, measurement_noise=False)
    with pytest.raises(ValueError, match='nonlinear measurement model'):
        TuningProblem(load_preset('range-bearing'), [])
    with pytest.raises(ValueError, match='no innovations'):
        TuningProblem(TRAIN, [make_segment(TRAIN, [0.1], [1.0])])


# ---------------------------------------------------------------------------
# The checks, and the round trip through the estimator
# ---------------------------------------------------------------------------

def test_consistency_and_prediction_checks_see_a_wrong_q():
    """With q = 0 on data with q = 0.5: NIS too large, not white, worse 2-s predictions."""
    problem = _wna_problem(0.5, 1.0, 1000, seed=6)
    wrong, right = NoiseSetting(0.0, (1.0,)), NoiseSetting(0.5, (1.0,))
    bad, good = (nis_consistency(problem.innovations(s)) for s in (wrong, right))
    assert bad.verdict == 'noise too small' and not bad.white
    assert good.consistent and good.white
    low, high = chi2_mean_bounds(999, 1, 0.99)
    assert (good.low, good.high) == (low, high)
    too_large = nis_consistency(problem.innovations(NoiseSetting(50.0, (10.0,))))
    assert too_large.verdict == 'noise too large'
    before, after = (prediction_errors(problem, s, 2.0) for s in (wrong, right))
    assert after.rmse['position'] < 0.5 * before.rmse['position']
    # rows whose t + 2 s is past the last truth (the last 20) are left out
    assert after.count == 999 - 20
    assert prediction_errors(TuningProblem(TRAIN, [make_segment(
        TRAIN, problem.segments[0].t_s, problem.segments[0].z)]), right, 2.0) is None


def _nis_of_the_estimator(settings, t_s, z, variance_m2):
    """Return the estimator's NIS over a stream (the initialising row has none)."""
    estimator = StreamEstimator(settings)
    return np.array([step.update.nis for step in (
        estimator.process(int(round(t * NS_PER_S)), float(v), variance_m2)
        for t, v in zip(t_s, z)) if step.update is not None])


@pytest.mark.parametrize('q_true, noise_std_m', [(0.0, 0.5), (0.5, 1.0)])
def test_round_trip_tuned_estimator_passes_the_nis_check(q_true, noise_std_m):
    """
    Tune on one simulated run, run the estimator with the tuned settings on a fresh run.

    Its mean NIS must lie inside the χ² 99 % bounds; the untuned defaults must not
    (q = 0 with R from a sensor that claims σ = 2 m where it has σ = 0.5 or 1 m).
    q = 0 is seed 000's simulator (kf_train.sim.TrainSimulation), q = 0.5 the random-force train.
    """
    def run(seed, rows):
        if q_true == 0.0:
            s = TrainSimulation(noise_std_m=noise_std_m, seed=seed).generate(rows)
            return s.t_s, s.measured_position_m
        s = white_noise_acceleration_scenario(q_true, noise_std_m, rows, seed=seed)
        return s.t_s, s.z[:, 0]
    t, z = run(21, 2000)
    problem = TuningProblem(TRAIN, [make_segment(TRAIN, t, z)])
    setting = estimate_noise(problem, NoiseParameterisation(problem)).setting
    tuned = EstimatorSettings(preset='train', gate_probability=1.0,
                              process_noise_density=setting.process_noise_density,
                              measurement_variance=setting.measurement_variances[0])
    t, z = run(22, 2000)
    nis = _nis_of_the_estimator(tuned, t, z, 4.0)
    low, high = chi2_mean_bounds(len(nis), 1, 0.99)
    assert low <= np.mean(nis) <= high
    untuned = _nis_of_the_estimator(EstimatorSettings(preset='train', gate_probability=1.0),
                                    t, z, 4.0)
    assert not low <= np.mean(untuned) <= high


# ---------------------------------------------------------------------------
# The running suggestion for /diagnostics
# ---------------------------------------------------------------------------

EPOCH_NS = 1_790_000_000 * NS_PER_S


def _feed(estimate, scenario, start=0, stop=None):
    """Add a scenario's rows to a running estimate, stamped from an epoch."""
    for t, z in zip(scenario.t_s[start:stop], scenario.z[start:stop]):
        estimate.add(EPOCH_NS + int(round(t * NS_PER_S)), z)


def test_running_estimate_suggests_the_windows_q():
    """A window of q = 2 data suggests q near 2; then q = 0 data suggest 0 with a bound."""
    estimate = RunningNoiseEstimate(TRAIN, window=300, min_samples=50)
    moving = white_noise_acceleration_scenario(2.0, 1.0, 300, seed=31)
    _feed(estimate, moving, stop=49)
    assert estimate.suggest([1.0]) is None          # fewer than min_samples
    _feed(estimate, moving, start=49)
    suggestion = estimate.suggest([1.0])
    assert suggestion.count == 299 and suggestion.low <= 2.0 <= suggestion.high
    # agrees with the offline estimate on the same window and R (same likelihood)
    problem = TuningProblem(TRAIN, [make_segment(TRAIN, moving.t_s, moving.z)])
    offline = estimate_noise(problem, NoiseParameterisation(problem, measurement_noise=False,
                                                            fixed=NoiseSetting(0.0, (1.0,))))
    assert suggestion.process_noise_density == pytest.approx(offline.estimates[0].value,
                                                             rel=2e-2)
    assert 'increase q' in suggestion.advice(0.01)
    assert 'decrease q about x' in suggestion.advice(200.0)
    assert 'is consistent' in suggestion.advice(2.0)
    still = white_noise_acceleration_scenario(0.0, 1.0, 300, seed=32, t0_s=100.0)
    _feed(estimate, still)                          # the window now holds only still data
    suggestion = estimate.suggest([1.0])
    assert suggestion.low == 0.0 and 0.0 < suggestion.high < 0.05
    assert 'decrease q' in suggestion.advice(2.0)


def test_running_estimate_restarts_on_an_older_stamp_and_refuses_bad_input():
    """An older stamp starts a new window; presets without q and bad sizes are refused."""
    estimate = RunningNoiseEstimate(TRAIN, window=10, min_samples=5)
    for k in range(1, 8):
        estimate.add(EPOCH_NS + k, [float(k)])
    estimate.add(EPOCH_NS, [0.0])
    assert len(estimate) == 1
    with pytest.raises(ValueError, match='no white-noise acceleration'):
        RunningNoiseEstimate(load_preset('robot'))
    with pytest.raises(ValueError, match='min_samples'):
        RunningNoiseEstimate(TRAIN, window=10, min_samples=20)


def test_running_estimate_imports_no_scipy():
    """The nodes may use the running estimate: it must not import scipy."""
    code = ('import sys; from kf_train.batch import RunningNoiseEstimate; '
            'from kf_train.presets import load_preset; '
            'e = RunningNoiseEstimate(load_preset("train"), min_samples=10)\n'
            'for k in range(40): e.add(10**9 + k * 10**8, [0.3 * k + (k % 3)])\n'
            'e.suggest([1.0]); print("scipy" in sys.modules)')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == 'False'


def test_running_estimate_with_a_control_input():
    """car-exact: its own noise explains its scenario, so the extra q suggested is ~0."""
    preset = load_preset('car-exact')
    scenario = car_scenario(seed=4, n_samples=300, exact=True)
    estimate = RunningNoiseEstimate(preset, window=300)
    with pytest.raises(ValueError, match='u must be given exactly'):
        estimate.add(EPOCH_NS, scenario.z[0])
    for t, z, u in zip(scenario.t_s, scenario.z, scenario.u):
        estimate.add(EPOCH_NS + int(round(t * NS_PER_S)), z, u)
    suggestion = estimate.suggest([1.0])
    assert suggestion.low == 0.0 and math.isfinite(suggestion.high)
    # the same likelihood offline: q compatible with 0, the same profile bound (R fixed)
    problem = TuningProblem(preset, [make_segment(preset, scenario.t_s, scenario.z,
                                                  scenario.u)])
    offline = estimate_noise(problem, NoiseParameterisation(problem, measurement_noise=False,
                                                            fixed=NoiseSetting(0.0, (1.0,))))
    assert offline.estimates[0].method == 'profile'
    # both bounds are solved to 1 % (running: bisection in log q to 1e-2) or better
    assert suggestion.high == pytest.approx(offline.estimates[0].high, rel=2e-2)
