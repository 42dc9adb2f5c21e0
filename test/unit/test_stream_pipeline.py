"""
The streamed replay's two-thread pipeline (reader ahead, writer behind) changes no byte.

kf-train replay --engine stream reads the next piece in a thread
(:func:`kf_train.replay.stream.prefetch`) and writes the previous block in another
(:func:`kf_train.io.table_output.in_background`) while the main thread filters. Here
both are replaced by plain sequential loops and the outputs compared byte for byte on
inputs of many blocks (and many reader pieces), with and without ids, gaps, --smooth;
an error raised inside a stage is the one-line error, with no partial output left.
"""

import os

from kf_train.cli.replay import main
from kf_train.io import columnar, table_output
from kf_train.replay import stream as replay_stream
import numpy as np
import pytest

pytestmark = pytest.mark.skipif(not columnar.available(), reason='needs the [fast] extra')


def _sequential_prefetch(items, depth=2):
    """Yield ``items`` in this thread (the pipeline's reader, without the thread)."""
    yield from items


def _sequential_in_background(blocks, consume, depth=2):
    """Consume every block in this thread (the pipeline's writer, without the thread)."""
    for block in blocks:
        consume(block)


def _write_input(path, rows, objects, gaps, seed=7):
    """Write a train CSV of ``rows`` rows; ``objects`` ids; every 97th z empty if ``gaps``."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(0.1 * rng.uniform(0.5, 1.5, rows))
    z = 0.5 * t + rng.standard_normal(rows)
    lines = [('id,' if objects else '') + 't,z_position']
    for k in range(rows):
        cell = '' if gaps and k % 97 == 5 else repr(float(z[k]))
        label = f'obj{k % objects},' if objects else ''
        lines.append(f'{label}{float(t[k])!r},{cell}')
    path.write_text('\n'.join(lines) + '\n')


def _replay(source, target, extra):
    """Run the streamed replay; return the output's bytes (a dataset: its parts' bytes)."""
    assert main(['--preset', 'train', str(source), '-o', str(target), '--engine', 'stream',
                 '--block-rows', '64'] + extra) == 0
    if os.path.isdir(target):
        return [(name, (target / name).read_bytes()) for name in sorted(os.listdir(target))]
    return target.read_bytes()


@pytest.mark.parametrize('objects', [0, 3])
@pytest.mark.parametrize('gaps', [False, True])
@pytest.mark.parametrize('smooth', [False, True])
@pytest.mark.parametrize('kind', ['csv', 'parquet', 'dataset'])
def test_pipelined_equals_sequential(tmp_path, monkeypatch, objects, gaps, smooth, kind):
    """Two threads or one, the same bytes (CSV, Parquet file, dataset directory)."""
    monkeypatch.setattr(replay_stream, 'BLOCK_BYTES', 4096)    # many reader pieces
    source = tmp_path / 'in.csv'
    _write_input(source, 3000, objects, gaps)
    extra = ['--smooth'] if smooth else []
    name = {'csv': 'out{}.csv', 'parquet': 'out{}.parquet', 'dataset': 'out{}/'}[kind]
    pipelined = _replay(source, tmp_path / name.format('-a').rstrip('/'), extra)
    with monkeypatch.context() as patch:
        patch.setattr(replay_stream, 'prefetch', _sequential_prefetch)
        patch.setattr(table_output, 'in_background', _sequential_in_background)
        sequential = _replay(source, tmp_path / name.format('-b').rstrip('/'), extra)
    if kind == 'parquet':   # same doubles (the file's metadata may name the writer's run)
        import polars as pl
        a = pl.read_parquet(tmp_path / 'out-a.parquet')
        b = pl.read_parquet(tmp_path / 'out-b.parquet')
        assert a.equals(b) and a.height == 3000
    else:
        assert pipelined == sequential
    if kind == 'dataset':
        assert len(pipelined) > 1            # several blocks, several part files


@pytest.mark.parametrize('where', ['reader', 'writer'])
def test_an_error_in_a_stage_is_one_line_and_no_output(tmp_path, capsys, monkeypatch, where):
    """A failure in the reader or writer thread: one line on stderr, OUTPUT untouched."""
    source, target = tmp_path / 'in.csv', tmp_path / 'out.csv'
    _write_input(source, 2000, 0, False)
    target.write_bytes(b'old\n')
    if where == 'reader':
        pieces = columnar.read_csv_pieces

        def failing_pieces(*args, **kwargs):
            for number, piece in enumerate(pieces(*args, **kwargs)):
                if number == 2:
                    raise ValueError('disk went away')
                yield piece
        monkeypatch.setattr(replay_stream, 'BLOCK_BYTES', 4096)
        monkeypatch.setattr(columnar, 'read_csv_pieces', failing_pieces)
    else:
        written = []

        def failing_write(self, columns, ids=None):
            written.append(len(columns[0]))
            if len(written) == 3:
                raise ValueError('disk went away')
            self.stream.write(b'x\n')
        monkeypatch.setattr(columnar.CsvWriter, 'write', failing_write)
    assert main(['--preset', 'train', str(source), '-o', str(target), '--engine', 'stream',
                 '--block-rows', '64']) == 1
    err = capsys.readouterr().err
    assert 'disk went away' in err and err.count('\n') == 1, err
    assert target.read_bytes() == b'old\n'
    assert sorted(os.listdir(tmp_path)) == ['in.csv', 'out.csv']   # no temporary left
