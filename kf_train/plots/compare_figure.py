"""
The figure of ``kf-train compare``: position RMSE and ANEES (with its χ² bounds) over time.

``comparison`` is a :class:`kf_train.evaluate.Comparison`.
"""

from kf_train.evaluate import Comparison
from kf_train.plots.figures import new_figure
import numpy as np


def comparison_figure(comparison: Comparison):
    """Return the figure: position RMSE and ANEES (with its 99% bounds) against time."""
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
