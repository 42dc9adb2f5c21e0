"""The rail run generator (kf_train.sim.rail): its physics invariants and its seeds."""

import dataclasses

from kf_train.sim.rail import (
    ACCEL_LIMIT_MPS2, BRAKE_LIMIT_MPS2, change_distance_m, FAMILIES, family_parameters,
    JERK_RANGE_MPS3, LINE_SPEED_RANGE_MPS, rail_run, rail_scenario, RailParameters, s_curve)
import numpy as np
import pytest

CASES = [('metro', 0), ('metro', 3), ('regional', 1), ('regional', 4)]


def _dense(run, step_s=0.01):
    """Return times every step_s over the whole plan and the state there."""
    t = np.arange(0.0, run.end_s, step_s)
    return t, run.state_at(t)


@pytest.mark.parametrize('family, seed', CASES)
def test_speed_acceleration_and_jerk_stay_within_the_limits(family, seed):
    params = family_parameters(family, seed)
    run = rail_run(params, seed)
    t, state = _dense(run)
    assert state.velocity_mps.min() >= 0.0
    # The plan is exact; only rounding (a few ulps of 1 m/s²) separates the integrated
    # acceleration from its planned limit.
    assert state.acceleration_mps2.max() <= params.accel_mps2 + 1e-12
    assert state.acceleration_mps2.min() >= -params.brake_mps2 - 1e-12
    assert state.velocity_mps.max() <= params.line_speed_mps + 1e-9
    # Jerk is piecewise constant in {-j, 0, +j}.
    jerks = np.unique(np.round(run._jerk / params.jerk_mps3, 12))
    assert set(jerks.tolist()) <= {-1.0, 0.0, 1.0}
    # Acceleration is continuous (jerk-limited): over 0.01 s it moves by at most j·0.01.
    assert np.max(np.abs(np.diff(state.acceleration_mps2))) <= params.jerk_mps3 * 0.01 + 1e-9


@pytest.mark.parametrize('family, seed', CASES)
def test_the_train_never_reverses_and_is_continuous(family, seed):
    run = rail_run(family_parameters(family, seed), seed)
    t, state = _dense(run)
    # Position never decreases: its steps are v·dt >= 0 up to rounding of positions
    # of ~10⁴ m (ulp ~2e-12 m).
    assert np.diff(state.position_m).min() >= -1e-9
    # Continuity at every phase boundary: the state just before equals the one at it.
    boundaries = run.phase_start_s[1:]
    before = run.state_at(boundaries - 1e-9)
    at = run.state_at(boundaries)
    assert np.max(np.abs(before.position_m - at.position_m)) < 1e-6
    assert np.max(np.abs(before.velocity_mps - at.velocity_mps)) < 1e-6
    assert np.max(np.abs(before.acceleration_mps2 - at.acceleration_mps2)) < 1e-6


@pytest.mark.parametrize('family, seed', CASES)
def test_it_dwells_standing_at_every_station(family, seed):
    params = family_parameters(family, seed)
    run = rail_run(params, seed)
    assert len(run.stops) >= 3
    for i, (arrive, depart) in enumerate(run.stops):
        t = np.linspace(arrive, depart, 50)
        state = run.state_at(t)
        assert np.all(state.velocity_mps == 0.0)
        assert np.all(state.acceleration_mps2 == 0.0)
        assert np.ptp(state.position_m) == 0.0
        if i > 0:  # the first stop is the remainder of a dwell
            assert params.dwell_s[0] - 1e-9 <= depart - arrive <= params.dwell_s[1] + 1e-9
    # Between stops it moves: each section covers at least the shortest spacing.
    stations = run.state_at(np.array([stop[0] for stop in run.stops])).position_m
    assert np.diff(stations).min() >= params.station_spacing_m[0] * 0.95


def test_a_seed_is_a_run_and_the_families_draw_within_their_ranges():
    first, _ = rail_scenario(7, 'regional')
    again, _ = rail_scenario(7, 'regional')
    other, _ = rail_scenario(8, 'regional')
    np.testing.assert_array_equal(first.z, again.z)
    np.testing.assert_array_equal(first.truth, again.truth)
    assert not np.array_equal(first.truth, other.truth)
    for name, family in FAMILIES.items():
        for seed in range(20):
            params = family_parameters(name, seed)
            for field in ('accel_mps2', 'brake_mps2', 'jerk_mps3', 'line_speed_mps'):
                low, high = getattr(family, field)
                assert low <= getattr(params, field) <= high


def test_the_noise_is_the_measurement_noise_asked_for():
    scenario, run = rail_scenario(2, 'metro', noise_std_m=1.0)
    residual = scenario.z[:, 0] - scenario.truth[:, 0]
    n = residual.size
    # The sample standard deviation of n = 6000 N(0, 1) draws has a standard error of
    # 1/sqrt(2n) = 0.009; 0.05 is more than 5 of them.
    assert abs(residual.std() - 1.0) < 0.05
    assert abs(residual.mean()) < 5.0 / np.sqrt(n)
    np.testing.assert_allclose(np.diff(scenario.t_s), 0.1, atol=1e-12)
    np.testing.assert_array_equal(scenario.truth[:, 1], run.state_at(scenario.t_s).velocity_mps)


def test_s_curves_reach_their_speed_and_cover_their_mean_speed_times_duration():
    for dv, accel, jerk in ((10.0, 1.0, 0.5), (0.3, 1.0, 0.5), (-15.0, 1.2, 0.8)):
        phases = s_curve(dv, accel, jerk)
        v0 = 15.0 if dv < 0 else 0.0
        v, a, distance = v0, 0.0, 0.0
        for duration, j in phases:
            distance += v * duration + a * duration ** 2 / 2 + j * duration ** 3 / 6
            v += a * duration + j * duration ** 2 / 2
            a += j * duration
            assert abs(a) <= accel + 1e-12
        assert v == pytest.approx(v0 + dv, abs=1e-9)
        assert a == pytest.approx(0.0, abs=1e-12)
        assert distance == pytest.approx(change_distance_m(v0, v0 + dv, accel, jerk), rel=1e-12)


@pytest.mark.parametrize('field, value', [
    ('accel_mps2', ACCEL_LIMIT_MPS2 + 0.01), ('brake_mps2', BRAKE_LIMIT_MPS2 + 0.01),
    ('jerk_mps3', JERK_RANGE_MPS3[0] - 0.01), ('jerk_mps3', JERK_RANGE_MPS3[1] + 0.01),
    ('line_speed_mps', LINE_SPEED_RANGE_MPS[0] - 1), ('line_speed_mps', 46.0),
    ('accel_mps2', float('nan')), ('station_spacing_m', (900.0, 800.0)),
    ('dwell_s', (-1.0, 10.0)), ('slow_zone_probability', 1.5), ('duration_s', True)])
def test_parameters_out_of_range_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=field):
        RailParameters(**{field: value})


def test_parameters_are_frozen_and_seeds_checked():
    params = RailParameters()
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.accel_mps2 = 1.0
    with pytest.raises(ValueError, match='seed'):
        rail_run(params, -1)
    with pytest.raises(ValueError, match='family'):
        family_parameters('tram', 0)
    with pytest.raises(ValueError, match='t_s'):
        rail_run(params, 0).state_at([-1.0])


@pytest.mark.parametrize('family, seed', [('metro', 2), ('regional', 5)])
def test_a_textured_run_keeps_every_invariant_and_varies_its_cruise(family, seed):
    """Texture: small speed changes in a cruise; limits, stops and spacing still hold."""
    plain = family_parameters(family, seed)
    params = dataclasses.replace(plain, texture_speed_mps=0.5)
    run = rail_run(params, seed)
    t, state = _dense(run)
    assert state.velocity_mps.min() >= 0.0
    assert state.acceleration_mps2.max() <= params.accel_mps2 + 1e-12
    assert state.acceleration_mps2.min() >= -params.brake_mps2 - 1e-12
    jerks = np.unique(np.round(run._jerk / params.jerk_mps3, 12))
    assert set(jerks.tolist()) <= {-1.0, 0.0, 1.0}
    for arrive, depart in run.stops:
        standing = run.state_at(np.linspace(arrive, depart, 20))
        assert np.all(standing.velocity_mps == 0.0) and np.ptp(standing.position_m) == 0.0
    stations = run.state_at(np.array([stop[0] for stop in run.stops])).position_m
    assert np.diff(stations).min() >= params.station_spacing_m[0] * 0.95
    assert np.diff(stations).max() <= params.station_spacing_m[1] + 1e-6
    assert state.velocity_mps.max() > params.line_speed_mps  # a downhill stretch


def test_a_textured_cruise_changes_its_speed_every_20_s():
    """Without coasting or slow zones, a plain cruise is flat; a textured one is not."""
    flat = RailParameters(line_speed_mps=20.0, station_spacing_m=(3000.0, 3000.0),
                          dwell_s=(30.0, 30.0), slow_zone_probability=0.0,
                          coast_drop_mps=(0.0, 0.0), duration_s=1800.0)
    plain = rail_run(flat, 4)
    textured = rail_run(dataclasses.replace(flat, texture_speed_mps=0.5), 4)
    assert [stop[0] for stop in plain.stops][:3] != [stop[0] for stop in textured.stops][:3]
    # Same sections (every draw is fixed): the texture only adds speed changes.
    stations = [run.state_at(np.array([s[0] for s in run.stops])).position_m
                for run in (plain, textured)]
    count = min(len(s) for s in stations)
    np.testing.assert_allclose(stations[0][:count], stations[1][:count], atol=1e-6)
    cruise_s = np.sum(plain.phase_duration_s[(plain._v0 == 20.0) & (plain._jerk == 0.0)])
    added = np.count_nonzero(textured._jerk) - np.count_nonzero(plain._jerk)
    # A piece of ~20 s changes speed (>= 2 jerk phases each way) unless its loop does
    # not fit (|δ| > 10·rate: under 32 % of the pieces): at least half of them do.
    assert added >= 0.5 * (cruise_s / 20.0) * 4
    with pytest.raises(ValueError, match='texture_speed_mps'):
        RailParameters(texture_speed_mps=5.0)
