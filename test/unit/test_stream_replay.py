"""
The streamed replay (kf_train.batch.stream, kf-train replay --engine stream).

* Byte for byte: a stream of at most ``--block-rows`` rows writes exactly what the
  in-memory replay (``--engine memory``, today's writer) writes, on several presets,
  with and without an id column and with --smooth; the polars and built-in codecs
  write the same bytes; Parquet holds the same doubles.
* State across blocks: blocks of 1, 7, 64 rows carry every object's state; how the
  input is cut into pieces never changes a bit.

Tolerances: a block boundary only changes the association of floating-point sums in
the vectorised recursions (run_linear_series, rts_smooth); the same 1e-9 bound at unit
scale that holds the vectorised path to the row-by-row one (test_replay.py) holds here,
with a margin of more than 1000 over the largest difference seen (~1e-12).
"""

import os

from kf_train.batch import (
    filter_table, group_rows, Rows, run_series, smooth_series, StreamingReplay)
from kf_train.cli.replay import main
from kf_train.filters import FilterOptions, make_filter
from kf_train.io import columnar
from kf_train.presets import load_preset
from kf_train.replay import output_columns, run_preset, smooth_bank
from kf_train.replay import stream as replay_stream
import numpy as np
import pytest

PRESETS = ['train', 'car', 'robot-exact', 'cv-position-velocity', 'range-bearing']


def _close(a, b, tol=1e-9):
    """Assert |a − b| <= tol · max(1, |b|) elementwise."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    assert np.all(np.abs(a - b) <= tol * np.maximum(1.0, np.abs(b))), np.max(np.abs(a - b))


def _table(preset, N, seed, objects=0):
    """Return (t, z, u, ids) of N rows; ``objects`` > 0 interleaves that many ids."""
    rng = np.random.default_rng(seed)
    T = preset.nominal_period_s
    if objects:
        ids = rng.integers(0, objects, N)
        t = np.empty(N)
        for k in range(objects):
            rows = np.flatnonzero(ids == k)
            t[rows] = rng.uniform(0, T) + np.cumsum(T * rng.uniform(0.3, 2.0, rows.size))
        order = np.argsort(t, kind='stable')
        t, ids = t[order], ids[order]
    else:
        ids = None
        t = np.cumsum(T * rng.uniform(0.5, 1.5, N))
    if preset.name == 'range-bearing':
        x, y = 35.0 + 2.0 * t, 45.0 + t
        z = np.column_stack([np.arctan2(y, x) + 1e-3 * rng.standard_normal(N),
                             np.hypot(x, y) + rng.standard_normal(N)])
    else:
        z = 0.5 * t[:, None] + rng.standard_normal((N, preset.dim_z))
    u = rng.standard_normal((N, preset.dim_u)) if preset.dim_u else None
    return t, z, u, ids


def _write_csv(path, preset, t, z, u, ids):
    """Write a replay input CSV (numbers as repr)."""
    header = (['id'] if ids is not None else []) + ['t'] + [
        c[0] for c in preset.measurement_columns()] + (['u'] if preset.dim_u else [])
    columns = ([[f'obj{k}' for k in ids]] if ids is not None else []) + [t.tolist()]
    columns += [z[:, i].tolist() for i in range(z.shape[1])]
    columns += [u[:, 0].tolist()] if u is not None else []
    with open(path, 'w') as stream:
        stream.write(','.join(header) + '\n')
        for row in zip(*columns):
            stream.write(','.join(v if isinstance(v, str) else repr(v) for v in row) + '\n')


def _reference(preset, t, z, u, ids, smooth):
    """Return the in-memory replay's output columns (what --engine memory writes)."""
    groups = None if ids is None else group_rows(ids)
    result = run_preset(preset, t, z, u, groups=groups)
    smoothed = None
    if smooth:
        smoothed = smooth_series(result) if groups is None else smooth_bank(result, groups)
    return output_columns(preset, result, smoothed)[1]


# ---------------------------------------------------------------------------
# Byte for byte
# ---------------------------------------------------------------------------

@pytest.mark.parametrize('name', PRESETS)
@pytest.mark.parametrize('objects', [0, 5])
@pytest.mark.parametrize('smooth', [False, True])
def test_stream_writes_todays_bytes(tmp_path, name, objects, smooth):
    """Streamed output (polars and built-in codecs) equals the in-memory replay's bytes."""
    preset = load_preset(name)
    source = tmp_path / 'in.csv'
    _write_csv(source, preset, *_table(preset, 800, 3, objects))
    extra = ['--smooth'] if smooth else []
    outputs = {}
    for engine, codec in (('memory', 'auto'), ('stream', 'builtin'), ('stream', 'auto')):
        target = tmp_path / f'{engine}-{codec}.csv'
        assert main(['--preset', name, str(source), '-o', str(target), '--engine', engine,
                     '--codec', codec] + extra) == 0
        outputs[engine, codec] = target.read_bytes()
    assert outputs['stream', 'builtin'] == outputs['memory', 'auto']
    assert outputs['stream', 'auto'] == outputs['memory', 'auto']
    assert sorted(os.listdir(tmp_path)) == sorted(['in.csv'] + [
        f'{e}-{c}.csv' for e, c in outputs])   # no temporary or spill file left


@pytest.mark.parametrize('name', ['train', 'car', 'range-bearing'])
@pytest.mark.parametrize('objects', [0, 4])
def test_one_block_equals_the_in_memory_numbers(name, objects):
    """filter_table with one block gives the in-memory replay's doubles, bit for bit."""
    preset = load_preset(name)
    t, z, u, ids = _table(preset, 2000, 5, objects)
    for smooth in (False, True):
        got = filter_table(preset, t, z, u, ids, smooth=smooth)
        expected = _reference(preset, t, z, u, ids, smooth)
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------
# State across block boundaries
# ---------------------------------------------------------------------------

@pytest.mark.parametrize('name', PRESETS)
@pytest.mark.parametrize('objects', [0, 3])
def test_state_carries_across_blocks(name, objects):
    """Blocks of 1, 7 and 64 rows equal one block (1e-9); row-by-row paths exactly."""
    preset = load_preset(name)
    N = 400 if objects or name == 'range-bearing' else 700
    t, z, u, ids = _table(preset, N, 11, objects)
    whole = filter_table(preset, t, z, u, ids, smooth=True, block_rows=N)
    for block_rows in (1, 7, 64):
        if block_rows == 1 and preset.linear and not objects:
            continue           # one row per call of the vectorised path: slow, nothing new
        got = filter_table(preset, t, z, u, ids, smooth=True, block_rows=block_rows)
        for a, b in zip(got, whole):
            _close(a, b)
        if not preset.linear:  # the EKF runs row by row: blocks change nothing
            n_forward = 1 + 2 * preset.dim_x * (2 if preset.horizon_s else 1)
            for a, b in zip(got[:n_forward], whole[:n_forward]):
                np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('kind', ['ukf', 'pf'])
def test_filters_carry_their_state_exactly(kind):
    """--filter: a snapshot per object carries across blocks, bit for bit (PF included)."""
    preset = load_preset('cv-position')
    filt = make_filter(preset, kind, FilterOptions(particles=300) if kind == 'pf' else None)
    t, z, u, ids = _table(preset, 120, 2, 3)
    whole = filter_table(preset, t, z, u, ids, filt=filt, block_rows=1000)
    for block_rows in (1, 7):
        got = filter_table(preset, t, z, u, ids, filt=filt, block_rows=block_rows)
        for a, b in zip(got, whole):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize('objects', [0, 6])
def test_how_the_input_is_cut_changes_nothing(objects):
    """Pieces of 1, 7, 100 and all rows, with the same blocks: identical output."""
    preset = load_preset('car')
    t, z, u, ids = _table(preset, 700, 8, objects)

    def run(piece):
        with StreamingReplay(preset, smooth=True, block_rows=64) as engine:
            blocks = []
            for start in range(0, t.shape[0], piece):
                cut = slice(start, start + piece)
                blocks += engine.push(Rows(t[cut], z[cut], u[cut],
                                           None if ids is None else ids[cut]))
            blocks += engine.finish()
        return [np.concatenate([b.columns[j] for b in blocks]) for j in range(len(
            engine.header))]

    reference = run(t.shape[0])
    for piece in (1, 7, 100):
        for a, b in zip(run(piece), reference):
            np.testing.assert_array_equal(a, b)


def test_interleaved_ids_equal_each_id_alone():
    """Ids interleaved and cut by blocks of 7: every id equals its rows filtered alone."""
    preset = load_preset('cv-position')
    t, z, u, ids = _table(preset, 600, 4, 5)
    got = filter_table(preset, t, z, u, ids, block_rows=7)
    for k in range(5):
        rows = np.flatnonzero(ids == k)
        alone = run_series(preset, t[rows], z[rows])
        _close(got[1][rows], alone.x[:, 0])
        _close(got[4][rows], alone.P[:, 1, 1])


def test_block_boundary_errors_name_the_lines(tmp_path, capsys, monkeypatch):
    """A bad time in a later block of text names its line and the id's previous line."""
    monkeypatch.setattr(replay_stream, 'BLOCK_BYTES', 64)
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    rows = [f'{"AB"[k % 2]},{0.1 * (k + 1)!r},{k}.5' for k in range(40)]
    rows[33] = 'B,0.5,1.0'                              # line 35: id B went back in time
    source.write_text('id,t,z_position\n' + '\n'.join(rows) + '\n')
    for codec in ('builtin', 'auto'):
        assert main(['--preset', 'train', str(source), '-o', str(target), '--codec', codec,
                     '--block-rows', '8']) == 1
        err = capsys.readouterr().err
        assert (f"{source} line 35, column 't': 0.5 is not after the previous row's t = "
                f"3.2 of id 'B' (line 33); t must increase per id") in err, err
        assert err.count('\n') == 1
        assert os.listdir(tmp_path) == ['in.csv']


# ---------------------------------------------------------------------------
# Columnar: Parquet and the number text
# ---------------------------------------------------------------------------

def test_polars_text_is_repr_for_every_double():
    """repr_strings: the text of random bits, subnormals, ±0, 1e308 and the band is repr."""
    pytest.importorskip('polars')
    rng = np.random.default_rng(17)
    bits = rng.integers(0, 2 ** 64, 200_000, dtype=np.uint64).view(np.float64)
    band = 10.0 ** rng.uniform(-9.5, -3.5, 50_000) * rng.choice([-1.0, 1.0], 50_000)
    special = np.array([0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1e308,
                        1.7976931348623157e308, 1e-9, 9.99e-10, 1e-5, -1e-5,
                        9.999999999999999e-05, 1e-4, 0.1, 1e16, 1e15, 123.0, np.nan,
                        np.inf, -np.inf])
    values = np.concatenate([special, bits, band, rng.standard_normal(50_000) * 10.0 ** (
        rng.integers(-12, 18, 50_000))])
    text = columnar.repr_strings(values).cast(str).to_list()
    expected = [repr(v) for v in values.tolist()]
    assert text == expected
    finite = np.isfinite(values)
    pl = pytest.importorskip('polars')
    body = ('v\n' + '\n'.join(np.array(expected)[finite]) + '\n').encode()
    back = pl.read_csv(body, schema={'v': pl.Float64})['v'].to_numpy()
    np.testing.assert_array_equal(back.view(np.uint64), values[finite].view(np.uint64))


@pytest.mark.parametrize('objects', [0, 3])
def test_parquet_in_and_out_hold_the_same_doubles(tmp_path, objects):
    """CSV -> Parquet, Parquet -> Parquet and a dataset directory hold the CSV's doubles."""
    pl = pytest.importorskip('polars')
    preset = load_preset('train')
    source = tmp_path / 'in.csv'
    t, z, u, ids = _table(preset, 3000, 6, objects)
    _write_csv(source, preset, t, z, u, ids)
    assert main(['--preset', 'train', str(source), '-o', str(tmp_path / 'out.csv')]) == 0
    schema = {'id': pl.String} if objects else None
    expected = pl.read_csv(tmp_path / 'out.csv', schema_overrides=schema)
    frame = pl.read_csv(source, schema_overrides=schema)
    frame.write_parquet(tmp_path / 'in.parquet')
    (tmp_path / 'ds').mkdir()
    frame[:1000].write_parquet(tmp_path / 'ds' / 'a.parquet')
    frame[1000:].write_parquet(tmp_path / 'ds' / 'b.parquet')
    for src, dst in (('in.csv', 'o1.parquet'), ('in.parquet', 'o2.parquet'),
                     ('ds', 'o3'), ('in.parquet', 'o4.csv')):
        target = str(tmp_path / dst) + (os.sep if dst == 'o3' else '')
        assert main(['--preset', 'train', str(tmp_path / src), '-o', target,
                     '--block-rows', '512']) == 0
        if dst.endswith('.csv'):
            got = pl.read_csv(target, schema_overrides=schema)
        else:
            got = pl.read_parquet(os.path.join(target, '*.parquet') if dst == 'o3'
                                  else target)
        small = pl.read_csv(source, schema_overrides=schema)
        assert got.columns == expected.columns
        assert got.height == small.height
    # Same blocks -> same doubles: the 512-row CSV replay equals every Parquet output.
    assert main(['--preset', 'train', str(source), '-o', str(tmp_path / 'b.csv'),
                 '--block-rows', '512']) == 0
    blocked = pl.read_csv(tmp_path / 'b.csv', schema_overrides=schema)
    for dst in ('o1.parquet', 'o2.parquet', 'o3/*.parquet'):
        assert pl.read_parquet(tmp_path / dst).equals(blocked)


@pytest.mark.parametrize('column, cell, message', [
    ('z_position', 'nan', "row 3, column 'z_position': non-finite value"),
    ('z_position', 'inf', "row 3, column 'z_position': non-finite value"),
    ('t', None, "row 3, column 't': empty or non-finite value"),
])
def test_parquet_errors_name_the_row(tmp_path, capsys, column, cell, message):
    """
    Bad Parquet cells and missing columns: one line naming the row, exit 1, no file.

    A null measurement is a row without one (test_replay_gaps.py); NaN is refused.
    """
    pl = pytest.importorskip('polars')
    source, target = tmp_path / 'in.parquet', tmp_path / 'out.parquet'
    value = float(cell) if cell else None
    data = {'t': [0.1, 0.2, 0.3], 'z_position': [1.0, 2.0, 3.0]}
    data[column][2] = value
    pl.DataFrame(data).write_parquet(source)
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 1
    err = capsys.readouterr().err
    assert f'{source} {message}' in err and err.count('\n') == 1, err
    pl.DataFrame({'t': [0.1], 'z': [1.0]}).write_parquet(source)
    assert main(['--preset', 'train', str(source), '-o', str(target)]) == 1
    assert "missing column 'z_position'" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ['in.parquet']


def test_without_polars_csv_works_and_parquet_says_what_to_install(tmp_path, capsys,
                                                                   monkeypatch):
    """No [fast] extra: the built-in CSV path writes the same bytes; Parquet is refused."""
    preset = load_preset('car')
    source = tmp_path / 'in.csv'
    _write_csv(source, preset, *_table(preset, 300, 1, 2))
    assert main(['--preset', 'car', str(source), '-o', str(tmp_path / 'a.csv')]) == 0
    monkeypatch.setattr(columnar, 'available', lambda: False)
    assert main(['--preset', 'car', str(source), '-o', str(tmp_path / 'b.csv')]) == 0
    assert (tmp_path / 'a.csv').read_bytes() == (tmp_path / 'b.csv').read_bytes()
    capsys.readouterr()
    assert main(['--preset', 'car', str(source), '-o', str(tmp_path / 'c.parquet')]) == 1
    err = capsys.readouterr().err
    assert "pip install 'kf_train[fast]'" in err and err.count('\n') == 1, err


def test_engine_usage_errors(tmp_path):
    """--block-rows 0, --workers 0 and --scheduler without dask are usage errors."""
    for extra in (['--block-rows', '0'], ['--workers', '0'], ['--scheduler', 'tcp://x:1']):
        with pytest.raises(SystemExit) as error:
            main(['--preset', 'train', 'in.csv', '-o', 'out.csv'] + extra)
        assert error.value.code == 2


@pytest.mark.parametrize('objects', [0, 4])
def test_plain_csv_goes_through_polars_unusual_csv_through_the_builtin_reader(
        tmp_path, monkeypatch, objects):
    """A plain file never falls back; blank lines and spaces do, with the same bytes."""
    pytest.importorskip('polars')
    preset = load_preset('car')
    source = tmp_path / 'in.csv'
    _write_csv(source, preset, *_table(preset, 500, 9, objects))
    assert main(['--preset', 'car', str(source), '-o', str(tmp_path / 'a.csv'),
                 '--codec', 'builtin']) == 0
    reads = []
    original = replay_stream.CsvSource.start
    monkeypatch.setattr(replay_stream.CsvSource, 'start',
                        lambda self: reads.append(self.path) or original(self))
    assert main(['--preset', 'car', str(source), '-o', str(tmp_path / 'b.csv')]) == 0
    assert reads == []
    assert (tmp_path / 'a.csv').read_bytes() == (tmp_path / 'b.csv').read_bytes()
    lines = source.read_text().splitlines()
    source.write_text('\n'.join(lines[:100] + ['', ' '] + lines[100:]).replace(',', ', ')
                      + '\n\n')
    assert main(['--preset', 'car', str(source), '-o', str(tmp_path / 'c.csv')]) == 0
    assert reads == [str(source)]
    assert (tmp_path / 'a.csv').read_bytes() == (tmp_path / 'c.csv').read_bytes()


def test_offline_modules_import_no_columnar_library():
    """The core, the estimator and the replay command import neither polars nor dask."""
    import subprocess
    import sys
    code = ('import sys, kf_train.core, kf_train.estimator.estimator, kf_train.cli.replay, '
            'kf_train.replay, '
            'kf_train.batch.stream, kf_train.batch.partition, kf_train.io.columnar\n'
            'print(sorted({m.split(".")[0] for m in sys.modules} & {"polars", "dask", '
            '"distributed", "pandas", "pyarrow"}))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.strip() == '[]'
