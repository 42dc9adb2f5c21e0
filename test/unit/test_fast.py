"""Tests of kf_train.filters.fast: the closed-form 2-state filter against the generic path."""

from fractions import Fraction
import math

from hypothesis import given, settings, strategies as st
from kf_train.filters import (
    constant_velocity_F, constant_velocity_model, FastTrainFilter, kalman, LinearModel,
    per_step_noise_terms, PerStepNoise, POSITION_H, white_noise_terms, WhiteNoiseAcceleration)
import numpy as np
import pytest

RTOL = 1e-9
NAN, INF = float('nan'), float('inf')


def _close(actual, expected):
    """Assert agreement to RTOL relative, with an absolute floor of RTOL times the scale."""
    expected = np.asarray(expected, dtype=float)
    scale = max(1.0, float(np.max(np.abs(expected))))
    np.testing.assert_allclose(actual, expected, rtol=RTOL, atol=RTOL * scale)


def _generic_run(x0, P0, noise, steps):
    """Yield (x, P, UpdateResult) of kalman.predict/update for steps of (z, dt, R)."""
    x, P = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
    for z, dt, R in steps:
        Q = np.zeros((2, 2)) if noise is None else noise(dt)
        x, P = kalman.predict(x, P, constant_velocity_F(dt), Q)
        x, P, result = kalman.update(x, P, [z], POSITION_H, [[R]])
        yield x, P, result


def _compare(x0, P0, noise, steps):
    """Run the fast and the generic filter side by side, comparing after every step."""
    fast = FastTrainFilter(x0, P0, noise)
    for (z, dt, R), (x, P, result) in zip(steps, _generic_run(x0, P0, noise, steps)):
        nis = fast.step(z, dt, R)
        _close(fast.x, x)
        _close(fast.P, P)
        _close(fast.innovation, result.innovation[0])
        _close(fast.innovation_variance, result.innovation_covariance[0, 0])
        _close(nis, result.nis)
        _close(fast.nis, result.nis)
        _close(fast.gain, result.gain[:, 0])
        assert fast.P[0, 1] == fast.P[1, 0]
    return fast


def _random_steps(rng, count, dt_choices=None, R_range=(0.01, 10.0)):
    """Return ``count`` (z, dt, R) rows of a noisy train with irregular dt."""
    steps, t = [], 0.0
    for _ in range(count):
        dt = float(rng.choice(dt_choices)) if dt_choices is not None else float(
            rng.exponential(0.1))
        t += dt
        R = float(rng.uniform(*R_range))
        steps.append((10.0 * t + float(rng.normal(0.0, math.sqrt(R))), dt, R))
    return steps


NOISES = [
    None,
    WhiteNoiseAcceleration(0.0),
    WhiteNoiseAcceleration(0.5),
    WhiteNoiseAcceleration(30.0),
    PerStepNoise([[0.0, 0.0], [0.0, 0.05]], 0.1),
    PerStepNoise([[1e-4, 2e-5], [2e-5, 1e-4]], 1.0),
]


@pytest.mark.parametrize('noise', NOISES, ids=repr)
def test_equals_generic_path_with_irregular_dt(noise):
    """Every step's state, covariance and statistics equal kalman.py's to 1e-9."""
    rng = np.random.default_rng(5)
    steps = _random_steps(rng, 300)
    # dt = 0 (two measurements at once) and whole multiples of a period, too
    steps += _random_steps(rng, 50, dt_choices=[0.0, 0.1, 0.2, 0.30000000000000004, 1.0])
    _compare([0.0, 5.0], np.eye(2), noise, steps)


def test_custom_noise_callable():
    """Any callable dt -> Q is used and its Q validated; results equal the generic path."""
    def noise(dt):
        return np.array([[0.2 * dt, 0.01 * dt], [0.01 * dt, 0.3 * dt]])
    steps = _random_steps(np.random.default_rng(6), 100)
    _compare([1.0, -2.0], [[4.0, 1.0], [1.0, 3.0]], noise, steps)

    bad = FastTrainFilter([0.0, 0.0], np.eye(2), lambda dt: [[1.0, 2.0], [2.0, 1.0]], R=1.0)
    before = bad.state
    with pytest.raises(ValueError, match=r'^Q must be positive semi-definite'):
        bad.step(0.0, 0.1)
    assert bad.state == before


@pytest.mark.parametrize('x0, P0, R, q', [
    # R ≪ P⁻00: the gain is 1 - 1e-7, where 1 - K0 would lose digits (a = R/S does not).
    ([0.0, 0.0], np.diag([1e3, 1e3]), 1e-4, 0.0),
    # A huge, strongly correlated prior.
    ([1e5, 50.0], [[1e12, 9.99e8], [9.99e8, 1e6]], 1.0, 1e-3),
    # R = 0: the position becomes certain after one update.
    ([0.0, 1.0], np.eye(2), 0.0, 0.1),
    # A nearly singular prior (correlation 1 - 1e-12).
    ([0.0, 1.0], [[1.0, 1.0 - 1e-12], [1.0 - 1e-12, 1.0]], 0.5, 0.0),
    # Q = 0 for 2000 steps: P shrinks towards zero.
    ([0.0, 5.0], np.eye(2), 1.0, 0.0),
])
def test_hard_cases_equal_the_generic_joseph_form(x0, P0, R, q):
    """Where the textbook update loses digits the fast path still matches Joseph to 1e-9."""
    rng = np.random.default_rng(7)
    count = 2000 if q == 0.0 and R == 1.0 else 200
    steps = [(float(10.0 * 0.1 * k + rng.normal()), 0.1, R) for k in range(1, count + 1)]
    fast = _compare(x0, P0, WhiteNoiseAcceleration(q), steps)
    P = fast.P
    assert P[0, 0] >= 0.0 and P[1, 1] >= 0.0


def _exact_run(x0, P0, steps):
    """Return each step's posterior (x, P) in exact rational arithmetic (Q = 0)."""
    x = [Fraction(v) for v in x0]
    P = [[Fraction(v) for v in row] for row in P0]
    out = []
    for z, dt, R in steps:
        z, dt, R = Fraction(z), Fraction(dt), Fraction(R)
        x = [x[0] + dt * x[1], x[1]]
        p00 = P[0][0] + 2 * dt * P[0][1] + dt * dt * P[1][1]
        p01, p11 = P[0][1] + dt * P[1][1], P[1][1]
        s = p00 + R
        k0, k1, y = p00 / s, p01 / s, z - x[0]
        x = [x[0] + k0 * y, x[1] + k1 * y]
        P = [[p00 - k0 * p00, p01 - k0 * p01], [p01 - k0 * p01, p11 - k1 * p01]]
        out.append((np.array([float(v) for v in x]),
                    np.array([[float(v) for v in row] for row in P]),
                    max(abs(float(p00)), abs(float(p01)), abs(float(p11)))))
    return out


@pytest.mark.parametrize('P0, R', [
    (np.diag([1e6, 1e6]), 1e-6),
    (np.diag([1e8, 1e4]), 1e-8),
    ([[1e12, 9.99e8], [9.99e8, 1e6]], 1e-3),
])
def test_badly_conditioned_cases_against_exact_arithmetic(P0, R):
    """
    Compare both paths with the exact rational solution where the update cancels digits.

    Here P shrinks by up to 10¹⁰ in one update, so P⁻11 - K1 P⁻01 loses that factor
    times the rounding of its terms whatever the form; each step's error may be
    64·eps·|P⁻|/|P| relative to |P| (the prior's scale over the posterior's),
    for the fast and for the generic path alike.
    """
    rng = np.random.default_rng(12)
    steps = [(float(10.0 * 0.1 * k + rng.normal()), 0.1, R) for k in range(1, 40)]
    exact = _exact_run([0.0, 0.0], P0, steps)
    fast = FastTrainFilter([0.0, 0.0], P0, None)
    x, P = np.zeros(2), np.asarray(P0, dtype=float)
    amplification = 1.0
    eps = np.finfo(float).eps
    for (z, dt, R), (x_exact, P_exact, prior_scale) in zip(steps, exact):
        fast.step(z, dt, R)
        x, P = kalman.predict(x, P, constant_velocity_F(dt), np.zeros((2, 2)))
        x, P, _ = kalman.update(x, P, [z], POSITION_H, [[R]])
        scale = np.max(np.abs(P_exact))
        amplification = max(amplification, prior_scale / scale)
        bound = 64 * eps * amplification
        for P_ours in (fast.P, P):
            assert np.max(np.abs(P_ours - P_exact)) <= bound * scale
        for x_ours in (fast.x, x):
            assert np.max(np.abs(x_ours - x_exact)) <= bound * np.max(np.abs(x_exact))


@settings(max_examples=150, deadline=None)
@given(
    p00=st.floats(1e-6, 1e6), p11=st.floats(1e-6, 1e6), rho=st.floats(-0.999, 0.999),
    z=st.floats(-1e4, 1e4), dt=st.floats(0.0, 10.0), R=st.floats(1e-6, 1e6),
    q=st.floats(0.0, 100.0))
def test_property_one_step_equals_generic(p00, p11, rho, z, dt, R, q):
    """One predict+update from any well-posed prior equals kalman.py's to 1e-9."""
    p01 = rho * math.sqrt(p00 * p11)
    P0 = [[p00, p01], [p01, p11]]
    _compare([3.0, -1.0], P0, WhiteNoiseAcceleration(q), [(z, dt, R)])


def test_step_is_predict_then_update_bit_for_bit():
    """step(z, dt, R) is exactly predict(dt) followed by update(z, R)."""
    noise = PerStepNoise([[0.01, 0.002], [0.002, 0.05]], 0.1)
    one = FastTrainFilter([0.0, 5.0], np.eye(2), noise)
    two = one.copy()
    for z, dt, R in _random_steps(np.random.default_rng(8), 200):
        nis = one.step(z, dt, R)
        two.predict(dt)
        result = two.update(z, R)
        assert one.state == two.state
        assert nis == result.nis == two.nis
        assert one.last_update() == result


def test_run_equals_step_by_step():
    """run() over a series gives each row's step() result, bit for bit, and the same end."""
    noise = WhiteNoiseAcceleration(0.3)
    steps = _random_steps(np.random.default_rng(9), 400)
    z, dt, R = (np.array(column) for column in zip(*steps))
    stepped = FastTrainFilter([0.0, 5.0], np.eye(2), noise)
    rows = []
    for row in steps:
        stepped.step(*row)
        rows.append(stepped.state + (stepped.innovation, stepped.innovation_variance,
                                     stepped.nis))
    rows = np.array(rows)
    batch = FastTrainFilter([0.0, 5.0], np.eye(2), noise)
    out = batch.run(z, dt, R)
    np.testing.assert_array_equal(out.x, rows[:, 0:2])
    np.testing.assert_array_equal(out.P[:, 0, 0], rows[:, 2])
    np.testing.assert_array_equal(out.P[:, 0, 1], rows[:, 3])
    np.testing.assert_array_equal(out.P[:, 1, 0], rows[:, 3])
    np.testing.assert_array_equal(out.P[:, 1, 1], rows[:, 4])
    np.testing.assert_array_equal(out.innovation, rows[:, 5])
    np.testing.assert_array_equal(out.innovation_variance, rows[:, 6])
    np.testing.assert_array_equal(out.nis, rows[:, 7])
    assert batch.state == stepped.state
    # Scalar dt and R broadcast; a default R is used when none is given.
    default = FastTrainFilter([0.0, 5.0], np.eye(2), noise, R=2.0)
    np.testing.assert_array_equal(default.run(z, 0.1).x,
                                  FastTrainFilter([0.0, 5.0], np.eye(2), noise)
                                  .run(z, np.full(z.shape, 0.1), 2.0).x)


def test_run_failure_names_the_row_and_keeps_the_good_rows():
    """A row that overflows raises naming it; the filter stays after the row before."""
    z = np.array([1.0, 2.0, 3.0, 4.0])
    dt = np.array([0.1, 0.1, 1e200, 0.1])
    fast = FastTrainFilter([0.0, 5.0], np.eye(2), WhiteNoiseAcceleration(1.0), R=1.0)
    reference = fast.copy()
    reference.step(1.0, 0.1)
    reference.step(2.0, 0.1)
    with pytest.raises(ValueError, match=r'^row 2: prediction produced a non-finite'):
        fast.run(z, dt)
    assert fast.state == reference.state
    with pytest.raises(ValueError, match=r'^dt_s must be >= 0'):
        fast.run(z, [0.1, -0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match=r'^dt_s must have length 4'):
        fast.run(z, [0.1, 0.1])
    with pytest.raises(ValueError, match=r'^R must be >= 0'):
        fast.run(z, 0.1, -1.0)
    assert fast.state == reference.state


def test_noise_terms_equal_the_models_bit_for_bit():
    """The closed-form Q(dt) entries are exactly models.py's for every kind of dt."""
    rng = np.random.default_rng(10)
    dts = [0.0, 0.1, 0.2, 0.3, 0.30000000000000004, 1.0, 2.0, 1e-9, 123.456]
    dts += rng.exponential(0.5, 200).tolist()
    wna = WhiteNoiseAcceleration(0.7)
    per_step = PerStepNoise([[0.01, 0.002], [0.002, 0.05]], 0.1)
    for dt in dts:
        Q = wna(dt)
        assert white_noise_terms(0.7, dt) == (Q[0, 0], Q[0, 1], Q[1, 1])
        assert Q[0, 1] == Q[1, 0]
        Q = per_step(dt)
        assert per_step_noise_terms(0.01, 0.002, 0.05, 0.1, dt) == (
            Q[0, 0], Q[0, 1], Q[1, 1])


def test_from_model_uses_the_models_noise_and_R():
    """from_model takes Q(dt) and R from a constant-velocity model and rejects others."""
    model = constant_velocity_model(WhiteNoiseAcceleration(0.2), R=4.0)
    fast = FastTrainFilter.from_model(model, [0.0, 1.0], np.eye(2))
    assert fast.R == 4.0
    steps = [(z, 0.1, 4.0) for z in (0.3, 0.1, 0.5)]
    for (z, dt, _), (x, P, _) in zip(steps, _generic_run([0.0, 1.0], np.eye(2),
                                                         model.Q, steps)):
        fast.step(z, dt)
        _close(fast.x, x)
        _close(fast.P, P)
    other = LinearModel(lambda dt: np.eye(2), WhiteNoiseAcceleration(0.2), POSITION_H,
                        [[1.0]])
    with pytest.raises(ValueError, match=r'^model must be the constant-velocity'):
        FastTrainFilter.from_model(other, [0.0, 1.0], np.eye(2))
    velocity = LinearModel(constant_velocity_F, WhiteNoiseAcceleration(0.2), [[0.0, 1.0]],
                           [[1.0]], measurement_names=('velocity',))
    with pytest.raises(ValueError, match=r'^model must be the constant-velocity'):
        FastTrainFilter.from_model(velocity, [0.0, 1.0], np.eye(2))


def test_accepts_numbers_of_any_real_type():
    """Ints and numpy scalars give the same result as floats, and the state stays float."""
    a = FastTrainFilter([0, 5], np.eye(2, dtype=int), WhiteNoiseAcceleration(1), R=1)
    b = FastTrainFilter([0.0, 5.0], np.eye(2), WhiteNoiseAcceleration(1.0), R=1.0)
    a.step(np.float32(1.5), np.float64(0.25), np.int64(2))
    b.step(1.5, 0.25, 2.0)
    assert a.state == b.state
    assert all(type(v) is float for v in a.state)


@pytest.mark.parametrize('call, pattern', [
    (lambda f: f.step(NAN, 0.1, 1.0), r'^z must be a finite number'),
    (lambda f: f.step(INF, 0.1, 1.0), r'^z must be a finite number'),
    (lambda f: f.step('z', 0.1, 1.0), r'^z must be a finite number'),
    (lambda f: f.step(None, 0.1, 1.0), r'^z must be a finite number'),
    (lambda f: f.step(np.float64(NAN), 0.1, 1.0), r'^z must be a finite number'),
    (lambda f: f.step(1.0, -0.1, 1.0), r'^dt must be >= 0'),
    (lambda f: f.step(1.0, NAN, 1.0), r'^dt must be finite'),
    (lambda f: f.step(1.0, INF, 1.0), r'^dt must be finite'),
    (lambda f: f.step(1.0, 'dt', 1.0), r'^dt must be a finite number'),
    (lambda f: f.step(1.0, 0.1, -1.0), r'^R must be a finite number >= 0'),
    (lambda f: f.step(1.0, 0.1, NAN), r'^R must be a finite number >= 0'),
    (lambda f: f.step(1.0, 0.1, INF), r'^R must be a finite number >= 0'),
    (lambda f: f.step(1.0, 0.1, [1.0, 2.0]), r'^R must be a finite number'),
    (lambda f: f.step(1.0, 0.1), r'^R must be given'),
    (lambda f: f.update(NAN, 1.0), r'^z must be a finite number'),
    (lambda f: f.update(1.0), r'^R must be given'),
    (lambda f: f.update(1.0, -2.0), r'^R must be a finite number >= 0'),
    (lambda f: f.predict(-1.0), r'^dt must be >= 0'),
    (lambda f: f.predict(NAN), r'^dt must be finite'),
    (lambda f: f.predict(1e300), r'^prediction produced a non-finite state'),
    (lambda f: f.step(1.0, 1e300, 1.0), r'^prediction produced a non-finite state'),
    (lambda f: f.step(1e300, 0.1, 1.0), r'^update produced an invalid NIS'),
])
def test_rejections_name_the_input_and_keep_the_state(call, pattern):
    """A rejected call raises ValueError naming the cause; the state is unchanged."""
    fast = FastTrainFilter([1.0, 2.0], [[2.0, 0.5], [0.5, 1.0]], WhiteNoiseAcceleration(1.0))
    fast.step(1.2, 0.1, 1.0)
    state, stats = fast.state, fast.last_update()
    with pytest.raises(ValueError, match=pattern):
        call(fast)
    assert fast.state == state
    assert fast.last_update() == stats


def test_update_overflow():
    """An update whose state overflows says so, as the generic path does; nothing changes."""
    P0 = [[1.0, 10.0], [10.0, 200.0]]
    fast = FastTrainFilter([0.0, 0.0], P0, None, R=1.0)
    pattern = r'^update produced a non-finite state'
    with pytest.raises(ValueError, match=pattern):
        fast.step(1.7e308, 0.0)
    with pytest.raises(ValueError, match=pattern):
        fast.update(1.7e308)
    with np.errstate(over='ignore'):
        with pytest.raises(ValueError, match=pattern):
            kalman.update([0.0, 0.0], P0, [1.7e308], POSITION_H, [[1.0]])
    assert fast.state == (0.0, 0.0, 1.0, 10.0, 200.0)


def test_singular_innovation_covariance():
    """S = P⁻00 + R = 0 raises as the generic path does; the state is unchanged."""
    fast = FastTrainFilter([1.0, 2.0], [[0.0, 0.0], [0.0, 1.0]], None)
    state = fast.state
    pattern = r'innovation covariance S .* singular'
    with pytest.raises(ValueError, match=pattern):
        fast.step(1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match=pattern):
        fast.update(1.0, 0.0)
    with pytest.raises(ValueError, match=pattern):
        kalman.update([1.0, 2.0], [[0.0, 0.0], [0.0, 1.0]], [1.0], POSITION_H, [[0.0]])
    assert fast.state == state


@pytest.mark.parametrize('x0, P0, noise, R, pattern', [
    ([1.0], np.eye(2), None, 1.0, r'^x must have length 2'),
    ([1.0, NAN], np.eye(2), None, 1.0, r'^x must be finite'),
    ([1.0, 2.0], [[1.0, 2.0], [2.0, 1.0]], None, 1.0, r'^P must be positive semi'),
    ([1.0, 2.0], [[1.0, 0.5], [0.0, 1.0]], None, 1.0, r'^P must be symmetric'),
    ([1.0, 2.0], np.eye(3), None, 1.0, r'^P must have shape'),
    ([1.0, 2.0], np.eye(2), 'q', 1.0, r'^noise must be None'),
    ([1.0, 2.0], np.eye(2), None, -1.0, r'^R must be a finite number >= 0'),
    ([1.0, 2.0], np.eye(2), None, NAN, r'^R must be a finite number'),
])
def test_constructor_rejects(x0, P0, noise, R, pattern):
    """A bad initial state, noise model or default R raises ValueError naming it."""
    with pytest.raises(ValueError, match=pattern):
        FastTrainFilter(x0, P0, noise, R)


def test_copies_are_independent():
    """x, P and copy() do not share state with the filter."""
    fast = FastTrainFilter([0.0, 1.0], np.eye(2), WhiteNoiseAcceleration(1.0), R=1.0)
    twin = fast.copy()
    x, P = fast.x, fast.P
    x[0] = P[0, 0] = 99.0
    fast.step(0.5, 0.1)
    assert twin.state == (0.0, 1.0, 1.0, 0.0, 1.0)
    assert fast.x[0] != 99.0 and fast.P[0, 0] != 99.0
    assert math.isnan(twin.nis)


def test_nis_is_chi2_with_one_degree_of_freedom_on_matching_data():
    """
    On data drawn from the filter's own model the mean NIS is 1 within its sampling error.

    The NIS values of a consistent filter are independent χ²(1) draws (mean 1, variance
    2), so the mean of n lies within 1 ± 5·√(2/n) except with probability < 1e-6.
    """
    rng = np.random.default_rng(11)
    q, R, dt, n = 0.5, 0.25, 0.1, 20000
    Q = WhiteNoiseAcceleration(q)(dt)
    L = np.linalg.cholesky(Q)
    truth = np.array([0.0, 10.0])
    P0 = np.diag([4.0, 1.0])
    fast = FastTrainFilter(truth + np.sqrt(np.diag(P0)) * rng.normal(size=2), P0,
                           WhiteNoiseAcceleration(q), R)
    F = constant_velocity_F(dt)
    total = 0.0
    for _ in range(n):
        truth = F @ truth + L @ rng.normal(size=2)
        total += fast.step(float(truth[0] + math.sqrt(R) * rng.normal()), dt)
    assert abs(total / n - 1.0) < 5.0 * math.sqrt(2.0 / n)
