"""Tests of kf-train replay, the series runners and the vectorised fast path."""

import io
import os
import subprocess
import sys

from kf_train import cli
from kf_train.batch import (
    affine_recursion, run_linear_series, run_series, smooth_series, time_steps_s)
from kf_train.cli.replay import main
from kf_train.io import read_table, required_columns
from kf_train.presets import load_preset, PRESET_NAMES
from kf_train.sim import scenario_for_preset
import numpy as np
import pytest

LINEAR = [name for name in PRESET_NAMES if name != 'range-bearing']


def _close(a, b, tol=1e-9):
    """
    Assert |a − b| <= tol · max(1, |b|) elementwise (1e-9 absolute at unit scale).

    The paths compared evaluate the same filters in float64 (vectorised, chunked or
    row by row) and differ by rounding only. The first-order bound of
    test_presets.ATOL, summed with the actual closed-loop products over the rows of
    test_fast_path_equals_generic_path and held against each element's own
    max(1, |b|), is <= 0.25 of 1e-9 on every preset but train's 1000 regular rows
    (Q too small to forget), where it reaches 0.9 of it; measured: <= 6e-5 of it.
    Tighter tolerances passed in are derived where they are used.
    """
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    assert np.all(np.abs(a - b) <= tol * np.maximum(1.0, np.abs(b))), np.max(np.abs(a - b))


# ---------------------------------------------------------------------------
# The building blocks
# ---------------------------------------------------------------------------

@pytest.mark.parametrize('N', [1, 2, 17, 1000, 4099])
@pytest.mark.parametrize('d', [1, 2, 3])
def test_affine_recursion_equals_the_loop(N, d):
    """x_k = A_k x_{k−1} + b_k by chunks equals the plain loop (constant and varying A)."""
    rng = np.random.default_rng(N * 10 + d)
    A = rng.uniform(-1, 1, (N, d, d)) / d
    b = rng.standard_normal((N, d))
    x0 = rng.standard_normal(d)
    for A_rows in (A, A[0]):
        x, expected = x0, []
        for k in range(N):
            x = (A_rows[k] if A_rows.ndim == 3 else A_rows) @ x + b[k]
            expected.append(x)
        # |A_k|∞ <= 1 and the products of these A shrink (their ∞-norms sum to <= 4 in
        # every case here): chunked or in order, each row rounds by <= (d + 1)u of its
        # terms, and the sum over rows stays < 1e-14 of the scale: 1e-12 has margin.
        _close(affine_recursion(A_rows, b, x0), np.array(expected), 1e-12)


def test_time_steps_are_whole_nanoseconds():
    """Times k·0.1 as doubles give dt = 0.1 exactly for every row; errors name the index."""
    t = np.arange(1, 100001) * 0.1
    dt = time_steps_s(t)
    assert np.all(dt == 0.1)
    assert time_steps_s([5.0, 5.5], t0_s=5.0).tolist() == [0.0, 0.5]
    with pytest.raises(ValueError, match=r't_s\[2\] = 0.2 is not after t_s\[1\] = 0.3'):
        time_steps_s([0.1, 0.3, 0.2])
    with pytest.raises(ValueError, match=r't_s\[0\] = 0.5 is before t0_s = 1.0'):
        time_steps_s([0.5], t0_s=1.0)
    with pytest.raises(ValueError, match='t_s must be finite'):
        time_steps_s([0.1, np.nan])


@pytest.mark.parametrize('name', LINEAR)
@pytest.mark.parametrize('jitter', [False, True])
def test_fast_path_equals_generic_path(name, jitter):
    """run_linear_series equals run_series (1e-9) on long series, regular or jittered."""
    preset = load_preset(name)
    rng = np.random.default_rng(PRESET_NAMES.index(name) + 100 * jitter)
    N = 300 if jitter else 1000  # the covariances converge within ~230 rows
    T = preset.nominal_period_s
    t = np.cumsum(T * rng.uniform(0.5, 1.5, N)) if jitter else np.arange(1, N + 1) * T
    z = 0.5 * t[:, None] + rng.standard_normal((N, preset.dim_z))
    u = rng.standard_normal((N, preset.dim_u)) if preset.dim_u else None
    for horizon in (None, 1.3):
        a = run_series(preset, t, z, u, horizon_s=horizon, t0_s=-0.05)
        b = run_linear_series(preset, t, z, u, horizon_s=horizon, t0_s=-0.05)
        for field in ('x', 'P', 'x_prior', 'P_prior', 'F', 'predicted_x', 'predicted_P'):
            if getattr(a, field) is None:
                assert getattr(b, field) is None
            else:
                _close(getattr(b, field), getattr(a, field))


def test_fast_path_without_process_noise_and_a_singular_prior():
    """Q = 0 with a singular P0 (no information form) still equals the generic path."""
    from kf_train.presets.loader import preset_from_mapping
    preset = preset_from_mapping({
        'name': 'pinned', 'motion': 'constant_velocity', 'states': ['position', 'velocity'],
        'measurements': ['position'], 'R': [0.5], 'process_noise': {'per_step': [0, 0]},
        'nominal_period_s': 0.1, 'initial_state': [0.0, 1.0], 'initial_covariance': [0, 4]})
    rng = np.random.default_rng(12)
    t = np.arange(1, 501) * 0.1
    z = t[:, None] + rng.standard_normal((500, 1))
    _close(run_linear_series(preset, t, z).x, run_series(preset, t, z).x)


def test_fast_path_on_empty_and_single_rows():
    """Zero and one rows work on both paths."""
    preset = load_preset('train')
    for t, z in (([], np.empty((0, 1))), ([0.1], [[1.0]])):
        a = run_series(preset, t, z)
        b = run_linear_series(preset, t, z)
        _close(b.x, a.x)
        _close(b.predicted_P, a.predicted_P)
    with pytest.raises(ValueError, match='not linear'):
        run_linear_series(load_preset('range-bearing'), [0.1], [[0.5, 10.0]])
    with pytest.raises(ValueError, match=r'u \(velocity\) is required'):
        run_linear_series(load_preset('robot'), [0.1], [[0.5]])
    with pytest.raises(ValueError, match='z must have shape'):
        run_linear_series(preset, [0.1, 0.2], [[0.5]])


# ---------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------

def _write(path, header, rows):
    """Write a CSV from a header list and row tuples."""
    with open(path, 'w', newline='') as stream:
        stream.write(','.join(header) + '\n')
        for row in rows:
            stream.write(','.join(str(v) for v in row) + '\n')


def _scenario_csv(path, name, seed=0):
    """Write the preset's seed scenario as a replay input; return the scenario."""
    preset = load_preset(name)
    s = scenario_for_preset(name, seed)
    header = ['t'] + [cols[0] for cols in preset.measurement_columns()]
    columns = [s.t_s] + [s.z[:, i] for i in range(preset.dim_z)]
    if preset.dim_u:
        header.append('u')
        columns.append(s.u[:, 0])
    _write(path, header, zip(*[map(repr, c.tolist()) for c in columns]))
    return s


def _read_output(path):
    """Return (header, {column: values}) of a replay output."""
    with open(path) as stream:
        header = stream.readline().strip().split(',')
    return header, read_table(str(path), [(h,) for h in header]).columns


@pytest.mark.parametrize('name', PRESET_NAMES)
def test_replay_writes_every_state_by_name(tmp_path, name):
    """The output has t, the states, var_<state> (predictions for train), nis, exactly."""
    preset = load_preset(name)
    s = _scenario_csv(tmp_path / 'in.csv', name)
    assert main(['--preset', name, str(tmp_path / 'in.csv'), '--output',
                 str(tmp_path / 'out.csv')]) == 0
    header, out = _read_output(tmp_path / 'out.csv')
    states = list(preset.state_names)
    expected = ['t'] + states + ['var_' + s for s in states]
    if name == 'train':
        expected += ['predicted_' + s for s in states] + ['var_predicted_' + s for s in states]
    assert header == expected + ['nis']
    reference = run_series(preset, s.t_s, s.z, s.u)
    np.testing.assert_array_equal(out['t'], s.t_s)
    for i, state in enumerate(states):
        _close(out[state], reference.x[:, i])
        _close(out['var_' + state], reference.P[:, i, i])
    _close(out['nis'], reference.nis)
    if preset.linear:  # the text round trip is exact: the vectorised doubles come back
        fast = run_linear_series(preset, s.t_s, s.z, s.u)
        np.testing.assert_array_equal(out[states[0]], fast.x[:, 0])


def test_horizon_smooth_and_t0_options(tmp_path):
    """--horizon adds or removes predictions, --smooth adds RTS columns, --t0 moves the prior."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    s = _scenario_csv(source, 'cv-position')
    preset = load_preset('cv-position')
    assert main(['--preset', 'cv-position', str(source), '-o', str(target),
                 '--horizon', '1.5', '--smooth']) == 0
    header, out = _read_output(target)
    assert header[5:] == ['predicted_position', 'predicted_velocity',
                          'var_predicted_position', 'var_predicted_velocity',
                          'smoothed_position', 'smoothed_velocity',
                          'var_smoothed_position', 'var_smoothed_velocity', 'nis']
    result = run_series(preset, s.t_s, s.z, horizon_s=1.5)
    _close(out['predicted_position'], result.predicted_x[:, 0])
    smoothed = smooth_series(result)
    _close(out['smoothed_velocity'], smoothed.x[:, 1])
    _close(out['var_smoothed_position'], smoothed.P[:, 0, 0])

    assert main(['--preset', 'train', str(source), '-o', str(target), '--horizon', '0']) == 0
    header, _ = _read_output(target)
    assert not any(h.startswith('predicted_') for h in header)

    _write(source, ['t', 'z_position'], [(100.5, 3.0), (101.5, 4.0)])
    assert main(['--preset', 'cv-position', str(source), '-o', str(target),
                 '--t0', '99.5']) == 0
    _, out = _read_output(target)
    _close(out['position'], run_series(preset, [1.0, 2.0], [[3.0], [4.0]]).x[:, 0])


def test_flexible_input_layout(tmp_path):
    """CRLF, quoted header, reordered and extra columns, the z_range alias, blank tail."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    source.write_bytes(b'"u", note ,"t","z_range"\r\n0.5,a,0.1,0.2\r\n0.25,"b, c",0.2,0.3\r\n'
                       b'\r\n\r\n')
    assert main(['--preset', 'robot', str(source), '-o', str(target)]) == 0
    _, out = _read_output(target)
    expected = run_series(load_preset('robot'), [0.1, 0.2], [[0.2], [0.3]], [[0.5], [0.25]])
    _close(out['position'], expected.x[:, 0])
    _write(source, ['t', 'z_position', 'z_range', 'u'], [(0.1, 1, 1, 0)])
    assert main(['--preset', 'robot', str(source), '-o', str(target)]) == 1


@pytest.mark.parametrize('rows, message', [
    ([('t', 'z'), (0.1, 1.0)], "line 1: missing column 'z_position'"),
    ([('t', 'z_position'), (0.1, 1.0), (0.2, 'abc')],
     "line 3, column 'z_position': 'abc' is not a number"),
    ([('t', 'z_position'), (0.1, 1.0), ('0.2x', 2.0)],
     "line 3, column 't': '0.2x' is not a number"),
    ([('t', 'z_position'), (0.1, 1.0), (0.3, 2.0), (0.3, 3.0)],
     "line 4, column 't': 0.3 is not after the previous row's t = 0.3"),
    ([('t', 'z_position'), (0.2, 1.0), (0.1, 2.0)],
     "line 3, column 't': 0.1 is not after"),
    ([('t', 'z_position'), (-0.1, 1.0)], "line 2, column 't': -0.1 is before the initial"),
    # an empty z is a row without measurement (test_replay_gaps.py); an empty t is not
    ([('t', 'z_position'), (0.1, 1.0), ('', 2.0)], "line 3, column 't': empty"),
    ([('t', 'z_position'), (0.1, 'nan')], "line 2, column 'z_position': 'nan' is not a "
                                          'finite number'),
    ([('t', 'z_position'), (0.1, 1.0, 5.0)], 'line 2: 3 fields, but the header has 2'),
    ([('t', 't', 'z_position')], "line 1: column 't' appears twice"),
    ([('t', 'z_position'), (1e12, 1.0)], "line 2, column 't': 1000000000000.0 s is out of"),
])
def test_bad_input_names_line_and_column(tmp_path, capsys, rows, message):
    """Bad input: exit 1, one line naming file, line and column, no output written."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _write(source, rows[0], rows[1:])
    assert main(['--preset', 'train', str(source), '--output', str(target)]) == 1
    err = capsys.readouterr().err
    assert f'{source} {message}' in err, err
    assert err.count('\n') == 1
    assert not target.exists()
    assert os.listdir(tmp_path) == ['in.csv']  # no temporary file left behind either


def test_existing_output_survives_bad_input(tmp_path):
    """A failed replay leaves an existing output file exactly as it was."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    target.write_text('precious\n')
    _write(source, ['t', 'z_position'], [(0.1, 'x')])
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 1
    assert target.read_text() == 'precious\n'
    assert main(['--preset', 'train', str(tmp_path / 'missing.csv'), '-o', str(target)]) == 1
    assert target.read_text() == 'precious\n'


def test_config_file_and_its_errors(tmp_path, capsys):
    """--config runs a user's YAML; an invalid one exits 1 naming the key."""
    config = tmp_path / 'mine.yaml'
    with open(load_preset('train').source) as stream:
        config.write_text(stream.read().replace('R: [[1.0]]', 'R: [[4.0]]'))
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _write(source, ['t', 'z_position'], [(0.1, 1.0), (0.2, 2.0)])
    assert main(['--config', str(config), str(source), '-o', str(target)]) == 0
    _, out = _read_output(target)
    preset = load_preset('train')
    expected = run_series(preset, [0.1, 0.2], [[1.0], [2.0]])
    assert not np.allclose(out['position'], expected.x[:, 0])  # R = 4 differs from R = 1
    config.write_text(config.read_text().replace('R: [[4.0]]', 'R: [[4.0, 1.0]]'))
    assert main(['--config', str(config), str(source), '-o', str(tmp_path / 'out2.csv')]) == 1
    assert f'{config}: R must have shape (1, 1)' in capsys.readouterr().err
    assert not (tmp_path / 'out2.csv').exists()


def test_usage_errors_exit_2(tmp_path):
    """Missing or conflicting options are usage errors (argparse, exit 2)."""
    for argv in (['--preset', 'train', '-o', 'x.csv'],
                 ['--preset', 'bus', 'in.csv', '-o', 'x.csv'],
                 ['--preset', 'train', '--config', 'a.yaml', 'in.csv', '-o', 'x.csv'],
                 ['--preset', 'train', 'in.csv', '-o', 'x.csv', '--horizon', '-1'],
                 ['--preset', 'train', 'in.csv', '-o', 'x.csv', '--t0', 'nan']):
        with pytest.raises(SystemExit) as error:
            main(argv)
        assert error.value.code == 2


def test_stdin_stdout_and_umbrella(monkeypatch, capsys):
    """'-' reads standard input and writes standard output; kf-train dispatches replay."""
    monkeypatch.setattr(sys, 'stdin', io.StringIO('t,z_position\n0.1,1.0\n'))
    assert cli.main(['replay', '--preset', 'train', '-', '--output', '-']) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith('t,position,velocity,var_position')
    assert out[1].startswith('0.1,')
    assert cli.main(['replay', '--list']) == 0
    assert 'range-bearing' in capsys.readouterr().out


def test_console_script_end_to_end(tmp_path):
    """The installed kf-train script replays a file and reports errors on stderr."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _scenario_csv(source, 'car')
    script = os.path.join(os.path.dirname(sys.executable), 'kf-train')
    done = subprocess.run([script, 'replay', '--preset', 'car', str(source), '--output',
                           str(target)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert target.read_text().startswith('t,position,velocity,var_position,var_velocity,nis\n')
    bad = subprocess.run([script, 'replay', '--preset', 'car', str(source), '--output',
                          str(tmp_path / 'o.csv'), '--config', 'x'], capture_output=True,
                         text=True, timeout=60)
    assert bad.returncode == 2


def test_fast_and_careful_parsers_agree(tmp_path):
    """The numpy parse and the cell-by-cell parse read the same numbers."""
    rng = np.random.default_rng(9)
    values = rng.standard_normal((500, 3)) * 10.0 ** rng.integers(-5, 5, (500, 3))
    values[:, 0] = np.arange(1, 501) * 0.1
    plain = tmp_path / 'plain.csv'
    _write(plain, ['t', 'z_position', 'u'], [tuple(map(repr, r)) for r in values.tolist()])
    quoted = tmp_path / 'quoted.csv'  # quotes force the careful parser
    _write(quoted, ['t', 'z_position', 'u', 'q'],
           [tuple(map(repr, r)) + ('"x"',) for r in values.tolist()])
    needed = required_columns(load_preset('car'))
    a, b = read_table(str(plain), needed), read_table(str(quoted), needed)
    for column in ('t', 'z_position', 'u'):
        np.testing.assert_array_equal(a.columns[column], b.columns[column])
    np.testing.assert_array_equal(a.lines, b.lines)
