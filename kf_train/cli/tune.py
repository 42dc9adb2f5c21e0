"""
``kf-train tune``: the noise of a preset's filter, estimated from logged measurements.

    kf-train tune [--preset P | --config FILE] INPUT --output PARAMS.yaml

The default preset is the estimator node's, ``rail`` (its IMM's noises are tuned by
:mod:`kf_train.tune.rail`); for the linear presets (``--preset train`` ...):

It finds the white-noise acceleration density q (``process_noise_density``) and the
measurement variance R (``measurement_variance``; ``measurement_velocity_variance``
too for cv-position-velocity) that make the data most likely under the estimator
node's own filter (:class:`kf_train.batch.TuningProblem`: exact likelihood of the
innovations, maximised with scipy by :mod:`kf_train.tune.noise_fit`), and prints:

* the estimates with their confidence intervals (curvature of the log-likelihood;
  a q the data cannot tell from 0 gets [0, its profile-likelihood bound]);
* the NIS consistency before (the preset's own noise) and after, against the two-sided
  99 % χ² bounds of the mean NIS, and the innovations' lag-1 whiteness;
* where the input has the truth (columns ``true_position``, ``true_velocity``), the
  RMSE of the prediction ``--horizon`` ahead (the preset's, else 2 s) before and after.

It writes PARAMS.yaml, ``estimator: ros__parameters:`` with the preset and the tuned
values, for ``estimator --ros-args --params-file PARAMS.yaml`` and for ``kf-train
replay BAG --params-file PARAMS.yaml``; ``--preset-output FILE`` also writes the tuned
preset, for ``kf-train replay TABLE --config FILE``.

Input: what ``kf-train replay`` reads (:mod:`kf_train.tune.inputs`): a CSV
(``t``, the measurement columns, ``u`` where the preset has a control, optionally
``id``: every id is an object of its own, all sharing the noise), Parquet with the
same columns, plus optional truth columns ``true_<state>``; or a rosbag2 bag (a
directory, ``.mcap`` or ``.db3``), its topics chosen as ``kf-train replay BAG`` chooses
them (``--topic``, ``--control-topic``), truth from ``--truth-topic`` (default
``ground_truth`` when there). A table does not carry the measurements' variance, so R
is estimated unless ``--fix-r`` gives it (for the rail preset, whose node learns a scale
on R online, R is its second differences' estimate, the scale's start, and is fitted only
with ``--estimate-r``). A bag does: when every message carries the
same variance, that is R (the node uses the message's variance) and q alone is
estimated, unless ``--estimate-r``; when the variances vary, one R is estimated (for
the rail preset, the rows' own variances are used, as the node uses them).
For the rail preset, the last 25 % of each segment is held out (``--holdout``): the
fit never sees it, and the start and the tuned setting are both run there by the node's
own estimator (:mod:`kf_train.tune.validation`); a tuned setting that predicts worse
or no better there (or on ``--validate INPUT``), or whose own innovations' mean NIS is
off 1 by more than 10× and further than the start's, is not written (the report says
'kept the start', exit code 0) unless ``--force``. The linear presets tune on all the
data.
Bad input is reported in one line (file, line or row, column; the bag and its topic)
with exit code 1.
"""

import argparse
import math
import os
import sys
from typing import List, Optional

from kf_train.presets import available_presets
from kf_train.tune import (
    DEFAULT_HOLDOUT, DEFAULT_NOISES, MIN_SPLIT_S, rail_preset_of, read_bag, reader_for,
    TUNABLE_NOISES, tune_linear, tune_rail, TuneOptions)

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2
_REFUSED = (('fix_q', '--fix-q'), ('initial_state', '--initial-state'), ('t0', '--t0'))


def _parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    parser = argparse.ArgumentParser(
        prog='kf-train tune',
        description="Estimate the estimator's noise from logged measurements (maximum "
                    "likelihood of the filter's innovations: the rail IMM's acceleration "
                    'and command noises by default, q for the linear presets; R where the '
                    'data do not carry it) and write them as a ROS params file.',
        epilog='Input: what kf-train replay reads: a CSV or Parquet (t, z_<measurement>, '
               'u, optional id, optional truth columns true_<state> for the prediction '
               'RMSE), or a bag (a rosbag2 directory, .mcap, .db3 or a ROS 1 .bag: the '
               'node measurement and control topics, truth from an Odometry topic). '
               'Needs scipy (pip install scipy).')
    parser.add_argument('input', metavar='INPUT',
                        help="the measurements: CSV ('-': stdin), a .parquet file or a "
                             'directory of them, or a rosbag2 bag (a directory, .mcap or .db3)')
    source = parser.add_mutually_exclusive_group()
    source.add_argument('--preset', metavar='NAME', choices=['rail'] + available_presets(),
                        default=None, help="a shipped preset (default rail, the node's): "
                                           '%(choices)s')
    source.add_argument('--config', metavar='FILE', help='a preset YAML file of your own')
    parser.add_argument('--output', '-o', metavar='PARAMS.yaml', required=True,
                        help='where to write the estimator params file')
    parser.add_argument('--preset-output', metavar='FILE',
                        help='also write the tuned preset, for kf-train replay --config')
    parser.add_argument('--fix-q', metavar='Q', type=float,
                        help='do not estimate q: use this density [m²/s³]')
    parser.add_argument('--fix-r', metavar='R', type=float, nargs='+',
                        help='do not estimate R: the measurement variance(s), one per '
                             'measurement (what the messages carry)')
    parser.add_argument('--initial-state', action='store_true',
                        help='also estimate the initial state (uses the prior '
                             'initialization)')
    parser.add_argument('--initialization', choices=('first_measurement', 'prior'),
                        help="the node's initialization (default first_measurement; prior "
                             'with --initial-state)')
    parser.add_argument('--first-velocity-std', metavar='MPS', type=float, default=100.0,
                        help='first_measurement: σ of the initial velocity [m/s] (100)')
    parser.add_argument('--t0', metavar='S', type=float,
                        help='prior: the time of the initial estimate [s] (default: one '
                             'nominal period before the first row of each object, as the node)')
    parser.add_argument('--horizon', metavar='S', type=float,
                        help="prediction horizon of the RMSE [s] (default: the preset's, "
                             'else 2; not for rail: its horizon_s)')
    parser.add_argument('--confidence', metavar='P', type=float, default=0.95,
                        help='confidence of the intervals (0.95)')
    add_rail_arguments(parser)
    bag = parser.add_argument_group('bag input (a rosbag2 directory, .mcap or .db3, or a '
                                    'ROS 1 .bag)')
    bag.add_argument('--topic', metavar='NAME', default=None,
                     help="the measurement topic (default: 'measurement' resolved in the "
                          'bag, else the only one of the expected type), as kf-train replay')
    bag.add_argument('--control-topic', metavar='NAME', default=None,
                     help="the control topic, for presets with one (default: 'control')")
    bag.add_argument('--truth-topic', metavar='NAME', default=None,
                     help='an Odometry topic with the true state, for the prediction RMSE '
                          "(default: 'ground_truth' if the bag has it)")
    bag.add_argument('--estimate-r', action='store_true',
                     help='estimate R even though the messages carry a variance (the '
                          "sensor's stated covariance is a guess), or for the rail preset "
                          'on a table, although its node learns a scale on R online')
    return parser


def _check_args(parser: argparse.ArgumentParser, args) -> None:
    """Refuse out-of-range options (exit 2)."""
    for option, value, low in (('--fix-q', args.fix_q, 0.0), ('--horizon', args.horizon, 0.0),
                               ('--first-velocity-std', args.first_velocity_std, 0.0)):
        if value is not None and not (math.isfinite(value) and value >= low):
            parser.error(f'{option} must be a finite number >= {low:g}, got {value}')
    for value in args.fix_r or ():
        if not (math.isfinite(value) and value > 0.0):
            parser.error(f'--fix-r must be finite numbers > 0, got {value}')
    if not 0.5 <= args.confidence < 1.0:
        parser.error(f'--confidence must be in [0.5, 1), got {args.confidence}')
    if args.t0 is not None and not math.isfinite(args.t0):
        parser.error(f'--t0 must be a finite number, got {args.t0}')
    if args.initial_state and args.initialization == 'first_measurement':
        parser.error('--initial-state needs --initialization prior')
    if args.estimate_r and args.fix_r is not None:
        parser.error('--estimate-r and --fix-r exclude each other')
    if reader_for(args.input) is not read_bag:
        for option in ('topic', 'control_topic', 'truth_topic'):
            if getattr(args, option) is not None:
                parser.error(f"--{option.replace('_', '-')} applies to a bag input only")


def add_rail_arguments(parser) -> None:
    """Add the rail preset's own options to ``kf-train tune``'s parser."""
    parser.add_argument('--rail-noises', metavar='NAMES',
                        help='rail preset: the noises to estimate, comma-separated '
                             '(default acceleration_noise,command_noise; also '
                             'capability_noise); R too unless the data carry it')
    parser.add_argument('--holdout', metavar='FRACTION', type=float, default=None,
                        help='rail preset only: hold out the last FRACTION of each '
                             f'segment (default {DEFAULT_HOLDOUT:g}; segments shorter than '
                             f'{MIN_SPLIT_S:g} s are kept whole; 0: off): the fit never sees '
                             'it; the start and the tuned setting are scored there by the '
                             "node's own estimator (2-s prediction against the later fix)")
    parser.add_argument('--validate', metavar='INPUT',
                        help='rail preset only: also score both settings on another input '
                             '(read as INPUT is), whole after its warm-up')
    parser.add_argument('--force', action='store_true',
                        help='rail preset only: write the tuned setting even when it '
                             'predicts worse or no better than the start on the '
                             'held-out part or on --validate, or its mean NIS is off '
                             'by more than 10x (without it nothing is '
                             "written, exit code 0, and the report says 'kept the start: "
                             "...')")


def check_rail_args(parser, args) -> List[str]:
    """Refuse the options that have no meaning for the rail preset (exit 2); return the noises."""
    for attribute, option in _REFUSED:
        if getattr(args, attribute, None) not in (None, False):
            parser.error(f'{option} does not apply to the rail preset (it has no q; '
                         'its noises are acceleration_noise and command_noise)')
    if args.horizon is not None:
        parser.error('--horizon does not apply to the rail preset (the held-out part is '
                     "scored at the node's horizon: the preset's horizon_s)")
    if args.initialization == 'prior':
        parser.error('--initialization prior does not apply to the rail preset (the node '
                     'starts it from the first measurement)')
    noises = [n.strip() for n in (args.rail_noises or ','.join(DEFAULT_NOISES)).split(',')]
    for name in noises:
        if name not in TUNABLE_NOISES:
            parser.error(f"--rail-noises: {name!r} is not one of {', '.join(TUNABLE_NOISES)}")
    if len(set(noises)) != len(noises):
        parser.error('--rail-noises: a noise is named twice')
    if args.fix_r is not None and len(args.fix_r) != 1:
        parser.error('--fix-r takes one variance for the rail preset (it measures the position)')
    if args.holdout is not None and not 0.0 <= args.holdout < 1.0:
        parser.error(f'--holdout must be in [0, 1), got {args.holdout}')
    return noises


def main(argv: Optional[List[str]] = None) -> int:
    """Run ``kf-train tune``; return the exit code."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    _check_args(parser, args)
    rail_only = [option for option, given in (('--rail-noises', args.rail_noises is not None),
                                              ('--holdout', args.holdout is not None),
                                              ('--validate', args.validate is not None),
                                              ('--force', args.force)) if given]
    if args.holdout is None:
        args.holdout = DEFAULT_HOLDOUT
    options = TuneOptions(**{name: getattr(args, name) for name in TuneOptions._fields})
    try:
        rail = rail_preset_of(options)
        if rail is not None:
            noises = check_rail_args(parser, args)
            text = tune_rail(options, rail, noises, os.path.abspath(args.config) if args.config
                             else 'rail')
        elif rail_only:
            parser.error(f'{rail_only[0]} applies to the rail preset only')
        else:
            text = tune_linear(options)
    except ImportError as error:
        print(f'kf-train tune: error: needs scipy ({error}); install it with '
              "'pip install scipy'", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ValueError as error:
        print(f'kf-train tune: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_BAD_INPUT
    print(text, file=sys.stderr if args.output == '-' else sys.stdout)
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
