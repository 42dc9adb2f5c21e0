"""
The replay's ``id`` column: a bank of independent objects equals each object alone.

Every test builds objects on their own irregular clocks, interleaves their rows in
time order and checks the bank (the API and ``kf-train replay``) against
``run_series`` / ``run_filter_series`` run on each object's rows alone, to 1e-9.
"""

import os

from kf_train.batch import bank, group_rows, run_bank, run_filter_series, run_series
from kf_train.batch import smooth_series
from kf_train.cli.replay import main
from kf_train.filters import FilterOptions, make_filter
from kf_train.io import read_table
from kf_train.presets import load_preset, PRESET_NAMES
import numpy as np
import pytest

FIELDS = ('x', 'P', 'x_prior', 'P_prior', 'F', 'predicted_x', 'predicted_P', 'nis')


def _close(a, b, tol=1e-9):
    """
    Assert |a − b| <= tol · max(1, |b|) elementwise.

    The bank runs each object's rows (a few to a few dozen) through the same filters
    as run_series does alone, vectorised across objects: rounding only, and over so
    few rows the first-order bound of test_presets.ATOL is < 1e-11 of the scale.
    ``tol = 0`` is used where the arithmetic is exact (integer-nanosecond dt).
    """
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    assert np.all(np.abs(a - b) <= tol * np.maximum(1.0, np.abs(b))), np.max(np.abs(a - b))


def _fleet(preset, counts, seed):
    """Return (t, z, u, ids) for objects with ``counts`` rows each, rows interleaved."""
    rng = np.random.default_rng(seed)
    T = preset.nominal_period_s
    t, ids = [], []
    for k, count in enumerate(counts):
        # Each object: its own start and its own jittered period (0.3 T .. 2 T).
        t.append(rng.uniform(0.0, 3 * T) + np.cumsum(T * rng.uniform(0.3, 2.0, count)))
        ids += [f'obj-{k}'] * count
    t, ids = np.concatenate(t), np.array(ids)
    order = np.argsort(t, kind='stable')
    t, ids = t[order], ids[order]
    N = t.shape[0]
    if preset.name == 'range-bearing':
        x, y = 35.0 + 2.0 * t, 45.0 + t
        z = np.column_stack([np.arctan2(y, x) + 1e-3 * rng.standard_normal(N),
                             np.hypot(x, y) + rng.standard_normal(N)])
    else:
        z = 0.5 * t[:, None] + rng.standard_normal((N, preset.dim_z))
    u = rng.standard_normal((N, preset.dim_u)) if preset.dim_u else None
    return t, z, u, ids


def _check_against_each_alone(result, preset, t, z, u, ids, horizon_s=None, filt=None):
    """Assert that every object's rows of ``result`` equal that object filtered alone."""
    for label in np.unique(ids):
        rows = np.flatnonzero(ids == label)
        u_k = None if u is None else u[rows]
        if filt is None:
            alone = run_series(preset, t[rows], z[rows], u_k, horizon_s=horizon_s)
        else:
            alone = run_filter_series(filt, t[rows], z[rows], u_k, horizon_s=horizon_s)
        for field in FIELDS:
            expected = getattr(alone, field)
            if expected is None:
                assert getattr(result, field) is None
            else:
                _close(getattr(result, field)[rows], expected)


@pytest.mark.parametrize('name', PRESET_NAMES)
def test_bank_equals_each_object_alone(name):
    """Every preset (linear: vectorised; EKF: object by object) with a horizon."""
    preset = load_preset(name)
    counts = [1, 2, 5, 40, 17, 3, 120]
    t, z, u, ids = _fleet(preset, counts, PRESET_NAMES.index(name))
    result = run_bank(preset, t, z, u, ids, horizon_s=1.5)
    np.testing.assert_array_equal(result.t_s, t)
    _check_against_each_alone(result, preset, t, z, u, ids, horizon_s=1.5)


@pytest.mark.parametrize('name', ['train', 'car-exact', 'robot', 'cv-position-velocity'])
@pytest.mark.parametrize('split', ['lock-step', 'alone', 'cost model'])
def test_both_bank_strategies_equal_each_object_alone(monkeypatch, name, split):
    """All objects in lock-step, all along their own axes, or the cost model's mix."""
    if split == 'lock-step':
        monkeypatch.setattr(bank, 'LOCKSTEP_STEP_S', 0.0)
    elif split == 'alone':
        monkeypatch.setattr(bank, 'SERIES_CALL_S', 0.0)
    else:  # a few long objects alone, the many short ones in lock-step
        monkeypatch.setattr(bank, 'SERIES_CALL_S', 1e-3)
        monkeypatch.setattr(bank, 'LOCKSTEP_STEP_S', 1e-4)
    preset = load_preset(name)
    counts = [400, 350] + [3, 1, 7, 2] * 5
    t, z, u, ids = _fleet(preset, counts, 7)
    result = run_bank(preset, t, z, u, ids)
    _check_against_each_alone(result, preset, t, z, u, ids)


@pytest.mark.parametrize('kind', ['ukf', 'pf', 'bootstrap-pf'])
def test_bank_of_other_filters_equals_each_object_alone(kind):
    """--filter ukf/pf/bootstrap-pf: object by object, a particle filter reseeded per object."""
    preset = load_preset('car')
    t, z, u, ids = _fleet(preset, [6, 3, 9], 3)
    filt = make_filter(preset, kind, FilterOptions(particles=200, seed=5))
    result = run_bank(preset, t, z, u, ids, filt=filt)
    _check_against_each_alone(result, preset, t, z, u, ids, filt=filt)


def test_groups_and_time_rules():
    """Per object: times increase, the first may sit at t0; objects may interleave."""
    groups = group_rows(np.array(['b', 'a', 'b', 'a']))
    assert groups.labels.tolist() == ['a', 'b']
    assert groups.rows(0).tolist() == [1, 3] and groups.rows(1).tolist() == [0, 2]
    for ids in ([7, 3, 7, 100], [-2, 5, -2, 5], [2 ** 40, 1, 2 ** 40, 1]):  # integer ids
        groups_int = group_rows(np.array(ids))
        assert groups_int.labels.tolist() == sorted(set(ids))
        assert [groups_int.labels[c] for c in groups_int.codes] == ids
    dt = bank.bank_time_steps([0.5, 0.0, 0.7, 0.25], groups, 0.0)
    _close(dt, [0.5, 0.0, 0.2, 0.25], 0.0)
    message = r"t_s\[3\] = 0.4 is not after t_s\[2\] = 0.4, the previous row of id 'b'"
    with pytest.raises(bank.TimeOrderError, match=message):
        bank.bank_time_steps([0.1, 0.2, 0.4, 0.4], group_rows(['a', 'a', 'b', 'b']))
    with pytest.raises(bank.TimeOrderError, match=r't_s\[1\] = -0.1 is before t0_s'):
        bank.bank_time_steps([0.1, -0.1], group_rows(['a', 'b']))
    with pytest.raises(ValueError, match='one entry per row'):
        run_bank(load_preset('train'), [0.1, 0.2], [[1.0], [2.0]], None, ['a'])


def _write(path, header, rows):
    """Write a CSV: strings as they are, numbers with repr()."""
    with open(path, 'w', encoding='utf-8') as stream:
        stream.write(','.join(header) + '\n')
        for row in rows:
            stream.write(','.join(v if isinstance(v, str) else repr(float(v)) for v in row)
                         + '\n')


@pytest.mark.parametrize('name', ['train', 'car', 'robot-exact', 'range-bearing'])
def test_replay_with_id_column(tmp_path, name):
    """The output keeps the id (first) and the row order; numbers equal each id alone."""
    preset = load_preset(name)
    t, z, u, ids = _fleet(preset, [30, 1, 12, 25], 11)
    header = ['t'] + [c[0] for c in preset.measurement_columns()] + ['id']
    columns = [t] + list(z.T) + [ids]
    if u is not None:
        header.append('u')
        columns.append(u[:, 0])
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _write(source, header, zip(*columns))
    assert main(['--preset', name, str(source), '-o', str(target), '--smooth']) == 0
    lines = target.read_text().splitlines()
    out_header = lines[0].split(',')
    assert out_header[:2] == ['id', 't']
    assert [line.split(',')[0] for line in lines[1:]] == ids.tolist()
    table = read_table(str(target), [(h,) for h in out_header[1:]], ids=True)
    assert [table.id_labels[c] for c in table.ids] == ids.tolist()
    np.testing.assert_array_equal(table.columns['t'], t)
    for label in np.unique(ids):
        rows = np.flatnonzero(ids == label)
        alone = run_series(preset, t[rows], z[rows], None if u is None else u[rows])
        smoothed = smooth_series(alone)
        for i, state in enumerate(preset.state_names):
            _close(table.columns[state][rows], alone.x[:, i])
            _close(table.columns['var_' + state][rows], alone.P[:, i, i])
            _close(table.columns['smoothed_' + state][rows], smoothed.x[:, i])
            _close(table.columns['var_smoothed_' + state][rows], smoothed.P[:, i, i])


def test_id_text_forms(tmp_path):
    """Ids are text: '1' and '01' differ; quoted, spaced and non-ASCII ids work."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    source.write_text('id,t,z_position\n1,0.1,1.0\n01,0.1,5.0\n1,0.2,1.5\n'
                      '" Zug ä",0.1,9.0\n Zug ä ,0.3,9.5\n', encoding='utf-8')
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 0
    lines = target.read_text(encoding='utf-8').splitlines()
    assert [line.split(',')[0] for line in lines[1:]] == ['1', '01', '1', 'Zug ä', 'Zug ä']
    preset = load_preset('train')
    out = read_table(str(target), [('position',)]).columns['position']
    _close(out[[0, 2]], run_series(preset, [0.1, 0.2], [[1.0], [1.5]]).x[:, 0])
    _close(out[[1]], run_series(preset, [0.1], [[5.0]]).x[:, 0])
    _close(out[[3, 4]], run_series(preset, [0.1, 0.3], [[9.0], [9.5]]).x[:, 0])


@pytest.mark.parametrize('rows, message', [
    ([('A', 0.1, 1.0), ('B', 0.2, 1.0), ('A', 0.1, 2.0)],
     "line 4, column 't': 0.1 is not after the previous row's t = 0.1 of id 'A' (line 2); "
     't must increase per id'),
    ([('A', 0.3, 1.0), ('B', 0.1, 1.0), ('B', 0.05, 2.0)],
     "line 4, column 't': 0.05 is not after the previous row's t = 0.1 of id 'B' (line 3)"),
    ([('A', 0.1, 1.0), ('B', -0.1, 1.0)],
     "line 3, column 't': -0.1 is before the initial time t0 = 0.0 s of id 'B'"),
    ([('A', 0.1, 1.0), ('', 0.2, 1.0)], "line 3, column 'id': empty id"),
    ([('A', 0.1, 1.0), ('B', 0.2, 'x')], "line 3, column 'z_position': 'x' is not a number"),
])
def test_bank_errors_name_line_and_column(tmp_path, capsys, rows, message):
    """Per-id time order, an empty id, a bad cell: one line naming it, exit 1, no file."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _write(source, ['id', 't', 'z_position'], rows)
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 1
    err = capsys.readouterr().err
    assert f'{source} {message}' in err, err
    assert err.count('\n') == 1
    assert os.listdir(tmp_path) == ['in.csv']


def test_large_bank_csv_round_trip(tmp_path):
    """300 objects × 50 rows through the bulk reader and writer: exact text round trip."""
    preset = load_preset('car')
    t, z, u, ids = _fleet(preset, [50] * 300, 21)
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _write(source, ['id', 't', 'z_position', 'u'], zip(ids, t, z[:, 0], u[:, 0]))
    assert main(['--preset', 'car', str(source), '-o', str(target)]) == 0
    table = read_table(str(target), [('position',), ('velocity',), ('var_velocity',)],
                       ids=True)
    bank = run_bank(preset, t, z, u, ids)
    np.testing.assert_array_equal(table.columns['position'], bank.x[:, 0])
    np.testing.assert_array_equal(table.columns['var_velocity'], bank.P[:, 1, 1])
    for label in ('obj-0', 'obj-299'):
        rows = np.flatnonzero(ids == label)
        _close(bank.x[rows], run_series(preset, t[rows], z[rows], u[rows]).x)
