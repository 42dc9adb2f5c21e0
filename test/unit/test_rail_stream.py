"""The rail scenario as a live stream (kf_train.sim.rail_stream) and the rail baselines."""

from kf_train.sim import (
    make_stream, PolynomialKF, rail_parameters, rail_scenario, RailParameters, RailStream,
    score_predictions, tuned_baselines)
from kf_train.sim.rail import family_parameters
from kf_train.sim.rail_eval import track
import numpy as np
import pytest


@pytest.mark.parametrize('family, seed', [('metro', 3), ('regional', 7)])
def test_the_stream_is_rail_scenario_sample_for_sample(family, seed):
    """Same seed, same family: the node's samples are rail_scenario's, to the last bit."""
    scenario, _ = rail_scenario(seed, family)
    stream = make_stream('rail', 10.0, seed, rail={'family': family})
    samples = [stream.next_sample() for _ in range(len(scenario.t_s))]
    assert np.array_equal([s.t_s for s in samples], scenario.t_s)
    assert np.array_equal([s.measured_position_m for s in samples], scenario.z[:, 0])
    truth = [(s.true_position_m, s.true_velocity_mps, s.true_acceleration_mps2)
             for s in samples]
    assert np.array_equal(truth, scenario.truth)
    assert all(s.control is None for s in samples)


def test_the_stream_goes_on_past_the_runs_duration():
    """Stations keep coming: planned as time goes, never reversing, stops included."""
    parameters = rail_parameters('metro', 1, line_speed_mps=20.0, station_spacing_m=[600, 700],
                                 dwell_s=[5.0, 6.0])
    stream = RailStream(10.0, 1, noise_std_m=0.0, initial_position_m=100.0,
                        parameters=parameters)
    samples = [stream.next_sample() for _ in range(int(3 * parameters.duration_s * 10))]
    position = np.array([s.true_position_m for s in samples])
    velocity = np.array([s.true_velocity_mps for s in samples])
    assert position[0] >= 100.0 and np.all(np.diff(position) >= 0.0)
    assert np.all(velocity >= 0.0) and velocity.max() <= 20.0
    assert np.array_equal(position, [s.measured_position_m for s in samples])  # σ = 0
    # A stop every ~60-70 s: far more than one run's duration holds.
    assert len(stream.run_until(samples[-1].t_s).stops) > 25


def test_rail_parameters_replace_what_is_given_and_check_it():
    """Given values replace the family's draw; the rest stays as drawn."""
    drawn = family_parameters('regional', 4)
    given = rail_parameters('regional', 4, accel_mps2=1.2, dwell_s=(1.0, 2.0))
    assert isinstance(given, RailParameters)
    assert given.accel_mps2 == 1.2 and given.dwell_s == (1.0, 2.0)
    assert given.brake_mps2 == drawn.brake_mps2 and given.jerk_mps3 == drawn.jerk_mps3
    assert rail_parameters('regional', 4) == drawn
    with pytest.raises(ValueError, match='brake_mps2'):
        rail_parameters(brake_mps2=2.0)
    with pytest.raises(ValueError, match='station_spacing_m'):
        rail_parameters(station_spacing_m=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match='family'):
        rail_parameters('tram', 1)


def test_an_unseeded_stream_still_runs():
    """An unseeded stream (seed None) draws fresh entropy, and a valid run."""
    stream = make_stream('rail', 10.0, None)
    assert stream.seed >= 0 and stream.next_sample().index == 1


def test_the_tuned_baselines_are_kalman_filters_at_their_best_q():
    """The best q of the grid is the best; CA tracks a rail run better than CV."""
    scenario, run = rail_scenario(2, 'metro')
    grid_cv, grid_ca = (0.3, 1.0, 3.0), (0.01, 0.03, 0.1)
    best = tuned_baselines(scenario, run, cv_grid=grid_cv, ca_grid=grid_ca)
    for name, dim, grid in (('CV', 2, grid_cv), ('CA', 3, grid_ca)):
        scores = [score_predictions(track(lambda z0, q=q: PolynomialKF(dim, q, z0), scenario),
                                    run).rmse_m for q in grid]
        assert best[name].score.rmse_m == min(scores)
        assert best[name].q == grid[int(np.argmin(scores))]
    assert best['CA'].score.rmse_m < best['CV'].score.rmse_m
    assert 0.8 <= best['CA'].score.coverage <= 1.0


def test_the_polynomial_kf_predicts_without_changing_itself():
    """predict_ahead leaves the filter as it was; F and Q are the white-noise model's."""
    kf = PolynomialKF(3, 0.1, 5.0)
    x_before, P_before = kf.filter.x, kf.filter.P
    x, P = kf.predict_ahead(2.0)
    assert np.array_equal(kf.filter.x, x_before) and np.array_equal(kf.filter.P, P_before)
    assert x[0] == 5.0
    # P(2 s)[0, 0] = σ² + 4 σ_v² + 4 σ_a² (F row [1, 2, 2]) + q·2⁵/20.
    expected = P_before[0, 0] + 4 * P_before[1, 1] + 4 * P_before[2, 2] + 0.1 * 32 / 20
    assert P[0, 0] == pytest.approx(expected, rel=1e-12)
