"""
``kf-train plot``: PNG figures of the seeds' filters, through matplotlib's Agg backend.

Simulates each preset's seed scenario (:mod:`kf_train.sim.scenarios`) and draws it
(:mod:`kf_train.plots.figures`; ``--preset rail``: :mod:`kf_train.plots.rail`), or
draws a ``kf-train replay`` output CSV (``--replay OUT.csv``, with ``--input IN.csv``
for the measurements).
"""

import argparse
import sys
from typing import List, Optional

from kf_train.plots import rail_figures, replay_figure_paths, scenario_figures
from kf_train.presets import available_presets, RAIL_PRESET_NAME

EXIT_OK = 0
EXIT_ERROR = 1


def _parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    parser = argparse.ArgumentParser(
        prog='kf-train plot',
        description='Write PNG figures (matplotlib Agg, no display needed).',
        epilog="Without --replay: simulates each preset's seed scenario (truth and seeded "
               'noise, kf_train.sim.scenarios), filters it and writes <preset>.png (the '
               'estimate with a ±2σ band against truth and measurements), '
               "range-bearing_track.png (the x-y track) and, for train, seed 000's three "
               'figures seed000_position.png, seed000_velocity.png and '
               'seed000_extrapolation.png. With --replay OUT.csv: draws a kf-train replay '
               'output, and the measurements of --input IN.csv; an output with a '
               'prediction and nis (train, rail, a bag replay) as four panels: the prediction '
               'error against the later fix with its ±2σ band, the regime probabilities, '
               'the NIS with its bounds, and a zoom on the longest standstill; time from '
               'the start in s.')
    parser.add_argument('--output-dir', '-o', metavar='DIR', default='.',
                        help='where to write the PNGs (default: the current directory)')
    parser.add_argument('--preset', metavar='NAME', action='append',
                        choices=available_presets() + [RAIL_PRESET_NAME],
                        help='only this preset (repeatable; default: all but rail of '
                             '%(choices)s; rail: rail.png and rail_run.png, the rail IMM '
                             'on a metro run)')
    parser.add_argument('--seed', metavar='N', type=int, default=0,
                        help='random seed of the simulated noise (default 0)')
    parser.add_argument('--replay', metavar='OUT', help='draw this replay output (a CSV, or '
                        "a bag replay's output bag: a directory or .mcap)")
    parser.add_argument('--input', metavar='IN',
                        help='with --replay: the replay input, for the measurements (a CSV, '
                             "or the replayed bag for a bag replay's output)")
    parser.add_argument('--horizon', metavar='S', type=float, default=None,
                        help='with --replay: the prediction horizon of the output [s] '
                             "(default: the estimator's default preset's)")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Run ``kf-train plot``; return the exit code."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.seed < 0:
        parser.error(f'--seed must be >= 0, got {args.seed}')
    if args.input and not args.replay:
        parser.error('--input goes with --replay')
    if args.replay and args.preset:
        parser.error('--preset does not apply to --replay')
    if args.horizon is not None and not (args.replay and 0.0 < args.horizon < float('inf')):
        parser.error('--horizon S (> 0) goes with --replay')
    try:
        if args.replay:
            paths = replay_figure_paths(args.output_dir, args.replay, args.input,
                                        horizon_s=args.horizon)
        else:
            paths = []
            for name in args.preset or available_presets():
                if name == RAIL_PRESET_NAME:
                    paths += rail_figures(args.output_dir, args.seed)
                else:
                    paths += scenario_figures(args.output_dir, name, args.seed)
    except (ValueError, RuntimeError, OSError) as error:
        print(f'kf-train plot: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_ERROR
    for path in paths:
        print(path)
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
