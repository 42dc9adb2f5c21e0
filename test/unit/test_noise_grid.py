"""The suggested q searched on grids of q at once (kf_train.batch.noise_grid) vs one at a time."""

import math

from kf_train.batch import noise_grid, RunningNoiseEstimate
from kf_train.batch.noise_grid import batched, FINE, GainCache, WindowLikelihood
from kf_train.batch.noise_likelihood import NoiseSetting
from kf_train.presets import load_preset
from kf_train.sim import car_scenario, white_noise_acceleration_scenario
import numpy as np
import pytest

EPOCH_NS = 1_700_000_000 * 1_000_000_000
# The one-q search stops the golden section on a bracket narrower than 1e-2 in log q
# and returns a point inside it, and bisects the likelihood-ratio bound to 1e-2 (its
# midpoint: within 5e-3); the grids put v̂ within FINE/2 of the minimiser and
# interpolate the bound within a FINE step. So the two v̂ are within 1e-2 + FINE/2 of
# each other and the two LR bounds within 5e-3 + FINE (plus the shift of the crossing
# by the two −ℓ(v̂), which differ by at most f''·(1.5e-2)²/2 ≈ 1e-3 · f'': negligible
# against the slope there).
V_HAT_TOLERANCE = 1e-2 + FINE / 2
LR_BOUND_TOLERANCE = 5e-3 + FINE + 1e-3


def _estimate(name, scenario, batched_search):
    """Return a running estimate of preset ``name`` holding the scenario's 300 rows."""
    preset = load_preset(name)
    estimate = RunningNoiseEstimate(preset, window=300)
    estimate.batched = batched_search
    for k, (t, z) in enumerate(zip(scenario.t_s, scenario.z)):
        args = (scenario.u[k],) if preset.dim_u else ()
        estimate.add(EPOCH_NS + int(round(t * 1e9)), z, *args)
    return estimate


CASES = [('train', q, seed) for q in (0.0, 0.01, 0.5, 2.0, 50.0) for seed in (1, 2)] + \
    [('car-exact', None, 4), ('car', None, 5), ('cv-position', 0.3, 5)]


def _scenario(name, q, seed):
    """Return 300 rows of the case's data."""
    if name.startswith('car'):
        return car_scenario(seed=seed, n_samples=300, exact=name == 'car-exact')
    return white_noise_acceleration_scenario(q, 1.0, 300, seed=seed)


@pytest.mark.parametrize('name, q, seed', CASES)
def test_the_batched_likelihood_is_the_one_q_likelihood(name, q, seed):
    estimate = _estimate(name, _scenario(name, q, seed), False)
    problem = estimate._problem()
    segment = problem.segments[0]
    likelihood = WindowLikelihood(problem.preset, segment.t_s, segment.z[:, 0], segment.u,
                                  1.0, 100.0)
    qs = np.exp(np.linspace(-15.0, 12.0, 28))
    expected = np.array([problem.log_likelihood(NoiseSetting(v, (1.0,))) for v in qs])
    # Two orders of the same sums over 299 rows: the covariance recursion carries a
    # relative rounding of ~299·20·u ≈ 7e-13 into every s_k, the mean one an absolute
    # ~7e-13·|x| into y_k (positions up to ~300 m against innovations of ~1 m: x100);
    # ℓ's terms move by that relative amount each, so 1e-10 of |ℓ| bounds it.
    np.testing.assert_allclose(likelihood.log_likelihoods(qs), expected, rtol=1e-10)


def _curvatures(estimate, v):
    """Return (f'', |f'''|) of −ℓ at log q = v (central differences, step 0.05)."""
    problem = estimate._problem()
    segment = problem.segments[0]
    likelihood = WindowLikelihood(problem.preset, segment.t_s, segment.z[:, 0], segment.u,
                                  1.0, 100.0)
    h = 0.05
    f = -likelihood.log_likelihoods(np.exp(v + h * np.arange(-2, 3)))
    second = (f[3] - 2.0 * f[2] + f[1]) / h ** 2
    third = (f[4] - 2.0 * f[3] + 2.0 * f[1] - f[0]) / (2.0 * h ** 3)
    return second, abs(third)


@pytest.mark.parametrize('name, q, seed', CASES)
def test_the_grids_suggest_what_one_q_at_a_time_suggests(name, q, seed):
    scenario = _scenario(name, q, seed)
    grid, one = (_estimate(name, scenario, flag).suggest([1.0]) for flag in (True, False))
    assert batched(load_preset(name))
    assert grid.count == one.count == 299
    if one.process_noise_density == 0.0:
        assert grid.process_noise_density == 0.0
    else:
        assert abs(math.log(grid.process_noise_density / one.process_noise_density)) \
            <= V_HAT_TOLERANCE
    if one.low == 0.0:                                       # the likelihood-ratio bound
        assert grid.low == 0.0
        if math.isinf(one.high):
            assert math.isinf(grid.high)
        else:
            assert abs(math.log(grid.high / one.high)) <= LR_BOUND_TOLERANCE
        return
    # Wald: v̂ ± z σ, σ = f''^(-1/2). The two v̂ are within V_HAT_TOLERANCE, so the two
    # f'' differ by |f'''|·V_HAT_TOLERANCE (the central differences' own h² errors,
    # h <= 1e-2, are ~1e-5 relative, inside the margin) and σ by half that relative.
    v = math.log(one.process_noise_density)
    second, third = _curvatures(_estimate(name, scenario, False), v)
    half_width = math.log(one.high) - v                      # z σ
    # ... with a margin of 1.5 on that first-order term.
    tolerance = V_HAT_TOLERANCE + half_width * 0.5 * third * V_HAT_TOLERANCE / second * 1.5
    assert abs(math.log(grid.low / one.low)) <= tolerance, (second, third, tolerance)
    assert abs(math.log(grid.high / one.high)) <= tolerance, (second, third, tolerance)


def test_presets_the_grids_do_not_run_search_one_q_at_a_time():
    preset = load_preset('cv-position-velocity')
    assert not batched(preset)
    assert not RunningNoiseEstimate(preset, window=300).batched


def _likelihood(name, scenario, t_s, cache=None):
    """Return the WindowLikelihood of a case's 300 rows at times t_s (R 1, σ_v 100)."""
    preset = load_preset(name)
    u = scenario.u if preset.dim_u else None
    return WindowLikelihood(preset, t_s, scenario.z[:, 0], u, 1.0, 100.0, cache)


@pytest.mark.parametrize('name', ['train', 'car'])
@pytest.mark.parametrize('capacity_q', [None, 250])
def test_the_gain_cache_gives_the_same_likelihood_bit_for_bit(name, capacity_q, monkeypatch):
    # The covariance pass kept from earlier windows of the same times (and grids that
    # repeat, overlap, hold a q twice, or one q alone) gives the very numbers computed
    # afresh; so after the store fills and is emptied (capacity_q q at 299 rows; a
    # larger grid is not kept).
    if capacity_q is not None:
        monkeypatch.setattr(noise_grid, 'MAX_CACHED_VALUES', capacity_q * 299)
    cache = GainCache()
    coarse = np.exp(np.linspace(-19.0, 12.0, 63))
    overlapping = np.concatenate((np.linspace(-2.5, -0.5, 201), np.linspace(-1.0, 0.0, 101)))
    grids = [coarse, np.exp(np.linspace(-3.0, -1.0, 201)), coarse, np.exp(overlapping),
             coarse[[7, 3, 3, 50]], coarse[:1], np.exp(np.linspace(-3.0, -1.0, 201))]
    rng = np.random.default_rng(3)
    for seed in range(3):
        scenario = (car_scenario(seed=seed, n_samples=300) if name == 'car'
                    else white_noise_acceleration_scenario(0.5, 1.0, 300, seed=seed))
        t_s = scenario.t_s - scenario.t_s[0]
        if seed == 2:                                       # other times: another key
            t_s = t_s + np.concatenate(([0.0], rng.uniform(0.0, 1e-3, t_s.size - 1)))
        cached = _likelihood(name, scenario, t_s, cache)
        fresh = _likelihood(name, scenario, t_s)
        for q in grids:
            assert np.array_equal(cached.log_likelihoods(q), fresh.log_likelihoods(q))
    assert len(cache.columns) <= cache.capacity
