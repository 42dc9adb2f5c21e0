"""
The filter family on the same seeded Monte-Carlo runs (``kf-train compare``'s engine).

For each run r = 0..runs−1 the preset's seed scenario
(:mod:`kf_train.sim.scenarios`) is simulated with seed ``seed + r``; every filter
then runs over the same rows from the same initial estimate. By default that
estimate is drawn from N(truth at t0, P0), so that the initial error has the
covariance the filter assumes and the NEES test below is valid from the first row;
``--initial preset`` uses the preset's fixed initial state instead (the seed's
setup). ``--preset rail`` runs its IMM on rail runs
(:mod:`kf_train.evaluate.compare_rail`).
Per filter it reports:

* the position RMSE over all rows of all runs, and at the last row [m];
* the average NEES: ANEES_k = mean over runs of e_kᵀ P_k⁻¹ e_k (e the estimation
  error, P the filter's covariance) and the fraction of rows k where it lies inside
  the two-sided 99% χ² interval. For a consistent filter runs·ANEES_k is
  χ²(runs·n), so the bounds are its 0.5% and 99.5% quantiles divided by runs
  (computed by :mod:`kf_train.filters.chi2`, no scipy);
* the wall-clock time per row (predict + update + reading the estimate) [µs];
* runs in which the filter raised (left out of the statistics, and counted).

The scores are :mod:`kf_train.evaluate.scores`'; ``kf-train compare``
(:mod:`kf_train.cli.compare`) prints a table, writes the per-row curves as CSV and draws
a figure (:func:`kf_train.plots.comparison_figure`). A particle filter's seed for run
r is derived from (seed, r) by ``numpy.random.SeedSequence``, so its draws are
independent of the scenario's noise (``pf`` and ``bootstrap-pf`` get the same seed).
The ``pf`` line also prints its counters: first updates drawn from the measurement,
progressive-correction stages, and the Metropolis-Hastings moves proposed and accepted.
"""

import time
from typing import Optional, Sequence, Tuple

from kf_train.batch import run_filter_series, SeriesError
from kf_train.evaluate.compare_rail import run_rail_comparison
from kf_train.evaluate.scores import Comparison, derived_seed, nees, summarise
from kf_train.filters import check_kind, FilterOptions, make_filter, PARTICLE_KINDS, psd_factor
from kf_train.presets import load_preset, Preset, RAIL_PRESET_NAME
from kf_train.sim import DEFAULT_RAIL_FAMILY, scenario_for_preset
import numpy as np

DEFAULT_RUNS = 100
DEFAULT_COMPARE_PARTICLES = 5000
"""Particles for the comparison (pf ~5x the UKF's time per row: ~1-2 min for 100 runs)."""
INITIAL_MODES = ('sampled', 'preset')


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
    summaries = [summarise(kind, sq_errors[kind], nees_rows[kind], failed[kind],
                           seconds[kind], steps[kind], preset.dim_x, len(t_s), counters[kind])
                 for kind in kinds]
    return Comparison(preset.name, runs, seed, initial, t_s, preset.dim_x, summaries)
