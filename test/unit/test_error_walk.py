"""The receiver's error walk: its rule, its rate learned, and every engine running it alike."""

import math

from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.filters import (
    ErrorWalk, FastRailModel, numba_available, RailModel, RailModelParameters)
from kf_train.filters.error_walk import NU_CLIP, position_walked
from kf_train.filters.noise_adaptation import NoiseScale
import numpy as np
import pytest

UNIT_ROUNDOFF = 2.0 ** -53
ENGINES = [RailModel] + ([FastRailModel] if numba_available() else [])


@pytest.mark.parametrize('fields', [
    {'rate_hz': -1.0}, {'rate_hz': math.inf}, {'learning_rate': -0.1},
    {'rate_hz': 0.5, 'rate_min_hz': 1.0}, {'rate_hz': 5.0, 'rate_max_hz': 3.0},
    {'rate_min_hz': 0.0}, {'rate_hz': True}])
def test_figures_out_of_range_are_refused(fields):
    with pytest.raises(ValueError):
        ErrorWalk(**fields)


def test_a_rate_of_zero_turns_the_walk_off():
    walk = ErrorWalk(rate_hz=0.0, rate_min_hz=1.0)          # bounds unused when off
    noise = NoiseScale(scale=0.2)
    assert not walk.enabled
    assert walk.learn(noise, 3.0, 1.0, 0.5) is noise
    assert walk.walk_after(noise, 0.5) == 0.0


def test_the_walk_after_a_fix_is_c_before_its_lesson_times_the_r_in_use():
    walk = ErrorWalk(rate_hz=0.5, learning_rate=0.1, rate_min_hz=0.01, rate_max_hz=10.0)
    noise = NoiseScale(scale=0.1, walk_gain=math.log(2.0), last_nu=1.5)
    taught = walk.learn(noise, 2.0, 4.0, 0.3)                    # ν = 2 / √4 = 1
    assert taught.walk_m2_per_s == pytest.approx(0.5 * 2.0 * 0.3, rel=4 * UNIT_ROUNDOFF)
    assert taught.walk_gain == pytest.approx(math.log(2.0) + 0.1 * 1.0 * 1.5, rel=1e-15)
    assert taught.last_nu == 1.0
    assert taught[:3] == noise[:3]                               # the scale is not its job
    # ν is clipped at 3σ; log c stays within its bounds.
    assert walk.learn(noise, -100.0, 1.0, 0.3).last_nu == -NU_CLIP
    high = NoiseScale(walk_gain=math.log(19.0), last_nu=3.0)
    assert walk.rate(walk.learn(high, 3.0, 1.0, 1.0)) == pytest.approx(10.0, rel=1e-12)
    low = NoiseScale(walk_gain=math.log(0.021), last_nu=-3.0)
    assert walk.rate(walk.learn(low, 3.0, 1.0, 1.0)) == pytest.approx(0.01, rel=1e-12)


def test_the_walk_adds_w_dt_to_every_position_variance_only():
    covs = np.arange(2 * 3 * 3, dtype=float).reshape(2, 3, 3)
    assert position_walked(covs, 0.5, 0.0) is covs and position_walked(covs, 0.0, 2.0) is covs
    out = position_walked(covs, 0.5, 2.0)
    expected = covs.copy()
    expected[:, 0, 0] += 1.0
    assert np.array_equal(out, expected) and out is not covs
    per_setting = position_walked(np.zeros((2, 4, 3, 3)), np.array([[1.0], [2.0]]),
                                  np.array([[3.0], [0.5]]))
    assert np.array_equal(per_setting[:, :, 0, 0], [[3.0] * 4, [1.0] * 4])
    assert not np.any(per_setting[:, :, 1:, :]) and not np.any(per_setting[:, :, :, 1:])


@pytest.mark.parametrize('engine', ENGINES)
def test_the_state_says_how_far_the_position_walks(engine):
    """Predicting (ahead too) adds w dt to every regime's P_pp; the rest is untouched."""
    model = engine(RailModelParameters())
    state = model.first_estimate(10.0, 2.0)
    state = model.update(model.predict(state, 0.1), 10.3)[0]
    still = state._replace(noise=state.noise._replace(walk_m2_per_s=0.0))
    moving = state._replace(noise=state.noise._replace(walk_m2_per_s=0.7))
    for dt_s in (0.1, 2.0, 7.5):
        a, b = model.predict(still, dt_s), model.predict(moving, dt_s)
        tolerance = 8 * UNIT_ROUNDOFF * np.max(np.abs(b.covariances))
        difference = b.covariances - a.covariances
        expected = np.zeros_like(difference)
        expected[:, 0, 0] = 0.7 * dt_s
        np.testing.assert_allclose(difference, expected, rtol=0, atol=tolerance)
        np.testing.assert_array_equal(a.means, b.means)
        (_, P_still), (_, P_moving) = (model.predict_ahead(s, dt_s) for s in (still, moving))
        assert P_moving[0, 0] - P_still[0, 0] == pytest.approx(0.7 * dt_s, abs=tolerance)


@pytest.mark.parametrize('engine', ENGINES)
def test_a_position_fix_teaches_the_walk_and_a_speed_does_not(engine):
    model = engine(RailModelParameters(noise_window=0))        # R as given: s stays 1
    walk = model.error_walk
    state = model.first_estimate(0.0, 1.0)
    state = model.update(model.predict(state, 0.1), 0.4, [[2.0]])[0]
    assert state.noise.walk_m2_per_s == pytest.approx(walk.rate_hz * 2.0)
    after, result = model.update(model.predict(state, 0.1), -0.5, [[0.5]])
    nu = float(result.innovation[0] / math.sqrt(result.innovation_covariance[0, 0]))
    assert after.noise.last_nu == pytest.approx(nu, rel=1e-12)
    assert after.noise.walk_gain == pytest.approx(
        walk.learning_rate * nu * state.noise.last_nu, rel=1e-12)
    assert after.noise.walk_m2_per_s == pytest.approx(walk.rate(state.noise) * 0.5)
    sped = model.update_velocity(after, 1.0, 0.04)[0]
    assert sped.noise == after.noise


def _run(model, errors: np.ndarray, given_m2: float) -> float:
    """Return c after a 20-m/s cruise measured with these errors, every fix given R."""
    state = model.first_estimate(float(errors[0]), given_m2)
    for k in range(1, errors.size):
        state = model.predict_update(state, 0.1, 2.0 * k + float(errors[k]), [[given_m2]])[0]
    return model.error_walk.rate(state.noise)


@pytest.mark.parametrize('engine', ENGINES)
@pytest.mark.parametrize('seed', [0, 1])
def test_c_falls_on_white_errors_and_rises_on_a_walking_one(engine, seed):
    """Whiteness of the innovations decides: over 2000 fixes c moves far toward the truth."""
    rng = np.random.default_rng(seed)
    count = 2000
    white = rng.normal(0.0, 1.0, count)
    # A receiver's filtered error: a walk of 0.1 m a fix (0.1 m²/s) under 2 cm of white.
    slow = np.cumsum(rng.normal(0.0, 0.1, count)) + rng.normal(0.0, 0.02, count)
    start_high = engine(RailModelParameters(error_walk_rate_hz=1.0))
    start_low = engine(RailModelParameters())
    # Seeds 0-4 end at 0.03-0.13 and at 2.94-3 (the bound): margins of 1.6× and 3×.
    assert _run(start_high, white, 1.0) < 0.2                  # from 1: down by > 5×
    assert _run(start_low, slow, 1.0) > 1.0                    # from 0.01: up by > 100×


def test_the_walk_can_be_turned_off_and_then_the_model_is_the_white_one():
    params = RailModelParameters(error_walk_rate_hz=0.0)
    model = RailModel(params)
    state = model.first_estimate(0.0, 1.0)
    for k in range(1, 30):
        state = model.predict_update(state, 0.1, 0.5 * k, [[1.0]])[0]
    assert state.noise.walk_m2_per_s == state.noise.walk_gain == state.noise.last_nu == 0.0


def test_a_rewind_replays_the_walk_exactly():
    """Out of sequence: the estimator rewinds and replays; the walk is part of the state."""
    ns = 1_000_000_000
    rng = np.random.default_rng(8)
    stamps = [ns + k * ns // 10 for k in range(150)]
    fixes = (2.0 * np.arange(150) * 0.1 + np.cumsum(rng.normal(0.0, 0.05, 150))).tolist()
    in_order = StreamEstimator()
    shuffled = StreamEstimator(EstimatorSettings(history_s=5.0))
    for stamp, z in zip(stamps, fixes):
        in_order.process(stamp, z, 1.0)
    order = list(range(150))
    order[120], order[124] = order[124], order[120]
    for k in order:
        shuffled.process(stamps[k], fixes[k], 1.0)
    rate_hz = in_order.error_walk_rate_hz()
    assert rate_hz != RailModelParameters().error_walk_rate_hz      # it has learned
    assert shuffled.error_walk_rate_hz() == pytest.approx(rate_hz, rel=1e-9)
    for estimator in (in_order, shuffled):
        for ours, theirs in zip(estimator.predict_to(stamps[-1] + 2 * ns),
                                in_order.predict_to(stamps[-1] + 2 * ns)):
            np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-12)


def test_only_the_rail_preset_has_a_walk():
    linear = StreamEstimator(EstimatorSettings(preset='train'))
    assert linear.error_walk_rate_hz() is None
    rail = StreamEstimator()
    assert rail.error_walk_rate_hz() is None                   # nothing measured yet
    rail.process(1_000_000_000, 0.0, 1.0)
    assert rail.error_walk_rate_hz() == RailModelParameters().error_walk_rate_hz
    assert RailModel(RailModelParameters(error_walk_rate_hz=0.0)).error_walk_rate_hz(
        RailModel().first_estimate(0.0)) is None
