"""The learned measurement noise (filters.noise_adaptation) and the no-reversal update."""

import dataclasses
import math

from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.filters import (
    hold_velocity, make_rail_filter, NoiseAdaptation, NoiseScale, RailModel, RailModelParameters)
from kf_train.filters.noise_adaptation import CLIP_NIS, CLIPPED_NIS_MEAN, STEP_MAX
from kf_train.sim.rail import family_parameters, rail_scenario
import numpy as np
import pytest

NS = 1_000_000_000


@pytest.fixture(scope='module')
def run():
    """Return (t, z) of a 300-s regional run, σ = 1 m at 10 Hz (white)."""
    params = dataclasses.replace(family_parameters('regional', 11), duration_s=300.0)
    scenario, _ = rail_scenario(11, 'regional', parameters=params)
    return scenario.t_s, scenario.z[:, 0]


@pytest.mark.parametrize('kwargs', [
    {'window': -1}, {'window': 1.5}, {'window': True}, {'prior': 0}, {'scale_min': 0.0},
    {'scale_max': float('inf')}, {'scale_min': 2.0}, {'scale_max': 0.5}])
def test_bad_settings_raise(kwargs):
    with pytest.raises(ValueError):
        NoiseAdaptation(**kwargs)


def test_one_step_is_the_fisher_scoring_step_written_out():
    rule = NoiseAdaptation(window=100, prior=20)
    # First fused measurement, r = 2 with s = 1 and h = 1.5: S = 3.5, a = 2 / 3.5; the
    # prior's information 20 / 2, forgotten by 1 - 1/100, plus a² / 2.
    first = rule.learn(NoiseScale(), 0.5, 3.5, 2.0)
    a = 2.0 / 3.5
    information = 10.0 * 0.99 + 0.5 * a * a
    score = 0.5 * a * (0.25 / 3.5 / CLIPPED_NIS_MEAN - 1.0)
    assert first.information == pytest.approx(information, rel=1e-15)
    assert first.count == 1
    assert first.scale == pytest.approx(math.exp(score / information), rel=1e-15)
    # A gross fix: its NIS counts as CLIP_NIS, and the step is at most STEP_MAX.
    gross = rule.learn(first, 1e3, first.scale * 2.0 + 1.5, 2.0)
    assert gross.scale == pytest.approx(first.scale * math.exp(STEP_MAX), rel=1e-15)
    late = NoiseScale(0.5, 50.0, 100)
    a = 0.5 * 2.0 / 2.5
    information = 50.0 * 0.99 + 0.5 * a * a
    score = 0.5 * a * (CLIP_NIS / CLIPPED_NIS_MEAN - 1.0)         # below STEP_MAX
    assert rule.learn(late, 1e3, 2.5, 2.0).scale == pytest.approx(
        0.5 * math.exp(score / information), rel=1e-15)
    # The clipped NIS's mean is E[min(χ²₁, 9)] = P(χ²₃ <= 9) + 9 P(χ²₁ > 9).
    assert CLIPPED_NIS_MEAN == pytest.approx(0.99500728, abs=1e-8)
    # Off: nothing changes.
    assert NoiseAdaptation(window=0).learn(first, 9.0, 1.0, 1.0) is first


def test_a_scale_far_too_large_falls_in_log_steps():
    # Innovations far smaller than R (a cold start's hAcc of a kilometre for fixes a few
    # metres off): s falls by a whole decade in tens of fixes, where the average of
    # y² - h this replaced needed hundreds.
    rule = NoiseAdaptation(window=50, prior=10)
    state = NoiseScale()
    for _ in range(60):
        S = state.scale * 1e5 + 1.0
        state = rule.learn(state, 3.0, S, 1e5)
    assert state.scale < 0.1


def test_the_default_prior_lets_the_first_fixes_decide():
    # A cold start: r = 10⁴ m² for fixes whose scatter calls for s = 10⁻³. The prior
    # (s = 1) weighs one fix, so after 100 fixes (20 s at 5 Hz) s is within a decade of
    # 10⁻³; with the old prior of 10 fixes it was 0.033.
    state, r = NoiseScale(), 1e4
    for _ in range(100):
        S = state.scale * r + 1.0
        state = NoiseAdaptation(window=50).learn(state, math.sqrt(1e-3 * r + 1.0), S, r)
    assert state.scale < 0.01
    assert NoiseAdaptation().prior == 1


def test_the_scale_stays_within_its_bounds():
    rule = NoiseAdaptation(window=10, prior=1, scale_min=0.1, scale_max=10.0)
    state = NoiseScale()
    for _ in range(50):   # innovations far smaller than the reported variance
        state = rule.learn(state, 0.0, state.scale * 1e6, 1e6)
    assert state.scale == 0.1
    for _ in range(50):   # far larger
        state = rule.learn(state, 1e3, state.scale * 1.0, 1.0)
    assert state.scale == 10.0


@pytest.mark.parametrize('told_std_m', [2.0, 0.5])
def test_a_wrong_r_is_learned(run, told_std_m):
    # The data's σ is 1 m; the filter is told 2 m (R 4× too large) or 0.5 m (4× too
    # small). The window's average of y² - h has a relative spread of about
    # sqrt(2 / window) = 0.14 per window; the median over the run's second half lies
    # well within ±40 % of the truth, and the told R is 4× off.
    t, z = run
    filt = make_rail_filter(float(z[0]), RailModelParameters(noise_std_m=told_std_m))
    learned = []
    for k in range(1, z.size):
        filt.predict(float(t[k] - t[k - 1]))
        filt.update(float(z[k]))
        learned.append(filt.state.noise.scale * told_std_m ** 2)
    assert 0.7 <= np.median(learned[len(learned) // 2:]) <= 1.4


def test_learning_off_keeps_r_as_given(run):
    t, z = run
    filt = make_rail_filter(float(z[0]), RailModelParameters(noise_window=0))
    for k in range(1, 50):
        filt.predict(float(t[k] - t[k - 1]))
        result = filt.update(float(z[k]))
        assert filt.state.noise[:3] == NoiseScale()[:3]      # s, J, count: (the walk learns)
    assert result.innovation_covariance[0, 0] > 1.0   # S = H P Hᵀ + R, R = 1 exactly


def test_a_rewind_replays_the_learned_scale_exactly(run):
    # Out of sequence: the estimator rewinds and replays; the scale is part of the state.
    t, z = run
    stamps = [int(round(s * NS)) + NS for s in t[:120]]
    in_order, shuffled = StreamEstimator(), StreamEstimator(EstimatorSettings(history_s=5.0))
    for stamp, value in zip(stamps, z[:120]):
        in_order.process(stamp, float(value), 1.0)
    order = list(range(120))
    order[100], order[103] = order[103], order[100]
    for k in order:
        try:
            shuffled.process(stamps[k], float(z[k]), 1.0)
        except ValueError:
            pytest.fail('an out-of-sequence measurement was rejected')
    assert shuffled.noise_scale() == pytest.approx(in_order.noise_scale(), rel=1e-9)
    assert in_order.noise_scale() != 1.0


def test_hold_velocity_is_the_conditional_mean_given_v_zero():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 6))
    P = A @ A.T + np.eye(6)
    x = rng.normal(size=6)
    x[1] = -0.7
    held = hold_velocity(x, P)
    # E[x | v = 0] = x + P[:, 1] (0 - v) / P_vv
    expected = x + P[:, 1] * (0.0 - x[1]) / P[1, 1]
    np.testing.assert_allclose(held, expected, rtol=1e-12, atol=1e-15)
    assert held[1] == 0.0
    x[1] = 0.3
    assert hold_velocity(x, P) is x
    # Stacked (settings × regimes) equals one regime at a time.
    xs = rng.normal(size=(3, 4, 6))
    Ps = np.broadcast_to(P, (3, 4, 6, 6))
    stacked = hold_velocity(xs, Ps)
    for k in range(3):
        for j in range(4):
            np.testing.assert_array_equal(stacked[k, j], hold_velocity(xs[k, j], P))


def test_a_train_standing_under_drifting_fixes_never_goes_backwards():
    # A stop, then the receiver drifts back 4 m over 30 s (what a real log shows):
    # no regime's velocity, nor the estimate's, goes below 0.
    model = RailModel()
    state = model.first_estimate(100.0)
    for k in range(1, 400):
        drift = -4.0 * max(0.0, (k - 100) / 300.0)
        state = model.predict(state, 0.1)
        state, _ = model.update(state, 100.0 + drift + 0.05 * np.sin(k))
        assert state.means[:, 1].min() >= 0.0
        x, _ = model.estimate(state)
        assert x[1] >= 0.0
