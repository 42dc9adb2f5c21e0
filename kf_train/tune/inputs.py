"""
What ``kf-train tune`` reads: a replay CSV, Parquet, or a rosbag2 bag, as tuning segments.

The inputs are those of ``kf-train replay``, read by the replay's own readers:

* a CSV (or '-', standard input): the replay's table reader
  (:func:`kf_train.io.read_table`: ``t``, the measurement columns, ``u``
  where the preset has a control, optionally ``id``), plus optional truth columns
  ``true_<state>``; a row with an empty measurement cell (a dropped sample) is left
  out, as the node never receives it;
* a ``.parquet`` file or a directory of Parquet files (the ``[fast]`` extra): the same
  columns, read by :mod:`kf_train.io.columnar`; errors name the row;
* a bag (a rosbag2 directory, MCAP or sqlite3, or a single ``.mcap`` / ``.db3`` file):
  the measurement (and control) topic chosen as ``kf-train replay BAG`` chooses it
  (``--topic``, ``--control-topic``; :class:`kf_train.io.bagio.BagInput`), and the
  truth from ``--truth-topic`` (nav_msgs/msg/Odometry; default ``ground_truth``
  when the bag has it, as ``kf-train simulate`` writes it).

A bag's measurement becomes a row at its header stamp (``t`` = stamp [s], as
``kf-train simulate`` writes the CSV of the same run), with the variance its message
carries (:attr:`TuneInput.measurement_variances`). The node fuses a measurement that
comes late by less than its ``history_s`` (1 s) in stamp order, so rows are sorted by
stamp; a stamp more than that behind the newest starts a new segment (the node resets
on a clock jump), and a repeated stamp keeps the first message. A row's control is the
node's (:meth:`kf_train.estimator.controls.Controls.for_interval_ending`): the one
stamped at the row, else the first later, else the latest earlier, else 0; controls
stamped between two measurements, which the node splits the prediction at, are not
(one control per row, as in the CSV). Truth is taken at the row's stamp, interpolated
linearly between truth messages (NaN outside them).

Every problem is a ``ValueError`` (``InputError`` for tables) with one line naming the
input.
"""

import bisect
import contextlib
import os
from typing import Callable, List, NamedTuple, Optional

from kf_train.batch import group_rows, MAX_ABS_TIME_S, Segment
from kf_train.filters import NS_PER_S
from kf_train.io import (
    check_times, ID_COLUMN, InputError, is_bag, read_table, required_columns, resolve_columns)
from kf_train.presets import Preset
from kf_train.replay import check_bank_times
import numpy as np

TRUTH_PREFIX = 'true_'
DEFAULT_TRUTH_TOPIC = 'ground_truth'
OUT_OF_ORDER_S = 1.0
"""A stamp this far behind the newest starts a new segment (the node's default history_s)."""


class TuneInput(NamedTuple):
    """The data to tune on."""

    segments: List[Segment]
    measurement_variances: Optional[np.ndarray] = None
    """(rows, m): each row's measurement variances as the data carry them (bags), or None."""
    summary: str = ''
    """What was read, for the report (e.g. the bag's topics)."""


class TopicOptions(NamedTuple):
    """The bag topics to read (None: resolved as ``kf-train replay BAG`` resolves them)."""

    topic: Optional[str] = None
    control_topic: Optional[str] = None
    truth_topic: Optional[str] = None


InputReader = Callable[[str, Preset, TopicOptions], TuneInput]


# ---------------------------------------------------------------------------
# Tables: CSV and Parquet
# ---------------------------------------------------------------------------

def _read_bytes(path: str) -> bytes:
    """Return the input's bytes ('-': standard input)."""
    if path == '-':
        import sys
        return sys.stdin.buffer.read() if hasattr(sys.stdin, 'buffer') else \
            sys.stdin.read().encode('utf-8')
    try:
        with open(path, 'rb') as stream:
            return stream.read()
    except OSError as error:
        raise InputError(f'{path}: cannot read: {error.strerror}') from None


def _header(data: bytes) -> List[str]:
    """Return the header's column names (the table reader checks it properly)."""
    line = data.split(b'\n', 1)[0].lstrip(b'\xef\xbb\xbf').decode('utf-8', 'replace')
    return [name.strip().strip('"').strip() for name in line.split(',')]


def table_segments(path: str, preset: Preset, columns: dict, lines: np.ndarray,
                   ids: Optional[np.ndarray] = None, id_labels: Optional[List[str]] = None,
                   missing: Optional[np.ndarray] = None) -> List[Segment]:
    """
    Return the segments (one per id) of a table's columns; InputError names the line.

    ``missing`` flags rows without a measurement (a dropped sample): they are left out,
    as the node, which never receives them, predicts across the gap.
    """
    t = columns['t']
    if t.shape[0] == 0:
        raise InputError(f'{path}: no rows: nothing to estimate from')
    first = float(np.min(t))
    if ids is None:
        check_times(path, t, lines, first, MAX_ABS_TIME_S)
    else:
        check_bank_times(path, t, lines, group_rows(ids), id_labels, first)
    if missing is not None and missing.any():
        keep = ~missing
        if not keep.any():
            raise InputError(f'{path}: no row has a measurement: nothing to estimate from')
        columns = {name: values[keep] for name, values in columns.items()}
        t, ids = columns['t'], None if ids is None else ids[keep]
    groups = group_rows(np.zeros(t.shape[0], dtype=np.int64) if ids is None else ids)
    z = np.column_stack([columns[next(n for n in names if n in columns)]
                         for names in preset.measurement_columns()])
    u = (np.column_stack([columns[n] for n in preset.control_columns()])
         if preset.dim_u else None)
    truth = None
    if any(TRUTH_PREFIX + state in columns for state in preset.state_names):
        truth = np.full((t.shape[0], preset.dim_x), np.nan)
        for i, state in enumerate(preset.state_names):
            if TRUTH_PREFIX + state in columns:
                truth[:, i] = columns[TRUTH_PREFIX + state]
    segments = []
    for k in range(groups.counts.shape[0]):
        rows = groups.rows(k)
        segments.append(Segment(t[rows], z[rows], None if u is None else u[rows],
                                None if truth is None else truth[rows]))
    return segments


def read_csv(path: str, preset: Preset, topics: TopicOptions = TopicOptions()) -> TuneInput:
    """Return the segments of a replay CSV (one per id), with truth where given."""
    data = _read_bytes(path)
    header = _header(data)
    truth_columns = [TRUTH_PREFIX + s for s in preset.state_names if TRUTH_PREFIX + s in header]
    needed = required_columns(preset)
    table = read_table(path, needed + [(c,) for c in truth_columns], data, ids=True,
                       gaps=needed[1:1 + preset.dim_z])   # a dropped sample: no measurement
    if table.rows == 0:
        raise InputError(f'{path}: no rows: nothing to estimate from')
    segments = table_segments(path, preset, table.columns, table.lines, table.ids,
                              table.id_labels, table.missing)
    gaps = 0 if table.missing is None else int(np.count_nonzero(table.missing))
    return TuneInput(segments, summary=f'{gaps} rows without a measurement (dropped samples) '
                     'left out' if gaps else '')


def _parquet_names(path: str, header: List[str], preset: Preset) -> List[str]:
    """Return the columns to read: t, measurements, controls, truth (the replay's names)."""
    try:
        wanted = resolve_columns(path, header, required_columns(preset))
    except InputError as error:                 # a schema has no line 1
        raise InputError(str(error).replace(f'{path} line 1:', f'{path}:', 1)) from None
    return wanted + [TRUTH_PREFIX + s for s in preset.state_names
                     if TRUTH_PREFIX + s in header]


def read_parquet(path: str, preset: Preset, topics: TopicOptions = TopicOptions()
                 ) -> TuneInput:
    """Return the segments of a Parquet file or dataset directory (errors name the row)."""
    from kf_train.io import columnar
    if not columnar.available():
        raise InputError(f'{path}: Parquet needs polars: {columnar.EXTRA_HINT}')
    try:
        header = columnar.parquet_columns(path)
        wanted = _parquet_names(path, header, preset)
        id_column = ID_COLUMN if ID_COLUMN in header else None
        pieces = list(columnar.read_parquet_pieces(path, wanted, id_column, 1 << 16))
    except columnar.ParquetError as error:
        at = '' if error.row is None else f' row {error.row + 1},'
        raise InputError(f'{path}{at} {error}') from None
    columns = {name: np.concatenate([p.columns[name] for p in pieces]) if pieces
               else np.empty(0) for name in wanted}
    ids = labels = None
    if id_column is not None and pieces:
        # Pieces code their ids into their own labels: make them table-wide.
        text = np.concatenate([np.asarray(p.labels, dtype=str)[p.codes] for p in pieces])
        names, ids = np.unique(text, return_inverse=True)
        ids, labels = ids.reshape(-1).astype(np.int64), [str(n) for n in names]
    rows = np.arange(1, columns['t'].shape[0] + 1, dtype=np.int64)
    try:
        segments = table_segments(path, preset, columns, rows, ids, labels)
    except InputError as error:                 # Parquet has rows, not lines
        raise InputError(str(error).replace(' line ', ' row ')) from None
    return TuneInput(segments)


# ---------------------------------------------------------------------------
# Bags
# ---------------------------------------------------------------------------

@contextlib.contextmanager
def _damaged_bag(path: str):
    """Turn what rosbags raises on some damaged files (TypeError) into the one-line error."""
    try:
        yield
    except TypeError as error:   # e.g. an MCAP cut right after its magic
        text = ' '.join(str(error).split())
        raise ValueError(f'{path}: not a readable bag (truncated or damaged?): {text}') \
            from None


def _bag_measurements(path: str, preset: Preset, topics: TopicOptions):
    """Return (stamps ns, z, variances, control stamps, controls, topic) of a bag."""
    from kf_train.io import bagio              # needs rosbags: imported when used
    measurement_type, control_type = bagio.expected_types(preset.measurement_names,
                                                          preset.control_names)
    stamps, z, variances, control_stamps, controls = [], [], [], [], []
    two = preset.dim_z == 2
    with _damaged_bag(path), bagio.BagInput(path, measurement_type, control_type,
                                            topics.topic, topics.control_topic) as bag:
        for message in bag.messages():
            if type(message) is bagio.Measurement:
                stamps.append(message.stamp_ns)
                if two:
                    z.append((message.position_m, message.velocity_mps))
                    variances.append((message.variance_m2, message.velocity_variance_m2s2))
                else:
                    z.append((message.position_m,))
                    variances.append((message.variance_m2,))
            else:
                control_stamps.append(message.stamp_ns)
                controls.append(message.value)
        topic = bag.measurement_topic + (f' and {bag.control_topic}' if bag.control_topic
                                         else '')
    return (np.array(stamps, dtype=np.int64), np.array(z, dtype=float).reshape(-1, preset.dim_z),
            np.array(variances, dtype=float).reshape(-1, preset.dim_z),
            control_stamps, controls, topic)


def _truth(path: str, topics: TopicOptions):
    """Return (stamps ns, [position, velocity]) of the truth topic, or None if absent."""
    from kf_train.io import bagio
    name = topics.truth_topic or DEFAULT_TRUTH_TOPIC
    try:
        with bagio.BagInput(path, bagio.ODOMETRY, None, name) as bag:
            rows = [(m.stamp_ns, m.position_m, m.velocity_mps) for m in bag.messages()]
    except ValueError as error:
        if topics.truth_topic is None and 'is not in the bag' in str(error):
            return None                        # no truth: the default is optional
        raise ValueError(str(error).replace('measurement topic', 'truth topic')) from None
    rows.sort(key=lambda row: row[0])
    stamps = np.array([r[0] for r in rows], dtype=np.int64)
    return stamps, np.array([r[1:] for r in rows], dtype=float).reshape(-1, 2)


def _truth_at(stamps_ns: np.ndarray, truth, base_ns: int, preset: Preset) -> np.ndarray:
    """Return the truth at ``stamps_ns``: exact where stamped so, interpolated inside."""
    out = np.full((stamps_ns.shape[0], preset.dim_x), np.nan)
    truth_ns, values = truth
    if truth_ns.size == 0:
        return out
    x = (stamps_ns - base_ns).astype(float)    # exact: differences of integers
    xp = (truth_ns - base_ns).astype(float)
    inside = (stamps_ns >= truth_ns[0]) & (stamps_ns <= truth_ns[-1])
    for i, state in enumerate(preset.state_names):
        column = {'position': 0, 'velocity': 1}.get(state)
        if column is not None:
            out[inside, i] = np.interp(x[inside], xp, values[:, column])
    # At a truth stamp, the truth itself (interp is exact there too, but say so).
    at = np.searchsorted(truth_ns, stamps_ns)
    hit = (at < truth_ns.size) & (truth_ns[np.minimum(at, truth_ns.size - 1)] == stamps_ns)
    for i, state in enumerate(preset.state_names):
        column = {'position': 0, 'velocity': 1}.get(state)
        if column is not None:
            out[hit, i] = values[at[hit], column]
    return out


def _controls_at(stamps_ns: np.ndarray, control_stamps: list, controls: list) -> np.ndarray:
    """Return each row's control as the node picks it (module doc)."""
    order = sorted(range(len(control_stamps)), key=control_stamps.__getitem__)
    by_stamp = {}
    for k in order:                            # the latest value per stamp, as the node
        by_stamp[control_stamps[k]] = controls[k]
    keys = sorted(by_stamp)
    u = np.zeros((stamps_ns.shape[0], 1))
    for row, stamp in enumerate(stamps_ns.tolist()):
        if stamp in by_stamp:
            u[row, 0] = by_stamp[stamp]
            continue
        i = bisect.bisect_right(keys, stamp)
        if i < len(keys):
            u[row, 0] = by_stamp[keys[i]]
        elif i:
            u[row, 0] = by_stamp[keys[i - 1]]
    return u


def _runs(stamps_ns: np.ndarray) -> List[np.ndarray]:
    """Return the row indices of each segment, each sorted by stamp (module doc)."""
    runs, current, newest = [], [], None
    limit = round(OUT_OF_ORDER_S * NS_PER_S)
    for k, stamp in enumerate(stamps_ns.tolist()):
        if newest is not None and stamp < newest - limit:
            runs.append(current)
            current, newest = [], None
        current.append(k)
        newest = stamp if newest is None else max(newest, stamp)
    runs.append(current)
    segments = []
    for run in runs:
        rows = np.array(run, dtype=np.int64)
        rows = rows[np.argsort(stamps_ns[rows], kind='stable')]
        keep = np.ones(rows.shape[0], dtype=bool)
        keep[1:] = np.diff(stamps_ns[rows]) > 0  # a repeated stamp: the first message
        segments.append(rows[keep])
    return segments


def read_bag(path: str, preset: Preset, topics: TopicOptions = TopicOptions()) -> TuneInput:
    """Return the segments of a bag's measurement topic, with the variances it carries."""
    stamps, z, variances, control_stamps, controls, topic = _bag_measurements(
        path, preset, topics)
    if stamps.size == 0:
        raise ValueError(f'{path}: no messages on {topic}: nothing to estimate from')
    bad = np.flatnonzero(~np.isfinite(z).all(axis=1))
    if bad.size:
        raise ValueError(f'{path}: measurement {int(bad[0]) + 1} on {topic} is not finite '
                         f'({z[bad[0]].tolist()})')
    truth = _truth(path, topics)
    u = (_controls_at(stamps, control_stamps, controls) if preset.dim_u else None)
    base_ns = int(stamps.min())
    segments, kept = [], []
    for rows in _runs(stamps):
        t = stamps[rows] / NS_PER_S               # as kf-train simulate writes t
        segments.append(Segment(
            t, z[rows], None if u is None else u[rows],
            None if truth is None else _truth_at(stamps[rows], truth, base_ns, preset)))
        kept.append(rows)
    rows = np.concatenate(kept)
    dropped = stamps.size - rows.size
    summary = (f'bag {os.path.basename(os.path.normpath(path))}: {stamps.size} measurements '
               f'on {topic}' + (f' ({dropped} with a repeated stamp ignored)' if dropped else '')
               + (f', {len(segments)} segments (stamps jumped back)' if len(segments) > 1
                  else '') + ('' if truth is None else ', truth from the bag'))
    return TuneInput(segments, variances[rows], summary)


# ---------------------------------------------------------------------------
# Choosing the reader
# ---------------------------------------------------------------------------

def is_parquet(path: str) -> bool:
    """Return whether ``path`` is a .parquet file or a directory holding Parquet files."""
    if path == '-':
        return False
    return path.endswith('.parquet') or (os.path.isdir(path) and not is_bag(path))


def reader_for(path: str) -> InputReader:
    """Return the reader of an input path: a bag, Parquet, else CSV (as kf-train replay)."""
    if path != '-' and is_bag(path):
        return read_bag
    if is_parquet(path):
        return read_parquet
    return read_csv
