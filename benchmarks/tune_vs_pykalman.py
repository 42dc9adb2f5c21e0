"""
``kf-train tune``'s maximum likelihood against pykalman's EM, on the same data and model.

Model: seed 000's train filter (constant velocity, position measured) with white-noise
acceleration q and measurement variance R, the prior x0 = [z₀, 0], P0 = diag(R0, 10⁴)
holding at the first row's time (pykalman's convention: its first observation is
corrected without a prediction). Data: :func:`kf_train.sim.white_noise_acceleration_scenario`
with known q and R. Three estimators, each on the same rows:

* ``kf-train tune``: :func:`kf_train.tune.noise_fit.estimate_noise` (L-BFGS-B on the exact
  log-likelihood of the innovations of kf_train's vectorised filter);
* EM on the same structured model, Q = q·Q₁(dt): pykalman's own E-step (its filter,
  RTS smoother and lag-one covariances) and its M-step statistics, projected on the
  model (q = ½ tr(Q₁⁻¹ Σ̂) maximises the expected log-likelihood for Q = q·Q₁, R as
  pykalman updates it). Its fixed point is the maximum-likelihood estimate, so it
  must agree with ``tune``: that is the oracle;
* pykalman's own ``KalmanFilter.em`` (a full 2×2 Q and R, more freedom than the
  model): its R, and the q each entry of its Q implies (Q₀₀·3/dt³, Q₀₁·2/dt², Q₁₁/dt).

Then the coverage of ``tune``'s 95 % intervals over seeded Monte-Carlo runs with the
truth known. Run: ``.venv/bin/python benchmarks/tune_vs_pykalman.py [--runs 200]``.
It prints figures; nothing is asserted (test/unit/test_tuning.py holds the assertions).
"""

import argparse
import math
import os
import sys
import time
from typing import NamedTuple

from kf_train.batch import (
    make_segment, NoiseParameterisation, NoiseSetting, noisy_preset, TuningProblem)
from kf_train.presets import load_preset
from kf_train.sim import white_noise_acceleration_scenario
from kf_train.tune import estimate_noise
import numpy as np

DT_S = 0.1
P0_VELOCITY = 1e4     # m²/s²: a wide prior on the velocity


class Case(NamedTuple):
    """Data, and the tuning problem in pykalman's convention (prior at the first row)."""

    preset: object
    problem: TuningProblem
    z: np.ndarray
    x0: np.ndarray
    P0: np.ndarray


def make_case(q: float, R: float, rows: int, seed: int) -> Case:
    """Return simulated rows with known q and R and the matching tuning problem."""
    preset = load_preset('train')
    scenario = white_noise_acceleration_scenario(q, math.sqrt(R), rows, dt_s=DT_S, seed=seed)
    z = scenario.z
    x0, P0 = np.array([z[0, 0], 0.0]), np.diag([R, P0_VELOCITY])
    preset = preset.__class__(**{**preset.__dict__, 'initial_state': x0,
                                 'initial_covariance': P0})
    problem = TuningProblem(preset, [make_segment(preset, scenario.t_s, z)],
                            initialization='prior', prior_lead_s=0.0)
    return Case(preset, problem, z, x0, P0)


def pykalman_filter(case: Case, setting: NoiseSetting):
    """Return pykalman's KalmanFilter for the case's model with ``setting``'s noise."""
    from pykalman import KalmanFilter
    preset = noisy_preset(case.preset, setting.process_noise_density,
                          setting.measurement_variances)
    return KalmanFilter(transition_matrices=preset.dynamics.F(DT_S),
                        observation_matrices=preset.model.H,
                        transition_covariance=preset.dynamics.Q(DT_S),
                        observation_covariance=preset.model.R,
                        initial_state_mean=case.x0, initial_state_covariance=case.P0)


def structured_em(case: Case, q: float, R: float, max_iterations: int = 3000,
                  tolerance: float = 1e-7):
    """
    Return (q, R, iterations) of EM for Q = q·Q₁(dt) with pykalman's E-step.

    The E-step (filter, smoother, lag-one covariances) and the M-step statistics
    (Σ̂ = pykalman's transition-covariance update, R̂ its observation-covariance update)
    are pykalman's; the M-step for q is q = ½ tr(Q₁⁻¹ Σ̂). Stops when log q and log R
    change by less than ``tolerance`` in an iteration.
    """
    from pykalman import standard
    F = case.preset.dynamics.F(DT_S)
    Q1 = noisy_preset(case.preset, 1.0).dynamics.Q(DT_S)
    H = case.preset.model.H
    for iteration in range(1, max_iterations + 1):
        predicted, predicted_P, _, filtered, filtered_P = standard._filter(
            F, H, q * Q1, np.array([[R]]), np.zeros(2), np.zeros(1), case.x0, case.P0, case.z)
        smoothed, smoothed_P, gains = standard._smooth(F, filtered, filtered_P, predicted,
                                                       predicted_P)
        pairs = standard._smooth_pair(smoothed_P, gains)
        sigma = standard._em_transition_covariance(F, np.zeros(2), smoothed, smoothed_P, pairs)
        R_new = float(standard._em_observation_covariance(case.z, np.zeros(1), H, smoothed,
                                                          smoothed_P)[0, 0])
        q_new = 0.5 * float(np.trace(np.linalg.solve(Q1, sigma)))  # argmax E[ℓ] for q·Q₁
        change = max(abs(math.log(q_new / q)), abs(math.log(R_new / R)))
        q, R = q_new, R_new
        if change < tolerance:
            break
    return q, R, iteration


def tune(case: Case):
    """Return tune's result for the case (q and R estimated)."""
    return estimate_noise(case.problem, NoiseParameterisation(case.problem))


def _compare(q_true: float, R_true: float, rows: int, seed: int, tolerance: float) -> None:
    """Print one case: the three estimators, their time and their log-likelihoods."""
    case = make_case(q_true, R_true, rows, seed)
    start, cpu = time.perf_counter(), time.process_time()
    result = tune(case)
    t_tune, c_tune = time.perf_counter() - start, time.process_time() - cpu
    (q_e, q_lo, q_hi), (r_e, r_lo, r_hi) = [(e.value, e.low, e.high) for e in result.estimates]
    start, cpu = time.perf_counter(), time.process_time()
    q_em, R_em, iterations = structured_em(case, 1.0, 1.0, tolerance=tolerance)
    t_em, c_em = time.perf_counter() - start, time.process_time() - cpu
    ll_em = case.problem.log_likelihood(NoiseSetting(q_em, (R_em,)))
    ll_pk = pykalman_filter(case, result.setting).loglikelihood(case.z)
    kf = pykalman_filter(case, NoiseSetting(1.0, (1.0,)))
    start, cpu = time.perf_counter(), time.process_time()
    kf = kf.em(case.z, n_iter=iterations,
               em_vars=['transition_covariance', 'observation_covariance'])
    t_full, c_full = time.perf_counter() - start, time.process_time() - cpu
    Q = kf.transition_covariance
    implied = (Q[0, 0] * 3 / DT_S ** 3, Q[0, 1] * 2 / DT_S ** 2, Q[1, 1] / DT_S)
    print(f'\n{rows} rows, q = {q_true:g} m²/s³, R = {R_true:g} m², seed {seed}')
    print(f'  tune (L-BFGS-B)     q = {q_e:.6g} [{q_lo:.4g}, {q_hi:.4g}]  R = {r_e:.6g} '
          f'[{r_lo:.4g}, {r_hi:.4g}]  ℓ = {result.log_likelihood:.6f}  '
          f'{c_tune:.3f} s CPU, {t_tune:.3f} s wall ({result.evaluations} likelihood '
          'evaluations)')
    print(f'  EM, same model      q = {q_em:.6g}  R = {R_em:.6g}  ℓ = {ll_em:.6f}  '
          f'{c_em:.3f} s CPU, {t_em:.3f} s wall ({iterations} iterations to |Δlog| < '
          f'{tolerance:g}): {c_em / c_tune:.0f}x the CPU time of tune')
    print(f'    |Δq|/q = {abs(q_em - q_e) / q_e:.2e} ({abs(q_em - q_e) / (q_hi - q_lo):.2e} of '
          f'the interval), |ΔR|/R = {abs(R_em - r_e) / r_e:.2e}; ℓ(tune) − ℓ(EM) = '
          f'{result.log_likelihood - ll_em:.2e}; pykalman.loglikelihood at the estimate '
          f'− tune ℓ = {ll_pk - result.log_likelihood:.2e}')
    print(f'  pykalman em (full Q) R = {kf.observation_covariance[0, 0]:.6g}  q implied by '
          f'Q00, Q01, Q11 = {implied[0]:.4g}, {implied[1]:.4g}, {implied[2]:.4g}  '
          f'{c_full:.3f} s CPU, {t_full:.3f} s wall ({iterations} iterations)')


def coverage(q_true: float, R_true: float, rows: int, runs: int) -> None:
    """
    Print how often tune's 95 % intervals hold the truth over seeded runs.

    Also for the natural-scale delta-method interval θ̂ ± 1.96·se(θ) (se = θ̂·se(log θ)),
    which tune reports as the standard error but not as the interval, and the
    estimates' mean and spread against the truth.
    """
    hits, delta_hits = np.zeros(2, dtype=int), np.zeros(2, dtype=int)
    values = np.zeros((runs, 2))
    start = time.process_time()
    for run in range(runs):
        case = make_case(q_true, R_true, rows, 1000 + run)
        result = tune(case)
        for i, (e, truth) in enumerate(zip(result.estimates, (q_true, R_true))):
            hits[i] += e.low <= truth <= e.high
            delta_hits[i] += abs(e.value - truth) <= 1.959964 * e.std_error
            values[run, i] = e.value
    seconds = time.process_time() - start
    sd = math.sqrt(runs * 0.95 * 0.05)
    print(f'\ncoverage of the 95 % intervals over {runs} runs of {rows} rows '
          f'(q = {q_true:g}, R = {R_true:g}, seeds 1000..{999 + runs}; binomial sd '
          f'{sd:.1f} runs):')
    for i, name in enumerate(('q', 'R')):
        print(f'  {name}: exp(log θ̂ ± 1.96 se) {hits[i]}/{runs} = {hits[i] / runs:.1%}; '
              f'θ̂ ± 1.96 se(θ̂) {delta_hits[i]}/{runs} = {delta_hits[i] / runs:.1%}; '
              f'estimates {np.mean(values[:, i]):.4g} ± {np.std(values[:, i]):.3g} (sd)')
    print(f'  {seconds / runs:.3f} s CPU per run')


def main(argv=None) -> int:
    """Print the comparison and the coverage."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--runs', type=int, default=200, help='Monte-Carlo runs (200)')
    parser.add_argument('--rows', type=int, default=300, help='rows per run (300)')
    parser.add_argument('--part', choices=('all', 'compare', 'coverage'), default='all',
                        help='what to run (all)')
    args = parser.parse_args(argv)
    import scipy.optimize  # noqa: F401 (imported once here, not inside the first timing)
    print(f'load average at start: {" ".join(f"{x:.2f}" for x in os.getloadavg())} '
          f'on {os.cpu_count()} CPUs', flush=True)
    if args.part in ('all', 'compare'):
        for q, R, rows, tolerance in ((0.5, 1.0, 500, 1e-7), (0.05, 1.0, 500, 1e-6),
                                      (0.5, 1.0, 2000, 1e-5)):
            _compare(q, R, rows, seed=1, tolerance=tolerance)
    if args.part in ('all', 'coverage'):
        coverage(0.5, 1.0, args.rows, args.runs)
    return 0


if __name__ == '__main__':
    sys.exit(main())
