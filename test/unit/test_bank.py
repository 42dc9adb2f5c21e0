"""
Tests of kf_train.batch.bank, the one vectorised multi-object engine.

Ported from the tests of the train fleet (TrainFleet, removed in issue 22:
the replay runs the bank, the fleet was only API and bench): N objects at once equal
N objects one by one, for every kind of process noise and both of the bank's
strategies (lock-step, each object along its own time axis); other objects never
change an object's result; bad input raises ValueError naming it and the row.
"""

from kf_train.batch import bank, run_bank, run_series, SeriesError
from kf_train.filters import (
    constant_velocity_F, kalman, NS_PER_S, per_step_noise_terms, POSITION_H)
from kf_train.presets import load_preset, preset_from_mapping
import numpy as np
import pytest

NAN, INF = float('nan'), float('inf')
NOISES = {
    'none': {'per_step': [[0.0, 0.0], [0.0, 0.0]]},
    'white': {'continuous': [[0.0, 0.0], [0.0, 0.7]]},
    'per-step': {'per_step': [[0.01, 0.002], [0.002, 0.05]]},
    'both': {'per_step': [[0.01, 0.0], [0.0, 0.05]], 'continuous': [[0.1, 0.0], [0.0, 0.3]]},
}
SPLITS = ['lock-step', 'alone', 'cost model']
FIELDS = ('x', 'P', 'x_prior', 'P_prior')


def _preset(noise: str, R: float = 0.7, period_s: float = 0.1):
    """Return the train's constant-velocity preset with the named process noise."""
    return preset_from_mapping({
        'name': f'train-{noise}', 'states': ['position', 'velocity'],
        'measurements': ['position'], 'motion': 'constant_velocity',
        'process_noise': NOISES[noise], 'R': [[R]], 'initial_state': [0.0, 5.0],
        'initial_covariance': [4.0, 1.0], 'nominal_period_s': period_s})


def _split(monkeypatch, split: str) -> None:
    """Make the bank run every object in lock-step, every object alone, or its mix."""
    if split == 'lock-step':
        monkeypatch.setattr(bank, 'LOCKSTEP_STEP_S', 0.0)
    elif split == 'alone':
        monkeypatch.setattr(bank, 'SERIES_CALL_S', 0.0)
    else:  # a few long objects alone, the many short ones in lock-step
        monkeypatch.setattr(bank, 'SERIES_CALL_S', 1e-3)
        monkeypatch.setattr(bank, 'LOCKSTEP_STEP_S', 1e-4)


def _objects(rng, counts, steps):
    """Return (t, z, ids): objects with ``counts`` rows, dt drawn by ``steps``, interleaved."""
    t, ids = [], []
    for k, count in enumerate(counts):
        t.append(rng.uniform(0.0, 0.3) + np.cumsum(steps(rng, count)))
        ids += [k] * count
    t, ids = np.concatenate(t), np.array(ids)
    order = np.argsort(t, kind='stable')
    t, ids = t[order], ids[order]
    z = 5.0 * t[:, None] + rng.normal(0.0, 1.0, (t.shape[0], 1))
    return t, z, ids


def _grid_steps(rng, count):
    """Return dt drawn from a few values (a bank caches Q(dt) per distinct dt)."""
    return rng.choice([0.05, 0.1, 0.2, 0.30000000000000004, 1.7], count)


def _close(a, b, tol=1e-9):
    """Assert |a − b| <= tol · max(1, |b|) elementwise (rounding only: test_replay_bank)."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    assert np.all(np.abs(a - b) <= tol * np.maximum(1.0, np.abs(b))), np.max(np.abs(a - b))


def _check_each_alone(result, preset, t, z, ids, horizon_s=None):
    """Assert that every object's rows of ``result`` equal that object filtered alone."""
    for label in np.unique(ids):
        rows = np.flatnonzero(ids == label)
        alone = run_series(preset, t[rows], z[rows], None, horizon_s=horizon_s)
        for field in FIELDS + (('predicted_x', 'predicted_P') if horizon_s else ()):
            _close(getattr(result, field)[rows], getattr(alone, field))


@pytest.mark.parametrize('noise', list(NOISES))
@pytest.mark.parametrize('split', SPLITS)
def test_bank_equals_each_object_alone(monkeypatch, noise, split):
    """Every object equals its own series, for every process noise and strategy."""
    _split(monkeypatch, split)
    preset = _preset(noise)
    rng = np.random.default_rng(20)
    t, z, ids = _objects(rng, [300, 250] + [1, 2, 5, 40, 17, 3, 12] * 3, _grid_steps)
    result = run_bank(preset, t, z, None, ids)
    np.testing.assert_array_equal(result.t_s, t)
    _check_each_alone(result, preset, t, z, ids)


@pytest.mark.parametrize('noise', ['white', 'per-step'])
@pytest.mark.parametrize('split', ['lock-step', 'alone'])
def test_bank_with_arbitrary_per_object_dt(monkeypatch, noise, split):
    """Each object on its own irregular clock (every dt distinct) equals its series."""
    _split(monkeypatch, split)
    preset = _preset(noise)
    rng = np.random.default_rng(26)
    t, z, ids = _objects(rng, [60] * 12, lambda r, n: r.exponential(0.3, n) + 1e-3)
    _check_each_alone(run_bank(preset, t, z, None, ids), preset, t, z, ids)


@pytest.mark.parametrize('split', ['lock-step', 'alone'])
def test_bank_equals_the_generic_path(monkeypatch, split):
    """A few objects of a bank against kalman.predict/update, row by row, to 1e-9."""
    _split(monkeypatch, split)
    preset = _preset('white', R=0.5)
    rng = np.random.default_rng(21)
    t, z, ids = _objects(rng, [100] * 5, lambda r, n: r.exponential(0.1, n) + 1e-3)
    result = run_bank(preset, t, z, None, ids)
    for label in range(5):
        x, P, previous = preset.initial_state, preset.initial_covariance, 0
        for row in np.flatnonzero(ids == label):
            stamp = int(np.rint(t[row] * NS_PER_S))  # the bank's dt: whole nanoseconds
            dt, previous = (stamp - previous) / NS_PER_S, stamp
            x, P = kalman.predict(x, P, constant_velocity_F(dt), preset.model.Q(dt))
            x, P, _ = kalman.update(x, P, z[row], POSITION_H, [[0.5]])
            # Rounding only, well conditioned (scalar S): as test_core_kalman.RTOL.
            np.testing.assert_allclose(result.x[row], x, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(result.P[row], P, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize('noise', ['white', 'per-step'])
def test_other_objects_leave_an_object_bit_for_bit(monkeypatch, noise):
    """In lock-step, adding other objects' rows changes no bit of an object's results."""
    _split(monkeypatch, 'lock-step')
    preset = _preset(noise)
    rng = np.random.default_rng(23)
    t, z, ids = _objects(rng, [30, 7, 19, 1, 25, 12], _grid_steps)
    mine = ids < 3
    alone = run_bank(preset, t[mine], z[mine], None, ids[mine])
    together = run_bank(preset, t, z, None, ids)
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(together, field)[mine], getattr(alone, field))


@pytest.mark.parametrize('split', ['lock-step', 'alone'])
def test_horizon_predictions_equal_each_object_alone(monkeypatch, split):
    """The predictions to t + horizon of every row equal each object's own series."""
    _split(monkeypatch, split)
    preset = _preset('white')
    rng = np.random.default_rng(24)
    t, z, ids = _objects(rng, [12, 3, 30, 1, 8], _grid_steps)
    result = run_bank(preset, t, z, None, ids, horizon_s=1.5)
    _check_each_alone(result, preset, t, z, ids, horizon_s=1.5)


def test_per_step_noise_of_a_preset_equals_the_scalar_terms():
    """A preset's per-step Q(dt) for an array of dt equals the scalar closed form exactly."""
    rng = np.random.default_rng(25)
    dt = np.concatenate([[0.0, 0.1, 0.2, 0.3, 0.30000000000000004, 1.0, 1e-9, 1e4],
                         rng.exponential(0.5, 500)])
    Q = _preset('per-step').dynamics.Q_batch(dt)
    for i, value in enumerate(dt.tolist()):
        q00, q01, q11 = per_step_noise_terms(0.01, 0.002, 0.05, 0.1, value)
        assert (Q[i, 0, 0], Q[i, 0, 1], Q[i, 1, 0], Q[i, 1, 1]) == (q00, q01, q01, q11), value


def test_results_are_new_arrays_and_inputs_are_kept():
    """The bank changes none of its inputs; writing a result changes no other run."""
    preset = _preset('white')
    t, z, ids = _objects(np.random.default_rng(22), [5, 9, 2], _grid_steps)
    copies = (t.copy(), z.copy(), ids.copy())
    first = run_bank(preset, t, z, None, ids)
    for array, copy in zip((t, z, ids), copies):
        np.testing.assert_array_equal(array, copy)
    second = run_bank(preset, t, z, None, ids)
    first.x[:] = first.P[:] = 99.0
    for field in FIELDS:
        assert not np.shares_memory(getattr(first, field), getattr(second, field))
    assert not (second.x == 99.0).any() and not (second.P == 99.0).any()


T = np.array([0.1, 0.1, 0.2, 0.2, 0.3, 0.3])
IDS = np.array([0, 1, 0, 1, 0, 1])


def _with(array, index, value):
    """Return a copy of ``array`` with ``value`` at ``index``."""
    array = np.array(array, dtype=float)
    array[index] = value
    return array


def _bank(t=T, z=np.ones((6, 1)), u=None, ids=IDS, name='train', **kwargs):
    """Run a small bank of two objects, three rows each."""
    return run_bank(load_preset(name), t, z, u, ids, **kwargs)


@pytest.mark.parametrize('call, pattern', [
    (lambda: _bank(z=_with(np.ones((6, 1)), 4, NAN)), r'^z must be finite, got .*nan'),
    (lambda: _bank(z=_with(np.ones((6, 1)), 2, INF)), r'^z must be finite, got .*inf'),
    (lambda: _bank(z=np.ones((5, 1))), r'^z must have shape \(6, 1\), got \(5, 1\)'),
    (lambda: _bank(z=np.ones((6, 2))), r'^z must have shape \(6, 1\), got \(6, 2\)'),
    (lambda: _bank(z='z'), r'^z must be numeric'),
    (lambda: _bank(t=_with(T, 1, NAN)), r'^t_s must be finite'),
    (lambda: _bank(t=_with(T, 1, INF)), r'^t_s must be finite'),
    (lambda: _bank(t=_with(T, 4, 0.15)),
     r'^t_s\[4\] = 0.15 is not after t_s\[2\] = 0.2, the previous row of id 0'),
    (lambda: _bank(t=_with(T, 2, 0.1)), r'^t_s\[2\] = 0.1 is not after t_s\[0\] = 0.1'),
    (lambda: _bank(t=_with(T, 0, -0.1)), r'^t_s\[0\] = -0.1 is before t0_s = 0.0 \(id 0\)'),
    (lambda: _bank(t=_with(T, 5, 1e300)), r'^times must be within'),
    (lambda: _bank(t=T[:, None]), r'^t_s must be a vector of 6 times, got shape \(6, 1\)'),
    (lambda: _bank(ids=IDS[:5]), r'^ids must have one entry per row \(6\), got 5'),
    (lambda: _bank(ids=IDS[:, None]), r'^ids must be a vector, got shape \(6, 1\)'),
    (lambda: _bank(u=np.ones((6, 1))), r"^preset 'train' has no control input, but u was"),
    (lambda: _bank(name='car'), r"^u \(acceleration\) is required by preset 'car'"),
    (lambda: _bank(name='car', u=np.ones((5, 1))), r'^u must have shape \(6, 1\)'),
    (lambda: _bank(name='car', u=_with(np.ones((6, 1)), 2, NAN)), r'^u must be finite'),
])
def test_rejected_rows_name_the_input(call, pattern):
    """Bad times, measurements, controls or ids raise ValueError naming them (and the row)."""
    with pytest.raises(ValueError, match=pattern):
        call()


@pytest.mark.parametrize('kwargs, pattern', [
    ({'horizon_s': -1.0}, r'^horizon_s must be >= 0, got -1.0'),
    ({'horizon_s': NAN}, r'^horizon_s must be finite'),
    ({'t0_s': NAN}, r'^t0_s must be finite'),
    ({'x0': [0.0, 1.0, 2.0]}, r'^x0 must have length 2, got 3'),
    ({'x0': [0.0, NAN]}, r'^x0 must be finite'),
    ({'P0': np.eye(3)}, r'^P0 must have shape \(2, 2\), got \(3, 3\)'),
    ({'P0': [[1.0, 0.5], [0.0, 1.0]]}, r'^P0 must be symmetric'),
    ({'P0': [[1.0, 2.0], [2.0, 1.0]]}, r'^P0 must be positive semi-definite'),
    ({'P0': [[INF, 0.0], [0.0, 1.0]]}, r'^P0 must be finite'),
])
def test_rejected_arguments_name_them(kwargs, pattern):
    """A bad horizon, start time, initial state or covariance raises ValueError naming it."""
    with pytest.raises(ValueError, match=pattern):
        _bank(**kwargs)


def test_time_order_error_names_the_rows():
    """A row not after its object's previous row names both rows."""
    with pytest.raises(bank.TimeOrderError) as caught:
        _bank(t=_with(T, 4, 0.15))
    assert (caught.value.row, caught.value.previous) == (4, 2)


def test_divergence_in_lock_step_names_the_row(monkeypatch):
    """An update whose state overflows (K1·y > max double) raises naming its row."""
    _split(monkeypatch, 'lock-step')
    z = _with(np.ones((6, 1)), 3, 1.7e308)
    with np.errstate(all='ignore'):
        with pytest.raises(SeriesError, match=r'^row 3: the filter diverged') as caught:
            _bank(z=z, P0=[[1.0, 10.0], [10.0, 200.0]])
    assert caught.value.row == 3


def test_empty_bank():
    """A bank of no rows is valid and returns empty results of the right shapes."""
    result = run_bank(load_preset('train'), np.zeros(0), np.zeros((0, 1)), None,
                      np.zeros(0, dtype=int), horizon_s=1.0)
    assert result.x.shape == (0, 2) and result.P.shape == (0, 2, 2)
    assert result.predicted_x.shape == (0, 2) and result.predicted_P.shape == (0, 2, 2)
