"""
The Monte-Carlo scores of a filter comparison: RMSE, NEES and ANEES against its χ² bounds.

:func:`summarise` turns one filter's runs (squared position errors and NEES per row)
into a :class:`FilterSummary`; a :class:`Comparison` holds every filter's, as
:func:`kf_train.evaluate.compare.run_comparison` measures them, and
:func:`write_curves` writes its per-row curves as CSV. The χ² quantiles are
:mod:`kf_train.filters.chi2`'s (no scipy).
"""

from typing import Dict, List, NamedTuple, Optional, Tuple

from kf_train.filters import chi2_quantile
import numpy as np

CONFIDENCE = 0.99


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


def anees_bounds(runs: int, dim_x: int, confidence: float = CONFIDENCE) -> Tuple[float, float]:
    """Return the two-sided interval of ANEES over ``runs`` runs of a consistent filter."""
    tail = 0.5 * (1.0 - confidence)
    dof = runs * dim_x                       # runs·ANEES ~ χ²(runs·n)
    return chi2_quantile(tail, dof) / runs, chi2_quantile(1.0 - tail, dof) / runs


def summarise(kind, sq_errors, nees_rows, failed, seconds, steps, dim_x, rows,
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
