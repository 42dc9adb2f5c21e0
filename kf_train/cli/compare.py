"""
``kf-train compare``: the filter family on the same seeded Monte-Carlo runs.

What is run and measured (RMSE, ANEES with its χ² bounds, time per row, failed runs)
is the engine's, :mod:`kf_train.evaluate.compare`.

It prints a table, writes the per-row curves as CSV and draws a figure (PNG through
matplotlib's Agg backend). The engine is :mod:`kf_train.evaluate`, the figure
:func:`kf_train.plots.comparison_figure`. A particle filter's seed for run r is derived from
(seed, r) by ``numpy.random.SeedSequence``, so its draws are independent of the
scenario's noise (``pf`` and ``bootstrap-pf`` get the same seed). The ``pf`` line
also prints its counters: first updates drawn from the measurement, progressive-
correction stages, and the Metropolis-Hastings moves proposed and accepted.
"""

import argparse
import os
import sys
from typing import List, Optional

from kf_train.cli.filter_options import add_filter_options, filter_options
from kf_train.evaluate import (
    Comparison, DEFAULT_COMPARE_PARTICLES, DEFAULT_RUNS, INITIAL_MODES, run_comparison,
    write_curves)
from kf_train.presets import available_presets, RAIL_PRESET_NAME
from kf_train.sim import RAIL_FAMILIES

EXIT_OK = 0
EXIT_ERROR = 1


def format_table(comparison: Comparison) -> str:
    """Return the printed table."""
    rows = comparison.t_s.shape[0]
    lines = [f'kf-train compare: preset {comparison.preset}, {comparison.runs} runs '
             f'(seeds {comparison.seed}..{comparison.seed + comparison.runs - 1}), '
             f'{rows} rows each, initial estimate '
             + {'sampled': 'drawn from N(truth, P0)',
                'first_measurement': "set by the first measurement, the preset's priors "
                                     f'for the rest (rail: 120-s {comparison.rail_family} '
                                     'runs)'}.get(
                 comparison.initial, "the preset's fixed initial state")]
    header = (f"{'filter':12s} {'runs':>5s} {'failed':>6s} {'RMSE pos [m]':>12s} "
              f"{'final [m]':>10s} {'mean ANEES':>11s} {'99% bounds':>15s} "
              f"{'rows in':>7s} {'µs/row':>9s}")
    lines += [header, '-' * len(header)]
    for s in comparison.summaries:
        bounds = f'[{s.anees_bounds[0]:.3f}, {s.anees_bounds[1]:.3f}]'
        lines.append(
            f'{s.kind:12s} {s.runs_ok:5d} {s.runs_failed:6d} {s.rmse_position_m:12.4g} '
            f'{s.final_rmse_position_m:10.4g} {s.mean_anees:11.4g} {bounds:>15s} '
            f'{100.0 * s.fraction_in_bounds:6.1f}% {1e6 * s.seconds_per_step:9.1f}')
    lines.append(f'ANEES: the average over runs of the NEES, {comparison.dim_x} states; a '
                 'consistent filter stays inside the 99% bounds on ~99% of the rows.')
    for s in comparison.summaries:
        if s.diagnostics:
            text = ', '.join(f'{key} {value:g}' for key, value in s.diagnostics.items())
            lines.append(f'{s.kind}: {text} (over all runs)')
    return '\n'.join(lines)


def _parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    parser = argparse.ArgumentParser(
        prog='kf-train compare',
        description='Run KF/EKF, UKF and particle filter on the same seeded Monte-Carlo '
                    'runs of a preset scenario; print RMSE, ANEES against the 99%% chi2 '
                    'bounds and time per row, and draw a figure.')
    parser.add_argument('--preset', metavar='NAME', default='range-bearing',
                        choices=available_presets() + [RAIL_PRESET_NAME],
                        help='a shipped preset (default %(default)s): %(choices)s')
    parser.add_argument('--runs', metavar='N', type=int, default=DEFAULT_RUNS,
                        help='Monte-Carlo runs (default %(default)d)')
    parser.add_argument('--filters', metavar='LIST', default=None,
                        help='comma-separated kinds among kf, ekf, ukf, pf, bootstrap-pf '
                             '(default: the exact filter, ukf and pf)')
    parser.add_argument('--initial', choices=INITIAL_MODES, default='sampled',
                        help='initial estimate: drawn from N(truth, P0) per run, or the '
                             "preset's fixed one (default %(default)s)")
    parser.add_argument('--output-dir', metavar='DIR', default='.',
                        help='where to write compare-<preset>.png and .csv (default .)')
    parser.add_argument('--no-figure', action='store_true', help='skip the figure')
    parser.add_argument('--rail-family', choices=RAIL_FAMILIES, default=None,
                        help='preset rail only: the family of its runs (default metro)')
    add_filter_options(parser)
    parser.set_defaults(particles=DEFAULT_COMPARE_PARTICLES)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Run ``kf-train compare``; return the exit code."""
    parser = _parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.runs < 1:
        parser.error(f'--runs must be >= 1, got {args.runs}')
    if args.seed < 0:
        parser.error(f'--seed must be >= 0, got {args.seed}')
    kinds = None
    if args.filters is not None:
        kinds = [kind.strip() for kind in args.filters.split(',') if kind.strip()]
    try:
        options = filter_options(args)
    except ValueError as error:
        parser.error(str(error))
    try:
        comparison = run_comparison(args.preset, runs=args.runs, seed=args.seed,
                                    kinds=kinds, options=options, initial=args.initial,
                                    rail_family=args.rail_family)
        print(format_table(comparison))
        os.makedirs(args.output_dir, exist_ok=True)
        stem = os.path.join(args.output_dir, f'compare-{comparison.preset}')
        written = [write_curves(comparison, stem + '.csv')]
        if not args.no_figure:
            from kf_train.plots import comparison_figure, save
            written.append(save(comparison_figure(comparison), stem + '.png'))
    except (ValueError, OSError) as error:
        print(f'kf-train compare: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_ERROR
    print('wrote ' + ', '.join(written))
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
