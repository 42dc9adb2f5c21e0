"""
Floor 5, evaluation: the filter family compared on seeded Monte-Carlo runs.

* :mod:`~kf_train.evaluate.compare`: :func:`run_comparison` over a preset's seed
  scenarios (the rail IMM's over rail runs: :mod:`~kf_train.evaluate.compare_rail`);
* :mod:`~kf_train.evaluate.scores`: RMSE, NEES and ANEES with its χ² bounds;
* :mod:`~kf_train.evaluate.later_fix`: the 2-s prediction scored against the later
  fix (real logs, which have no truth).
"""

from kf_train.evaluate.compare import (
    DEFAULT_COMPARE_PARTICLES, default_kinds, DEFAULT_RUNS, INITIAL_MODES, position_indices,
    run_comparison)
from kf_train.evaluate.compare_rail import run_rail_comparison
from kf_train.evaluate.later_fix import (
    errors as later_fix_errors, later_fix, LaterFixErrors, LaterFixScore, MATCH_TOLERANCE_S,
    MAX_BRACKET_S, score as later_fix_score)
from kf_train.evaluate.scores import (
    anees_bounds, Comparison, CONFIDENCE, derived_seed, FilterSummary, nees, summarise,
    write_curves)

__all__ = [
    'anees_bounds', 'Comparison', 'CONFIDENCE', 'DEFAULT_COMPARE_PARTICLES', 'DEFAULT_RUNS',
    'default_kinds', 'derived_seed', 'FilterSummary', 'INITIAL_MODES', 'later_fix',
    'later_fix_errors', 'later_fix_score', 'LaterFixErrors', 'LaterFixScore',
    'MATCH_TOLERANCE_S', 'MAX_BRACKET_S', 'nees',
    'position_indices', 'run_comparison', 'run_rail_comparison', 'summarise', 'write_curves',
]
