"""
Monte-Carlo consistency of the core estimator: NEES and NIS against their χ² bounds.

The truth is drawn from the very model the filter assumes (constant velocity driven by
white-noise acceleration of density q, position measured with variance R, initial
state drawn from the prior). Then (Bar-Shalom, Li & Kirubarajan, §5.4):

* NEES at the last step, eᵀ P⁻¹ e, is χ²(2) in each run; over N independent runs its
  sum is χ²(2N);
* NIS is χ²(1) at every step and white in time, so its sum over N runs and K steps is
  χ²(NK).

The test passes when both averages lie inside their two-sided 99% bounds, and checks
that it can fail: with Q or R mis-set by 10× either way, the averages leave the bounds
in the direction the mis-setting predicts (too small noise: too large NEES/NIS). The
seed is fixed, so the outcome is reproducible; for a matched filter each average
lies outside its bounds for 1% of seeds by construction.
"""

import dataclasses

from kf_train.estimator import EstimatorSettings, NS_PER_S, StreamEstimator
from kf_train.filters import chi2_mean_bounds, constant_velocity_F, WhiteNoiseAcceleration
import numpy as np
import pytest

RUNS = 100
STEPS = 40
DT_S = 1.0
Q_DENSITY = 1.0      # m²/s³: with dt = 1 s the process noise matters as much as R
R_M2 = 1.0
PRIOR_MEAN = (0.0, 10.0)
PRIOR_VARIANCES = (4.0, 1.0)
SEED = 1
MATCHED = EstimatorSettings(
    preset='train', gate_probability=1.0,
    initialization='prior', initial_state=PRIOR_MEAN, initial_covariance=PRIOR_VARIANCES,
    nominal_period_s=DT_S, process_noise_density=Q_DENSITY, measurement_variance=R_M2)


def _monte_carlo(settings):
    """Return (mean final NEES, mean NIS) of the filter over RUNS seeded runs."""
    F = constant_velocity_F(DT_S)
    Q_chol = np.linalg.cholesky(WhiteNoiseAcceleration(Q_DENSITY)(DT_S))
    nees, nis = [], []
    for run in range(RUNS):
        rng = np.random.default_rng([SEED, run])
        # The prior holds one period before the first stamp; the truth starts there.
        x = np.array(PRIOR_MEAN) + np.sqrt(PRIOR_VARIANCES) * rng.standard_normal(2)
        estimator = StreamEstimator(settings)
        for k in range(1, STEPS + 1):
            x = F @ x + Q_chol @ rng.standard_normal(2)   # x_k = F x_k-1 + w, w ~ N(0, Q)
            z = x[0] + np.sqrt(R_M2) * rng.standard_normal()  # z = H x + v, v ~ N(0, R)
            step = estimator.process(int(k * DT_S * NS_PER_S), z, R_M2)
            nis.append(step.update.nis)
        error = x - step.x
        nees.append(error @ np.linalg.solve(step.P, error))  # NEES = eᵀ P⁻¹ e
    return float(np.mean(nees)), float(np.mean(nis))


NEES_BOUNDS = chi2_mean_bounds(RUNS, 2)
NIS_BOUNDS = chi2_mean_bounds(RUNS * STEPS, 1)


def test_matched_filter_is_consistent():
    """The matched filter's average NEES and NIS lie inside their χ² 99% bounds."""
    nees, nis = _monte_carlo(MATCHED)
    assert NEES_BOUNDS[0] <= nees <= NEES_BOUNDS[1], (nees, NEES_BOUNDS)
    assert NIS_BOUNDS[0] <= nis <= NIS_BOUNDS[1], (nis, NIS_BOUNDS)


@pytest.mark.parametrize('name, factor, direction', [
    ('process_noise_density', 0.1, 'high'),
    ('process_noise_density', 10.0, 'low'),
    ('measurement_variance', 0.1, 'high'),
    ('measurement_variance', 10.0, 'low'),
])
def test_mis_set_noise_is_detected(name, factor, direction):
    """Q or R mis-set by 10× pushes both averages out of their bounds, the predicted way."""
    settings = dataclasses.replace(MATCHED, **{name: getattr(MATCHED, name) * factor})
    nees, nis = _monte_carlo(settings)
    if direction == 'high':  # the filter trusts too much: errors larger than it claims
        assert nees > NEES_BOUNDS[1] and nis > NIS_BOUNDS[1], (nees, nis)
    else:
        assert nees < NEES_BOUNDS[0] and nis < NIS_BOUNDS[0], (nees, nis)
