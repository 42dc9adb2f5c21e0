"""
The figure of a replay with a prediction: where the prediction failed, and why.

``kf-train plot --replay OUT.csv`` draws this for an output with ``predicted_position``
and ``nis`` (the table replay of a preset with a horizon, train or rail; any bag
replay's CSV or output bag) instead of one panel per state. Four panels, time from the
first row in s (never epoch seconds):

1. the ``horizon_s`` prediction's error against the later fix (the measured position
   at t + horizon_s, from ``--input``: the replay's input table or bag; without it,
   against the later estimate), inside its ±2σ band (σ² = ``var_predicted_position``);
2. the regime probabilities ``p_<regime>`` (when the output has them);
3. the NIS, with its expected value 1 (one position per fix: χ²(1)) and the 95 %
   bounds of a single NIS and of its mean over a sliding window;
4. a zoom of panel 1 on the longest standstill (|velocity| below
   :data:`STANDSTILL_MPS` for at least :data:`MIN_STOP_S`), with the velocity; the
   panel says so when there is none.

:func:`replay_series` computes every plotted number (tested numerically); drawing
decimates long lines to at most :data:`MAX_DRAWN_POINTS` points, the statistics never.
"""

from typing import Dict, NamedTuple, Optional, Tuple

from kf_train.filters import chi2_mean_bounds, chi2_quantile
from kf_train.plots.figures import new_figure
import numpy as np

STANDSTILL_MPS = 0.2
"""A train slower than this [m/s] stands (for the zoom on a stop)."""
MIN_STOP_S = 10.0
"""The shortest standstill the zoom shows [s]."""
ZOOM_MARGIN_S = 60.0
"""The zoom shows this long before and after the standstill [s]."""
NIS_WINDOW = 50
"""Fixes in the NIS's sliding mean."""
MAX_DRAWN_POINTS = 4000
"""Longer lines are drawn decimated (every k-th point); statistics use every row."""
NIS_CONFIDENCE = 0.95


class ReplaySeries(NamedTuple):
    """The plotted numbers of a replay output; times from its first row [s]."""

    t_s: np.ndarray
    """Each row's time from the first row [s]."""
    error_m: np.ndarray
    """Each row's prediction minus the later fix (or estimate) [m]; NaN without one."""
    sigma_m: np.ndarray
    """The prediction's standard deviation [m]."""
    outside: float
    """The fraction of the rows with an error that fall outside ±2σ."""
    regimes: Dict[str, np.ndarray]
    """The regime probabilities by name (empty without regimes)."""
    nis: np.ndarray
    """Each row's NIS (NaN where it fused no measurement)."""
    nis_mean: np.ndarray
    """The sliding mean of the last NIS_WINDOW NIS values, at each row (NaN before)."""
    nis_bounds: Tuple[float, float]
    """The 95 % bounds of one NIS (χ²(1))."""
    nis_mean_bounds: Tuple[float, float]
    """The 95 % bounds of the mean of NIS_WINDOW NIS values."""
    stop: Optional[Tuple[float, float]]
    """The longest standstill (start, end) [s from the first row], or None."""
    velocity_mps: np.ndarray
    """The estimated velocity [m/s]."""
    against: str
    """What the error is taken against: 'fix' or 'estimate'."""


def later_values(t_s: np.ndarray, times_s: np.ndarray, values: np.ndarray,
                 horizon_s: float, tolerance_s: float) -> np.ndarray:
    """Return the value at t + horizon_s for each t: the nearest within tolerance, else NaN."""
    keep = np.isfinite(values)
    times_s, values = times_s[keep], values[keep]
    out = np.full(t_s.shape[0], np.nan)
    if not times_s.size:
        return out
    target = t_s + horizon_s
    right = np.clip(np.searchsorted(times_s, target), 1, times_s.size - 1) \
        if times_s.size > 1 else np.zeros(t_s.shape[0], dtype=int)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(times_s[left] - target) <= np.abs(times_s[right] - target),
                       left, right)
    close = np.abs(times_s[nearest] - target) <= tolerance_s
    out[close] = values[nearest[close]]
    return out


def longest_standstill(t_s: np.ndarray, velocity_mps: np.ndarray
                       ) -> Optional[Tuple[float, float]]:
    """Return the longest (start, end) with |velocity| < STANDSTILL_MPS, if >= MIN_STOP_S."""
    still = np.abs(velocity_mps) < STANDSTILL_MPS
    if not still.any():
        return None
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    lengths = t_s[ends] - t_s[starts]
    best = int(np.argmax(lengths))
    if lengths[best] < MIN_STOP_S:
        return None
    return float(t_s[starts[best]]), float(t_s[ends[best]])


def sliding_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Return the mean of the last ``window`` finite values at each row (NaN before)."""
    finite = np.isfinite(values)
    count = np.cumsum(finite)
    total = np.cumsum(np.where(finite, values, 0.0))
    out = np.full(values.shape[0], np.nan)
    index = np.flatnonzero(finite & (count >= window))
    if index.size:
        # The row where the window's first value is: the (count - window)-th finite one.
        positions = np.flatnonzero(finite)
        first = positions[count[index] - window]
        before = np.where(first > 0, total[np.maximum(first - 1, 0)], 0.0)
        out[index] = (total[index] - before) / window
    return out


def replay_series(columns: Dict[str, np.ndarray], horizon_s: float,
                  fixes: Optional[Tuple[np.ndarray, np.ndarray]] = None) -> ReplaySeries:
    """
    Return the plotted numbers of a replay output's ``columns`` (by name, full length).

    ``fixes``: (times [s], positions [m]) measured, on the output's clock; None takes
    the later estimate instead. A fix counts for t + horizon_s when within half the
    fixes' median period.
    """
    t = np.asarray(columns['t'], dtype=float)
    if fixes is None:
        times, values, against = t, np.asarray(columns['position'], dtype=float), 'estimate'
    else:
        times, values = (np.asarray(a, dtype=float) for a in fixes)
        order = np.argsort(times, kind='stable')
        times, values, against = times[order], values[order], 'fix'
    period = float(np.median(np.diff(times))) if times.size > 1 else 0.0
    later = later_values(t, times, values, horizon_s, 0.5 * period)
    error = np.asarray(columns['predicted_position'], dtype=float) - later
    sigma = np.sqrt(np.asarray(columns['var_predicted_position'], dtype=float))
    scored = np.isfinite(error)
    outside = float(np.mean(np.abs(error[scored]) > 2.0 * sigma[scored])) \
        if scored.any() else float('nan')
    regimes = {name[2:]: np.asarray(values, dtype=float)
               for name, values in columns.items() if name.startswith('p_')}
    nis = np.asarray(columns.get('nis', np.full(t.shape[0], np.nan)), dtype=float)
    tail = 0.5 * (1.0 - NIS_CONFIDENCE)
    velocity = np.asarray(columns['velocity'], dtype=float)
    t_rel = t - t[0] if t.size else t
    return ReplaySeries(
        t_rel, error, sigma, outside, regimes, nis, sliding_mean(nis, NIS_WINDOW),
        (chi2_quantile(tail, 1), chi2_quantile(1.0 - tail, 1)),
        chi2_mean_bounds(NIS_WINDOW, 1, NIS_CONFIDENCE), longest_standstill(t_rel, velocity),
        velocity, against)


def drawn(count: int) -> slice:
    """Return the rows a line of ``count`` points is drawn with (every k-th)."""
    return slice(None, None, max(1, -(-count // MAX_DRAWN_POINTS)))


def replay_figure(title: str, series: ReplaySeries, horizon_s: float):
    """Return the four-panel figure of a replay (module doc)."""
    figure, axes = new_figure(4, 1, size=(11.0, 12.0))
    figure.suptitle(title)
    s = series
    _error_panel(axes[0], s, horizon_s, drawn(s.t_s.shape[0]))
    axes[1].set_title('regime probabilities (stacked)' if s.regimes
                      else 'no regimes in this output')
    if s.regimes:   # stacked areas: a 98-minute run of crossing lines reads as noise
        rows = drawn(s.t_s.shape[0])
        axes[1].stackplot(s.t_s[rows], *[values[rows] for values in s.regimes.values()],
                          labels=list(s.regimes), linewidth=0)
    axes[1].set_ylim(0.0, 1.0)
    axes[1].set_ylabel('probability [-]')
    if s.regimes:
        axes[1].legend(loc='upper right', ncol=len(s.regimes), fontsize='small')
    _nis_panel(axes[2], s)
    _zoom_panel(axes[3], s, horizon_s)
    for ax in axes:
        ax.set_xlabel('time from start [s]')
        ax.grid(True, alpha=0.3)
    return figure


def _error_panel(ax, s: ReplaySeries, horizon_s: float, rows: slice) -> None:
    """Draw the prediction error inside its ±2σ band."""
    t = s.t_s[rows]
    ax.fill_between(t, -2.0 * s.sigma_m[rows], 2.0 * s.sigma_m[rows], color='tab:blue',
                    alpha=0.25, linewidth=0, label='±2σ of the prediction')
    ax.plot(t, s.error_m[rows], color='k', linewidth=0.7,
            label=f'{horizon_s:g}-s prediction − later {s.against}')
    ax.set_ylabel('prediction error [m]')
    # The start's wide prior band would flatten the rest: limit to the 99.5th percentile.
    size = np.fmax(np.abs(s.error_m), 2.0 * s.sigma_m)
    if np.isfinite(size).any():
        limit = 1.2 * float(np.nanpercentile(size, 99.5))
        ax.set_ylim(-limit, limit)
    ax.set_title(f'{horizon_s:g}-s prediction against the later {s.against}: '
                 f'{100.0 * s.outside:.1f} % outside ±2σ (≈5 % if the band is honest)')
    ax.legend(loc='upper right', fontsize='small')


def _nis_panel(ax, s: ReplaySeries) -> None:
    """Draw the NIS, its sliding mean and their bounds."""
    rows = drawn(s.t_s.shape[0])
    ax.semilogy(s.t_s[rows], s.nis[rows], '.', color='0.5', markersize=2, label='NIS')
    ax.semilogy(s.t_s[rows], s.nis_mean[rows], color='tab:purple', linewidth=1.0,
                label=f'mean of {NIS_WINDOW}')
    ax.axhline(1.0, color='k', linewidth=0.8, label='expected 1 (χ²(1))')
    for bound in s.nis_bounds:
        ax.axhline(bound, color='0.5', linestyle=':', linewidth=0.8)
    for bound in s.nis_mean_bounds:
        ax.axhline(bound, color='tab:purple', linestyle='--', linewidth=0.8)
    ax.set_ylabel('NIS [-]')
    ax.set_title('NIS: dotted, 95 % of one NIS; dashed, 95 % of the mean')
    ax.legend(loc='upper right', ncol=3, fontsize='small')


def _zoom_panel(ax, s: ReplaySeries, horizon_s: float) -> None:
    """Draw the prediction error and the velocity around the longest standstill."""
    if s.stop is None:
        ax.set_title(f'no standstill (|v| < {STANDSTILL_MPS:g} m/s for {MIN_STOP_S:g} s) '
                     'to zoom on')
        ax.set_ylabel('prediction error [m]')
        return
    start, end = s.stop
    window = (s.t_s >= start - ZOOM_MARGIN_S) & (s.t_s <= end + ZOOM_MARGIN_S)
    zoom = s._replace(t_s=s.t_s[window], error_m=s.error_m[window],
                      sigma_m=s.sigma_m[window])
    _error_panel(ax, zoom, horizon_s, drawn(int(window.sum())))
    ax.set_title(f'the longest standstill, {start:.0f}-{end:.0f} s ({end - start:.0f} s)')
    ax.axvspan(start, end, color='tab:red', alpha=0.08)
    speed = ax.twinx()
    speed.plot(s.t_s[window], s.velocity_mps[window], color='tab:green', linewidth=0.8)
    speed.set_ylabel('velocity [m/s]', color='tab:green')
