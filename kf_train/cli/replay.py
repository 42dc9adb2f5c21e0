"""
``kf-train replay``: a preset's filter over a CSV or Parquet table (or a bag), offline.

A bag INPUT (rosbag2, or a ROS 1 ``.bag``) goes to :mod:`kf_train.replay.bag` (the
estimator node's session).

The command streams (:mod:`kf_train.replay.stream`: any size in bounded memory,
CSV or Parquet) unless ``--engine memory`` asks for
:func:`kf_train.replay.memory.replay`, which holds the whole table; ``--engine dask``
runs a fleet on Dask (:mod:`kf_train.replay.fleet_dask`). The table reading and
writing they share is :mod:`kf_train.io.tables`.

Input CSV: a header row, then one row per measurement. Columns (any order; other
columns are ignored):

* ``t`` [s]: the measurement time. The initial estimate holds at t0 = 0 (``--t0``);
  the first row may be at t0, later rows must increase (times are taken to whole
  nanoseconds, as ROS stamps are).
* the preset's measurements, ``z_<name>``: ``z_position``, ``z_velocity``,
  ``z_bearing`` [rad], ``z_range`` [m]. The rail preset also reads measured speeds
  when the header has ``z_velocity`` [m/s] (a GNSS Doppler), with its variance
  ``var_z_velocity`` [m²/s²]: each row's speed is fused after its position; either
  may be empty (:class:`~kf_train.batch.RailSeriesFilter`).
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
id), for the rail preset its regime probabilities ``p_<regime>`` and ``nis`` (of the
row's position; NaN where it fused none), one output row per input row, in the input's
order. Numbers are written exactly
as Python's shortest round-trip ``repr`` writes them (:mod:`kf_train.io.csvio`
produces the same text in bulk): reading them back gives the computed doubles exactly.

With an ``id`` column, linear presets run as a vectorised bank
(:func:`kf_train.batch.bank.run_bank`: ids with few rows in lock-step, ids with many
along their own time axis); the results equal filtering each id alone. The EKF preset
and ``--filter`` run id by id.

Without ``--preset`` or ``--config`` a table runs the estimator node's default preset
(:data:`kf_train.estimator.DEFAULT_PRESET`, ``rail``), as a bag replay does.

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
import math
import sys
from typing import List, Optional

from kf_train.batch import RailSeriesFilter
from kf_train.cli.engine_options import add_engine_options, check_engine_options
from kf_train.cli.filter_options import add_filter_options, filter_options
from kf_train.estimator import DEFAULT_PRESET, RAIL_FILTER_KINDS
from kf_train.filters import Filter, FILTER_KINDS, make_filter
from kf_train.io import is_bag
from kf_train.presets import available_presets, RAIL_PRESET_NAME, RailPreset, SPEED_COLUMN
from kf_train.replay import (
    collector_frozen, input_columns, is_parquet, load_any_preset, run_engine)
import numpy as np

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2


def _parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    parser = argparse.ArgumentParser(
        prog='kf-train replay',
        description='Run a filter over recorded measurements, offline. INPUT is a CSV or '
                    'Parquet table (a preset filter, any size, streamed in blocks; '
                    'estimates to CSV or Parquet) or a rosbag2 bag: a directory (MCAP or '
                    "sqlite3), .mcap or .db3, or a ROS 1 .bag (the estimator node's own "
                    'session and parameters; estimates to CSV, or to an MCAP bag of the node '
                    'topics).',
        epilog='Table input: a header, then rows with t [s], the measurements z_position, '
               'z_velocity, z_bearing [rad], z_range [m] the preset uses, and u when it '
               'has a control input (the control over the interval ending at the row); '
               'the rail preset also fuses a measured speed z_velocity [m/s] with its '
               'variance var_z_velocity [m²/s²] when the table has them; '
               'optionally id: each id is an independent object with its own series. '
               'Output: id (if given), t, each state by name, var_<state>; '
               'predicted_<state> and var_predicted_<state> at t + horizon; '
               'smoothed_<state> and var_smoothed_<state> with --smooth; rail: '
               'p_<regime> and nis. Presets: '
               + ', '.join(available_presets() + [RAIL_PRESET_NAME]) + ' (rail: the '
               'IMM of docs/rail.md, started by the first row). Bad input names the line '
               'and column, exits 1 and writes nothing.')
    parser.add_argument('input', metavar='INPUT', nargs='?',
                        help='measurements: CSV, a .parquet file or a directory of Parquet '
                             "files ('-' reads CSV from standard input), or a rosbag2 bag "
                             '(a directory, .mcap or .db3) or a ROS 1 .bag: see the bag '
                             'options')
    source = parser.add_mutually_exclusive_group()
    source.add_argument('--preset', metavar='NAME',
                        choices=available_presets() + [RAIL_PRESET_NAME],
                        help='a shipped preset: %(choices)s (default, without --config: '
                             f"the estimator node's default, {DEFAULT_PRESET})")
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
        'bag replay (INPUT a rosbag2 directory, .mcap or .db3, or a ROS 1 .bag): the '
        "estimator node's own session and parameters; --output X.csv, or a directory or "
        'X.mcap for a bag')
    bag.add_argument('--params-file', metavar='FILE', action='append',
                     help='a ROS params file (node estimator); may be repeated')
    bag.add_argument('-p', dest='parameter', metavar='NAME:=VALUE', action='append',
                     help='set one node parameter, as ros2 run ... -p')
    bag.add_argument('--topic', metavar='NAME', default=None,
                     help="the measurement topic (default: 'measurement' resolved in the "
                          'bag, else the only one of the expected type)')
    bag.add_argument('--control-topic', metavar='NAME', default=None,
                     help="the control topic, for presets with one (default: 'control')")
    bag.add_argument('--velocity-topic', metavar='NAME', default=None,
                     help='the measured speeds the rail preset fuses, of type '
                          'TwistWithCovarianceStamped (-p velocity_type:=twist: TwistStamped '
                          "with -p measurement_velocity_variance:=V) (default: 'velocity' "
                          'when the bag has it with that type, as the node subscribes it; '
                          '-p velocity_type:=none fuses none)')
    bag.add_argument('--track', metavar='FILE', default=None,
                     help='the measurement topic is sensor_msgs/NavSatFix, projected onto '
                          'this track (GeoJSON LineString or CSV lat,lon; or a network of '
                          'LineStrings: the path chosen live, fix by fix): the same as -p '
                          'measurement_type:=navsatfix -p track:=FILE. With it INPUT may '
                          'also be a CSV of fixes: t [s], lat, lon [deg], optional '
                          'accuracy_m (horizontal σ [m])')
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
            is_bag(args.input) or args.track is not None
            or (args.preset is None and args.config is None
                and not args.input.lower().endswith('.csv')
                and not is_parquet(args.input))):
        return _bag_main(parser, args)
    if args.preset is None and args.config is None:
        args.preset = DEFAULT_PRESET   # the node's default preset, as a bag replay runs
    if args.input is None or args.output is None:
        parser.error('INPUT and --output OUTPUT are required')
    for option in ('params_file', 'parameter', 'topic', 'control_topic', 'velocity_topic'):
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
        if isinstance(preset, RailPreset) and SPEED_COLUMN in input_columns(args.input):
            preset = preset.with_speed()   # the rail IMM fuses the rows' speeds too
        filt = _make_filter(preset, args, options)
        summary = run_engine(
            args.engine, preset, args.input, args.output, filt, horizon_s=args.horizon,
            smooth=args.smooth, t0_s=args.t0, block_rows=args.block_rows, codec=args.codec,
            spill_dir=args.spill_dir, workers=args.workers, scheduler=args.scheduler)
    except ValueError as error:
        print(f'kf-train replay: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.output != '-':
        print(f'kf-train replay: {summary.rows} rows with preset {preset.name} -> '
              f'{args.output} ({summary.seconds:.3f} s)', file=sys.stderr)
    return EXIT_OK


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
    return _run_bag(args)


def _run_bag(args: argparse.Namespace) -> int:
    """Run the bag replay for parsed ``kf-train replay`` arguments; return the exit code."""
    from kf_train.replay import bag, fix_table   # need rosbags: imported when used
    try:
        track = [] if args.track is None else [
            'measurement_type:=navsatfix', f'track:={args.track}']
        config = bag.load_config(args.params_file or [], (args.parameter or []) + track)
        with collector_frozen():
            if args.track is None or is_bag(args.input):
                summary = bag.replay_bag(args.input, args.output, config, args.topic,
                                         args.control_topic, args.velocity_topic)
            else:                            # --track: a CSV of fixes (t, lat, lon)
                summary = fix_table.replay_fix_table(args.input, args.output, config)
    except ValueError as error:
        print(f'kf-train replay: error: {" ".join(str(error).split())}', file=sys.stderr)
        return 1
    rate = summary.measurements / summary.seconds if summary.seconds > 0 else math.inf
    print(f'kf-train replay: {summary.measurements} measurements on '
          f'{summary.measurement_topic}, {summary.controls} controls, '
          + (f'{summary.velocities} speeds on {summary.velocity_topic} '
             f'({summary.velocities_rejected} rejected), ' if summary.velocity_topic else '')
          + (_fixes_text(summary.fixes) if summary.fixes else '')
          + f'{summary.rejected} rejected -> {summary.estimates} estimates in '
          f'{args.output} ({summary.seconds:.3f} s, {rate:.0f} measurements/s)',
          file=sys.stderr)
    return 0


def _fixes_text(fixes: dict) -> str:
    """Return what the track did with the fixes, for the summary line."""
    return (f"({fixes['fixes.received']} fixes: {fixes['fixes.no_fix']} without a position, "
            f"{fixes['fixes.off_track']} off the track, {fixes['fixes.pending']} held; "
            f"direction {fixes['track_direction']}"
            + (f", last on element {fixes['track_element']}" if 'track_element' in fixes
               else '') + '), ')


if __name__ == '__main__':
    sys.exit(main())
