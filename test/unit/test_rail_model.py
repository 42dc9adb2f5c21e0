"""The rail IMM (kf_train.filters.rail_model): its physics, its mathematics, its honesty."""

import dataclasses
import math

from hypothesis import given, settings, strategies as st
from kf_train.filters.imm import check_transition_matrix, IMMState, make_state
from kf_train.filters.rail_dynamics import (
    _phi, relaxation_noise, relaxation_transition, RelaxationNoise)
from kf_train.filters.rail_model import (
    ACCELERATE, BRAKE, CRUISE, make_rail_filter, MODE_NAMES, RailModel, RailModelParameters,
    STAND)
from kf_train.filters.validation import as_covariance, as_matrix
from kf_train.presets.rail import (
    load_rail_preset, rail_preset_from_mapping, RAIL_PRESET_PATH)
from kf_train.sim.rail import family_parameters, rail_scenario
import numpy as np
import pytest
from scipy.linalg import expm

HORIZON_S = 2.0
MONTE_CARLO = [('metro', 11), ('metro', 12), ('regional', 11), ('regional', 12)]


def _generator(tau):
    """Return A of ṗ = v, v̇ = a, ȧ = (ℓ - a)/τ, ℓ̇ = 0."""
    A = np.zeros((4, 4))
    A[0, 1] = A[1, 2] = 1.0
    A[2, 2], A[2, 3] = -1.0 / tau, 1.0 / tau
    return A


@pytest.mark.parametrize('tau', [0.3, 0.7, 2.0])
@pytest.mark.parametrize('dt', [1e-4, 0.1, 0.5, 2.0, 30.0])
def test_the_transition_is_the_matrix_exponential(dt, tau):
    # scipy's expm (Padé 13, scaling and squaring) is accurate to ~1e-15 relative to
    # ‖F‖; our closed form loses at most a few digits in φ2, φ3 below x = 0.1 (where
    # the series takes over). 1e-12 of ‖F‖ covers both with margin.
    F = relaxation_transition(dt, tau)[0]
    expected = expm(_generator(tau) * dt)
    np.testing.assert_allclose(F, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize('dt', [1e-3, 0.1, 2.0])
def test_the_process_noise_is_van_loans_integral(dt):
    # Van Loan: expm([[-A, Qc], [0, Aᵀ]] dt) holds Q = E22ᵀ E12. For dt·|A| <= 3 the
    # exponential is accurate to ~1e-14 of ‖Q‖ (beyond that its e^(+dt/τ) block loses
    # digits, so long dt is checked by the doubling identity below).
    tau, q_a, q_l = 0.7, 2e-4, 3e-5
    A = _generator(tau)
    block = np.zeros((8, 8))
    block[:4, :4], block[:4, 4:], block[4:, 4:] = -A, np.diag([0, 0, q_a, q_l]), A.T
    E = expm(block * dt)
    expected = E[4:, 4:].T @ E[:4, 4:]
    Q = relaxation_noise(dt, tau, q_a, q_l)
    np.testing.assert_allclose(Q, expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    assert np.min(np.linalg.eigvalsh(Q)) >= -1e-15 * np.abs(Q).max()


@pytest.mark.parametrize('dt', [0.05, 3.0, 60.0])
def test_the_process_noise_composes_over_time(dt):
    # Q(2t) = F(t) Q(t) F(t)ᵀ + Q(t) holds exactly for the integral; Gauss-Legendre on
    # panels of τ/2 is exact to rounding (~1e-15 of ‖Q‖ per panel, 240 panels at 60 s).
    tau = 0.7
    F = relaxation_transition(dt, tau)[0]
    half = relaxation_noise(dt, tau, 1e-4, 1e-4)
    whole = relaxation_noise(2 * dt, tau, 1e-4, 1e-4)
    np.testing.assert_allclose(whole, F @ half @ F.T + half, rtol=0,
                               atol=1e-12 * np.abs(whole).max())


def test_the_phi_series_joins_the_closed_form():
    # Just below x = 0.1 the series is used; the closed form is still good there: φ3 =
    # x²/2 - φ2 cancels ~x²/2 down to ~x³/6, losing a factor 3/x = 30 of accuracy, so
    # the two agree to ~1e-14 relative. Far below, the series keeps full accuracy where
    # the closed form would have nothing left (x = 1e-6: φ3 = 1.7e-19).
    x = np.array([0.1 * (1.0 - 1e-9), 0.05, 1e-6])
    phi1, phi2, phi3 = _phi(x)
    closed1 = -np.expm1(-x)
    closed2 = x - closed1
    closed3 = x * x / 2.0 - closed2
    np.testing.assert_allclose(phi1, closed1, rtol=1e-15)
    np.testing.assert_allclose(phi2[:2], closed2[:2], rtol=1e-13)
    np.testing.assert_allclose(phi3[:2], closed3[:2], rtol=1e-12)
    assert phi3[2] == pytest.approx(1e-18 / 6.0 - 1e-24 / 24.0, rel=1e-14)
    assert phi2[2] == pytest.approx(1e-12 / 2.0 - 1e-18 / 6.0, rel=1e-14)


@pytest.mark.parametrize('tau', [0.01, 0.3, 0.7, 2.0, 1e6])
def test_the_noise_series_is_the_quadrature(tau):
    # The power series (dt <= 1.5 τ) against the Gauss-Legendre quadrature, both within
    # ~1e-15 of ‖Q‖ of the integral: entries compared relative to sqrt(Q_aa Q_bb), the
    # largest an entry can be, since the tiny dt give entries from dt to dt⁷ in size.
    # The series is in x = dt/τ, so no τ (1e6 s here) makes a power overflow.
    q_a, q_l = 2e-4, 3e-5
    noise = RelaxationNoise(tau, q_a, q_l)
    for dt in np.concatenate([np.geomspace(1e-6 * tau, 1.5 * tau, 60),
                              [1.5 * tau * (1 + 1e-12)]]):
        Q = noise(float(dt))
        expected = relaxation_noise(float(dt), tau, q_a, q_l)
        scale = np.sqrt(np.outer(np.diag(expected), np.diag(expected)))
        scale[scale == 0.0] = 1.0
        assert np.max(np.abs(Q - expected) / scale) <= 1e-13, dt
        assert np.array_equal(Q, Q.T)


@pytest.mark.parametrize('dt', [1e-9, 0.037, 0.1, 0.1 + 1e-7, 0.35, 1.2, 5.0, 400.0])
def test_the_regimes_matrices_pass_the_checks_the_stack_skips(dt):
    # RailModel stacks its regimes' F(dt) and Q(dt) unchecked (cheap at every new dt of
    # a jittered stream): they are what kalman.predict's checks accept, for any dt.
    F, Q, F_t, matrix = RailModel()._for_dt(dt)
    for j in range(4):
        as_matrix('F', F[j], 6, 6)
        as_covariance('Q', Q[j], 6)
        np.testing.assert_array_equal(F_t[j], F[j].T)
    check_transition_matrix(matrix, 4)
    assert matrix[BRAKE, STAND] == 0.0  # brake -> stand is the state's, added per step


def test_the_phi_functions_of_a_float_are_those_of_an_array():
    # One dt at a time (floats, math.expm1) and many (arrays, numpy.expm1) may differ
    # in the last bit of e^-x, and φ2, φ3 by the cancellation's factor 3/x <= 30.
    for x in (1e-7, 0.0999, 0.1, 0.5, 3.0, 40.0):
        for scalar, array in zip(_phi(x), _phi(np.array([x]))):
            assert scalar == pytest.approx(float(array[0]), rel=1e-14, abs=0.0)


def test_entering_a_regime_is_an_exact_linear_transformation():
    model = RailModel()
    rng = np.random.default_rng(0)
    L = rng.normal(size=(6, 6))
    P = L @ L.T
    x = rng.normal(size=6)
    plateau = model.parameters.plateau_std_mps2
    for mode, source, sign in ((ACCELERATE, 4, 1.0), (BRAKE, 5, -1.0)):
        # x' = T x + w: ℓ' = ±(A or B) + w, w ~ N(0, plateau²), the rest unchanged.
        T = np.eye(6)
        T[3] = 0.0
        T[3, source] = sign
        W = np.zeros((6, 6))
        W[3, 3] = plateau ** 2
        new_x, new_P = model.entry(mode, x, P)
        np.testing.assert_allclose(new_x, T @ x, rtol=1e-15)
        np.testing.assert_allclose(new_P, T @ P @ T.T + W, rtol=1e-14, atol=1e-15)
    new_x, new_P = model.entry(CRUISE, x, P)
    assert new_x[3] == 0.0 and new_P[3, 3] == model.parameters.cruise_std_mps2 ** 2
    assert np.all(new_P[3, np.arange(6) != 3] == 0.0)


def _state(v_mps, v_std, mode=BRAKE):
    """Return a rail IMM state sure of one mode, with velocity v ± v_std."""
    x = np.array([100.0, v_mps, -0.8, -0.9, 0.8, 0.9])
    P = np.diag([0.1, v_std ** 2, 0.01, 0.01, 0.01, 0.01])
    mu = np.full(4, 1e-6)
    mu[mode] = 1.0
    return make_state(np.tile(x, (4, 1)), np.tile(P, (4, 1, 1)), mu)


def test_only_a_slow_braking_train_can_stop():
    model = RailModel()
    fast = model.transition(0.1, _state(15.0, 0.2))
    slow = model.transition(0.1, _state(0.05, 0.1))
    # At 15 ± 0.2 m/s, P(v <= 0.3 m/s) is Φ(-73.5): 0 in floats.
    assert fast[BRAKE, STAND] == 0.0
    # At 0.05 ± 0.1 m/s, Φ(2.5) = 0.994 of the stop rate (1/s) over 0.1 s.
    expected = 1.0 - math.exp(-0.1 * (1 / 30 + 1 / 100 + 0.994))
    assert slow[BRAKE, STAND] == pytest.approx(expected * 0.994 / (1 / 30 + 1 / 100 + 0.994),
                                               rel=1e-3)
    for matrix in (fast, slow):
        np.testing.assert_allclose(matrix.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.all(fast[STAND, [CRUISE, BRAKE]] == 0.0)  # a standing train departs accelerating


@settings(max_examples=200, deadline=None)
@given(st.floats(-0.5, 30.0), st.floats(-1.5, 1.3), st.floats(-1.5, 1.3),
       st.floats(0.01, 3.0), st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4))
def test_no_regime_predicts_a_reversal(v, a, command, v_std, mu):
    if sum(mu) == 0.0:
        mu = [0.25] * 4
    x = np.array([50.0, v, a, command, 0.8, 0.9])
    P = np.diag([0.2, v_std ** 2, 0.05, 0.05, 0.02, 0.02])
    model = RailModel()
    state = make_state(np.tile(x, (4, 1)), np.tile(P, (4, 1, 1)), mu)
    x_now, _ = model.estimate(state)
    ahead, P_ahead = model.predict_ahead(state, HORIZON_S)
    # Every regime's mean path only moves forward (the stand regime's stays put),
    # so the mixture predicts no position behind the current one and no negative speed.
    assert ahead[0] >= x_now[0] - 1e-9
    assert ahead[1] >= -1e-12
    assert np.all(np.isfinite(P_ahead)) and P_ahead[0, 0] > 0.0


@pytest.fixture(scope='module')
def tracked():
    """Run the default rail filter over short seeded runs; keep what the tests need."""
    runs = []
    for family, seed in MONTE_CARLO:
        params = dataclasses.replace(family_parameters(family, seed), duration_s=240.0)
        scenario, run = rail_scenario(seed, family, parameters=params)
        t, z = scenario.t_s, scenario.z[:, 0]
        filt = make_rail_filter(z[0])
        rows = []
        for k in range(t.size):
            nis = None
            if k:
                filt.predict(t[k] - t[k - 1])
                nis = filt.update(z[k]).nis
            x, P = filt.mean, filt.covariance
            ahead, P_ahead = filt.predict_ahead(HORIZON_S)
            rows.append((t[k], x, P, filt.mode_probabilities, filt.state, ahead, P_ahead, nis))
        runs.append((run, rows))
    return runs


def test_mode_probabilities_sum_to_one_on_rail_runs(tracked):
    for _, rows in tracked:
        for row in rows:
            mu = row[3]
            assert np.all(mu >= 0.0)
            assert mu.sum() == pytest.approx(1.0, abs=1e-12)


def test_predictions_never_go_backwards_on_rail_runs(tracked):
    for _, rows in tracked:
        for _, x, _, _, _, ahead, _, _ in rows:
            assert ahead[0] >= x[0] - 1e-9
            assert ahead[1] >= -1e-12


def test_stopped_means_stopped(tracked):
    stand, speed, moved = [], [], []
    for run, rows in tracked:
        for t, x, _, mu, state, ahead, _, _ in rows[1:]:
            # The stand regime's own state is stopped, exactly, after every step.
            assert np.all(state.means[STAND, 1:4] == 0.0)
            assert np.all(state.covariances[STAND, 1:4, :] == 0.0)
            # From 8 s after each stop (the filter needs a few seconds to be sure) to
            # 2 s before the departure (after that the truth moves within 2 s).
            if any(arrive + 8.0 <= t <= depart - 2.0 for arrive, depart in run.stops[1:]):
                stand.append(mu[STAND])
                speed.append(abs(x[1]))
                moved.append(ahead[0] - x[0])
    stand, speed, moved = np.array(stand), np.array(speed), np.array(moved)
    assert stand.size > 500
    # Mostly sure it stands; noise bursts that look like a departure make it doubt
    # now and then (a price of noticing a real departure within ~1.5 s).
    assert np.median(stand) > 0.9
    assert np.percentile(stand, 5) > 0.75
    assert np.mean(speed) < 0.05
    # The 2-s prediction moves only by the chance of leaving: a departure within 2 s
    # has prior probability 1 - e^(-2/30) = 6.4 % and covers ~1.3 m (A = 1.2 m/s²,
    # τ = 0.7 s), 0.09 m on average; the doubts above add about as much again.
    assert np.all(moved >= -1e-9)  # rounding of positions ~1e3 m (ulp 1e-13)
    assert np.mean(moved) < 0.3


def test_monte_carlo_consistency(tracked):
    errors, stds, nis = [], [], []
    for run, rows in tracked:
        for t, x, _, _, _, ahead, P_ahead, value in rows:
            if t >= 10.0 and t + HORIZON_S <= run.parameters.duration_s:
                errors.append(ahead[0] - float(run.state_at(t + HORIZON_S).position_m))
                stds.append(math.sqrt(P_ahead[0, 0]))
            if value is not None and t >= 10.0:
                nis.append(value)
    errors, stds, nis = np.array(errors), np.array(stds), np.array(nis)
    coverage = np.mean(np.abs(errors) <= 2.0 * stds)
    # The target band of the 2σ coverage is 85-99 %. Errors are correlated over the
    # ~3 s a maneuver takes to be recognised, so these ~8600 predictions are worth
    # ~8600/30 ≈ 290 independent ones: the coverage is known to ±1.3 % (1σ), and the
    # measured value (95-96 %) must lie in the band.
    assert 0.85 <= coverage <= 0.99, coverage
    # The normalised innovation squared of the mixture is χ²(1) with mean 1 for an
    # exact model; innovations are white, so the mean of ~9500 values has a standard
    # error of √(2/9500) = 0.015. The IMM's mixture is an approximation (moment
    # matching, a model of the maneuvers, not the generator's), so the band is wider
    # than the sampling error: 0.7-1.3 rejects a filter off by 30 % in its variances.
    assert 0.7 <= nis.mean() <= 1.3, nis.mean()
    # Tails: a brake or a departure that begins within the horizon cannot be foreseen,
    # and such a change is ahead ~10 % of the time (metro: ~6 ramp onsets per 100 s,
    # each ahead for 2 s); the band is a Gaussian's, so for a second or so the truth
    # is several σ out. Beyond 4σ (Gaussian: 6e-5) it must stay under 2 % (measured
    # 1.3 %); a filter that diverged or lost its variance would be far beyond.
    tail = np.mean(np.abs(errors) > 4.0 * stds)
    assert tail < 0.02, tail


def test_hostile_inputs_leave_the_filter_as_it_was():
    filt = make_rail_filter(0.0)
    for k in range(1, 50):
        filt.predict(0.1)
        filt.update(0.0)
    kept = filt.snapshot()
    for bad in (float('nan'), float('inf'), [1.0, 2.0], None):
        with pytest.raises(ValueError):
            filt.update(bad)
        assert filt.snapshot() is kept
    for bad in (-0.1, float('nan'), float('inf')):
        with pytest.raises(ValueError):
            filt.predict(bad)
        assert filt.snapshot() is kept
    # A 10⁶ m outlier is computed (finite) and flagged by its NIS, for a χ² gate.
    filt.predict(0.1)
    trial = filt.snapshot()
    result = filt.update(1e6)
    assert result.nis > 1e10
    assert np.all(np.isfinite(filt.mean)) and filt.mode_probabilities.sum() == pytest.approx(1)
    filt.restore(trial)  # what a gate does: go back and skip it
    assert isinstance(filt.snapshot(), IMMState)
    assert filt.mode_names == MODE_NAMES


def test_parameters_are_checked():
    with pytest.raises(ValueError, match='response_time_s'):
        RailModelParameters(response_time_s=0.0)
    with pytest.raises(ValueError, match='stop_rate_hz'):
        RailModelParameters(stop_rate_hz=-1.0)
    with pytest.raises(ValueError, match='noise_std_m'):
        RailModelParameters(noise_std_m=float('nan'))


def test_the_rail_preset_file_holds_the_defaults():
    preset = load_rail_preset()
    # The file documents the defaults: every figure in it is the dataclass default.
    assert preset.parameters == RailModelParameters()
    assert (preset.name, preset.nominal_period_s, preset.horizon_s) == ('rail', 0.1, 2.0)


@pytest.mark.parametrize('change, message', [
    ({'colour': 'red'}, "unknown key 'colour'"),
    ({'model': 'constant_velocity'}, "'model'"),
    ({'R': [[0.0]]}, "'R'"),
    ({'R': 1.0}, "'R'"),
    ({'parameters': {'stop_speed_mps': -1.0}}, 'stop_speed_mps'),
    ({'parameters': {'tau': 1.0}}, "'parameters.tau'"),
    ({'horizon_s': 0}, "'horizon_s'"),
])
def test_a_bad_rail_preset_is_refused_naming_the_key(change, message):
    import yaml
    with open(RAIL_PRESET_PATH, encoding='utf-8') as stream:
        data = yaml.safe_load(stream)
    data.update(change)
    with pytest.raises(ValueError, match=message):
        rail_preset_from_mapping(data)
