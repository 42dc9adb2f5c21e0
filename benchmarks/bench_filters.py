"""
``make bench`` row 6: time per update of the filter family on the range-bearing seed.

Each filter runs the seed scenario (scenario 0, 100 rows, the preset's initial state)
through :func:`kf_train.batch.run_filter_series` (predict + update + reading
the estimate per row); after an untimed warm-up, the best of a few repeats is reported
per row, and as a ratio to the UKF's. Prints figures only: issue 14 asks for the
particle filter's time per update reported against the UKF, not for a bound.
"""

import time
from typing import List

from bench_common import Row

CASES = (('ekf', {}), ('ukf', {}), ('pf', {'particles': 1000}), ('pf', {'particles': 2000}),
         ('pf', {'particles': 5000}), ('bootstrap-pf', {'particles': 5000}))


def _seconds_per_row(preset, kind: str, overrides: dict, scenario, repeats: int) -> float:
    """Return the best time per row [s] of ``repeats`` runs over the scenario."""
    from kf_train.batch import run_filter_series
    from kf_train.filters import make_filter
    filt = make_filter(preset, kind, seed=0, **overrides)
    run_filter_series(filt, scenario.t_s, scenario.z, horizon_s=0.0)   # warm-up, untimed
    best = float('inf')
    for _ in range(repeats):
        start = time.perf_counter()
        run_filter_series(filt, scenario.t_s, scenario.z, horizon_s=0.0)
        best = min(best, time.perf_counter() - start)
    return best / scenario.t_s.shape[0]


def row_filters(quick: bool) -> List[Row]:
    """Return row 6: µs per update of EKF, UKF, pf (N = 1000, 2000, 5000), bootstrap-pf."""
    from kf_train.presets import load_preset
    from kf_train.sim import scenario_for_preset
    preset = load_preset('range-bearing')
    scenario = scenario_for_preset('range-bearing', 0)
    repeats = 1 if quick else 5
    times = [(kind, overrides, _seconds_per_row(preset, kind, overrides, scenario, repeats))
             for kind, overrides in CASES]
    ukf = next(seconds for kind, _, seconds in times if kind == 'ukf')
    rows = []
    for kind, overrides, seconds in times:
        case = kind + (f", N = {overrides['particles']}" if overrides else '')
        rows.append(('6', 'range-bearing update', case, f'{seconds * 1e6:.4g} µs per update',
                     f'{seconds / ukf:.2f}× the UKF', 'reported vs UKF (issue 14)'))
    return rows
