"""
``kf-train compare``: the filter family on the same seeded Monte-Carlo runs.

For each run r = 0..runs−1 the preset's seed scenario
(:mod:`kf_train.sim.scenarios`) is simulated with seed ``seed + r``; every filter
then runs over the same rows from the same initial estimate. By default that
estimate is drawn from N(truth at t0, P0), so that the initial error has the
covariance the filter assumes and the NEES test below is valid from the first row;
``--initial preset`` uses the preset's fixed initial state instead (the seed's
setup). ``--preset rail`` runs its IMM on rail runs (:mod:`kf_train.cli.compare_rail`).
Per filter it reports:

* the position RMSE over all rows of all runs, and at the last row [m];
* the average NEES: ANEES_k = mean over runs of e_kᵀ P_k⁻¹ e_k (e the estimation
  error, P the filter's covariance) and the fraction of rows k where it lies inside
  the two-sided 99% χ² interval. For a consistent filter runs·ANEES_k is
  χ²(runs·n), so the bounds are its 0.5% and 99.5% quantiles divided by runs
  (computed by :mod:`kf_train.filters.chi2`, no scipy);
* the wall-clock time per row (predict + update + reading the estimate) [µs];
* runs in which the filter raised (left out of the statistics, and counted).

It prints a table, writes the per-row curves as CSV and draws a figure (PNG through
matplotlib's Agg backend). A particle filter's seed for run r is derived from
(seed, r) by ``numpy.random.SeedSequence``, so its draws are independent of the
scenario's noise (``pf`` and ``bootstrap-pf`` get the same seed). The ``pf`` line
also prints its counters: first updates drawn from the measurement, progressive-
correction stages, and the Metropolis-Hastings moves proposed and accepted.
"""

import argparse
import os
import sys
import time
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

from kf_train.batch import run_filter_series, SeriesError
from kf_train.cli.filter_options import add_filter_options, filter_options
from kf_train.filters import (
    check_kind, chi2_quantile, FilterOptions, make_filter, PARTICLE_KINDS, psd_factor)
from kf_train.presets import available_presets, load_preset, Preset, RAIL_PRESET_NAME
from kf_train.sim import DEFAULT_RAIL_FAMILY, RAIL_FAMILIES, scenario_for_preset
import numpy as np

EXIT_OK = 0
EXIT_ERROR = 1
DEFAULT_RUNS = 100
DEFAULT_COMPARE_PARTICLES = 5000
"""Particles for the comparison (pf ~5x the UKF's time per row: ~1-2 min for 100 runs)."""
CONFIDENCE = 0.99
INITIAL_MODES = ('sampled', 'preset')


class FilterSummary(NamedTuple):
    """One filter's Monte-Carlo statistics."""

    kind: str
    runs_ok: int
    runs_failed: int
    rmse_position_m: float
    """Position RMSE over all rows of the successful runs."""
    final_rmse_position_m: float
    """Position RMSE at the last row."""
    mean_anees: float
    """ANEES averaged over the rows."""
    fraction_in_bounds: float
    """Fraction of rows whose ANEES lies inside the 99% χ² interval."""
    anees_bounds: Tuple[float, float]
    """The 99% interval of ANEES for runs_ok runs."""
    seconds_per_step: float
    rmse_per_row_m: np.ndarray
    """Position RMSE at each row over the runs (rows,)."""
    anees_per_row: np.ndarray
    """ANEES at each row (rows,)."""
    diagnostics: Dict[str, float]
    """Filter counters summed over the runs (UKF regularisations, PF resamplings)."""


class Comparison(NamedTuple):
    """What :func:`run_comparison` measured."""

    preset: str
    runs: int
    seed: int
    initial: str
    t_s: np.ndarray
    """Row times of the scenario (rows,) [s]."""
    dim_x: int
    summaries: List[FilterSummary]
    rail_family: Optional[str] = None
    """The rail runs' family (``metro`` or ``regional``); None for the other presets."""


def position_indices(preset: Preset) -> Tuple[int, ...]:
    """Return the state indices that make up the position."""
    measurement = getattr(preset.model, 'measurement', None)
    if measurement is not None and hasattr(measurement, 'x_index'):
        return (measurement.x_index, measurement.y_index)
    if 'position' in preset.state_names:
        return (preset.state_names.index('position'),)
    return (0,)


def default_kinds(preset: Preset) -> Tuple[str, ...]:
    """Return the filters compared by default: the exact one, the UKF and the PF."""
    return ('kf' if preset.linear else 'ekf', 'ukf', 'pf')


def derived_seed(seed: int, run: int, stream: int) -> int:
    """Return an independent 63-bit seed for (seed, run, stream)."""
    state = np.random.SeedSequence([int(seed), int(run), int(stream)]).generate_state(
        2, dtype=np.uint32)
    return int(state[0]) << 31 | int(state[1]) >> 1


def nees(errors: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Return e_kᵀ P_k⁻¹ e_k per row; inf where P_k is singular."""
    out = np.empty(errors.shape[0])
    for k, (e, Pk) in enumerate(zip(errors, P)):
        try:
            out[k] = float(e @ np.linalg.solve(Pk, e))
        except np.linalg.LinAlgError:
            out[k] = np.inf
    out[~np.isfinite(out) | (out < 0.0)] = np.inf
    return out


def run_comparison(preset_name: str, *, runs: int = DEFAULT_RUNS, seed: int = 0,
                   kinds: Optional[Sequence[str]] = None,
                   options: Optional[FilterOptions] = None,
                   initial: str = 'sampled', rail_family: Optional[str] = None
                   ) -> Comparison:
    """
    Run every filter on ``runs`` seeded scenarios of a shipped preset.

    ``rail_family`` (preset rail only; default metro) chooses the rail runs' family.
    """
    if not isinstance(runs, int) or isinstance(runs, bool) or runs < 1:
        raise ValueError(f'runs must be a positive integer, got {runs!r}')
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
    if initial not in INITIAL_MODES:
        raise ValueError(f"initial must be one of {', '.join(INITIAL_MODES)}, got {initial!r}")
    if preset_name == RAIL_PRESET_NAME:  # its IMM, from each run's first measurement
        from kf_train.cli.compare_rail import run_rail_comparison
        return run_rail_comparison(runs, seed, kinds, family=rail_family or DEFAULT_RAIL_FAMILY)
    if rail_family is not None:
        raise ValueError(f'a rail family is for preset rail only, not {preset_name}')
    preset = load_preset(preset_name)
    kinds = tuple(default_kinds(preset) if kinds is None else kinds)
    if not kinds:
        raise ValueError('no filter to compare')
    for kind in kinds:
        check_kind(kind)
    options = options or FilterOptions(particles=DEFAULT_COMPARE_PARTICLES)
    # Build each filter once: bad options fail before any run.
    filters = {kind: make_filter(preset, kind, options) for kind in kinds}
    position = list(position_indices(preset))
    P0 = preset.initial_covariance
    G0 = psd_factor('initial_covariance', P0, preset.dim_x)
    sq_errors = {kind: [] for kind in kinds}
    nees_rows = {kind: [] for kind in kinds}
    seconds = dict.fromkeys(kinds, 0.0)
    steps = dict.fromkeys(kinds, 0)
    failed = dict.fromkeys(kinds, 0)
    counters = {kind: {} for kind in kinds}
    t_s = None
    for r in range(runs):
        scenario = scenario_for_preset(preset.name, seed + r)
        if t_s is None:
            t_s = scenario.t_s
        x0 = preset.initial_state
        if initial == 'sampled':
            rng = np.random.default_rng(derived_seed(seed, r, 1))
            x0 = scenario.truth0 + G0 @ rng.standard_normal(G0.shape[1])  # x0 ~ N(x_true, P0)
        for kind in kinds:
            filt = filters[kind]
            if kind in PARTICLE_KINDS:
                filt.reset(x0, P0, seed=derived_seed(seed, r, 2))
            start = time.perf_counter()
            try:
                result = run_filter_series(filt, scenario.t_s, scenario.z, scenario.u,
                                           t0_s=scenario.t0_s, horizon_s=0.0, x0=x0, P0=P0)
            except SeriesError:
                failed[kind] += 1
                continue
            seconds[kind] += time.perf_counter() - start
            steps[kind] += scenario.t_s.shape[0]
            errors = result.x - scenario.truth
            sq_errors[kind].append(np.sum(errors[:, position] ** 2, axis=1))
            nees_rows[kind].append(nees(errors, result.P))
            for key, value in filt.diagnostics().items():
                if key != 'ess':
                    counters[kind][key] = counters[kind].get(key, 0) + value
    summaries = [_summary(kind, sq_errors[kind], nees_rows[kind], failed[kind],
                          seconds[kind], steps[kind], preset.dim_x, len(t_s), counters[kind])
                 for kind in kinds]
    return Comparison(preset.name, runs, seed, initial, t_s, preset.dim_x, summaries)


def anees_bounds(runs: int, dim_x: int, confidence: float = CONFIDENCE) -> Tuple[float, float]:
    """Return the two-sided interval of ANEES over ``runs`` runs of a consistent filter."""
    tail = 0.5 * (1.0 - confidence)
    dof = runs * dim_x                       # runs·ANEES ~ χ²(runs·n)
    return chi2_quantile(tail, dof) / runs, chi2_quantile(1.0 - tail, dof) / runs


def _summary(kind, sq_errors, nees_rows, failed, seconds, steps, dim_x, rows,
             counters) -> FilterSummary:
    """Return the statistics of one filter's successful runs."""
    ok = len(sq_errors)
    if not ok:
        nan_rows = np.full(rows, np.nan)
        return FilterSummary(kind, 0, failed, np.nan, np.nan, np.nan, np.nan, (np.nan, np.nan),
                             np.nan, nan_rows, nan_rows, counters)
    sq = np.array(sq_errors)                 # (runs, rows) squared position errors
    per_row = np.array(nees_rows)
    anees = per_row.mean(axis=0)             # ANEES_k = mean over runs of NEES
    low, high = anees_bounds(ok, dim_x)
    return FilterSummary(
        kind, ok, failed, float(np.sqrt(sq.mean())), float(np.sqrt(sq[:, -1].mean())),
        float(anees.mean()), float(np.mean((anees >= low) & (anees <= high))), (low, high),
        seconds / steps, np.sqrt(sq.mean(axis=0)), anees, counters)


# ---------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------

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


def write_curves(comparison: Comparison, path: str) -> str:
    """Write the per-row RMSE and ANEES of every filter as CSV; return the path."""
    header = ['t']
    columns = [comparison.t_s]
    for s in comparison.summaries:
        header += [f'rmse_position_{s.kind}', f'anees_{s.kind}']
        columns += [s.rmse_per_row_m, s.anees_per_row]
    lines = [','.join(header)]
    lines += [','.join(repr(float(v)) for v in row) for row in zip(*columns)]
    with open(path, 'w', encoding='utf-8') as stream:
        stream.write('\n'.join(lines) + '\n')
    return path


def comparison_figure(comparison: Comparison):
    """Return the figure: position RMSE and ANEES (with its 99% bounds) against time."""
    from kf_train.plots import new_figure
    figure, (ax_rmse, ax_nees) = new_figure(2, 1, size=(8.0, 7.0))
    colours = {'kf': 'tab:blue', 'ekf': 'tab:blue', 'ukf': 'tab:green', 'pf': 'tab:red',
               'bootstrap-pf': 'tab:orange'}
    t = comparison.t_s
    for s in comparison.summaries:
        colour = colours.get(s.kind)
        ax_rmse.plot(t, s.rmse_per_row_m, color=colour,
                     label=f'{s.kind.upper()} ({1e6 * s.seconds_per_step:.0f} µs/row)')
        infinite = int(np.sum(~np.isfinite(s.anees_per_row)))
        # A collapsed (singular) covariance gives an infinite NEES: say so, as a log
        # axis cannot draw it.
        ax_nees.plot(t, np.where(np.isfinite(s.anees_per_row), s.anees_per_row, np.nan),
                     color=colour, label=s.kind.upper() + (
                         f' (infinite on {infinite} of {t.shape[0]} rows)' if infinite else ''))
    ax_rmse.set_yscale('log')
    ax_rmse.set_ylabel('position RMSE [m]')
    ax_rmse.set_title(f'{comparison.preset}: {comparison.runs} Monte-Carlo runs')
    ax_rmse.legend(loc='upper right')
    ax_rmse.grid(True, which='both', alpha=0.3)
    finite = [s for s in comparison.summaries if s.runs_ok]
    if finite:
        low, high = finite[0].anees_bounds
        ax_nees.axhspan(low, high, color='0.8', alpha=0.6,
                        label=f'99% χ² bounds ({finite[0].runs_ok} runs)')
    ax_nees.axhline(comparison.dim_x, color='0.4', linewidth=0.8, linestyle='--')
    ax_nees.set_yscale('log')
    ax_nees.set_xlabel('t [s]')
    ax_nees.set_ylabel(f'ANEES ({comparison.dim_x} states)')
    ax_nees.legend(loc='upper right')
    ax_nees.grid(True, which='both', alpha=0.3)
    return figure


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
            from kf_train.plots import save
            written.append(save(comparison_figure(comparison), stem + '.png'))
    except (ValueError, OSError) as error:
        print(f'kf-train compare: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_ERROR
    print('wrote ' + ', '.join(written))
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
