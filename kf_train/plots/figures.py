"""
PNG figures of the seeds' filters and of a replay output, through matplotlib's Agg backend.

Figures are drawn on ``matplotlib.figure.Figure`` objects with an Agg canvas; pyplot
is never imported, so no display and no global figure state are involved, and the
functions are safe to call from a node or a test.

* :func:`seed000_figures`: seed 000's three figures (position; velocity with the raw
  difference and running-average baselines; the 2-s extrapolation from the last 10
  samples), with the filter's ±2σ band added to the Kalman curves.
* :func:`preset_figure`: for any preset, one panel per state: the estimate with its
  ±2σ band against the truth and the measurements (bearing and range are shown
  converted to x and y).
* :func:`track_figure`: the x-y track of the range-bearing preset.
* ``--preset rail``: :func:`kf_train.plots.rail.rail_figures`, the rail IMM over a
  station stop (its 2-s prediction band and regime probabilities) and a whole run.

:func:`scenario_figures` simulates a preset's seed scenario (:mod:`kf_train.sim.scenarios`)
and draws it, :func:`replay_figure_paths` a ``kf-train replay`` output CSV (with its
input for the measurements): ``kf-train plot`` (:mod:`kf_train.cli.plotting`). matplotlib
(the extra ``[plot]``) is imported when a figure is made.
"""

import csv
import os
from typing import Dict, List, Optional, Sequence

from kf_train.batch import run_series
from kf_train.estimator import DEFAULT_PRESET, resolve_preset
from kf_train.filters import as_duration, as_finite_array, as_vector, NS_PER_S, RangeBearing
from kf_train.io import header_names, ID_COLUMN, is_bag, read_table
from kf_train.presets import load_preset, Preset
from kf_train.sim import baselines, scenario_for_preset
import numpy as np

SEED000_HORIZON_S = 2.0
"""Seed 000 extrapolates SamplesIntoTheFuture = 20 samples of 0.1 s."""
SEED000_LAST_SAMPLES = 10
"""Nlast: the extrapolation uses the last 10 samples (11 buffer entries)."""
SEED000_WINDOW = 5
"""WindowSize of the running average."""
DPI = 100


def new_figure(rows: int = 1, cols: int = 1, size=(8.0, 5.0)):
    """Return (figure, axes list) on an Agg canvas; no pyplot, no display."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:  # pragma: no cover - the [plot] extra
        raise RuntimeError(
            "kf-train plot needs matplotlib: pip install 'kf_train[plot]'") from None
    figure = Figure(figsize=size, layout='constrained')
    FigureCanvasAgg(figure)
    axes = figure.subplots(rows, cols, squeeze=False)
    return figure, [ax for row in axes for ax in row]


def save(figure, path: str) -> str:
    """Write the figure as a PNG; return the path."""
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    figure.savefig(path, dpi=DPI, format='png')
    return path


def _band(ax, t, mean, var, color: str, label: str) -> None:
    """Plot a mean with a shaded ±2σ band."""
    sigma = np.sqrt(np.maximum(var, 0.0))
    ax.plot(t, mean, color=color, label=label)
    ax.fill_between(t, mean - 2.0 * sigma, mean + 2.0 * sigma, color=color, alpha=0.2,
                    linewidth=0.0, label=f'{label} ±2σ')


# ---------------------------------------------------------------------------
# Seed 000
# ---------------------------------------------------------------------------

def build_seed000_figures(t_s, measured_m, truth_m, x_hist, P_hist, dt_s) -> Dict[str, object]:
    """
    Return seed 000's three figures as {name: Figure}; see :func:`seed000_figures`.

    The seed's buffers hold the prior at t = 0 in front of the N samples (and a
    measurement of 0 there, which was never made). Here only the N samples are
    plotted; the baselines are still computed exactly as the seed does, from the
    buffer [0, z_1, …, z_N] (so their first values include the seed's artificial
    start), and then drawn at the sample times.
    """
    t = as_vector('t_s', t_s)
    N = t.shape[0]
    z = as_vector('measured_m', measured_m, N)
    truth = as_vector('truth_m', truth_m, N)
    x_hist = as_finite_array('x_hist', x_hist)
    P_hist = as_finite_array('P_hist', P_hist)
    if x_hist.shape != (N, 2):
        raise ValueError(f'x_hist must have shape ({N}, 2), got {x_hist.shape}')
    if P_hist.shape != (N, 2, 2):
        raise ValueError(f'P_hist must have shape ({N}, 2, 2), got {P_hist.shape}')
    dt_s = as_duration('dt_s', dt_s)
    if N < 2 or dt_s == 0.0:
        raise ValueError('seed 000 figures need at least 2 samples and dt_s > 0')
    figures = {}

    # Position: truth, measurements, Kalman estimate.
    figure, (ax,) = new_figure()
    ax.plot(t, truth, color='g', label='True position')
    ax.plot(t, z, color='c', label='Measurements')
    _band(ax, t, x_hist[:, 0], P_hist[:, 0, 0], 'm', 'Kalman estimated displacement')
    ax.set(title='Position estimation results', xlabel='Time (s)', ylabel='Position (m)')
    ax.legend(loc='best')
    figures['seed000_position'] = figure

    # Velocity: truth, raw difference, running average, Kalman.
    raw = baselines.raw_difference_velocity(z, dt_s)      # [0, (z1 − 0)/dt, …]: N + 1
    average = baselines.running_average(raw, SEED000_WINDOW)
    true_velocity = np.gradient(truth, t)
    figure, (ax,) = new_figure()
    ax.plot(t, true_velocity, color='m', label='True velocity')
    ax.plot(t, raw[1:], color='g', label='Estimated velocity by raw consecutive samples')
    ax.plot(t, average[1:], color='c', label='Estimated velocity by running average')
    _band(ax, t, x_hist[:, 1], P_hist[:, 1, 1], 'k', 'Estimated velocity by Kalman filter')
    ax.set(title='Velocity estimation results', xlabel='Time (s)', ylabel='Velocity (m/s)')
    ax.legend(loc='best')
    figures['seed000_velocity'] = figure

    figures['seed000_extrapolation'] = _extrapolation_figure(t, truth, x_hist, average, dt_s)
    return figures


def _extrapolation_figure(t, truth, x_hist, average, dt_s: float):
    """
    Return seed 000's figure of the extrapolation to t_N + 2 s from each of the last samples.

    As in the seed, both projections start from the Kalman position; the running
    average (N + 1 values, index 0 at t0) supplies only its velocity.
    """
    N = t.shape[0]
    ahead_samples = int(round(SEED000_HORIZON_S / dt_s))
    last = slice(max(0, N - SEED000_LAST_SAMPLES - 1), N)
    t_last = t[last]
    target_t = t[-1] + ahead_samples * dt_s
    ahead_s = target_t - t_last                          # (30:-1:20)·dt in the seed
    # The seed's truth is a straight line: extend it from its last two samples.
    true_future = truth[-1] + (truth[-1] - truth[-2]) / (t[-1] - t[-2]) * (target_t - t[-1])
    by_average = baselines.extrapolate(x_hist[last, 0], average[1:][last], ahead_s)
    by_kalman = baselines.extrapolate(x_hist[last, 0], x_hist[last, 1], ahead_s)
    figure, (ax,) = new_figure()
    ax.plot(t_last, np.full(t_last.shape, true_future), color='m', label='True position')
    ax.plot(t_last, by_average, color='c', label='Estimated position by running average')
    ax.plot(t_last, by_kalman, color='k', label='Estimated position by Kalman filter')
    ax.set(title=f'Extrapolation {ahead_samples} samples ahead (at t = {target_t:g})',
           xlabel='Time of sample used for extrapolation (s)',
           ylabel='Expected position (m)')
    ax.legend(loc='best')
    return figure


def seed000_figures(output_dir: str, t_s, measured_m, truth_m, x_hist, P_hist,
                    dt_s) -> List[str]:
    """
    Write seed 000's three figures as PNGs in ``output_dir``; return their paths.

    ``t_s`` (N,) are the sample times, ``measured_m`` and ``truth_m`` (N,) the measured
    and true positions, ``x_hist`` (N, 2) and ``P_hist`` (N, 2, 2) the filter's
    estimates at the samples, ``dt_s`` the sample period.
    """
    figures = build_seed000_figures(t_s, measured_m, truth_m, x_hist, P_hist, dt_s)
    return [save(figure, os.path.join(output_dir, name + '.png'))
            for name, figure in figures.items()]


# ---------------------------------------------------------------------------
# Any preset
# ---------------------------------------------------------------------------

def measured_states(preset: Preset, z: np.ndarray) -> Dict[int, np.ndarray]:
    """Return {state index: values} for the states the measurements show directly."""
    shown = {}
    measurement = getattr(preset.model, 'measurement', None)
    if isinstance(measurement, RangeBearing):
        bearing, distance = z[:, 0], z[:, 1]
        sx, sy = measurement.sensor_position_m
        shown[measurement.x_index] = sx + distance * np.cos(bearing)
        shown[measurement.y_index] = sy + distance * np.sin(bearing)
        return shown
    H = getattr(preset.model, 'H', None)
    if H is None:
        return shown
    for i, row in enumerate(H):
        nonzero = np.flatnonzero(row)
        if nonzero.size == 1 and row[nonzero[0]] == 1.0:
            shown[int(nonzero[0])] = z[:, i]
    return shown


def preset_figure(title: str, state_names: Sequence[str], t0_s: float, x0, P0, t_s, x, P,
                  truth=None, truth0=None, measured: Optional[Dict[int, np.ndarray]] = None,
                  smoothed=None):
    """
    Return a figure with one panel per state: estimate ±2σ, truth and measurements.

    The estimate starts at the prior (x0, P0) at t0_s when x0 is given; ``smoothed``
    is an optional (x, P) pair drawn dashed.
    """
    n = len(state_names)
    figure, axes = new_figure(n, 1, size=(8.0, 2.6 * n + 0.8))
    t_all = np.concatenate([[t0_s], t_s])
    for i, (ax, name) in enumerate(zip(axes, state_names)):
        if truth is not None:
            true_values = truth[:, i] if truth0 is None else np.concatenate(
                [[truth0[i]], truth[:, i]])
            ax.plot(t_s if truth0 is None else t_all, true_values, color='g', label='truth')
        if measured and i in measured:
            ax.plot(t_s, measured[i], '.', color='c', markersize=3, label='measurements')
        if x0 is None:
            _band(ax, t_s, x[:, i], P[:, i, i], 'm', 'estimate')
        else:
            _band(ax, t_all, np.concatenate([[x0[i]], x[:, i]]),
                  np.concatenate([[P0[i, i]], P[:, i, i]]), 'm', 'estimate')
        if smoothed is not None:
            xs, Ps = smoothed
            sigma = np.sqrt(np.maximum(Ps[:, i, i], 0.0))
            ax.plot(t_s, xs[:, i], '--', color='b', label='smoothed')
            ax.plot(t_s, xs[:, i] + 2 * sigma, ':', color='b', linewidth=0.8)
            ax.plot(t_s, xs[:, i] - 2 * sigma, ':', color='b', linewidth=0.8)
        ax.set_ylabel(name)
        ax.legend(loc='best', fontsize='small')
    axes[0].set_title(title)
    axes[-1].set_xlabel('Time (s)')
    return figure


def track_figure(title: str, x0, x, truth=None, truth0=None, measured_xy=None,
                 indices=(0, 2)):
    """Return the x-y track: truth, measurements (converted), estimate (from x0 if given)."""
    i, j = indices
    figure, (ax,) = new_figure(size=(7.0, 6.0))
    if truth is not None:
        ax.plot(truth[:, i], truth[:, j], color='r', label='True trajectory')
        if truth0 is not None:
            ax.plot(truth0[i], truth0[j], '*', color='r', label='Initial truth')
    if measured_xy is not None:
        ax.plot(measured_xy[0], measured_xy[1], '.', color='c', markersize=3,
                label='Measurements (converted)')
    if x0 is None:
        ax.plot(x[:, i], x[:, j], color='g', label='Estimated trajectory')
    else:
        ax.plot(np.concatenate([[x0[i]], x[:, i]]), np.concatenate([[x0[j]], x[:, j]]),
                color='g', label='Estimated trajectory')
        ax.plot(x0[i], x0[j], '*', color='g', label='Initial estimate')
    ax.set(title=title, xlabel='x (m)', ylabel='y (m)')
    ax.set_aspect('equal', adjustable='datalim')
    ax.legend(loc='best')
    return figure


def scenario_figures(output_dir: str, name: str, seed: int = 0) -> List[str]:
    """Simulate a shipped preset's seed scenario, filter it and write its figures."""
    preset = load_preset(name)
    scenario = scenario_for_preset(name, seed)
    result = run_series(preset, scenario.t_s, scenario.z, scenario.u, t0_s=scenario.t0_s,
                        horizon_s=0)
    measured = measured_states(preset, scenario.z)
    paths = [save(preset_figure(
        f'{name} (seed {preset.seed}): estimate ±2σ, truth and measurements',
        preset.state_names, scenario.t0_s, preset.initial_state, preset.initial_covariance,
        scenario.t_s, result.x, result.P, scenario.truth, scenario.truth0, measured),
        os.path.join(output_dir, f'{name}.png'))]
    measurement = getattr(preset.model, 'measurement', None)
    if isinstance(measurement, RangeBearing):
        indices = (measurement.x_index, measurement.y_index)
        paths.append(save(track_figure(
            'True trajectory vs estimated trajectory', preset.initial_state, result.x,
            scenario.truth, scenario.truth0, (measured[indices[0]], measured[indices[1]]),
            indices), os.path.join(output_dir, f'{name}_track.png')))
    if name == 'train':
        paths += seed000_figures(output_dir, scenario.t_s, scenario.z[:, 0],
                                 scenario.truth[:, 0], result.x, result.P,
                                 preset.nominal_period_s)
    return paths


# ---------------------------------------------------------------------------
# A replay output
# ---------------------------------------------------------------------------

def replay_figure_paths(output_dir: str, replay_csv: str, input_csv: Optional[str] = None,
                        t0_s: float = 0.0, horizon_s: Optional[float] = None) -> List[str]:
    """
    Draw a ``kf-train replay`` output (and its input's measurements); return paths.

    An output with ``predicted_position`` and ``nis`` (train, rail, a bag's) gets the figure of
    :mod:`kf_train.plots.replay_figure` (``input_csv`` may then be the replayed bag);
    ``horizon_s`` None is the estimator's default preset's.
    """
    if is_bag(replay_csv):      # a bag replay's output bag: its estimates, as its CSV's
        return [_prediction_figure(output_dir, replay_csv, None, input_csv, horizon_s)]
    header = _csv_header(replay_csv)
    if 'predicted_position' in header and 'nis' in header:
        return [_prediction_figure(output_dir, replay_csv, header, input_csv, horizon_s)]
    states = [c for c in header if c != 't' and not c.startswith(
        ('var_', 'predicted_', 'smoothed_')) and 'var_' + c in header]
    if not states:
        raise ValueError(f'{replay_csv}: no state columns with var_<state> found; is it a '
                         'kf-train replay output?')
    wanted = ['t'] + states + ['var_' + s for s in states]
    smoothed = all('smoothed_' + s in header for s in states)
    if smoothed:
        wanted += ['smoothed_' + s for s in states] + ['var_smoothed_' + s for s in states]
    table = read_table(replay_csv, [(c,) for c in wanted])
    col = table.columns
    N, n = table.rows, len(states)
    x = np.column_stack([col[s] for s in states]) if N else np.empty((0, n))
    P = np.zeros((N, n, n))
    for i, s in enumerate(states):
        P[:, i, i] = col['var_' + s]
    smooth_pair = None
    if smoothed:
        xs = np.column_stack([col['smoothed_' + s] for s in states])
        Ps = np.zeros((N, n, n))
        for i, s in enumerate(states):
            Ps[:, i, i] = col['var_smoothed_' + s]
        smooth_pair = (xs, Ps)
    measured = {}
    xy = None
    if input_csv is not None:
        in_header = _csv_header(input_csv)
        direct = [s for s in states if 'z_' + s in in_header]
        polar = ('z_bearing' in in_header and 'z_range' in in_header
                 and 'x' in states and 'y' in states)
        needed = [('t',)] + [('z_' + s,) for s in direct]
        needed += [('z_bearing',), ('z_range',)] if polar else []
        inputs = read_table(input_csv, needed)
        if inputs.rows != N or not np.array_equal(inputs.columns['t'], col['t']):
            raise ValueError(f'{input_csv} does not have the rows of {replay_csv}')
        for s in direct:
            measured[states.index(s)] = inputs.columns['z_' + s]
        if polar:
            b, r = inputs.columns['z_bearing'], inputs.columns['z_range']
            xy = (r * np.cos(b), r * np.sin(b))
            measured.setdefault(states.index('x'), xy[0])
            measured.setdefault(states.index('y'), xy[1])
    base = os.path.splitext(os.path.basename(replay_csv))[0]
    # A replay output has no row for the prior: the curves start at the first row.
    figure = preset_figure(f'{base}: estimate ±2σ', states, t0_s, None, None, col['t'], x, P,
                           measured=measured, smoothed=smooth_pair)
    paths = [save(figure, os.path.join(output_dir, base + '.png'))]
    if 'x' in states and 'y' in states and N:
        indices = (states.index('x'), states.index('y'))
        paths.append(save(track_figure(f'{base}: x-y track', None, x, measured_xy=xy,
                                       indices=indices),
                          os.path.join(output_dir, base + '_track.png')))
    return paths


def _prediction_figure(output_dir: str, replay_csv: str, header: Optional[List[str]],
                       input_path: Optional[str], horizon_s: Optional[float]) -> str:
    """Draw the prediction figure of a replay output (CSV, or bag: no header); return it."""
    from kf_train.plots.replay_figure import replay_figure, replay_series
    if horizon_s is None:
        horizon_s = resolve_preset(DEFAULT_PRESET).horizon_s
    if header is None:
        from kf_train.io import bagio_output
        columns = bagio_output.read_output_bag(replay_csv)
    else:
        columns = _number_columns(replay_csv, header)
    fixes = None
    if input_path is not None:
        fixes = _bag_fixes(input_path) if is_bag(input_path) else _table_fixes(input_path)
    base = os.path.splitext(os.path.basename(replay_csv.rstrip(os.sep)))[0]
    series = replay_series(columns, horizon_s, fixes)
    return save(replay_figure(f'{base}: where the prediction fails, and why', series,
                              horizon_s), os.path.join(output_dir, base + '.png'))


def _number_columns(path: str, header: List[str]) -> Dict[str, np.ndarray]:
    """Return a CSV's numeric columns by name (empty cells and 'nan' as NaN)."""
    try:
        with open(path, encoding='utf-8-sig', newline='') as stream:
            rows = list(csv.reader(stream))[1:]
    except OSError as error:
        raise ValueError(f'{path}: cannot read: {error.strerror}') from None
    columns = {}
    for index, name in enumerate(header):
        if name == ID_COLUMN:
            if len({row[index] for row in rows}) > 1:
                raise ValueError(f"{path}: several ids; plot one object's rows")
            continue
        try:
            columns[name] = np.array([float(row[index]) if row[index] else np.nan
                                      for row in rows])
        except (ValueError, IndexError) as error:
            raise ValueError(f'{path}: column {name!r}: {error}') from None
    if not rows:
        raise ValueError(f'{path}: no rows to draw')
    return columns


def _table_fixes(path: str):
    """Return (t [s], z_position [m]) of a replay input table."""
    header = _csv_header(path)
    if 'z_position' not in header:
        raise ValueError(f'{path}: no z_position column for the fixes')
    columns = _number_columns(path, header)
    return columns['t'], columns['z_position']


def _bag_fixes(path: str):
    """Return (stamps [s], positions [m]) of a bag's measurement topic (as replay reads)."""
    from kf_train.io import bagio
    stamps, positions = [], []
    with bagio.BagInput(path) as bag:
        for message in bag.messages():
            stamps.append(message.stamp_ns)
            positions.append(message.position_m)
    return np.array(stamps, dtype=np.int64) / NS_PER_S, np.array(positions)


def _csv_header(path: str) -> List[str]:
    """Return the column names of a CSV file."""
    try:
        with open(path, encoding='utf-8-sig', newline='') as stream:
            line = stream.readline()
    except OSError as error:
        raise ValueError(f'{path}: cannot read: {error.strerror}') from None
    return header_names(path, line.rstrip('\r\n'))
