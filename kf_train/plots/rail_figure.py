"""
The rail demo's figure: a stop seen by the estimator, and its regime probabilities.

Four panels on one PNG (matplotlib's Agg canvas through
:func:`kf_train.plots.figures.new_figure`; no pyplot):

1. Around the stop: distance still to go to the stopping point, true and estimated,
   and the position predicted ``horizon_s`` earlier for each time with its ±2σ band.
2. The error of those predictions against the truth, inside its own ±2σ band: an
   honest band holds the error ~95 % of the time.
3. Velocity, true and estimated (±2σ), around the stop.
4. The regime probabilities over the whole run, the true stops shaded.

``series`` is a :class:`kf_train.cli.demo_rail.RailSeries` (any object with its
fields: the demo is a command, a floor above), ``run`` the exact truth
(:class:`kf_train.sim.RailRun`).
"""

from kf_train.plots.figures import new_figure, save
import numpy as np

BEFORE_ARRIVAL_S = 30.0
"""The stop panels start this long before the train stops [s]."""
AFTER_ARRIVAL_S = 15.0
"""... and end this long after [s] (or at the last estimate)."""
REGIME_COLOURS = {'stand': 'tab:red', 'accelerate': 'tab:green', 'cruise': 'tab:blue',
                  'brake': 'tab:orange'}


def rail_figure(path: str, series, run, stop, horizon_s: float) -> str:
    """Draw the figure (see the module doc) into ``path``; return the path."""
    arrival = float(stop[0])
    figure, axes = new_figure(4, 1, size=(9.0, 11.0))
    t = series.estimate_t_s
    window = (t >= arrival - BEFORE_ARRIVAL_S) & (t <= arrival + AFTER_ARRIVAL_S)
    stop_position = float(run.state_at(arrival).position_m)
    _stop_panels(axes[:3], series, run, window, stop_position, horizon_s)
    for ax in axes[:3]:
        ax.axvline(arrival, color='0.5', linestyle=':', linewidth=1.0)
        ax.set_xlim(arrival - BEFORE_ARRIVAL_S, arrival + AFTER_ARRIVAL_S + horizon_s)
    _regime_panel(axes[3], series, run)
    figure.suptitle(f'Rail run over DDS: the estimator with its defaults (a stop at '
                    f't = {arrival:.1f} s)')
    return save(figure, path)


def _stop_panels(axes, series, run, window, stop_position: float, horizon_s: float) -> None:
    """Draw distance to go, prediction error and velocity around the stop."""
    t = series.estimate_t_s[window]
    truth = run.state_at(t)
    target = t + horizon_s
    predicted = series.prediction[window, 0]
    two_sigma = 2.0 * np.sqrt(np.maximum(series.prediction[window, 1], 0.0))
    ax = axes[0]
    ax.plot(t, stop_position - truth.position_m, 'k-', label='truth')
    ax.plot(t, stop_position - series.estimate[window, 0], 'b.', markersize=3,
            label='estimate')
    ax.fill_between(target, stop_position - predicted - two_sigma,
                    stop_position - predicted + two_sigma, color='tab:orange', alpha=0.3,
                    label=f'{horizon_s:g}-s prediction ±2σ (at its target time)')
    ax.plot(target, stop_position - predicted, color='tab:orange', linewidth=1.0)
    ax.set_ylabel('distance to the stop [m]')
    ax.legend(loc='upper right', fontsize=8)
    ax = axes[1]
    inside = target <= run.end_s
    error = predicted[inside] - run.state_at(target[inside]).position_m
    ax.fill_between(target[inside], -two_sigma[inside], two_sigma[inside], color='tab:orange',
                    alpha=0.3, label='±2σ of the prediction')
    ax.plot(target[inside], error, 'k-', linewidth=1.0,
            label=f'{horizon_s:g}-s prediction − truth')
    ax.axhline(0.0, color='0.5', linewidth=0.5)
    ax.set_ylabel('prediction error [m]')
    ax.legend(loc='upper right', fontsize=8)
    ax = axes[2]
    velocity_2sigma = 2.0 * np.sqrt(np.maximum(series.estimate[window, 3], 0.0))
    ax.plot(t, truth.velocity_mps, 'k-', label='truth')
    ax.plot(t, series.estimate[window, 1], 'b-', linewidth=1.0, label='estimate')
    ax.fill_between(t, series.estimate[window, 1] - velocity_2sigma,
                    series.estimate[window, 1] + velocity_2sigma, color='tab:blue', alpha=0.2,
                    label='estimate ±2σ')
    ax.set_ylabel('velocity [m/s]')
    ax.set_xlabel('time [s]')
    ax.legend(loc='upper right', fontsize=8)


def _regime_panel(ax, series, run) -> None:
    """Draw the regime probabilities over the run, the true stops shaded."""
    t = series.estimate_t_s
    for start, end in run.stops:
        ax.axvspan(start, min(end, t[-1]), color='0.85', linewidth=0)
    for k, name in enumerate(series.regime_names):
        ax.plot(t, series.regimes[:, k], color=REGIME_COLOURS.get(name), linewidth=1.2,
                label=name)
    if not series.regime_names:
        ax.text(0.5, 0.5, 'the estimator has no regimes', ha='center',
                transform=ax.transAxes)
    else:
        ax.legend(loc='center right', fontsize=8)
    ax.set_xlim(t[0], t[-1])
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel('regime probability')
    ax.set_xlabel('time [s] (grey: the train stands)')
