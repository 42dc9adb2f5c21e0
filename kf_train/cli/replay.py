"""
``kf-train replay``: a preset's filter over a CSV or Parquet table (or a bag), offline.

A rosbag2 INPUT goes to :mod:`kf_train.cli.bag_replay` (the estimator node's session).

The command streams (:mod:`kf_train.cli.replay_stream`: any size in bounded memory,
CSV or Parquet) unless ``--engine memory`` asks for :func:`replay` below, which holds
the whole table; ``--engine dask`` runs a fleet on Dask
(:mod:`kf_train.cli.fleet_dask`). The table reading and writing both share is
:mod:`kf_train.io.tables`.

Input CSV: a header row, then one row per measurement. Columns (any order; other
columns are ignored):

* ``t`` [s]: the measurement time. The initial estimate holds at t0 = 0 (``--t0``);
  the first row may be at t0, later rows must increase (times are taken to whole
  nanoseconds, as ROS stamps are).
* the preset's measurements, ``z_<name>``: ``z_position``, ``z_velocity``,
  ``z_bearing`` [rad], ``z_range`` [m].
* ``u`` when the preset has a control input: the control applied over the interval
  that ends at that row.
* optionally ``id``: rows with different ids are independent objects (a fleet of
  trains in one file). Every id has its own series from the initial estimate at t0;
  its times must increase, rows of different ids may interleave. Ids are text,
  compared after stripping surrounding spaces.

Each row: predict from its id's previous time to ``t``, then update. Output CSV: the
``id`` (when given), ``t``, one column per state by name, ``var_<state>``, then where a
horizon applies (the preset's, or ``--horizon S``) ``predicted_<state>`` and
``var_predicted_<state>`` at t + S (the row's control held over the horizon), and with
``--smooth`` the RTS-smoothed ``smoothed_<state>`` and ``var_smoothed_<state>`` (per
id), one output row per input row, in the input's order. Numbers are written exactly
as Python's shortest round-trip ``repr`` writes them (:mod:`kf_train.io.csvio`
produces the same text in bulk): reading them back gives the computed doubles exactly.

With an ``id`` column, linear presets run as a vectorised bank
(:func:`kf_train.batch.series.run_bank`: ids with few rows in lock-step, ids with many
along their own time axis); the results equal filtering each id alone. The EKF preset
and ``--filter`` run id by id.

``--preset rail`` (or a ``--config`` file with ``model: rail_regimes``) runs the rail
IMM (docs/rail.md) row by row, started by each id's first row as the streaming
estimator's default is (:mod:`kf_train.batch.rail_series`); ``--filter`` kf or ekf
only, no ``--smooth``.

``--filter kf|ekf|ukf|pf|bootstrap-pf`` runs that filter of the family
(:mod:`kf_train.filters.family`) row by row instead, with the same columns (variances
from the filter's covariance; for the particle filters the particles'); ``--alpha``,
``--beta``, ``--kappa`` tune the UKF, ``--particles``, ``--seed``,
``--resample-threshold`` the particle filters, ``--roughening`` the bootstrap one.

An empty measurement cell means no measurement in that row: the row is predicted, not
updated, and the output ends with a column ``updated`` (1.0 or 0.0) when the input has
such rows (a complete input's output is unchanged); 'nan' is refused, not missing.

Bad input (a missing column, a non-numeric or non-finite cell, an empty t, u or id,
a row with the wrong number of fields, a non-increasing ``t`` (per id)) is reported
with the file, line and column, the exit code is 1, and no output file is written:
output goes to a temporary file in the same directory that replaces OUTPUT only when
complete.
"""


import argparse
import glob
import os
import sys
import time
from typing import List, NamedTuple, Optional, Sequence, Tuple

from kf_train.batch import (
    bank_time_steps, DEFAULT_BLOCK_ROWS, filter_table, group_rows, Groups, MAX_ABS_TIME_S,
    output_header, RailSeriesFilter, resolve_horizon, RowError, rts_smooth, run_bank,
    run_filter_series, run_linear_series, run_series, SeriesResult, SmootherResult,
    TimeOrderError)
from kf_train.cli.filter_options import add_filter_options, filter_options
from kf_train.cli.replay_engines import add_engine_options, check_engine_options, run_engine
from kf_train.estimator import RAIL_FILTER_KINDS
from kf_train.filters import Filter, FILTER_KINDS, make_filter, NS_PER_S, PARTICLE_KINDS
from kf_train.io import (
    format_csv, ID_COLUMN, InputError, read_table, required_columns, resolve_columns,
    write_atomic)
from kf_train.presets import (
    available_presets, is_rail_preset_file, load_preset, load_preset_file, load_rail_preset,
    Preset, RAIL_PRESET_NAME, RailPreset)
import numpy as np

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2


def check_times(path: str, t: np.ndarray, lines: np.ndarray, t0_s: float) -> None:
    """Raise InputError naming the line of the first time out of range or order."""
    where = "{path} line {line}, column 't'"
    big = np.flatnonzero(np.abs(t) > MAX_ABS_TIME_S)
    if big.size:
        k = int(big[0])
        raise InputError(where.format(path=path, line=lines[k])
                         + f': {float(t[k])!r} s is out of range '
                         f'(|t| <= {MAX_ABS_TIME_S:g} s)')
    t_ns = np.rint(t * NS_PER_S).astype(np.int64)
    t0_ns = int(round(t0_s * NS_PER_S))
    if t.size and t_ns[0] < t0_ns:
        raise InputError(where.format(path=path, line=lines[0])
                         + f': {float(t[0])!r} is before the initial time t0 = {t0_s!r} s '
                         '(set it with --t0)')
    bad = np.flatnonzero(np.diff(t_ns) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise InputError(where.format(path=path, line=lines[k])
                         + f": {float(t[k])!r} is not after the previous row's t = "
                         f'{float(t[k - 1])!r} '
                         '(t must increase)')


def check_bank_times(path: str, t: np.ndarray, lines: np.ndarray, groups: Groups,
                     labels: Sequence[str], t0_s: float) -> None:
    """Raise InputError naming the line of the first time out of range or order per id."""
    where = "{path} line {line}, column 't'"
    big = np.flatnonzero(np.abs(t) > MAX_ABS_TIME_S)
    if big.size:
        k = int(big[0])
        raise InputError(where.format(path=path, line=lines[k])
                         + f': {float(t[k])!r} s is out of range '
                         f'(|t| <= {MAX_ABS_TIME_S:g} s)')
    try:
        bank_time_steps(t, groups, t0_s)
    except TimeOrderError as error:
        k, label = error.row, labels[groups.codes[error.row]]
        if error.previous is None:
            raise InputError(where.format(path=path, line=lines[k])
                             + f': {float(t[k])!r} is before the initial time t0 = '
                             f"{t0_s!r} s of id '{label}' (set it with --t0)") from None
        j = error.previous
        raise InputError(where.format(path=path, line=lines[k])
                         + f": {float(t[k])!r} is not after the previous row's t = "
                         f"{float(t[j])!r} of id '{label}' (line {lines[j]}); t must "
                         'increase per id') from None


# ---------------------------------------------------------------------------
# Running and writing
# ---------------------------------------------------------------------------

def run_preset(preset: Preset, t, z, u=None, *, t0_s: float = 0.0, horizon_s=None,
               fast: bool = True, filt: Optional[Filter] = None, ids=None,
               groups: Optional[Groups] = None) -> SeriesResult:
    """
    Run a preset over arrays: the vectorised path for linear presets, else the loop.

    With ``ids`` (one label per row; or their ``groups``) every id is an independent
    object: see :func:`kf_train.batch.series.run_bank`.
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
        check_times(input_path, t, table.lines, t0_s)
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


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------

def _parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    parser = argparse.ArgumentParser(
        prog='kf-train replay',
        description='Run a filter over recorded measurements, offline. INPUT is a CSV or '
                    'Parquet table (a preset filter, any size, streamed in blocks; '
                    'estimates to CSV or Parquet) or a rosbag2 bag: a directory (MCAP or '
                    "sqlite3), .mcap or .db3 (the estimator node's own session and "
                    'parameters; estimates to CSV, or to an MCAP bag of the node topics).',
        epilog='Table input: a header, then rows with t [s], the measurements z_position, '
               'z_velocity, z_bearing [rad], z_range [m] the preset uses, and u when it '
               'has a control input (the control over the interval ending at the row); '
               'optionally id: each id is an independent object with its own series. '
               'Output: id (if given), t, each state by name, var_<state>; '
               'predicted_<state> and var_predicted_<state> at t + horizon; '
               'smoothed_<state> and var_smoothed_<state> with --smooth. Presets: '
               + ', '.join(available_presets() + [RAIL_PRESET_NAME]) + ' (rail: the '
               'IMM of docs/rail.md, started by the first row). Bad input names the line '
               'and column, exits 1 and writes nothing.')
    parser.add_argument('input', metavar='INPUT', nargs='?',
                        help='measurements: CSV, a .parquet file or a directory of Parquet '
                             "files ('-' reads CSV from standard input), or a rosbag2 bag "
                             '(a directory, .mcap or .db3): see the bag options')
    source = parser.add_mutually_exclusive_group()
    source.add_argument('--preset', metavar='NAME',
                        choices=available_presets() + [RAIL_PRESET_NAME],
                        help='a shipped preset: %(choices)s')
    source.add_argument('--config', metavar='FILE', help='a preset YAML file of your own')
    parser.add_argument('--output', '-o', metavar='OUTPUT',
                        help='where to write the estimates: CSV, a .parquet file or a '
                             "directory (a Parquet dataset); '-' writes CSV to standard "
                             'output')
    parser.add_argument('--horizon', metavar='S', type=float, default=None,
                        help="predict S seconds ahead of every row (default: the preset's "
                             'horizon; 0 turns prediction off)')
    parser.add_argument('--smooth', action='store_true',
                        help='also write the RTS-smoothed estimates')
    parser.add_argument('--t0', metavar='S', type=float, default=0.0,
                        help='time at which the initial estimate holds [s] (default 0)')
    parser.add_argument('--list', action='store_true',
                        help='list the shipped presets and exit')
    add_engine_options(parser)
    parser.add_argument('--filter', choices=FILTER_KINDS, default=None,
                        help='run this filter of the family row by row (default: the '
                             "preset's exact filter, vectorised where linear): %(choices)s")
    add_filter_options(parser)
    bag = parser.add_argument_group(
        "bag replay (INPUT a rosbag2 directory, .mcap or .db3): the estimator node's own "
        'session and parameters; --output X.csv, or a directory or X.mcap for a bag')
    bag.add_argument('--params-file', metavar='FILE', action='append',
                     help='a ROS params file (node estimator); may be repeated')
    bag.add_argument('-p', dest='parameter', metavar='NAME:=VALUE', action='append',
                     help='set one node parameter, as ros2 run ... -p')
    bag.add_argument('--topic', metavar='NAME', default=None,
                     help="the measurement topic (default: 'measurement' resolved in the "
                          'bag, else the only one of the expected type)')
    bag.add_argument('--control-topic', metavar='NAME', default=None,
                     help="the control topic, for presets with one (default: 'control')")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Run ``kf-train replay``; return the exit code."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.list:
        for name in available_presets() + [RAIL_PRESET_NAME]:
            print(f'{name:22s} {load_any_preset(name, None).description}')
        return EXIT_OK
    if args.input is not None and args.input != '-' and (
            is_bag(args.input) or (args.preset is None and args.config is None
                                   and not args.input.lower().endswith('.csv'))):
        return _bag_main(parser, args)
    if args.preset is None and args.config is None:
        parser.error('one of --preset NAME or --config FILE is required')
    if args.input is None or args.output is None:
        parser.error('INPUT and --output OUTPUT are required')
    for option in ('params_file', 'parameter', 'topic', 'control_topic'):
        if getattr(args, option):
            parser.error(f"--{option.replace('_', '-')} applies to a bag input only")
    check_engine_options(parser, args)
    for option, value in (('--horizon', args.horizon), ('--t0', args.t0)):
        if value is not None and not np.isfinite(value):
            parser.error(f'{option} must be a finite number, got {value}')
    if args.horizon is not None and args.horizon < 0.0:
        parser.error(f'--horizon must be >= 0, got {args.horizon}')
    try:
        options = filter_options(args)
    except ValueError as error:
        parser.error(str(error))
    try:
        preset = load_any_preset(args.preset, args.config)
        filt = _make_filter(preset, args, options)
        summary = run_engine(args, preset, filt)
    except ValueError as error:
        print(f'kf-train replay: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.output != '-':
        print(f'kf-train replay: {summary.rows} rows with preset {preset.name} -> '
              f'{args.output} ({summary.seconds:.3f} s)', file=sys.stderr)
    return EXIT_OK


def load_any_preset(name: Optional[str], path: Optional[str]):
    """Return a shipped preset by name or a preset file; rail ones as a RailPreset."""
    if name == RAIL_PRESET_NAME:
        return load_rail_preset()
    if name:
        return load_preset(name)
    return load_rail_preset(path) if is_rail_preset_file(path) else load_preset_file(path)


def _make_filter(preset, args, options) -> Optional[Filter]:
    """Return the row-by-row filter ``--filter`` asks for (the rail IMM for rail), or None."""
    if not isinstance(preset, RailPreset):
        return None if args.filter is None else make_filter(preset, args.filter, options)
    if args.filter not in (None,) + RAIL_FILTER_KINDS:
        raise ValueError(f'--filter {args.filter}: preset {preset.name!r} is an IMM of four '
                         'Kalman filters; it runs with kf (or ekf, the same) only')
    if args.smooth:
        raise ValueError(f'--smooth: preset {preset.name!r} is an IMM (a mixture), and the '
                         'RTS smoother needs one linear-Gaussian model')
    return RailSeriesFilter(preset)


def is_bag(path: str) -> bool:
    """Return whether ``path`` names a bag (a .mcap or .db3 file, a directory), not a table."""
    if path.endswith(('.mcap', '.db3')):
        return True
    # A directory holding Parquet files is a dataset for the columnar path, not a bag.
    return os.path.isdir(path) and not glob.glob(os.path.join(path, '**', '*.parquet'),
                                                 recursive=True)


def bag_replay_module():
    """Return kf_train.cli.bag_replay (imported when used: it needs rosbags)."""
    from kf_train.cli import bag_replay
    return bag_replay


def _bag_main(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Run ``kf-train replay BAG``: the node's parameters, not a preset's options."""
    if args.output is None:
        parser.error('a bag input needs --output X.csv, X.mcap or DIR')
    for option in ('preset', 'config', 'horizon', 'filter'):
        if getattr(args, option) is not None:
            parser.error(f'--{option} applies to a CSV input; for a bag give node parameters '
                         f'(-p preset:=NAME, -p horizon_s:=S, -p filter:=KIND)')
    if args.smooth:
        parser.error('--smooth applies to a CSV input only')
    return bag_replay_module().bag_main(args)


if __name__ == '__main__':
    sys.exit(main())
