"""Tests of kf_train.batch.fleet: N filters at once equal N filters one by one."""

import math

from kf_train.batch.fleet import _per_step_noise_arrays, TrainFleet
from kf_train.filters import (
    constant_velocity_F, FastTrainFilter, kalman, per_step_noise_terms, PerStepNoise, POSITION_H,
    WhiteNoiseAcceleration)
import numpy as np
import pytest

NAN, INF = float('nan'), float('inf')
NOISES = [
    None,
    WhiteNoiseAcceleration(0.7),
    PerStepNoise([[0.01, 0.002], [0.002, 0.05]], 0.1),
    lambda dt: np.array([[0.2 * dt, 0.01 * dt], [0.01 * dt, 0.3 * dt]]),
]
NOISE_IDS = ['none', 'white', 'per-step', 'callable']


def _start(rng, n):
    """Return random means (n, 2) and covariances (n, 2, 2) for n filters."""
    x0 = np.column_stack([rng.normal(0.0, 10.0, n), rng.normal(5.0, 2.0, n)])
    a = rng.uniform(0.1, 10.0, n)
    d = rng.uniform(0.1, 10.0, n)
    b = rng.uniform(-0.9, 0.9, n) * np.sqrt(a * d)
    P0 = np.stack([np.column_stack([a, b]), np.column_stack([b, d])], axis=1)
    return x0, P0


def _singles(x0, P0, noise):
    """Return one FastTrainFilter per filter of a fleet."""
    return [FastTrainFilter(x0[i], P0[i], noise) for i in range(x0.shape[0])]


def _assert_same(fleet, singles, index=None):
    """Assert that the fleet's filters equal the single filters bit for bit."""
    numbers = range(len(fleet)) if index is None else index
    for i in numbers:
        single = singles[i]
        assert fleet.filter_state(i) == single.state, i
        for ours, theirs in ((fleet.innovation, single.innovation),
                             (fleet.innovation_variance, single.innovation_variance),
                             (fleet.nis, single.nis)):
            assert ours[i] == theirs or (math.isnan(ours[i]) and math.isnan(theirs)), i


@pytest.mark.parametrize('noise', NOISES, ids=NOISE_IDS)
@pytest.mark.parametrize('chunk_size', [7, 32768])
def test_fleet_equals_each_filter_alone(noise, chunk_size):
    """Per-filter z, dt and R: every filter equals a FastTrainFilter fed the same, bitwise."""
    rng = np.random.default_rng(20)
    n = 53  # not a multiple of the chunk size
    x0, P0 = _start(rng, n)
    fleet = TrainFleet(x0, P0, noise, chunk_size=chunk_size)
    singles = _singles(x0, P0, noise)
    for k in range(40):
        z = rng.normal(0.0, 10.0, n) + k
        dt = rng.choice([0.0, 0.05, 0.1, 0.2, 0.30000000000000004, 1.7], n)
        R = rng.uniform(0.01, 5.0, n)
        fleet.step(z, dt, R)
        for i, single in enumerate(singles):
            single.step(float(z[i]), float(dt[i]), float(R[i]))
        _assert_same(fleet, singles)


@pytest.mark.parametrize('noise', NOISES[1:3], ids=NOISE_IDS[1:3])
def test_fleet_with_arbitrary_per_filter_dt(noise):
    """
    Per-filter dt of any value: every filter equals its FastTrainFilter to a few ulps.

    Q(dt) is then computed by numpy for the whole array, whose dt² is correctly
    rounded, where CPython's float ** (used by models.py and the scalar path) is off
    by one ulp for about 1 dt in 700; the states agree to 1e-13.
    """
    rng = np.random.default_rng(26)
    n = 40
    x0, P0 = _start(rng, n)
    fleet = TrainFleet(x0, P0, noise, R=0.7)
    singles = [FastTrainFilter(x0[i], P0[i], noise, R=0.7) for i in range(n)]
    for k in range(60):
        z = rng.normal(0.0, 1.0, n) + k
        dt = rng.exponential(0.3, n)
        fleet.step(z, dt)
        for i, single in enumerate(singles):
            single.step(float(z[i]), float(dt[i]))
    for i, single in enumerate(singles):
        np.testing.assert_allclose(fleet.filter_state(i), single.state, rtol=1e-13,
                                   atol=1e-13)
        np.testing.assert_allclose(fleet.nis[i], single.nis, rtol=1e-12, atol=1e-13)


def test_fleet_equals_the_generic_path():
    """A few filters of a fleet against kalman.predict/update, to 1e-9."""
    rng = np.random.default_rng(21)
    n = 5
    noise = WhiteNoiseAcceleration(0.4)
    x0, P0 = _start(rng, n)
    fleet = TrainFleet(x0, P0, noise)
    states = [(x0[i], P0[i]) for i in range(n)]
    for k in range(100):
        z = rng.normal(0.0, 1.0, n) + 0.5 * k
        dt = rng.exponential(0.1, n)
        fleet.step(z, dt, 0.5)
        for i in range(n):
            x, P = kalman.predict(*states[i], constant_velocity_F(dt[i]), noise(dt[i]))
            x, P, result = kalman.update(x, P, [z[i]], POSITION_H, [[0.5]])
            states[i] = (x, P)
            np.testing.assert_allclose(fleet.x[i], x, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(fleet.P[i], P, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(fleet.nis[i], result.nis, rtol=1e-9, atol=1e-12)


def test_scalar_inputs_and_default_R_broadcast():
    """A scalar z, dt or R is shared by all filters; a default R (scalar or per filter) is used."""
    rng = np.random.default_rng(22)
    n = 10
    noise = WhiteNoiseAcceleration(0.2)
    x0, P0 = _start(rng, n)
    R = rng.uniform(0.5, 2.0, n)
    a = TrainFleet(x0, P0, noise, R=R)
    b = TrainFleet(x0, P0[0], noise)
    singles = [FastTrainFilter(x0[i], P0[0], noise) for i in range(n)]
    for k in range(20):
        a.step(np.full(n, 3.0), 0.1)
        b.step(3.0, np.full(n, 0.1), 1.5)
        for single in singles:
            single.step(3.0, 0.1, 1.5)
    _assert_same(b, singles)
    check = [FastTrainFilter(x0[i], P0[i], noise, R=R[i]) for i in range(n)]
    for k in range(20):
        for single in check:
            single.step(3.0, 0.1)
    _assert_same(a, check)


def test_index_steps_only_those_filters():
    """With index only the named filters change; the rest stay bit for bit as they were."""
    rng = np.random.default_rng(23)
    n = 30
    noise = PerStepNoise([[0.0, 0.0], [0.0, 0.05]], 0.1)
    x0, P0 = _start(rng, n)
    fleet = TrainFleet(x0, P0, noise, R=np.linspace(0.5, 2.0, n), chunk_size=4)
    singles = [FastTrainFilter(x0[i], P0[i], noise, R=float(fleet.R[i])) for i in range(n)]
    for k in range(30):
        index = rng.choice(n, size=int(rng.integers(0, n)), replace=False)
        z = rng.normal(0.0, 1.0, index.size) + k
        dt = rng.exponential(0.2, index.size)
        fleet.step(z, dt, index=index)
        for j, i in enumerate(index):
            singles[i].step(float(z[j]), float(dt[j]))
        _assert_same(fleet, singles)


def test_predict_and_update_apart():
    """predict() and update() alone equal the single filter's, and keep the statistics."""
    rng = np.random.default_rng(24)
    n = 12
    noise = WhiteNoiseAcceleration(1.0)
    x0, P0 = _start(rng, n)
    fleet = TrainFleet(x0, P0, noise, R=1.0)
    singles = [FastTrainFilter(x0[i], P0[i], noise, R=1.0) for i in range(n)]
    z = rng.normal(size=n)
    fleet.update(z)
    for i, single in enumerate(singles):
        single.update(float(z[i]))
    _assert_same(fleet, singles)
    dt = rng.exponential(0.3, n)
    fleet.predict(dt)
    fleet.predict(0.25, index=[1, 3])
    for i, single in enumerate(singles):
        single.predict(float(dt[i]))
    singles[1].predict(0.25)
    singles[3].predict(0.25)
    _assert_same(fleet, singles)  # the statistics are still those of the update


def test_vectorised_noise_terms_equal_the_scalar_ones():
    """The (n,) per-step noise and white-noise terms equal the scalar closed forms."""
    rng = np.random.default_rng(25)
    dt = np.concatenate([[0.0, 0.1, 0.2, 0.3, 0.30000000000000004, 1.0, 1e-9, 1e4],
                         rng.exponential(0.5, 500)])
    noise = PerStepNoise([[0.01, 0.002], [0.002, 0.05]], 0.1)
    q00, q01, q11 = _per_step_noise_arrays(noise, dt)
    for i, value in enumerate(dt):
        assert (q00[i], q01[i], q11[i]) == per_step_noise_terms(0.01, 0.002, 0.05, 0.1,
                                                                float(value))
        Q = noise(float(value))
        assert (q00[i], q01[i], q11[i]) == (Q[0, 0], Q[0, 1], Q[1, 1])
    fleet = TrainFleet(np.zeros((dt.size, 2)), np.eye(2), WhiteNoiseAcceleration(0.3))
    terms = fleet._noise_terms(dt)(dt, [np.empty(dt.size) for _ in range(3)])
    Q = np.array([WhiteNoiseAcceleration(0.3)(float(value)) for value in dt])
    for k, (row, col) in enumerate(((0, 0), (0, 1), (1, 1))):
        # numpy's dt² is correctly rounded, CPython's dt ** 2 not always: an ulp or
        # two after the products.
        np.testing.assert_array_max_ulp(terms[k], Q[:, row, col], maxulp=4)


def test_views_are_read_only_and_properties_are_copies():
    """State and statistics views cannot be written; x and P are fresh arrays."""
    fleet = TrainFleet([[0.0, 1.0], [2.0, 3.0]], np.eye(2), None, R=1.0)
    with pytest.raises(ValueError):
        fleet.state.position[0] = 5.0
    with pytest.raises(ValueError):
        fleet.nis[0] = 5.0
    x, P = fleet.x, fleet.P
    x[0, 0] = P[0, 0, 0] = 99.0
    assert fleet.filter_state(0) == (0.0, 1.0, 1.0, 0.0, 1.0)
    np.testing.assert_array_equal(fleet.x, [[0.0, 1.0], [2.0, 3.0]])
    np.testing.assert_array_equal(fleet.P, [np.eye(2), np.eye(2)])
    assert len(fleet) == 2 and np.isnan(fleet.nis).all()


def _fleet_after_one_step():
    """Return a 6-filter fleet after one step and a copy of all its arrays."""
    x0 = np.column_stack([np.arange(6.0), np.ones(6)])
    fleet = TrainFleet(x0, np.eye(2), WhiteNoiseAcceleration(1.0), R=1.0, chunk_size=4)
    fleet.step(np.arange(6.0), 0.1)
    return fleet, _snapshot(fleet)


def _snapshot(fleet):
    """Return copies of every state and statistics array of a fleet."""
    return [a.copy() for a in fleet.state] + [
        fleet.innovation.copy(), fleet.innovation_variance.copy(), fleet.nis.copy()]


def _big(index, value):
    """Return an array of six ones with ``value`` at ``index``."""
    array = np.ones(6)
    array[index] = value
    return array


@pytest.mark.parametrize('call, pattern', [
    (lambda f: f.step(_big(4, NAN), 0.1), r'^z must be finite, got nan for filter 4'),
    (lambda f: f.step(_big(2, INF), 0.1), r'^z must be finite, got inf for filter 2'),
    (lambda f: f.step(np.ones(5), 0.1), r'^z must be a scalar or have shape \(6,\)'),
    (lambda f: f.step('z', 0.1), r'^z must be numeric'),
    (lambda f: f.step(np.ones(6), _big(3, -0.1)), r'^dt_s must be >= 0, got -0.1 for filter 3'),
    (lambda f: f.step(np.ones(6), -1.0), r'^dt_s must be >= 0, got -1.0$'),
    (lambda f: f.step(np.ones(6), _big(1, NAN)), r'^dt_s must be finite, got nan for filter 1'),
    (lambda f: f.step(np.ones(6), 0.1, _big(5, -2.0)), r'^R must be >= 0, got -2.0 for filter 5'),
    (lambda f: f.step(np.ones(6), 0.1, INF), r'^R must be finite'),
    (lambda f: f.step(np.ones(6), _big(2, 1e300)),
     r'^filter 2: prediction produced a non-finite state'),
    (lambda f: f.step(_big(3, 1e300), 0.1), r'^filter 3: update produced an invalid NIS'),
    (lambda f: f.predict(_big(0, 1e300)), r'^filter 0: prediction produced a non-finite'),
    (lambda f: f.step(np.ones(2), 0.1, index=[0, 0]), r'^index must not repeat'),
    (lambda f: f.step(np.ones(2), 0.1, index=[0, 6]), r'^index must be in \[0, 6\)'),
    (lambda f: f.step(np.ones(2), 0.1, index=[0.0, 1.0]), r'^index must be a 1-D array'),
    (lambda f: f.step(np.ones(3), 0.1, index=[0, 1]), r'^z must be a scalar or have shape'),
    (lambda f: f.step([1e300, 1.0], 0.1, index=[4, 3]),
     r'^filter 4: update produced an invalid NIS'),
    (lambda f: f.update(None), r'^z must be given'),
])
def test_rejections_name_the_input_and_filter_and_change_nothing(call, pattern):
    """A rejected step raises ValueError naming the cause; no filter changes."""
    fleet, before = _fleet_after_one_step()
    with np.errstate(over='ignore'):
        with pytest.raises(ValueError, match=pattern):
            call(fleet)
    for ours, theirs in zip(_snapshot(fleet), before):
        np.testing.assert_array_equal(ours, theirs)


def test_singular_innovation_covariance_names_the_filter():
    """S = P⁻00 + R = 0 in one filter raises naming it; nothing changes."""
    P0 = np.array([np.eye(2), [[0.0, 0.0], [0.0, 1.0]], np.eye(2)])
    fleet = TrainFleet(np.zeros((3, 2)), P0, None)
    before = _snapshot(fleet)
    with pytest.raises(ValueError, match=r'^filter 1: innovation covariance S .* singular'):
        fleet.step(np.ones(3), 0.0, [1.0, 0.0, 1.0])
    for ours, theirs in zip(_snapshot(fleet), before):
        np.testing.assert_array_equal(ours, theirs)


def test_update_overflow_names_the_filter():
    """An update whose state overflows (K1·y > max double) is named as such."""
    P0 = np.array([np.eye(2), [[1.0, 10.0], [10.0, 200.0]]])
    fleet = TrainFleet(np.zeros((2, 2)), P0, None, R=1.0)
    single = FastTrainFilter([0.0, 0.0], P0[1], None, R=1.0)
    before = _snapshot(fleet)
    pattern = r'update produced a non-finite state'
    with np.errstate(over='ignore'):
        with pytest.raises(ValueError, match=r'^filter 1: ' + pattern):
            fleet.step([0.0, 1.7e308], 0.0)
        with pytest.raises(ValueError, match=r'^' + pattern):
            single.step(1.7e308, 0.0)
    for ours, theirs in zip(_snapshot(fleet), before):
        np.testing.assert_array_equal(ours, theirs)


def test_missing_R():
    """Without a default R every update must pass one."""
    fleet = TrainFleet(np.zeros((2, 2)), np.eye(2), None)
    with pytest.raises(ValueError, match=r'^R must be given'):
        fleet.step(np.ones(2), 0.1)


@pytest.mark.parametrize('x0, P0, kwargs, pattern', [
    (np.zeros((3, 3)), np.eye(2), {}, r'^x0 must have shape \(N, 2\)'),
    (np.zeros(3), np.eye(2), {}, r'^x0 must have shape \(N, 2\)'),
    ([[0.0, NAN]], np.eye(2), {}, r'^x0 must be finite'),
    (np.zeros((2, 2)), np.eye(3), {}, r'^P0 must have shape \(2, 2, 2\) or \(2, 2\)'),
    (np.zeros((2, 2)), [np.eye(2), [[1.0, 0.5], [0.0, 1.0]]], {},
     r'^P0 must be symmetric, .* for filter 1'),
    (np.zeros((2, 2)), [[[1.0, 2.0], [2.0, 1.0]], np.eye(2)], {},
     r'^P0 must be positive semi-definite, .* for filter 0'),
    (np.zeros((2, 2)), [[INF, 0.0], [0.0, 1.0]], {}, r'^P0 must be finite'),
    (np.zeros((2, 2)), np.eye(2), {'R': [1.0, -1.0]}, r'^R must be >= 0'),
    (np.zeros((2, 2)), np.eye(2), {'R': [1.0, 1.0, 1.0]}, r'^R must be a scalar or have'),
    (np.zeros((2, 2)), np.eye(2), {'chunk_size': 0}, r'^chunk_size must be >= 1'),
    (np.zeros((2, 2)), np.eye(2), {'noise': 3.0}, r'^noise must be None'),
])
def test_constructor_rejects(x0, P0, kwargs, pattern):
    """Bad initial states, covariances, R, noise or chunk size raise ValueError naming them."""
    noise = kwargs.pop('noise', None)
    with pytest.raises(ValueError, match=pattern):
        TrainFleet(x0, P0, noise, **kwargs)


def test_empty_fleet_and_empty_index():
    """A fleet of none and an index of none are valid and do nothing."""
    empty = TrainFleet(np.zeros((0, 2)), np.zeros((0, 2, 2)), None, R=1.0)
    empty.step(np.zeros(0), 0.1)
    assert len(empty) == 0 and empty.x.shape == (0, 2)
    fleet, before = _fleet_after_one_step()
    fleet.step(np.zeros(0), 0.1, index=np.zeros(0, dtype=int))
    for ours, theirs in zip(_snapshot(fleet), before):
        np.testing.assert_array_equal(ours, theirs)
