"""
``kf-train replay`` in bounded memory: read, filter and write block by block.

Readers hand :class:`kf_train.batch.stream.StreamingReplay` the rows in pieces and the
writer takes its output blocks as they come, so memory holds a block or two whatever
the input's size. Formats by name: ``.parquet`` (or a directory of Parquet files, one
dataset) in and out, else CSV; '-' is standard input or output (CSV).

Two CSV paths give the same bytes:

* with the ``[fast]`` extra, polars reads and writes (:mod:`kf_train.io.columnar`);
  anything it cannot vouch for (blank lines, a bad cell, an error to report) sends
  the whole replay back to the start on the built-in path, which names the line;
* without it, the built-in path: the file in blocks of lines, each parsed by
  :func:`kf_train.io.tables.read_table` and written by :mod:`kf_train.io.csvio`.

Parquet needs the extra. Output goes to a temporary file (or directory) beside OUTPUT
that replaces it only when complete, so bad input leaves no partial output.

Gaps (an empty measurement cell, a null in Parquet) are found while reading: the first
one makes the replay start again from the top with the ``updated`` column
(:class:`kf_train.batch.GapsFound`), so a complete input pays nothing and keeps its
bytes. Standard input is copied to a temporary file first, so it can be read again;
standard output is written when the output is complete.
"""

import io
import os
import queue
import re
import shutil
import sys
import tempfile
import threading
import time
from typing import Dict, Iterator, List, Optional

from kf_train.batch import DEFAULT_BLOCK_ROWS, GapsFound, RowError, Rows, StreamingReplay
from kf_train.io import (
    columnar, decode_text, HEADER_LINE, header_names, ID_COLUMN, InputError, open_output,
    read_table, required_columns, resolve_columns, UTF8_BOM)
from kf_train.replay.memory import ReplaySummary
from kf_train.replay.progress import Progress
import numpy as np

# Bytes of CSV text the built-in reader parses at a time.
BLOCK_BYTES = 1 << 20


def is_parquet(path: str) -> bool:
    """Return whether ``path`` names Parquet: a .parquet file or a directory."""
    return path != '-' and (path.endswith('.parquet') or os.path.isdir(path)
                            or path.endswith(os.sep))


class Labels:
    """The ids of a stream: text -> code, in order of first appearance."""

    def __init__(self):
        """Start with no id."""
        self.codes: Dict[str, int] = {}
        self.names: List[str] = []

    def encode(self, local_codes: np.ndarray, local_labels: List[str]) -> np.ndarray:
        """Return the stream codes of rows given as codes into ``local_labels``."""
        table = np.empty(len(local_labels), dtype=np.int64)
        for i, label in enumerate(local_labels):
            code = self.codes.get(label)
            if code is None:
                code = self.codes[label] = len(self.names)
                self.names.append(label)
            table[i] = code
        return table[local_codes]


class Source:
    """An input: pieces of rows, and the line (or row) number of every stream row."""

    def __init__(self, path: str, preset, where: str = 'line'):
        """Read ``path`` for ``preset``; ``where`` is 'line' (CSV) or 'row' (Parquet)."""
        self.path, self.preset, self.where = path, preset, where
        self.needed = required_columns(preset)
        self.gaps_needed = self.needed[1:1 + preset.dim_z]   # measurements may be empty
        self.wanted: List[str] = []
        self.id_column: Optional[str] = None
        self.labels = Labels()
        self.rows = 0
        self.total: Optional[int] = None   # rows in the input, when known (the bar's end)
        self.index: List[tuple] = []   # per piece: (first row, rows, first line, lines)

    @property
    def gaps(self) -> List[str]:
        """Return the columns (as the file names them) whose empty cells mean no measurement."""
        return self.wanted[1:1 + self.preset.dim_z]

    def rows_of(self, columns: Dict[str, np.ndarray], codes, labels,
                lines: Optional[np.ndarray] = None, missing=None) -> Rows:
        """Return a piece as engine rows (codes made stream-wide; ``lines`` if not plain)."""
        t = columns[self.wanted[0]]
        N = t.shape[0]
        z = np.column_stack([columns[name] for name in self.wanted[1:1 + self.preset.dim_z]])
        u = None
        if self.preset.dim_u:
            u = np.column_stack([columns[name] for name in self.wanted[1 + self.preset.dim_z:]])
        stream_codes = None if codes is None else self.labels.encode(codes, labels)
        first_line = self.rows + 2 if lines is None else int(lines[0])
        plain = lines is None or int(lines[-1]) - first_line + 1 == N
        self.index.append((self.rows, N, first_line, None if plain else lines))
        self.rows += N
        return Rows(t, z.reshape(N, self.preset.dim_z), u, stream_codes, missing)

    def number(self, row: int) -> int:
        """Return the file line (CSV) or the 1-based data row (Parquet) of a stream row."""
        if self.where == 'row':
            return row + 1
        for first, count, first_line, lines in reversed(self.index):
            if first <= row < first + count:
                return first_line + row - first if lines is None else int(lines[row - first])
        return row + 2


def input_columns(path: str) -> List[str]:
    """Return the column names of a CSV or Parquet input ([] for standard input)."""
    if path == '-':
        return []
    if is_parquet(path):
        return columnar.parquet_columns(path)
    with _open(path) as stream:
        return _header_of(path, stream.readline())


def _header_of(path: str, data: bytes) -> List[str]:
    """Return the header's names, checked as the in-memory replay checks them."""
    head = data.partition(b'\n')[0]
    if head.startswith(UTF8_BOM):
        head = head[len(UTF8_BOM):]
    text = decode_text(path, head.rstrip(b'\r'))
    if not text.strip():
        raise InputError(f'{path} line {HEADER_LINE}: expected a header row naming the '
                         'columns, e.g. t,z_position')
    return header_names(path, text)


class CsvSource(Source):
    """A CSV read block by block with the in-memory replay's exact parser."""

    def start(self) -> None:
        """Read and check the header."""
        self.stream = _open(getattr(self, 'spooled', None) or self.path)
        head = self.stream.readline()
        header = _header_of(self.path, head)
        self.wanted = resolve_columns(self.path, header, self.needed)
        self.id_column = ID_COLUMN if ID_COLUMN in header else None
        self.head = head.rstrip(b'\r\n')

    def pieces(self) -> Iterator[Rows]:
        """Yield the rows, a few MiB of text at a time."""
        try:
            line = 2
            for block in _line_blocks(self.stream):
                table = self._parse(self.head, block, line)
                if table.rows:
                    yield self.rows_of(table.columns, table.ids, table.id_labels,
                                       table.lines - 2 + line, table.missing)
                line += block.count(b'\n')
        finally:
            self.stream.close()

    def _parse(self, head: bytes, block: bytes, line: int):
        """Parse one block; errors name the file's line."""
        try:
            return read_table(self.path, self.needed, head + b'\n' + block, ids=True,
                              gaps=self.gaps_needed)
        except InputError as error:
            prefix = f'{self.path} line '
            message = str(error)
            if message.startswith(prefix):
                match = re.match(r'\d+', message[len(prefix):])
                if match and int(match.group()) > HEADER_LINE:
                    number = int(match.group()) - 2 + line
                    message = prefix + str(number) + message[len(prefix) + match.end():]
            raise InputError(message) from None


def _stdin():
    """Return standard input as a binary stream (a text one, as in tests, is encoded)."""
    if hasattr(sys.stdin, 'buffer'):
        return sys.stdin.buffer
    return io.BytesIO(sys.stdin.read().encode('utf-8'))


def _spool_stdin() -> str:
    """
    Copy standard input to a temporary file and return its path.

    A replay may have to read its input twice (a gap found late, an error to name), so
    standard input goes to disk first, not to memory.
    """
    handle, path = tempfile.mkstemp(prefix='kf-train-stdin-', suffix='.csv')
    with os.fdopen(handle, 'wb') as out:
        shutil.copyfileobj(_stdin(), out, BLOCK_BYTES)
    return path


def _open(path: str):
    """Open a file for reading; InputError if it cannot be."""
    try:
        return open(path, 'rb')
    except OSError as error:
        raise InputError(f'{path}: cannot read: {error.strerror}') from None


def _line_blocks(stream) -> Iterator[bytes]:
    """Yield the text in blocks of whole lines (no quoted field cut), CR LF made LF."""
    rest = b''
    while True:
        data = stream.read(BLOCK_BYTES)
        text = rest + data
        if not data:
            if text:
                yield text.replace(b'\r\n', b'\n').replace(b'\r', b'\n')
            return
        cut = text.rfind(b'\n') + 1
        quoted = b'"' in text                           # rare: then never cut inside one
        while quoted and cut and text.count(b'"', 0, cut) % 2:
            cut = text.rfind(b'\n', 0, cut - 1) + 1
        if cut == 0:
            rest = text
            continue
        rest = text[cut:]
        block = text[:cut]
        if b'\r' in block:
            block = block.replace(b'\r\n', b'\n').replace(b'\r', b'\n')
        yield block


class FastCsvSource(Source):
    """A CSV parsed by polars block by block; raises columnar.NotPlain if unusual."""

    def start(self) -> None:
        """Read and check the header."""
        self.stream = _open(self.path)
        self.header = _header_of(self.path, self.stream.readline())
        self.wanted = resolve_columns(self.path, self.header, self.needed)
        self.id_column = ID_COLUMN if ID_COLUMN in self.header else None

    def pieces(self) -> Iterator[Rows]:
        """Yield the rows, a few MiB of text at a time."""
        try:
            for piece in columnar.read_csv_pieces(_line_blocks(self.stream), self.header,
                                                  self.wanted, self.id_column, self.gaps):
                yield self.rows_of(piece.columns, piece.codes, piece.labels,
                                   missing=piece.missing)
        finally:
            self.stream.close()


class ParquetSource(Source):
    """A Parquet file or dataset directory, read by polars."""

    def start(self) -> None:
        """Read the schema and find the columns."""
        self.where = 'row'
        header = columnar.parquet_columns(self.path)
        try:
            self.wanted = resolve_columns(self.path, header, self.needed)
        except InputError as error:          # a schema has no line 1
            raise InputError(str(error).replace(
                f'{self.path} line {HEADER_LINE}:', f'{self.path}:', 1)) from None
        self.id_column = ID_COLUMN if ID_COLUMN in header else None
        self.total = columnar.parquet_rows(self.path)

    def pieces(self) -> Iterator[Rows]:
        """Yield the rows in pieces of a block."""
        for piece in columnar.read_parquet_pieces(self.path, self.wanted, self.id_column,
                                                  DEFAULT_BLOCK_ROWS, self.gaps):
            yield self.rows_of(piece.columns, piece.codes, piece.labels,
                               missing=piece.missing)


# ---------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------

def _row_message(source: Source, error: RowError) -> str:
    """Return the one-line message of a row error: file, line (or row) and column."""
    where, path = source.where, source.path
    at = f'{path} {where} {source.number(error.row)}'
    label = None
    if source.id_column is not None and error.obj is not None:
        label = source.labels.names[error.obj]
    if error.kind == 'range':
        return f"{at}, column 't': {error.reason}"
    if error.kind == 't0':
        of = '' if label is None else f" of id '{label}'"
        return f"{at}, column 't': {error.reason}{of} (set it with --t0)"
    if error.kind == 'order':
        if label is None:
            return f"{at}, column 't': {error.reason} (t must increase)"
        return (f"{at}, column 't': {error.reason} of id '{label}' ({where} "
                f'{source.number(error.previous)}); t must increase per id')
    return f'{at}: {error.reason}'


def prefetch(items: Iterator, depth: int = 2) -> Iterator:
    """
    Yield from ``items``, produced in a second thread up to ``depth`` ahead.

    polars parses without holding the GIL, so reading the next piece overlaps filtering
    this one. An exception in the producer is raised here; stopping early (an error on
    this side) stops the producer at its next piece.
    """
    pending: 'queue.Queue' = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def produce() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        pending.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            pending.put((end, None))
        except BaseException as error:            # handed to the consuming thread
            pending.put((end, error))

    thread = threading.Thread(target=produce, name='kf-train-reader', daemon=True)
    thread.start()
    try:
        while True:
            item, error = pending.get()
            if error is not None:
                raise error
            if item is end:
                return
            yield item
    finally:
        stop.set()
        thread.join()


def _blocks(source: Source, engine: StreamingReplay) -> Iterator[tuple]:
    """Yield the output blocks (columns, codes) of a whole input (a bar after 2 s)."""
    pieces = source.pieces()
    if not isinstance(source, CsvSource):            # polars readers: read ahead
        pieces = prefetch(pieces)
    with Progress(source.total, 'rows', 'replay') as progress:
        for rows in pieces:
            for block in engine.push(rows):
                yield block.columns, block.codes
            progress.advance(rows.t.shape[0])
        for block in engine.finish():
            yield block.columns, block.codes


def _run_once(source: Source, output_path: str, fast_output: bool, options: dict):
    """Replay once from ``source``; return the output header."""
    source.start()
    with StreamingReplay(source.preset, **options) as engine:
        header = ([ID_COLUMN] if source.id_column else []) + engine.header
        output = open_output(output_path, header, fast_output)
        try:
            output.run(_blocks(source, engine), source.labels.names)
        except BaseException:
            output.abort()
            raise
        output.commit()
    return header


def _sources(preset, input_path: str, fast: bool) -> List[Source]:
    """Return the readers to try in turn (the fast one first, when it applies)."""
    if is_parquet(input_path):
        return [ParquetSource(input_path, preset, 'row')]
    if fast and input_path != '-':
        return [FastCsvSource(input_path, preset), CsvSource(input_path, preset)]
    return [CsvSource(input_path, preset)]


def stream_replay(preset, input_path: str, output_path: str, *, horizon_s=None,
                  smooth: bool = False, t0_s: float = 0.0, filt=None,
                  block_rows: int = DEFAULT_BLOCK_ROWS, codec: str = 'auto',
                  spill_dir: Optional[str] = None) -> ReplaySummary:
    """
    Replay ``input_path`` into ``output_path`` in bounded memory; raise InputError.

    ``codec``: 'auto' (polars when installed), 'polars' or 'builtin'. ``block_rows``
    fixes the blocks (the numbers depend on it, not on how the input is read).
    """
    start = time.perf_counter()
    have = columnar.available()
    parquet = is_parquet(input_path) or is_parquet(output_path)
    if (parquet or codec == 'polars') and not have:
        raise InputError(f'{input_path if is_parquet(input_path) else output_path}: '
                         f'Parquet needs polars: {columnar.EXTRA_HINT}'
                         if parquet else f'--codec polars: {columnar.EXTRA_HINT}')
    fast = have and codec != 'builtin'
    options = {'horizon_s': horizon_s, 't0_s': t0_s, 'filt': filt, 'smooth': smooth,
               'block_rows': block_rows, 'spill_dir': spill_dir, 'gaps': False}
    spooled = _spool_stdin() if input_path == '-' else None
    try:
        while True:
            try:
                rows, header = _replay_with(preset, input_path, output_path, fast, options,
                                            spooled)
            except GapsFound:                  # rows without a measurement: again, with
                options['gaps'] = True         # the column that flags them
                continue
            return ReplaySummary(rows, header, time.perf_counter() - start)
    finally:
        if spooled is not None:
            os.unlink(spooled)


def _replay_with(preset, input_path: str, output_path: str, fast: bool, options: dict,
                 spooled: Optional[str]):
    """Replay with the readers in turn until one vouches for the input; return (rows, header)."""
    sources = _sources(preset, input_path, fast)
    for attempt, source in enumerate(sources):
        source.spooled = spooled
        last = attempt == len(sources) - 1
        try:
            header = _run_once(source, output_path, fast, options)
        except columnar.NotPlain:
            continue                      # read it again, the careful way
        except RowError as error:
            if not last:
                continue                  # the careful reader names the line
            raise InputError(_row_message(source, error)) from None
        except columnar.ParquetError as error:
            at = '' if error.row is None else f' row {error.row + 1},'
            raise InputError(f'{input_path}{at} {error}') from None
        except InputError:
            raise
        except ValueError as error:
            raise InputError(f'{input_path}: {error}') from None
        return source.rows, header
    raise AssertionError('the careful reader never gives up')  # pragma: no cover
