"""
Tests of ``kf-train tune``: report, params file, tuned preset for replay, errors.

That the estimator node takes the params file is tested in test/ros/test_tune_params_file.py.
"""

import io
import math
import os
import sys

from kf_train import cli
from kf_train.batch import noisy_preset, run_linear_series
from kf_train.cli.replay import main as replay_main
from kf_train.cli.tune import main as tune_main
from kf_train.presets import load_preset, load_preset_file
from kf_train.sim import white_noise_acceleration_scenario
import numpy as np
import pytest
import yaml


def main(argv):
    """Run kf-train tune with the train preset unless one is given (the default is rail)."""
    argv = [str(a) for a in argv]
    if '--preset' not in argv and '--config' not in argv:
        argv = ['--preset', 'train'] + argv
    return tune_main(argv)


def _write_csv(path, rows=400, q=0.5, noise_std_m=1.0, seed=11, truth=True, ids=None):
    """Write a replay CSV of the random-force train (with truth columns); return it."""
    scenario = white_noise_acceleration_scenario(q, noise_std_m, rows, seed=seed)
    header = (['id'] if ids else []) + ['t', 'z_position'] + (
        ['true_position', 'true_velocity'] if truth else [])
    lines = [','.join(header)]
    for k, (t, z) in enumerate(zip(scenario.t_s.tolist(), scenario.z[:, 0].tolist())):
        cells = ([ids[k % len(ids)]] if ids else []) + [repr(t), repr(z)]
        if truth:
            cells += [repr(v) for v in scenario.truth[k].tolist()]
        lines.append(','.join(cells))
    with open(path, 'w') as stream:
        stream.write('\n'.join(lines) + '\n')
    return scenario


@pytest.fixture(scope='module')
def tuned(tmp_path_factory):
    """Run kf-train tune once on a CSV with truth; return (dir, stdout, exit code)."""
    directory = tmp_path_factory.mktemp('tune')
    _write_csv(str(directory / 'in.csv'))
    out = io.StringIO()
    stdout, sys.stdout = sys.stdout, out
    try:
        code = main([str(directory / 'in.csv'), '--output', str(directory / 'params.yaml'),
                     '--preset-output', str(directory / 'tuned.yaml')])
    finally:
        sys.stdout = stdout
    return directory, out.getvalue(), code


def test_the_verb_is_registered():
    """``kf-train tune`` dispatches to kf_train.cli.tune."""
    assert cli.COMMANDS['tune'][0] == 'kf_train.cli.tune'
    assert 'tune' in cli.usage()


def test_report_and_params_file(tuned):
    """It prints estimates with intervals, NIS and RMSE before/after; writes the params."""
    directory, text, code = tuned
    assert code == 0, text
    lines = text.splitlines()
    q_line = next(line for line in lines if 'process_noise_density' in line)
    r_line = next(line for line in lines if 'measurement_variance' in line)
    assert '[' in q_line and '[' in r_line
    assert any(line.startswith('NIS, mean of 399') and 'before' in line
               and 'noise too small' in line and 'after' in line and '(consistent)' in line
               for line in lines), text
    rmse = next(line for line in lines if line.startswith('2-s prediction RMSE'))
    before = float(rmse.split('position before ')[1].split(' m')[0])
    after = float(rmse.split('after ')[1].split(' m')[0])
    assert after < before
    params = yaml.safe_load((directory / 'params.yaml').read_text())
    values = params['estimator']['ros__parameters']
    assert values['preset'] == 'train'
    assert 0.5 / 3 < values['process_noise_density'] < 0.5 * 3
    assert 1.0 / 1.5 < values['measurement_variance'] < 1.0 * 1.5
    assert values['initialization'] == 'first_measurement'
    assert (directory / 'params.yaml').read_text().startswith('# Written by kf-train tune')


def test_replay_takes_the_tuned_preset(tuned, tmp_path):
    """``--preset-output`` writes a preset file replay --config runs: the tuned filter."""
    directory, _, _ = tuned
    values = yaml.safe_load(open(directory / 'params.yaml'))['estimator']['ros__parameters']
    preset = load_preset_file(str(directory / 'tuned.yaml'))
    assert preset.name == 'train-tuned'
    expected = noisy_preset(load_preset('train'), values['process_noise_density'],
                            [values['measurement_variance']])
    for dt in (0.1, 2.0):
        assert np.allclose(preset.dynamics.Q(dt), expected.dynamics.Q(dt), rtol=1e-15, atol=0)
    assert preset.model.R[0, 0] == values['measurement_variance']
    out = str(tmp_path / 'out.csv')
    assert replay_main([str(directory / 'in.csv'), '--config', str(directory / 'tuned.yaml'),
                        '--output', out]) == 0
    table = np.genfromtxt(out, delimiter=',', names=True)
    data = np.genfromtxt(directory / 'in.csv', delimiter=',', names=True)
    result = run_linear_series(expected, data['t'], data['z_position'])
    assert np.allclose(table['position'], result.x[:, 0], rtol=0, atol=1e-9)


def test_ids_share_the_noise_and_estimating_r_can_be_turned_off(tmp_path, capsys):
    """An id column gives several objects; --fix-r keeps R (and writes it)."""
    path = str(tmp_path / 'fleet.csv')
    _write_csv(path, rows=300, ids=['a', 'b'], truth=False)
    assert main([path, '-o', str(tmp_path / 'p.yaml'), '--fix-r', '1.0']) == 0
    text = capsys.readouterr().out
    assert '300 rows (2 objects), 298 innovations' in text
    assert 'measurement_variance [' not in text       # not estimated ...
    assert 'no truth columns' in text
    values = yaml.safe_load(open(tmp_path / 'p.yaml'))['estimator']['ros__parameters']
    assert values['measurement_variance'] == 1.0       # ... but fixed, and written


def test_a_preset_without_q_estimates_r_alone(tmp_path, capsys):
    """The robot preset has no white-noise acceleration: R alone is estimated, q stays 0."""
    path = tmp_path / 'robot.csv'
    rng = np.random.default_rng(2)
    t = np.arange(1, 201) * 0.1
    truth = 0.05 * t * np.cos(2.0 * t)
    speed = np.concatenate([[0.0], np.diff(truth) / 0.1]) + 0.2 * rng.standard_normal(200)
    z = truth + 0.03 * rng.standard_normal(200)
    path.write_text('t,z_position,u\n' + ''.join(
        f'{a!r},{b!r},{c!r}\n' for a, b, c in zip(t.tolist(), z.tolist(), speed.tolist())))
    assert main([str(path), '--preset', 'robot', '-o', str(tmp_path / 'p.yaml')]) == 0
    values = yaml.safe_load(open(tmp_path / 'p.yaml'))['estimator']['ros__parameters']
    assert values['process_noise_density'] == 0.0 and values['measurement_variance'] > 0.0
    assert 'process_noise_density [' not in capsys.readouterr().out


@pytest.mark.parametrize('content, args, message', [
    ('t,z\n0.1,1\n', [], "missing column 'z_position'"),
    ('t,z_position\n0.1,1\n0.2,x\n', [], "line 3, column 'z_position': 'x' is not a number"),
    ('t,z_position\n0.2,1\n0.1,2\n', [], "line 3, column 't'"),
    ('t,z_position\n', [], 'no rows'),
    ('t,z_position\n0.1,1\n0.2,1\n0.3,1\n0.4,1\n0.5,1\n', [], 'measurements do not vary'),
    ('t,z_position\n0.1,1\n0.2,2\n', ['--fix-r', '1', '2'], '--fix-r needs 1 variance'),
    ('t,z_bearing,z_range\n0.1,1,2\n', ['--config', 'RANGE_BEARING'],
     'nonlinear measurement model'),
])
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, content, args, message):
    """Bad input: exit 1, one line naming the problem, no traceback, no output file."""
    path = tmp_path / 'in.csv'
    path.write_text(content)
    args = [str(load_preset('range-bearing').source) if a == 'RANGE_BEARING' else a
            for a in args]
    code = main([str(path), '-o', str(tmp_path / 'p.yaml')] + args)
    err = capsys.readouterr().err
    assert code == 1
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert err.startswith('kf-train tune: error: ') and 'Traceback' not in err
    assert not os.path.exists(tmp_path / 'p.yaml')


def test_missing_scipy_is_one_line(tmp_path, capsys, monkeypatch):
    """Without scipy (an optional extra) tune says so in one line."""
    path = str(tmp_path / 'in.csv')
    _write_csv(path, rows=50, truth=False)
    monkeypatch.setitem(sys.modules, 'scipy', None)
    assert main([path, '-o', str(tmp_path / 'p.yaml')]) == 1
    err = capsys.readouterr().err
    assert 'needs scipy' in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize('args, message', [
    (['--fix-q', '-1'], '--fix-q must be a finite number >= 0'),
    (['--fix-r', '0'], '--fix-r must be finite numbers > 0'),
    (['--confidence', '1.5'], '--confidence must be in'),
    (['--initial-state', '--initialization', 'first_measurement'],
     '--initial-state needs --initialization prior'),
])
def test_bad_options_are_usage_errors(tmp_path, capsys, args, message):
    """Out-of-range options exit 2 with argparse's one-line message."""
    with pytest.raises(SystemExit) as exit_info:
        main(['in.csv', '-o', str(tmp_path / 'p.yaml')] + args)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_standard_input_and_the_initial_state(tmp_path, capsys, monkeypatch):
    """'-' reads stdin; --initial-state estimates x0 in prior mode and writes it."""
    path = tmp_path / 'in.csv'
    _write_csv(str(path), rows=200, q=0.05, truth=False)
    monkeypatch.setattr(sys, 'stdin', io.TextIOWrapper(io.BytesIO(path.read_bytes())))
    assert main(['-', '-o', str(tmp_path / 'p.yaml'), '--initial-state']) == 0
    text = capsys.readouterr().out
    assert 'initialization prior' in text and 'x0[position]' in text
    values = yaml.safe_load(open(tmp_path / 'p.yaml'))['estimator']['ros__parameters']
    assert values['initialization'] == 'prior'
    x0 = values['initial_state']
    # the truth at t0 (0.1 s before the first row at 0.1 s) is [0, 10]
    assert len(x0) == 2 and abs(x0[0]) < 3.0 and math.isclose(x0[1], 10.0, abs_tol=3.0)
