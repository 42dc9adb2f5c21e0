"""
Tables in and out: the CSV a replay reads (checked, named line and column) and writes.

:func:`read_table` reads the columns a preset needs (:func:`required_columns`) from a
CSV: plain files (decimal numbers, commas, newlines) are converted in bulk by
:mod:`kf_train.io.csvio`; anything else, and every error, goes through the csv module
cell by cell, so that an :class:`InputError` names the file, the line and the column.
:func:`format_csv` writes estimates as CSV text in which every number is Python's
shortest round-trip ``repr``. The input layout is described in ``kf-train replay
--help`` (:mod:`kf_train.cli.replay`).
"""

import csv
import io
from typing import Dict, Iterator, List, NamedTuple, Optional, Sequence, Tuple
import warnings

from kf_train.filters import NS_PER_S
from kf_train.io import csvio
from kf_train.presets import Preset
import numpy as np

HEADER_LINE = 1
ID_COLUMN = 'id'
UTF8_BOM = b'\xef\xbb\xbf'
TIME_CELL = "{path} line {line}, column 't'"


class InputError(ValueError):
    """Bad input: the message names the file, and the line and column when it can."""


class Table(NamedTuple):
    """The columns a preset needs, read from a CSV."""

    columns: Dict[str, np.ndarray]
    """Column name (as in the file) -> values (N,)."""
    rows: int
    lines: np.ndarray
    """The file line of every row (1 is the header)."""
    ids: Optional[np.ndarray] = None
    """With an ``id`` column: each row's object, an index into ``id_labels`` (N,)."""
    id_labels: Optional[List[str]] = None
    """The distinct ids, sorted."""
    missing: Optional[np.ndarray] = None
    """With ``gaps``: the rows with an empty measurement cell (N,) (its value NaN), or None."""


def required_columns(preset: Preset) -> List[Tuple[str, ...]]:
    """Return the columns a preset needs: each entry lists the accepted names."""
    return ([('t',)] + list(preset.measurement_columns())
            + [(name,) for name in preset.control_columns() if preset.dim_u])


def header_names(path: str, line: str) -> List[str]:
    """Return the header's column names (whitespace and surrounding quotes stripped)."""
    names = []
    for cell in next(csv.reader([line])):
        name = cell.strip()
        if len(name) >= 2 and name[0] == name[-1] == '"':
            name = name[1:-1].strip()
        names.append(name)
    seen = set()
    for name in names:
        if name in seen and name:
            raise InputError(f"{path} line {HEADER_LINE}: column '{name}' appears twice")
        seen.add(name)
    return names


def resolve_columns(path: str, header: List[str], needed: Sequence[Tuple[str, ...]]) -> List[str]:
    """Return, for every needed column, the name the file uses; raise if one is missing."""
    resolved = []
    for names in needed:
        present = [name for name in names if name in header]
        if not present:
            also = f" (or '{names[1]}')" if len(names) > 1 else ''
            needs = ', '.join(' or '.join(alternatives) for alternatives in needed)
            raise InputError(
                f"{path} line {HEADER_LINE}: missing column '{names[0]}'{also}; needed: "
                f"{needs}; the header has: {', '.join(header)}")
        if len(present) > 1:
            raise InputError(f"{path} line {HEADER_LINE}: columns {' and '.join(present)} "
                             'both give the same measurement; keep one')
        resolved.append(present[0])
    return resolved


def _parse_fast(body: str, ncols: int) -> Optional[np.ndarray]:
    """Return the numeric table (rows, ncols), or None when anything needs a closer look."""
    if not body:
        return np.empty((0, ncols))
    if '"' in body or 'x' in body or 'X' in body:  # quotes, hex floats: the careful path
        return None
    rows = body.count('\n') + 1
    raw = np.frombuffer(body.encode('utf-8'), dtype=np.uint8)
    separators = np.flatnonzero((raw == ord(',')) | (raw == ord('\n')))
    if separators.size != rows * ncols - 1:
        return None
    # Every row must have exactly ncols fields: newlines sit at every ncols-th separator.
    newlines = np.flatnonzero(raw[separators] == ord('\n'))
    if not np.array_equal(newlines, np.arange(ncols - 1, separators.size, ncols)):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        try:
            values = np.fromstring(body.replace('\n', ','), sep=',')
        except (ValueError, DeprecationWarning):
            return None
    if values.size != rows * ncols:
        return None
    return values.reshape(rows, ncols)


def _cell(path: str, line: int, column: str, text: str, empty_ok: bool = False) -> float:
    """Return a cell's value (NaN for an empty one if ``empty_ok``); raise InputError."""
    cell = text.strip()
    where = f"{path} line {line}, column '{column}'"
    if not cell:
        if empty_ok:
            return float('nan')
        raise InputError(f'{where}: empty cell, expected a number')
    try:
        if '_' in cell:
            raise ValueError(cell)
        value = float(cell)
    except ValueError:
        raise InputError(f'{where}: {text!r} is not a number') from None
    if not np.isfinite(value):
        raise InputError(f'{where}: {text!r} is not a finite number')
    return value


def _parse_careful(path: str, body: str, header: List[str], wanted: List[str],
                   labelled: Optional[str] = None, empty_ok=frozenset()):
    """
    Return (values (rows, len(wanted)), lines (rows,), labels) parsing cell by cell.

    ``labelled`` names a text column (the id) returned as stripped strings (rows,);
    an empty cell of a column in ``empty_ok`` is NaN.
    """
    index = [header.index(name) for name in wanted]
    label_index = None if labelled is None else header.index(labelled)
    values, lines, labels = [], [], []
    reader = csv.reader(io.StringIO(body))
    for row in reader:
        line = reader.line_num + HEADER_LINE
        if not row or all(not cell.strip() for cell in row):
            continue  # blank line
        if len(row) != len(header):
            raise InputError(f'{path} line {line}: {len(row)} fields, but the header has '
                             f'{len(header)}')
        values.append([_cell(path, line, name, row[i], name in empty_ok)
                       for name, i in zip(wanted, index)])
        lines.append(line)
        if label_index is not None:
            label = row[label_index].strip()
            if not label:
                raise InputError(f"{path} line {line}, column '{labelled}': empty id")
            labels.append(label)
    return (np.array(values, dtype=float).reshape(len(values), len(wanted)),
            np.array(lines, dtype=np.int64), labels)


def _read_bytes(path: str, text) -> bytes:
    """Return the file's bytes (or ``text``'s), without a BOM, every line end a newline."""
    if text is None:
        try:
            with open(path, 'rb') as stream:
                data = stream.read()
        except OSError as error:
            raise InputError(f'{path}: cannot read: {error.strerror}') from None
    else:
        data = text.encode('utf-8') if isinstance(text, str) else bytes(text)
    if data.startswith(UTF8_BOM):
        data = data[len(UTF8_BOM):]
    if b'\r' in data:
        data = data.replace(b'\r\n', b'\n').replace(b'\r', b'\n')
    return data


def decode_text(path: str, data: bytes) -> str:
    """Return UTF-8 text; raise InputError otherwise."""
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError as error:
        raise InputError(f'{path}: not UTF-8 text ({error.reason})') from None


def read_table(path: str, needed: Sequence[Tuple[str, ...]], text=None,
               ids: bool = False, gaps: Sequence[Tuple[str, ...]] = ()) -> Table:
    """
    Read the needed columns of a CSV (``text``, str or bytes, given, or read from ``path``).

    With ``ids`` and an ``id`` column in the header, the table's ``ids`` and
    ``id_labels`` say which object every row belongs to. The columns in ``gaps``
    (entries of ``needed``: the measurements) may have empty cells: their value is NaN
    and the table's ``missing`` flags the rows that have one ('nan' text is refused).

    Plain files (decimal numbers, commas, newlines) are converted in bulk by
    :mod:`kf_train.io.csvio`; anything else, and every error, goes through the csv
    module cell by cell, so that a message can name the line and the column.
    """
    data = _read_bytes(path, text)
    head, _, body = data.partition(b'\n')
    head_text = decode_text(path, head)
    if not head_text.strip():
        raise InputError(f'{path} line {HEADER_LINE}: expected a header row naming the '
                         'columns, e.g. t,z_position')
    header = header_names(path, head_text)
    wanted = resolve_columns(path, header, needed)
    labelled = ID_COLUMN if ids and ID_COLUMN in header else None
    body = body.rstrip(b'\n')
    index = [header.index(name) for name in wanted]
    fields = csvio.split_fields(body, len(header))
    if fields is not None:
        values = csvio.parse_numbers(body, fields.starts[:, index], fields.ends[:, index])
        labels = None
        if values is not None and labelled is not None:
            i = header.index(labelled)
            labels = csvio.parse_labels(body, fields.starts[:, i], fields.ends[:, i])
        if values is not None and np.all(np.isfinite(values)) and (
                labelled is None or labels is not None):
            decode_text(path, body)            # the other columns must be text too
            lines = np.arange(values.shape[0], dtype=np.int64) + HEADER_LINE + 1
            codes, names = labels if labels is not None else (None, None)
            return Table(dict(zip(wanted, values.T)), values.shape[0], lines, codes, names)
    body_text = decode_text(path, body)
    if labelled is None:
        table = _parse_fast(body_text, len(header))
        if table is not None:
            values = table[:, index]
            if np.all(np.isfinite(values)):
                lines = np.arange(values.shape[0], dtype=np.int64) + HEADER_LINE + 1
                return Table(dict(zip(wanted, values.T)), values.shape[0], lines)
    # Something is off (or unusual): parse cell by cell to name the line and column.
    empty_ok = frozenset(name for name, names in zip(wanted, needed) if names in gaps)
    values, lines, labels = _parse_careful(path, body_text, header, wanted, labelled,
                                           empty_ok)
    codes = names = missing = None
    if labelled is not None:
        names, codes = np.unique(np.array(labels, dtype=str), return_inverse=True)
        codes, names = codes.reshape(-1).astype(np.int64), [str(n) for n in names]
    if empty_ok:
        gap = np.isnan(values[:, [wanted.index(name) for name in sorted(empty_ok)]]).any(axis=1)
        missing = gap if gap.any() else None
    return Table(dict(zip(wanted, values.T)), values.shape[0], lines, codes, names, missing)


def format_csv(header: Sequence[str], columns: Sequence[np.ndarray],
               rows_per_chunk: int = csvio.BLOCK_ROWS, labels: Optional[Sequence[str]] = None,
               codes: Optional[np.ndarray] = None) -> Iterator[bytes]:
    """
    Yield the CSV text in chunks: the header, then rows of shortest round-trip numbers.

    With ``labels`` and ``codes``, every row starts with the text ``labels[codes[row]]``
    (the id column, first in ``header``).
    """
    yield (','.join(header) + '\n').encode('utf-8')
    N = len(columns[0]) if columns else 0
    prefix = None if labels is None else (csvio.format_labels(labels), codes)
    for start in range(0, N, rows_per_chunk):
        yield csvio.format_rows(columns, start, min(start + rows_per_chunk, N), prefix)


def check_time_range(path: str, t: np.ndarray, lines: np.ndarray, max_abs_s: float) -> None:
    """Raise InputError naming the line of the first time beyond ±``max_abs_s``."""
    big = np.flatnonzero(np.abs(t) > max_abs_s)
    if big.size:
        k = int(big[0])
        raise InputError(TIME_CELL.format(path=path, line=lines[k])
                         + f': {float(t[k])!r} s is out of range (|t| <= {max_abs_s:g} s)')


def check_times(path: str, t: np.ndarray, lines: np.ndarray, t0_s: float,
                max_abs_s: float) -> None:
    """Raise InputError naming the line of the first time out of range or order."""
    check_time_range(path, t, lines, max_abs_s)
    t_ns = np.rint(t * NS_PER_S).astype(np.int64)
    t0_ns = int(round(t0_s * NS_PER_S))
    if t.size and t_ns[0] < t0_ns:
        raise InputError(TIME_CELL.format(path=path, line=lines[0])
                         + f': {float(t[0])!r} is before the initial time t0 = {t0_s!r} s '
                         '(set it with --t0)')
    bad = np.flatnonzero(np.diff(t_ns) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise InputError(TIME_CELL.format(path=path, line=lines[k])
                         + f": {float(t[k])!r} is not after the previous row's t = "
                         f'{float(t[k - 1])!r} (t must increase)')


def time_order_error(path: str, t: np.ndarray, lines: np.ndarray, t0_s: float, row: int,
                     previous: Optional[int], label: str) -> InputError:
    """
    Return the InputError for an id's row out of time order (``previous``: its last row).

    ``previous`` None: the id's first row is before t0. The rows are those
    :func:`kf_train.batch.bank_time_steps` names in its TimeOrderError.
    """
    where = TIME_CELL.format(path=path, line=lines[row])
    if previous is None:
        return InputError(where + f': {float(t[row])!r} is before the initial time t0 = '
                          f"{t0_s!r} s of id '{label}' (set it with --t0)")
    return InputError(where + f": {float(t[row])!r} is not after the previous row's t = "
                      f"{float(t[previous])!r} of id '{label}' (line {lines[previous]}); t "
                      'must increase per id')
