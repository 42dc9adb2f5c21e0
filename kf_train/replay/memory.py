"""
The in-memory replay: a whole CSV table read, checked, filtered in blocks and written.

:func:`replay` (``kf-train replay --engine memory``) holds the whole table; it filters
it in the blocks of the streamed replay (:func:`kf_train.batch.stream.filter_table`),
so both write the same bytes. :func:`run_preset` runs a preset over arrays (the
vectorised path for linear presets), :func:`output_columns` names its results. The
table format is :mod:`kf_train.io.tables`'; the command line is
:mod:`kf_train.cli.replay`.
"""

import sys
import time
from typing import List, NamedTuple, Optional, Sequence, Tuple

from kf_train.batch import (
    bank_time_steps, DEFAULT_BLOCK_ROWS, filter_table, group_rows, Groups, MAX_ABS_TIME_S,
    output_header, resolve_horizon, RowError, rts_smooth, run_bank, run_filter_series,
    run_linear_series, run_series, SeriesResult, SmootherResult, TimeOrderError)
from kf_train.filters import Filter, PARTICLE_KINDS
from kf_train.io import (
    check_time_range, check_times, format_csv, ID_COLUMN, InputError, read_table,
    required_columns, resolve_columns, time_order_error, write_atomic)
from kf_train.presets import (
    is_rail_preset_file, load_preset, load_preset_file, load_rail_preset, Preset,
    RAIL_PRESET_NAME)
import numpy as np


def check_bank_times(path: str, t: np.ndarray, lines: np.ndarray, groups: Groups,
                     labels: Sequence[str], t0_s: float) -> None:
    """Raise InputError naming the line of the first time out of range or order per id."""
    check_time_range(path, t, lines, MAX_ABS_TIME_S)
    try:
        bank_time_steps(t, groups, t0_s)
    except TimeOrderError as error:
        raise time_order_error(path, t, lines, t0_s, error.row, error.previous,
                               labels[groups.codes[error.row]]) from None


def run_preset(preset: Preset, t, z, u=None, *, t0_s: float = 0.0, horizon_s=None,
               fast: bool = True, filt: Optional[Filter] = None, ids=None,
               groups: Optional[Groups] = None) -> SeriesResult:
    """
    Run a preset over arrays: the vectorised path for linear presets, else the loop.

    With ``ids`` (one label per row; or their ``groups``) every id is an independent
    object: see :func:`kf_train.batch.bank.run_bank`.
    """
    if ids is not None or groups is not None:
        return run_bank(preset, t, z, u, ids, t0_s=t0_s, horizon_s=horizon_s, fast=fast,
                        filt=filt, groups=groups)
    if filt is not None:  # --filter: any filter of the family, row by row
        return run_filter_series(filt, t, z, u, t0_s=t0_s, horizon_s=horizon_s)
    if fast and preset.linear:
        return run_linear_series(preset, t, z, u, t0_s=t0_s, horizon_s=horizon_s)
    return run_series(preset, t, z, u, t0_s=t0_s, horizon_s=horizon_s)


def smooth_bank(result: SeriesResult, groups: Groups) -> SmootherResult:
    """Return the RTS smoothing of every object of a bank on its own rows."""
    N, n = result.x.shape
    x, P = result.x.copy(), result.P.copy()
    gains = np.zeros((N, n, n))    # row k: the gain into k from the object's next row
    for k in np.flatnonzero(groups.counts > 1):        # one row: already smoothed
        rows = groups.rows(k)
        smoothed = rts_smooth(result.x[rows], result.P[rows], result.x_prior[rows],
                              result.P_prior[rows], result.F[rows])
        x[rows], P[rows] = smoothed.x, smoothed.P
        gains[rows[:-1]] = smoothed.gain
    return SmootherResult(x, P, gains)


def output_columns(preset: Preset, result: SeriesResult,
                   smoothed: Optional[SmootherResult] = None
                   ) -> Tuple[List[str], List[np.ndarray]]:
    """Return the output header and columns for a filtered (and smoothed) series."""
    names = preset.state_names
    header, columns = ['t'], [result.t_s]

    def add(prefix: str, x: np.ndarray, P: np.ndarray) -> None:
        for i, name in enumerate(names):
            header.append(prefix + name)
            columns.append(x[:, i])
        for i, name in enumerate(names):
            header.append('var_' + prefix + name)
            columns.append(P[:, i, i])

    add('', result.x, result.P)
    if result.predicted_x is not None:
        add('predicted_', result.predicted_x, result.predicted_P)
    if smoothed is not None:
        add('smoothed_', smoothed.x, smoothed.P)
    if result.nis is not None:          # last, as kf_train.batch.output_header has it
        header.append('nis')
        columns.append(result.nis)
    return header, columns


class ReplaySummary(NamedTuple):
    """What a replay did."""

    rows: int
    columns: List[str]
    seconds: float


def replay(preset: Preset, input_path: str, output_path: str, *, horizon_s=None,
           smooth: bool = False, t0_s: float = 0.0, fast: bool = True,
           filt: Optional[Filter] = None, block_rows: int = DEFAULT_BLOCK_ROWS,
           spill_dir: Optional[str] = None) -> ReplaySummary:
    """
    Replay ``input_path`` through ``preset`` into ``output_path``; raise InputError.

    The table is read whole, then filtered in blocks of ``block_rows`` exactly as the
    streamed replay filters it (:func:`kf_train.batch.stream.filter_table`), so both
    write the same bytes for any input size. ``fast`` False filters the whole table as
    one block (a complete table only), whatever ``block_rows`` says.
    """
    if smooth and filt is not None and filt.kind in PARTICLE_KINDS:
        raise ValueError('--smooth needs a Gaussian filter (kf, ekf or ukf): the RTS '
                         'smoother does not apply to particles')
    start = time.perf_counter()
    text = None
    if input_path == '-':
        text = sys.stdin.buffer.read() if hasattr(sys.stdin, 'buffer') else sys.stdin.read()
    needed = required_columns(preset)
    table = read_table(input_path, needed, text, ids=True,
                       gaps=needed[1:1 + preset.dim_z])
    t = table.columns['t']
    if table.ids is None:
        check_times(input_path, t, table.lines, t0_s, MAX_ABS_TIME_S)
    else:
        check_bank_times(input_path, t, table.lines, group_rows(table.ids), table.id_labels,
                         t0_s)
    wanted = resolve_columns(input_path, list(table.columns), needed)
    z = np.column_stack([table.columns[name] for name in wanted[1:1 + preset.dim_z]]
                        ) if table.rows else np.empty((0, preset.dim_z))
    u = None
    if preset.dim_u:
        u = np.column_stack([table.columns[name] for name in wanted[1 + preset.dim_z:]]) \
            if table.rows else np.empty((0, preset.dim_u))
    if not fast and table.missing is None:
        block_rows = max(table.rows, 1)
    try:
        columns = filter_table(preset, t, z, u, table.ids, horizon_s=horizon_s, t0_s=t0_s,
                               filt=filt, smooth=smooth, block_rows=block_rows,
                               missing=table.missing, spill_dir=spill_dir)
    except RowError as error:
        raise InputError(f'{input_path} line {table.lines[error.row]}: {error.reason}'
                         ) from None
    except ValueError as error:
        raise InputError(f'{input_path}: {error}') from None
    header = output_header(preset, resolve_horizon(preset, horizon_s), smooth,
                           table.missing is not None)
    if table.ids is None:
        write_atomic(output_path, format_csv(header, columns))
    else:
        header = [ID_COLUMN] + header
        write_atomic(output_path, format_csv(header, columns, labels=table.id_labels,
                                             codes=table.ids))
    return ReplaySummary(table.rows, header, time.perf_counter() - start)


def load_any_preset(name: Optional[str], path: Optional[str]):
    """Return a shipped preset by name or a preset file; rail ones as a RailPreset."""
    if name == RAIL_PRESET_NAME:
        return load_rail_preset()
    if name:
        return load_preset(name)
    return load_rail_preset(path) if is_rail_preset_file(path) else load_preset_file(path)
