"""Tests of kf_train.filters.family: one interface for KF, EKF, UKF and PF, and replay --filter."""

import os

from kf_train.batch import run_filter_series, run_series, SeriesError, time_steps_s
from kf_train.cli.replay import main as replay_main
from kf_train.filters import (
    FILTER_KINDS, FilterOptions, gaussian_model, GaussianFilter, make_filter, UpdateResult)
from kf_train.presets import load_preset, PRESET_NAMES
from kf_train.sim import scenario_for_preset
import numpy as np
import pytest

LINEAR = [name for name in PRESET_NAMES if name != 'range-bearing']


def _kinds(preset):
    """Return the kinds that apply to a preset."""
    return [kind for kind in FILTER_KINDS if kind != 'kf' or preset.linear]


def _filter(preset, kind):
    """Return a small, seeded filter of a kind."""
    return make_filter(preset, kind, particles=300, seed=7)


def _rows(name, rows=30):
    """Return (preset, dt, z, u) for the first rows of a preset's scenario."""
    preset = load_preset(name)
    scenario = scenario_for_preset(name, 1)
    dt = time_steps_s(scenario.t_s)[:rows]
    u = None if scenario.u is None else scenario.u[:rows]
    return preset, dt, scenario.z[:rows], u


@pytest.mark.parametrize('name', PRESET_NAMES)
def test_kf_and_ekf_are_the_presets_exact_path(name):
    """'kf' and 'ekf' through the interface equal run_series bit for bit."""
    preset = load_preset(name)
    scenario = scenario_for_preset(name, 2)
    expected = run_series(preset, scenario.t_s, scenario.z, scenario.u, horizon_s=1.0)
    for kind in ('kf', 'ekf') if preset.linear else ('ekf',):
        got = run_filter_series(make_filter(preset, kind), scenario.t_s, scenario.z,
                                scenario.u, horizon_s=1.0)
        for a, b in zip(got, expected):
            if isinstance(a, np.ndarray):
                np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('name', PRESET_NAMES)
def test_every_kind_has_the_same_interface(name):
    """predict, update (UpdateResult), predict_ahead, mean, covariance on every kind."""
    preset, dt, z, u = _rows(name, rows=5)
    n, m = preset.dim_x, preset.dim_z
    for kind in _kinds(preset):
        filt = _filter(preset, kind)
        if kind != 'pf':
            np.testing.assert_array_equal(filt.mean, preset.initial_state)
        for k in range(dt.shape[0]):
            u_k = None if u is None else u[k]
            filt.predict(dt[k], u_k)
            result = filt.update(z[k])
            assert isinstance(result, UpdateResult)
            assert result.innovation.shape == (m,)
            assert result.innovation_covariance.shape == (m, m)
            assert result.gain.shape == (n, m)
            assert np.isfinite(result.nis) and result.nis >= 0.0
        x, P = filt.mean, filt.covariance
        assert x.shape == (n,) and P.shape == (n, n)
        np.testing.assert_array_equal(filt.x, x)
        np.testing.assert_array_equal(filt.P, P)
        before = filt.snapshot()
        ahead = filt.predict_ahead(2.0, None if u is None else u[-1])
        assert ahead[0].shape == (n,) and ahead[1].shape == (n, n)
        np.testing.assert_array_equal(filt.mean, x)  # the look-ahead changed nothing
        after = filt.snapshot()
        for a, b in zip(before, after):
            if isinstance(a, np.ndarray):
                np.testing.assert_array_equal(a, b)
        assert isinstance(filt.diagnostics(), dict)


@pytest.mark.parametrize('name', ['car', 'range-bearing'])
def test_out_of_sequence_replay_with_snapshots_equals_in_order(name):
    """
    Rewind to the snapshot before a late row, fuse it, replay the rest: bit for bit.

    This is what a streaming estimator does with an out-of-sequence measurement; for
    the particle filter the snapshot carries the generator, so the draws repeat too.
    """
    preset, dt, z, u = _rows(name, rows=16)
    for kind in _kinds(preset):
        in_order = _filter(preset, kind)
        expected = []
        for k in range(16):
            in_order.predict(dt[k], None if u is None else u[k])
            in_order.update(z[k])
            expected.append(in_order.mean)
        late = _filter(preset, kind)
        snapshots = {}
        for k in list(range(10)) + list(range(11, 16)):  # row 10 arrives last
            snapshots[k] = late.snapshot()
            late.predict(dt[k] if k != 11 else dt[10] + dt[11], None if u is None else u[k])
            late.update(z[k])
        late.restore(snapshots[11])
        for k in range(10, 16):
            late.predict(dt[k], None if u is None else u[k])
            late.update(z[k])
        np.testing.assert_array_equal(late.mean, expected[-1])


@pytest.mark.parametrize('name', ['robot', 'range-bearing'])
def test_rejected_steps_leave_every_kind_unchanged(name):
    """A bad z, dt or u raises ValueError and the state (snapshot) is exactly as before."""
    preset, dt, z, u = _rows(name, rows=3)
    bad_z = np.full(preset.dim_z + 1, 1.0)
    for kind in _kinds(preset):
        filt = _filter(preset, kind)
        filt.predict(dt[0], None if u is None else u[0])
        filt.update(z[0])
        before = filt.snapshot()
        calls = [lambda: filt.update(bad_z), lambda: filt.update(np.full(preset.dim_z, np.nan)),
                 lambda: filt.predict(-1.0, None if u is None else u[1])]
        calls.append(lambda: filt.predict(0.1) if u is not None else filt.predict(0.1, [1.0]))
        for call in calls:
            with pytest.raises(ValueError):
                call()
            after = filt.snapshot()
            for a, b in zip(before, after):
                if isinstance(a, np.ndarray):
                    np.testing.assert_array_equal(a, b)
                else:
                    assert a == b


def test_reset_restarts_every_kind():
    """reset() returns to the preset's estimate; a reset PF repeats its draws exactly."""
    preset, dt, z, _ = _rows('range-bearing', rows=5)
    for kind in _kinds(preset):
        filt = _filter(preset, kind)
        runs = []
        for _ in range(2):
            filt.reset()
            for k in range(5):
                filt.predict(dt[k])
                filt.update(z[k])
            runs.append(filt.mean)
        np.testing.assert_array_equal(runs[0], runs[1])
    pf = _filter(preset, 'pf')
    pf.reset(seed=99)
    assert pf.seed == 99


def test_make_filter_checks_its_arguments():
    """Unknown kinds, kf on a nonlinear preset and bad tuning raise ValueError."""
    linear, nonlinear = load_preset('train'), load_preset('range-bearing')
    for call, message in [
            (lambda: make_filter(linear, 'lkf'), 'filter must be one of kf, ekf, ukf, pf'),
            (lambda: make_filter(nonlinear, 'kf'), "filter 'kf' needs a linear one"),
            (lambda: make_filter(linear, 'pf', particles=0), 'n_particles must be'),
            (lambda: make_filter(linear, 'pf', seed=-3), 'seed must be'),
            (lambda: make_filter(linear, 'ukf', alpha=-1.0), 'alpha must be > 0'),
            (lambda: make_filter(nonlinear, 'ukf', kappa=-4.0), 'kappa must be > -n = -4'),
            (lambda: make_filter(linear, 'pf', bogus=1), 'bogus'),
            (lambda: gaussian_model(linear, 'pf'), 'no \\(x, P\\) model')]:
        with pytest.raises((ValueError, TypeError), match=message):
            call()


def test_gaussian_models_plug_into_model_code():
    """gaussian_model returns pure models with predict(x, P, dt, u) and update(x, P, z)."""
    preset = load_preset('car')
    for kind in ('kf', 'ekf', 'ukf'):
        model = gaussian_model(preset, kind, FilterOptions(alpha=0.5))
        x, P = model.predict(preset.initial_state, preset.initial_covariance, 0.1, [1.0])
        x, P, result = model.update(x, P, [0.1])
        assert x.shape == (2,) and result.nis >= 0.0
    assert isinstance(make_filter(preset, 'ukf'), GaussianFilter)


def test_run_filter_series_names_the_failing_row():
    """A row the filter rejects is reported as a SeriesError with its index."""
    preset = load_preset('range-bearing')
    with pytest.raises(SeriesError, match='row 1'):
        # P0 = 0: the target flies into the sensor, reached at row 1's time.
        run_filter_series(make_filter(preset, 'ekf'), [0.1, 0.2], [[0.8, 0.1], [0.8, 0.1]],
                          x0=[0.2, -1.0, 0.2, -1.0], P0=np.zeros((4, 4)))


# ---------------------------------------------------------------------------
# kf-train replay --filter
# ---------------------------------------------------------------------------

def _write_input(path, name):
    """Write a preset's scenario as a replay input CSV; return the scenario."""
    preset = load_preset(name)
    scenario = scenario_for_preset(name, 0)
    header = ['t'] + [columns[0] for columns in preset.measurement_columns()]
    columns = [scenario.t_s] + list(scenario.z.T)
    if preset.dim_u:
        header += list(preset.control_columns())
        columns += list(scenario.u.T)
    with open(path, 'w', encoding='utf-8') as stream:
        stream.write(','.join(header) + '\n')
        for row in zip(*columns):
            stream.write(','.join(repr(float(v)) for v in row) + '\n')
    return scenario


def _read(path):
    """Return (header, values) of an output CSV."""
    with open(path, encoding='utf-8') as stream:
        header = stream.readline().strip().split(',')
    return header, np.loadtxt(path, delimiter=',', skiprows=1, ndmin=2)


@pytest.mark.parametrize('name', PRESET_NAMES)
def test_replay_filter_option_on_every_preset(name, tmp_path):
    """--filter ekf|ukf|pf: the default's columns; the UKF equals it where linear."""
    source = tmp_path / 'in.csv'
    _write_input(source, name)
    default = tmp_path / 'default.csv'
    assert replay_main(['--preset', name, str(source), '-o', str(default)]) == 0
    header, values = _read(default)
    for kind in ('ekf', 'ukf', 'pf'):
        out = tmp_path / f'{kind}.csv'
        assert replay_main(['--preset', name, str(source), '-o', str(out), '--filter', kind,
                            '--particles', '200', '--seed', '3']) == 0
        got_header, got = _read(out)
        assert got_header == header
        assert got.shape == values.shape and np.all(np.isfinite(got))
        if kind != 'pf' and (kind == 'ekf' or name != 'range-bearing'):
            np.testing.assert_allclose(got, values, rtol=1e-9, atol=1e-9)


def test_replay_pf_is_reproducible_and_seeded(tmp_path):
    """The same --seed writes the same file; another seed another one."""
    source = tmp_path / 'in.csv'
    _write_input(source, 'range-bearing')
    texts = []
    for seed in ('1', '1', '2'):
        out = tmp_path / f'pf{len(texts)}.csv'
        assert replay_main(['--preset', 'range-bearing', str(source), '-o', str(out),
                            '--filter', 'pf', '--particles', '300', '--seed', seed,
                            '--roughening', '0.1']) == 0
        texts.append(out.read_text())
    assert texts[0] == texts[1] != texts[2]


def test_replay_filter_errors(tmp_path, capsys):
    """--smooth with pf, kf on range-bearing: exit 1, no file; bad tuning: exit 2."""
    source = tmp_path / 'in.csv'
    _write_input(source, 'range-bearing')
    out = tmp_path / 'out.csv'
    assert replay_main(['--preset', 'range-bearing', str(source), '-o', str(out),
                        '--filter', 'pf', '--smooth']) == 1
    assert '--smooth needs a Gaussian filter' in capsys.readouterr().err
    assert replay_main(['--preset', 'range-bearing', str(source), '-o', str(out),
                        '--filter', 'kf']) == 1
    assert "filter 'kf' needs a linear one" in capsys.readouterr().err
    assert not os.path.exists(out)
    for option, value, message in [('--particles', '0', '--particles must be in'),
                                   ('--alpha', '0', '--alpha must be > 0'),
                                   ('--resample-threshold', '2', '--resample-threshold'),
                                   ('--roughening', '-1', '--roughening')]:
        with pytest.raises(SystemExit) as exit_info:
            replay_main(['--preset', 'range-bearing', str(source), '-o', str(out),
                         '--filter', 'pf', option, value])
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err
    # The UKF smooths; a horizon works with every kind.
    assert replay_main(['--preset', 'range-bearing', str(source), '-o', str(out),
                        '--filter', 'ukf', '--smooth', '--horizon', '1']) == 0
    header, values = _read(out)
    assert 'smoothed_x' in header and 'var_predicted_vy' in header
    assert np.all(np.isfinite(values))
