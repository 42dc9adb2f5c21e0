"""
kf-train replay: rows without a measurement, the same bytes in every engine, polish.

* An empty measurement cell (CSV) or a null (Parquet) is a row without measurement:
  predicted, not updated, flagged in a last column ``updated``; 'nan' is refused.
* The streamed and the in-memory replay write the same bytes over many blocks (small
  ``--block-rows``), with and without an ``id`` column and ``--smooth``, through both
  CSV codecs.
* An output path in a missing or unwritable directory: one line, exit 1.
* The progress bar (tqdm) draws only when asked, and never changes what is written.

Tolerance of the gap rows against the row-by-row reference: the vectorised path and
the loop evaluate the same recursion in a different order; over ~300 rows of a
well-conditioned 2-state filter their rounding differences stay below 1e-12 relative
(seen: 4e-13 for the car preset); 1e-9 leaves a margin of over 1000.
"""

import io
import os

from kf_train.batch import run_series
from kf_train.cli.replay import main
from kf_train.cli.simulate import main as simulate_main
from kf_train.io import read_table, required_columns
from kf_train.presets import load_preset
from kf_train.replay import progress
import numpy as np
import pytest

TOL = 1e-9


def _log(path, rows=300, ids=False, gaps=True, seed=3):
    """Write a train log with empty z_position cells (and an id column) to ``path``."""
    rng = np.random.default_rng(seed)
    t = np.round(np.arange(1, rows + 1) * 0.1, 1)
    z = [repr(v) for v in (10.0 * t + rng.normal(0.0, 1.0, rows)).tolist()]
    if gaps:
        for k in np.flatnonzero(rng.random(rows) < 0.25):
            z[k] = ''
        z[40:70] = [''] * 30                          # a long gap across a block edge
    header = ('id,' if ids else '') + 't,z_position'
    lines = [header]
    for k in range(rows):
        label = f'T{k % 3},' if ids else ''
        lines.append(f'{label}{float(t[k])!r},{z[k]}')
    path.write_text('\n'.join(lines) + '\n')
    return path


def _run(argv, capsys):
    """Run kf-train replay; return (exit code, stderr)."""
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


@pytest.mark.parametrize('ids', [False, True])
@pytest.mark.parametrize('smooth', [False, True])
def test_stream_equals_memory_byte_for_byte_over_many_blocks(tmp_path, capsys, ids, smooth):
    """Blocks of 64 rows: stream (polars and built-in) and memory write the same bytes."""
    pytest.importorskip('polars')
    for gaps in (False, True):
        source = _log(tmp_path / f'in-{gaps}.csv', ids=ids, gaps=gaps)
        outputs = []
        for engine, codec in (('stream', 'auto'), ('stream', 'builtin'), ('memory', 'auto')):
            out = tmp_path / f'{engine}-{codec}-{gaps}.csv'
            argv = ['--preset', 'train', source, '-o', out, '--block-rows', '64',
                    '--engine', engine, '--codec', codec] + (['--smooth'] if smooth else [])
            assert _run(argv, capsys)[0] == 0
            outputs.append(out.read_bytes())
        assert outputs[0] == outputs[1] == outputs[2]
        header = outputs[0].split(b'\n', 1)[0].decode()
        assert header.endswith(',updated') == gaps
        assert header.startswith('id,') == ids


@pytest.mark.parametrize('name', ['train', 'car', 'range-bearing'])
def test_block_size_never_depends_on_the_engine(tmp_path, capsys, name):
    """Other presets (linear with control, EKF): stream and memory equal at 50 rows/block."""
    preset = load_preset(name)
    rng = np.random.default_rng(1)
    rows = 230
    t = np.round(np.arange(1, rows + 1) * 0.1, 1)
    columns = {'t': t}
    for k, column in enumerate(c[0] for c in preset.measurement_columns()):
        columns[column] = (100.0 + 10 * t if 'bearing' not in column else 0.3 + 0 * t
                           ) + rng.normal(0.0, 0.01 if 'bearing' in column else 1.0, rows)
    for column in preset.control_columns():
        columns[column] = rng.normal(0.0, 1.0, rows)
    text = [','.join(columns)] + [','.join(repr(float(columns[c][k])) for c in columns)
                                  for k in range(rows)]
    text[20] = text[20].split(',', 1)[0] + ',' + ','.join([''] * (len(columns) - 1))
    if preset.dim_u:                 # the control must be there: only z empty
        cells = text[20].split(',')
        cells[-1] = repr(float(columns['u'][19]))
        text[20] = ','.join(cells)
    source = tmp_path / 'in.csv'
    source.write_text('\n'.join(text) + '\n')
    a, b = tmp_path / 'a.csv', tmp_path / 'b.csv'
    assert _run(['--preset', name, source, '-o', a, '--block-rows', '50'], capsys)[0] == 0
    assert _run(['--preset', name, source, '-o', b, '--block-rows', '50', '--engine',
                 'memory'], capsys)[0] == 0
    assert a.read_bytes() == b.read_bytes()


def test_a_gap_row_is_predicted_not_updated(tmp_path, capsys):
    """The estimate of a row without measurement is the row-by-row reference's prior."""
    source = _log(tmp_path / 'in.csv')
    out = tmp_path / 'out.csv'
    assert _run(['--preset', 'train', source, '-o', out, '--block-rows', '64'], capsys)[0] == 0
    got = np.genfromtxt(out, delimiter=',', names=True)
    table = read_table(str(source), required_columns(load_preset('train')),
                       gaps=[('z_position',)])
    missing = table.missing
    assert missing is not None and 30 <= missing.sum() < 150
    np.testing.assert_array_equal(got['updated'], np.where(missing, 0.0, 1.0))
    ref = run_series(load_preset('train'), table.columns['t'], table.columns['z_position'],
                     missing=missing)
    np.testing.assert_array_equal(ref.x[missing], ref.x_prior[missing])
    scale = np.maximum(1.0, np.abs(ref.x[:, 0]))
    assert np.max(np.abs(got['position'] - ref.x[:, 0]) / scale) < TOL
    assert np.max(np.abs(got['var_position'] - ref.P[:, 0, 0])) < TOL
    complete = _log(tmp_path / 'complete.csv', gaps=False)
    assert _run(['--preset', 'train', complete, '-o', out], capsys)[0] == 0
    assert 'updated' not in out.read_text().split('\n', 1)[0]


@pytest.mark.parametrize('cell', ['nan', 'NaN', 'inf'])
def test_nan_is_not_missing(tmp_path, capsys, cell):
    """'nan' (or inf) is refused with the line and column: only an empty cell is missing."""
    source = tmp_path / 'in.csv'
    source.write_text(f't,z_position\n0.1,1.0\n0.2,{cell}\n')
    code, err = _run(['--preset', 'train', source, '-o', tmp_path / 'o.csv'], capsys)
    assert code == 1 and "line 3, column 'z_position'" in err and err.count('\n') == 1
    assert not (tmp_path / 'o.csv').exists()


def test_parquet_nulls_are_gaps_like_empty_csv_cells(tmp_path, capsys):
    """A null z in Parquet gives the bytes of the CSV with an empty cell."""
    pl = pytest.importorskip('polars')
    source = _log(tmp_path / 'in.csv')
    frame = pl.read_csv(source, schema_overrides={'z_position': pl.Float64})
    frame.write_parquet(tmp_path / 'in.parquet')
    a, b = tmp_path / 'a.csv', tmp_path / 'b.csv'
    assert _run(['--preset', 'train', source, '-o', a, '--block-rows', '64'], capsys)[0] == 0
    assert _run(['--preset', 'train', tmp_path / 'in.parquet', '-o', b, '--block-rows', '64'],
                capsys)[0] == 0
    assert a.read_bytes() == b.read_bytes()


def test_standard_input_with_a_late_gap(tmp_path, capsys, monkeypatch):
    """A gap found after the first block (a second pass) works from stdin to stdout."""
    source = _log(tmp_path / 'in.csv', rows=400, gaps=False)
    lines = source.read_text().split('\n')
    lines[350] = lines[350].split(',')[0] + ','
    source.write_text('\n'.join(lines))
    expected = tmp_path / 'expected.csv'
    assert _run(['--preset', 'train', source, '-o', expected, '--block-rows', '64'],
                capsys)[0] == 0
    monkeypatch.setattr('sys.stdin', io.StringIO(source.read_text()))
    assert main(['--preset', 'train', '-', '-o', '-', '--block-rows', '64']) == 0
    assert capsys.readouterr().out == expected.read_text()


def test_a_simulated_csv_with_dropouts_replays(tmp_path, capsys):
    """kf-train simulate writes empty z_position for dropped samples; replay reads them."""
    sim = tmp_path / 'run.csv'
    assert simulate_main(['--duration', '30', '-p', 'dropout_probability:=0.3', '--seed', '4',
                          '-o', str(sim)]) == 0
    dropped = [line for line in sim.read_text().split('\n')[1:] if line.split(',')[1:2] == ['']]
    assert dropped
    out = tmp_path / 'out.csv'
    assert _run(['--preset', 'train', sim, '-o', out], capsys)[0] == 0
    got = np.genfromtxt(out, delimiter=',', names=True)
    assert got.shape[0] == 300 and int((got['updated'] == 0.0).sum()) == len(dropped)


@pytest.mark.parametrize('output', ['missing/o.csv', 'missing/o.parquet', 'missing/ds/'])
def test_output_in_a_missing_directory_is_one_line(tmp_path, capsys, output):
    """A missing directory: one line naming it, exit 1, for every output kind."""
    source = _log(tmp_path / 'in.csv', rows=20, gaps=False)
    for engine in (['stream'], ['memory']) if output.endswith('.csv') else (['stream'],):
        code, err = _run(['--preset', 'train', source, '-o', tmp_path / output,
                          '--engine'] + engine, capsys)
        assert code == 1 and err.count('\n') == 1 and 'does not exist' in err, err
        assert 'Traceback' not in err


def test_output_in_an_unwritable_directory_is_one_line(tmp_path, capsys, monkeypatch):
    """An unwritable directory (as os.access reports it; root writes anywhere)."""
    source = _log(tmp_path / 'in.csv', rows=20, gaps=False)
    real = os.access
    locked = str(tmp_path / 'locked')
    os.mkdir(locked)
    monkeypatch.setattr(os, 'access', lambda p, mode: False if str(p) == locked
                        else real(p, mode))
    code, err = _run(['--preset', 'train', source, '-o', os.path.join(locked, 'o.csv')],
                     capsys)
    assert code == 1 and err.count('\n') == 1 and 'not writable' in err


def test_progress_bar_draws_only_when_asked():
    """A forced bar writes to its stream; counted() passes every item through unchanged."""
    pytest.importorskip('tqdm')
    stream = io.StringIO()
    with progress.Progress(10, 'rows', 'replay', stream=stream, force=True) as bar:
        assert bar.active
        bar.advance(10)
    assert 'replay' in stream.getvalue()
    quiet = progress.Progress(10, 'rows', stream=io.StringIO())     # not a terminal
    assert not quiet.active
    items = list(range(3 * progress.EVERY + 5))
    assert list(progress.counted(iter(items), len(items), 'msg', force=False)) == items
    assert list(progress.counted(iter(items), len(items), 'msg', force=True)) == items


def test_dask_partitions_refuse_gaps_by_name():
    """The Dask partition function names the id and time of a row without measurement."""
    pd = pytest.importorskip('pandas')
    from kf_train.batch.partition import filter_partition
    frame = pd.DataFrame({'id': ['a', 'a', 'a'], 't': [0.1, 0.2, 0.3],
                          'z_position': [1.0, np.nan, 3.0]})
    with pytest.raises(ValueError, match=r"id 'a', t = 0.2: empty or non-finite measurement"):
        filter_partition(frame, 'train')
