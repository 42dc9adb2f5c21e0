"""
``kf-train compare --preset rail``: the rail IMM on seeded Monte-Carlo rail runs.

The rail preset has one filter, its IMM of four Kalman filters (``kf``; ``ekf`` is the
same, the regimes being linear). Run r is the first ``duration_s`` of the rail run of
seed ``seed + r`` of a family, metro-like by default or regional-like
(:func:`kf_train.sim.rail.rail_scenario`, σ = 1 m at 10 Hz: departures, cruising,
slow zones, brakes and dwells), filtered row by row from
its first measurement as the streaming estimator's default starts
(:class:`kf_train.batch.RailSeriesFilter`). The truth has position, velocity and
acceleration, so the NEES is taken over those three states (the filter's other
states, the commanded acceleration and the capabilities A and B, have no truth).
The scores are :mod:`kf_train.evaluate.scores`'; the table, curves and figure those of
``kf-train compare`` (:mod:`kf_train.cli.compare`).
"""

import dataclasses
import time
from typing import Optional, Sequence

from kf_train.batch import RailSeriesFilter, run_filter_series, SeriesError
from kf_train.estimator import RAIL_FILTER_KINDS
from kf_train.evaluate.scores import Comparison, nees, summarise
from kf_train.presets import load_rail_preset
from kf_train.sim import DEFAULT_RAIL_FAMILY, family_parameters, rail_scenario
import numpy as np

RAIL_RUN_S = 120.0
"""Length of each Monte-Carlo rail run [s] (a departure, a cruise and a stop or two)."""
SCORED_STATES = 3
"""Position, velocity and acceleration: the states the rail truth has."""


def run_rail_comparison(runs: int, seed: int, kinds: Optional[Sequence[str]],
                        family: str = DEFAULT_RAIL_FAMILY, duration_s: float = RAIL_RUN_S):
    """Return the :class:`~kf_train.evaluate.scores.Comparison` of the rail IMM over ``runs``."""
    kinds = tuple(kinds or ('kf',))
    for kind in kinds:
        if kind not in RAIL_FILTER_KINDS:
            raise ValueError(f'filter {kind!r}: preset rail is an IMM of four Kalman '
                             'filters; compare it as kf (or ekf, the same)')
    filt = RailSeriesFilter(load_rail_preset())
    sq_errors = {kind: [] for kind in kinds}
    nees_rows = {kind: [] for kind in kinds}
    seconds, failed = dict.fromkeys(kinds, 0.0), dict.fromkeys(kinds, 0)
    t_s, steps = None, 0
    for r in range(runs):
        params = dataclasses.replace(family_parameters(family, seed + r), duration_s=duration_s)
        scenario, _ = rail_scenario(seed + r, family, parameters=params)
        t_s = scenario.t_s if t_s is None else t_s
        steps += scenario.t_s.shape[0]
        for kind in kinds:
            start = time.perf_counter()
            try:
                result = run_filter_series(filt, scenario.t_s, scenario.z, horizon_s=0.0,
                                           t0_s=scenario.t0_s)
            except SeriesError:
                failed[kind] += 1
                continue
            seconds[kind] += time.perf_counter() - start
            errors = result.x[:, :SCORED_STATES] - scenario.truth
            sq_errors[kind].append(errors[:, 0] ** 2)
            nees_rows[kind].append(nees(errors, result.P[:, :SCORED_STATES, :SCORED_STATES]))
    summaries = [summarise(kind, sq_errors[kind], nees_rows[kind], failed[kind],
                           seconds[kind], max(steps, 1), SCORED_STATES, len(t_s), {})
                 for kind in kinds]
    return Comparison('rail', runs, seed, 'first_measurement', np.asarray(t_s), SCORED_STATES,
                      summaries, rail_family=family)
