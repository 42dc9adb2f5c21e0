"""``kf-train replay`` and ``compare`` with the rail preset: the IMM row by row (issue 11)."""

import csv
import dataclasses
import importlib.util
import math
import shutil

from kf_train.batch import RailSeriesFilter
from kf_train.cli.compare import format_table
from kf_train.cli.replay import main
from kf_train.estimator import DEFAULT_PRESET, EstimatorSettings, StreamEstimator
from kf_train.evaluate import run_comparison
from kf_train.presets import load_rail_preset, RAIL_PRESET_PATH
from kf_train.sim import family_parameters, rail_scenario
import numpy as np
import pytest

NS = 1_000_000_000


@pytest.fixture(scope='module')
def run_csv(tmp_path_factory):
    """Write a 50-s metro run (two trains in a second file) as replay CSVs."""
    directory = tmp_path_factory.mktemp('rail')
    params = dataclasses.replace(family_parameters('metro', 4), duration_s=50.0)
    scenario, _ = rail_scenario(4, 'metro', parameters=params)
    t, z = scenario.t_s.tolist(), scenario.z[:, 0].tolist()
    path = directory / 'run.csv'
    path.write_text('t,z_position\n' + ''.join(f'{a!r},{b!r}\n' for a, b in zip(t, z)))
    fleet = directory / 'fleet.csv'
    rows = [f'{label},{a!r},{b + offset!r}\n' for a, b in zip(t, z)
            for label, offset in (('a', 0.0), ('b', 500.0))]
    fleet.write_text('id,t,z_position\n' + ''.join(rows))
    return path, fleet, t, z


def _read(path):
    """Return (header, rows as floats) of a CSV (the id column, if any, dropped)."""
    with open(path, newline='') as stream:
        rows = list(csv.reader(stream))
    header = rows[0]
    start = 1 if header[0] == 'id' else 0
    return header[start:], np.array([[float(c) for c in row[start:]] for row in rows[1:]])


def test_streamed_and_in_memory_replay_agree_and_are_the_live_estimator(run_csv, tmp_path):
    path, _, t, z = run_csv
    outputs = []
    for name, extra in (('memory.csv', ['--engine', 'memory']),
                        ('stream.csv', ['--block-rows', '97']), ('default.csv', [])):
        assert main(['--preset', 'rail', str(path), '-o', str(tmp_path / name)] + extra) == 0
        outputs.append((tmp_path / name).read_bytes())
    # Blocks of 97 rows restore the IMM between blocks: the same bytes.
    assert outputs[0] == outputs[1] == outputs[2]
    header, rows = _read(tmp_path / 'memory.csv')
    names = load_rail_preset().state_names
    assert header[:7] == ['t', *names]
    assert 'predicted_braking_capability' in header and 'smoothed_position' not in header
    # The streaming estimator with the defaults but no gate (replay gates nothing): the
    # same arithmetic on the same whole-nanosecond stamps, so the same doubles.
    estimator = StreamEstimator(EstimatorSettings(gate_probability=1.0))
    column = {name: i for i, name in enumerate(header)}
    for k, (t_k, z_k) in enumerate(zip(t, z)):
        step = estimator.process(int(round(t_k * NS)), z_k, 1.0)
        np.testing.assert_array_equal(rows[k, 1:7], step.x)
        np.testing.assert_array_equal(rows[k, 7:13], np.diag(step.P))
        np.testing.assert_array_equal(
            rows[k, column['predicted_position']:column['predicted_position'] + 6],
            step.predicted_x)
    # The first row set the position (first_measurement), with the priors for the rest.
    assert rows[0, 1] == z[0] and rows[0, column['var_velocity']] == 400.0


def test_a_rail_preset_file_and_the_id_column(run_csv, tmp_path):
    path, fleet, _, _ = run_csv
    mine = tmp_path / 'my_rail.yaml'
    shutil.copy(RAIL_PRESET_PATH, mine)
    assert main(['--config', str(mine), str(path), '-o', str(tmp_path / 'a.csv')]) == 0
    assert main(['--preset', 'rail', str(path), '-o', str(tmp_path / 'b.csv')]) == 0
    assert (tmp_path / 'a.csv').read_bytes() == (tmp_path / 'b.csv').read_bytes()
    # Two trains in one file: each starts at its own first row, as alone.
    assert main(['--preset', 'rail', str(fleet), '-o', str(tmp_path / 'f.csv'),
                 '--block-rows', '64']) == 0
    _, alone = _read(tmp_path / 'b.csv')
    _, both = _read(tmp_path / 'f.csv')
    np.testing.assert_array_equal(both[0::2], alone)
    np.testing.assert_allclose(both[1::2, 1], alone[:, 1] + 500.0, rtol=0, atol=1e-9)


def test_every_csv_path_writes_the_regimes_and_the_nis(run_csv, tmp_path):
    """p_<regime> and nis in every CSV output of a rail replay: the same columns, bytes."""
    path, fleet, t, z = run_csv
    runs = {'memory': ['--engine', 'memory'], 'builtin': ['--codec', 'builtin'],
            'blocks': ['--block-rows', '97']}
    if importlib.util.find_spec('polars') is not None:
        runs['polars'] = ['--codec', 'polars']
    outputs = {}
    for name, extra in runs.items():
        assert main(['--preset', 'rail', str(path), '-o', str(tmp_path / name)] + extra) == 0
        outputs[name] = (tmp_path / name).read_bytes()
    assert len(set(outputs.values())) == 1, list(outputs)
    header, rows = _read(tmp_path / 'memory')
    regimes = [f'p_{name}' for name in load_rail_preset().mode_names]
    assert header[-5:] == regimes + ['nis']
    # The streaming estimator (no gate) after every stamp: its regimes and its NIS.
    estimator = StreamEstimator(EstimatorSettings(gate_probability=1.0))
    for k, (t_k, z_k) in enumerate(zip(t, z)):
        step = estimator.process(int(round(t_k * NS)), z_k, 1.0)
        np.testing.assert_array_equal(rows[k, -5:-1], estimator.mode_probabilities()[1])
        if k == 0:
            assert math.isnan(rows[k, -1])     # the first fix starts the filter: no NIS
        else:
            assert rows[k, -1] == step.update.nis
    # Every id of a fleet (the bank's path) gets the columns of the file alone.
    for name, extra in (('fleet', ['--block-rows', '64']),
                        ('fleet_memory', ['--engine', 'memory'])):
        assert main(['--preset', 'rail', str(fleet), '-o', str(tmp_path / name)] + extra) == 0
        fleet_header, both = _read(tmp_path / name)
        assert fleet_header == header
        np.testing.assert_array_equal(both[0::2, -5:], rows[:, -5:])


def test_a_table_without_a_preset_runs_the_node_default(run_csv, tmp_path):
    """No --preset: the node's default preset (rail), as a bag replay; CSV and Parquet."""
    path, _, _, _ = run_csv
    assert DEFAULT_PRESET == 'rail'     # else name the new default's preset below
    assert main([str(path), '-o', str(tmp_path / 'default.csv')]) == 0
    assert main(['--preset', 'rail', str(path), '-o', str(tmp_path / 'rail.csv')]) == 0
    assert (tmp_path / 'default.csv').read_bytes() == (tmp_path / 'rail.csv').read_bytes()
    assert main(['--preset', 'train', str(path), '-o', str(tmp_path / 'train.csv')]) == 0
    assert (tmp_path / 'train.csv').read_bytes() != (tmp_path / 'rail.csv').read_bytes()


def test_parquet_input_is_the_csv_replay(run_csv, tmp_path):
    pl = pytest.importorskip('polars')
    path, _, _, _ = run_csv
    pl.read_csv(path).write_parquet(tmp_path / 'in.parquet')
    assert main([str(tmp_path / 'in.parquet'), '-o', str(tmp_path / 'p.csv')]) == 0
    assert main(['--preset', 'rail', str(path), '-o', str(tmp_path / 'c.csv')]) == 0
    assert (tmp_path / 'p.csv').read_bytes() == (tmp_path / 'c.csv').read_bytes()


@pytest.mark.parametrize('extra, words', [
    (['--smooth'], 'RTS smoother'),
    (['--filter', 'ukf'], 'kf (or ekf, the same) only'),
    (['--filter', 'pf'], 'kf (or ekf, the same) only'),
])
def test_what_the_imm_cannot_do_is_refused(run_csv, tmp_path, capsys, extra, words):
    path, _, _, _ = run_csv
    assert main(['--preset', 'rail', str(path), '-o', str(tmp_path / 'x.csv')] + extra) == 1
    assert words in capsys.readouterr().err
    assert not (tmp_path / 'x.csv').exists()


def test_list_names_the_rail_preset(capsys):
    assert main(['--list']) == 0
    assert any(line.startswith('rail ') for line in capsys.readouterr().out.splitlines())


def test_the_series_filter_waits_for_its_first_measurement():
    filt = RailSeriesFilter(load_rail_preset())
    prior = filt.mean
    filt.predict(5.0)  # nothing to propagate yet
    np.testing.assert_array_equal(filt.mean, prior)
    assert filt.update([120.0], [[4.0]]) is None
    assert filt.mean[0] == 120.0 and filt.covariance[0, 0] == 4.0
    kept = filt.snapshot()
    filt.predict(0.1)
    assert filt.update([121.0]).nis >= 0.0
    filt.restore(kept)
    assert filt.mean[0] == 120.0
    with pytest.raises(ValueError, match='no control input'):
        filt.predict(0.1, [1.0])
    assert math.isclose(sum(filt.diagnostics().values()), 1.0)


def test_compare_runs_the_rail_imm_on_rail_runs():
    comparison = run_comparison('rail', runs=2, seed=3)
    [summary] = comparison.summaries
    assert (summary.kind, summary.runs_ok, summary.runs_failed) == ('kf', 2, 0)
    assert comparison.dim_x == 3 and comparison.t_s.shape == (1200,)
    # Position RMSE of the IMM on σ = 1 m measurements: well under σ once it has a few.
    assert summary.rmse_position_m < 1.0
    assert 'set by the first measurement' in format_table(comparison)
    with pytest.raises(ValueError, match='IMM of four Kalman filters'):
        run_comparison('rail', runs=1, kinds=['ukf'])
    with pytest.raises(ValueError, match='runs must be'):
        run_comparison('rail', runs=0)


def test_compare_takes_the_rail_family(capsys):
    metro = run_comparison('rail', runs=1, seed=3)
    regional = run_comparison('rail', runs=1, seed=3, rail_family='regional')
    assert '120-s metro runs' in format_table(metro)
    assert '120-s regional runs' in format_table(regional)
    # Other runs (a regional line is drawn from other ranges): other errors.
    assert regional.summaries[0].rmse_position_m != metro.summaries[0].rmse_position_m
    with pytest.raises(ValueError, match='for preset rail only'):
        run_comparison('train', runs=1, rail_family='regional')
    from kf_train.cli.compare import main as compare_main
    assert compare_main(['--preset', 'train', '--runs', '1', '--rail-family', 'metro',
                         '--no-figure']) == 1
    assert 'for preset rail only' in capsys.readouterr().err


def test_plot_draws_the_rail_preset(tmp_path, capsys):
    pytest.importorskip('matplotlib')
    from kf_train.cli.plotting import main as plot_main
    assert plot_main(['--preset', 'rail', '-o', str(tmp_path)]) == 0
    for name in ('rail.png', 'rail_run.png'):
        assert (tmp_path / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'rail.png' in capsys.readouterr().out
