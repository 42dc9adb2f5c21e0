"""
CSV and Parquet through polars: the replay's fast path (the ``kf_train[fast]`` extra).

Why polars (measurements in ``docs/scale.md``, script ``benchmarks/io_libraries.py``):
on our tables it writes CSV about 3x faster than pyarrow and reads and writes Parquet
faster too; and its number text is Python's ``repr`` (the shortest string that reads
back to the same double) for every double except two layout rules, which
:func:`text_expression` rewrites (inside the write), so a replay writes the same bytes with
or without it.

* Readers yield :class:`Piece` s of ``chunk_rows`` rows: float64 columns, and the id
  column as codes into the piece's sorted labels. A CSV reader that meets anything it
  cannot vouch for (a blank line, an empty or non-finite cell, text that is not a
  number) raises :class:`NotPlain`: the caller then reads the file the careful way,
  which names the line. Parquet has no lines: its errors name the row.
* Writers take blocks of output columns (and the id of every row).

Nothing else in the package imports polars; this module imports it on first use, so
``import kf_train.io.columnar`` works without it (:func:`available` says whether it is
there).
"""

import math
import os
from typing import Callable, Dict, Iterable, Iterator, List, NamedTuple, Optional, Sequence

import numpy as np

# Outside [1e-9, 1e-4) and for finite values, polars writes a double exactly as repr().
_REPR_LOW, _REPR_HIGH = 1e-9, 1e-4
# Within that band polars writes decimals (0.0000123) from here on, exponents below.
_REPR_DECIMAL = 1e-5
# The doubles of that decimal part whose repr has a single digit: 1e-05 .. 9e-05.
_SINGLE_DIGIT_E05 = np.array([float(f'{d}e-05') for d in range(1, 10)])
EXTRA_HINT = "install the fast extra: pip install 'kf_train[fast]' (polars)"
# Parquet written with LZ4: estimates are noisy doubles that no codec shrinks much
# (zstd files are ~20 % smaller), and LZ4 writes them in a third of zstd's CPU time.
COMPRESSION = 'lz4'


class NotPlain(Exception):
    """The fast reader cannot vouch for this input: read it the careful way."""


class Piece(NamedTuple):
    """Rows read: the wanted float64 columns, and each row's id as a code into labels."""

    columns: Dict[str, np.ndarray]
    codes: Optional[np.ndarray]
    labels: Optional[List[str]]
    missing: Optional[np.ndarray] = None
    """Rows with an empty (null) cell in a column that may have gaps (NaN there), or None."""


def available() -> bool:
    """Return whether polars can be imported."""
    try:
        _pl()
    except ImportError:
        return False
    return True


def _pl():
    """Return the polars module (ImportError when the extra is not installed)."""
    import polars
    return polars


def _codes(ids) -> tuple:
    """Return (codes, sorted labels) of a polars string Series."""
    pl = _pl()
    labels = ids.unique().sort()
    codes = ids.cast(pl.Enum(labels)).to_physical().to_numpy().astype(np.int64)
    return codes, labels.to_list()


def _piece(frame, wanted: Sequence[str], id_column: Optional[str],
           bad: Callable[[str, int], Exception], gaps: Sequence[str] = ()) -> Piece:
    """
    Return a batch as a Piece; ``bad(column, row)`` builds the error for a bad cell.

    An empty (null) cell of a column in ``gaps`` is NaN and flags its row missing; a NaN
    or infinite value is bad anywhere.
    """
    pl = _pl()
    columns = {}
    missing = None
    for name in wanted:
        series = frame.get_column(name)
        nulls = series.is_null().to_numpy() if series.null_count() else None
        if nulls is not None and name not in gaps:
            raise bad(name, int(np.argmax(nulls)))
        values = series.cast(pl.Float64).to_numpy()
        finite = np.isfinite(values)
        if nulls is not None:
            missing = nulls if missing is None else missing | nulls
            finite |= nulls
        if not finite.all():
            raise bad(name, int(np.argmin(finite)))
        columns[name] = values
    if id_column is None:
        return Piece(columns, None, None, missing)
    ids = frame.get_column(id_column).cast(pl.String).str.strip_chars()
    empty = ids.is_null() | (ids.str.len_bytes() == 0)
    if empty.any():
        raise bad(id_column, int(empty.arg_max()))
    codes, labels = _codes(ids)
    return Piece(columns, codes, labels, missing)


def read_csv_pieces(blocks: Iterable[bytes], header: Sequence[str], wanted: Sequence[str],
                    id_column: Optional[str], gaps: Sequence[str] = ()) -> Iterator[Piece]:
    """
    Yield the rows of CSV text given in blocks of whole lines (no header); raise NotPlain.

    ``header`` names the columns (the caller read line 1). Each block is parsed on its
    own, so memory holds one block (polars' own streaming reader reads ahead without
    bound on a slow consumer). Empty cells of the columns in ``gaps`` flag missing rows.
    """
    pl = _pl()
    keep = [i for i, name in enumerate(header) if name in set(wanted) | {id_column}]
    schema = {name: (pl.Float64 if name in wanted else pl.String) for name in header}
    try:
        for block in blocks:
            frame = pl.read_csv(block, has_header=False, schema=schema, columns=keep)
            yield _piece(frame, wanted, id_column, lambda column, row: NotPlain(column), gaps)
    except (pl.exceptions.PolarsError, OSError, ValueError) as error:
        raise NotPlain(str(error)) from None


class ParquetError(ValueError):
    """Bad Parquet input; ``row`` is the 0-based row of the dataset, ``column`` its column."""

    def __init__(self, message: str, row: Optional[int] = None, column: Optional[str] = None):
        """Store the message, the row and the column."""
        super().__init__(message)
        self.row, self.column = row, column


def parquet_source(path: str) -> str:
    """Return what polars scans for ``path``: the file, or every Parquet file below a dir."""
    if os.path.isdir(path):
        return os.path.join(path, '**', '*.parquet')
    return path


def parquet_columns(path: str) -> List[str]:
    """Return the column names of a Parquet file or dataset directory."""
    pl = _pl()
    try:
        return list(pl.scan_parquet(parquet_source(path)).collect_schema().names())
    except (pl.exceptions.PolarsError, OSError) as error:
        raise ParquetError(f'cannot read Parquet: {" ".join(str(error).split())[:300]}'
                           ) from None


def parquet_rows(path: str) -> Optional[int]:
    """Return the number of rows of a Parquet file or dataset (from its metadata), or None."""
    pl = _pl()
    try:
        return int(pl.scan_parquet(parquet_source(path)).select(pl.len()).collect().item())
    except (pl.exceptions.PolarsError, OSError, ValueError):
        return None      # the reader reports what is wrong


def read_parquet_pieces(path: str, wanted: Sequence[str], id_column: Optional[str],
                        chunk_rows: int, gaps: Sequence[str] = ()) -> Iterator[Piece]:
    """Yield the Parquet file's (or dataset's) rows in pieces (nulls in ``gaps``: missing)."""
    pl = _pl()
    keep = list(wanted) + ([id_column] if id_column else [])
    done = 0

    def bad(column: str, row: int) -> ParquetError:
        what = 'non-finite value' if column in gaps else 'empty or non-finite value'
        return ParquetError(f"column '{column}': {what}", done + row, column)

    try:
        # Slice by slice: polars' collect_batches reads ahead without bound when the
        # consumer is slower than the reader (the whole dataset, in the end).
        scan = pl.scan_parquet(parquet_source(path)).select(keep)
        while True:
            frame = scan.slice(done, chunk_rows).collect()
            if not frame.height:
                break
            yield _piece(frame, wanted, id_column, bad, gaps)
            done += frame.height
    except (pl.exceptions.PolarsError, OSError) as error:
        raise ParquetError(f'cannot read Parquet: {" ".join(str(error).split())[:300]}'
                           ) from None


# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------

def repr_strings(values: np.ndarray, name: str = ''):
    """
    Return the doubles as a polars Series: Float64 if polars writes them as repr(), else text.

    The Series form of :func:`text_expression` (tests, and anyone who needs the text).
    """
    pl = _pl()
    values = np.asarray(values, dtype=np.float64)
    expression = text_expression(values, 'v')
    if expression is None:
        return pl.Series(name, values)
    return pl.DataFrame({'v': values}).select(expression).to_series().alias(name)


def text_expression(values: np.ndarray, name: str):
    """
    Return None if polars writes column ``name`` (``values``) as repr(), else its repr text.

    The text is a polars expression on ``pl.col(name)``, evaluated by polars in its own
    threads without the GIL while the block is written. polars' shortest round-trip
    digits are repr's, but its layout differs in one band, 1e-9 <= |v| < 1e-4:

    * below 1e-5 polars writes the exponent form with a one-digit exponent, 1.5e-7,
      where repr pads it, 1.5e-07: polars' text with 'e-' made 'e-0' (every value of
      this part has a one-digit negative exponent, and no other 'e-');
    * from 1e-5 it writes 0.0000123 where repr writes 1.23e-05: the digits after
      '0.0000' are repr's mantissa (:func:`_scientific_e05`).

    Non-finite values, rare, are written as repr writes them. Which case applies is
    decided from the column's minimum and maximum (two passes without a temporary), so
    a column outside the band, or wholly inside one part of it (the train preset's
    variances on most rows of a long log), costs no per-row mask.
    """
    pl = _pl()
    if not values.size:
        return None
    low, high = float(values.min()), float(values.max())
    if not (math.isfinite(low) and math.isfinite(high)):
        return _mixed_text(name, values, True)
    if low >= 0.0:
        small, large = low, high                  # the range of |v|
    elif high <= 0.0:
        small, large = -high, -low
    else:                                         # both signs: |v| may be anything
        size = np.abs(values)
        odd = (size >= _REPR_LOW) & (size < _REPR_HIGH)
        if not odd.any():
            return None
        small, large = float(size.min()), float(size.max())
    if large < _REPR_LOW or small >= _REPR_HIGH:
        return None
    column = pl.col(name)
    if small >= _REPR_LOW and large < _REPR_DECIMAL:
        return _exponent_padded(column).alias(name)
    if small >= _REPR_DECIMAL and large < _REPR_HIGH:
        return _scientific_e05(column, values).alias(name)
    return _mixed_text(name, values, False)


def _exponent_padded(column):
    """Return repr's text of doubles with 1e-9 <= |v| < 1e-5: polars' with 'e-' made 'e-0'."""
    pl = _pl()
    return column.cast(pl.String).str.replace_all('e-', 'e-0', literal=True)


def _mixed_text(name: str, values: np.ndarray, non_finite: bool):
    """Return repr's text of a column that crosses the band (or has non-finite values)."""
    pl = _pl()
    column = pl.col(name)
    size = column.abs()
    text = pl.when(size.is_between(_REPR_LOW, _REPR_DECIMAL, closed='left')).then(
        _exponent_padded(column)).when(size.is_between(
            _REPR_DECIMAL, _REPR_HIGH, closed='left')).then(_scientific_e05(column, values))
    if non_finite:
        text = text.when(column.is_nan()).then(pl.lit('nan')).when(
            column == float('inf')).then(pl.lit('inf')).when(
                column == float('-inf')).then(pl.lit('-inf'))
    return text.otherwise(column.cast(pl.String)).alias(name)


def _scientific_e05(column, values: np.ndarray):
    """
    Return repr's text of doubles with 1e-5 <= |v| < 1e-4 (d.ddde-05), from polars' digits.

    polars writes |v| there as 0.0000ddd (shortest round-trip digits, repr's): the
    digits after the prefix '0.0000' are repr's mantissa, d.dd, exponent -05 (a single
    digit: d alone, no point). String slicing, ≈3x faster than re-writing the values in
    polars' scientific notation and splitting the text. ``values`` (the column's, or a
    superset) say whether the rare cases need their branch: a sign, a single digit.
    """
    pl = _pl()
    negative = bool((values < 0.0).any())
    text = (column.abs() if negative else column).cast(pl.String)
    point = pl.lit('.')
    if np.isin(np.abs(values), _SINGLE_DIGIT_E05).any():     # 1e-05, 2e-05, ...
        point = pl.when(text.str.len_bytes() == 7).then(pl.lit('')).otherwise(point)
    mantissa = pl.concat_str([text.str.slice(6, 1), point, text.str.slice(7), pl.lit('e-05')])
    if not negative:
        return mantissa
    return pl.when(column < 0.0).then(pl.concat_str([pl.lit('-'), mantissa])).otherwise(
        mantissa)


def _frame(header: Sequence[str], columns: Sequence[np.ndarray], ids):
    """Return a block as a polars DataFrame of float64 columns (the id first when given)."""
    pl = _pl()
    data = [] if ids is None else [ids.alias(header[0])]
    names = header if ids is None else header[1:]
    data += [pl.Series(name, column) for name, column in zip(names, columns)]
    return pl.DataFrame(data)


def id_series(labels: Sequence[str], codes: np.ndarray):
    """Return the id text of every row: ``labels[codes]``, as a polars Series."""
    pl = _pl()
    return pl.Series('id', list(labels), dtype=pl.String).gather(codes)


class CsvWriter:
    """Write blocks of output columns as CSV text, numbers exactly as repr() writes them."""

    def __init__(self, stream, header: Sequence[str]):
        """Write the header to the binary ``stream``."""
        self.stream, self.header = stream, list(header)
        stream.write((','.join(self.header) + '\n').encode('utf-8'))

    def write(self, columns: Sequence[np.ndarray], ids=None) -> None:
        """Write one block (``ids``: a Series from :func:`id_series`, or None)."""
        if not len(columns[0]):
            return
        names = self.header if ids is None else self.header[1:]
        texts = [text_expression(np.asarray(column, dtype=np.float64), name)
                 for name, column in zip(names, columns)]
        frame = _frame(self.header, columns, ids).lazy()
        texts = [text for text in texts if text is not None]
        if texts:
            frame = frame.with_columns(texts)
        frame.sink_csv(self.stream, include_header=False)


def write_parquet_file(path: str, header: Sequence[str], has_id: bool,
                       blocks: Iterable[tuple]) -> None:
    """
    Write blocks (columns, ids) into one Parquet file, as they come (bounded memory).

    polars pulls the blocks through an IO source and streams them into the file; an
    exception raised while producing a block propagates unchanged.
    """
    pl = _pl()
    from polars.io.plugins import register_io_source
    schema = {name: pl.Float64 for name in header}
    if has_id:
        schema[header[0]] = pl.String

    def source(with_columns, predicate, n_rows, batch_size) -> Iterator:
        for columns, ids in blocks:
            yield _frame(header, columns, ids)

    register_io_source(source, schema=schema).sink_parquet(path, compression=COMPRESSION)


def write_parquet_part(path: str, header: Sequence[str], columns: Sequence[np.ndarray],
                       ids=None) -> None:
    """Write one block as a Parquet file (a part of a dataset directory)."""
    _frame(header, columns, ids).write_parquet(path, compression=COMPRESSION)
