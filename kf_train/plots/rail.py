"""
The rail IMM over a stop, its 2-s prediction and regimes (``kf-train plot --preset rail``).

A seeded metro-like rail run (:func:`kf_train.sim.rail_scenario`, σ = 1 m at 10 Hz)
is filtered row by row as the streaming estimator's default does
(:class:`kf_train.batch.RailSeriesFilter`), recording after every measurement the
estimate, the prediction 2 s ahead (the IMM's mixture moments) and the regime
probabilities. ``rail.png`` shows the window around the first station stop: the
position predicted 2 s earlier with its ±2σ band against the truth (as residuals
from the truth, which is kilometres long), the velocity estimate ±2σ against the
truth, and the regime probabilities (stand, accelerate, cruise, brake).
``rail_run.png`` shows the whole run: speed, and the 2-s prediction error with its
±2σ band.
"""

import dataclasses
import os
from typing import List, NamedTuple

from kf_train.batch import RailSeriesFilter
from kf_train.plots.figures import new_figure, save
from kf_train.presets import load_rail_preset
from kf_train.sim import family_parameters, rail_scenario
import numpy as np

RAIL_PLOT_S = 240.0
"""Length of the plotted run [s]."""
HORIZON_S = 2.0
WINDOW_S = (-40.0, 25.0)
"""The close-up: from 40 s before the first stop to 25 s after the arrival."""
MODE_COLOURS = ('tab:gray', 'tab:green', 'tab:blue', 'tab:red')


class RailTrack(NamedTuple):
    """What the rail IMM did over a run, row by row."""

    t_s: np.ndarray
    x: np.ndarray
    P: np.ndarray
    predicted_x: np.ndarray
    """The prediction made at t_s for t_s + 2 s (N, 6)."""
    predicted_P: np.ndarray
    probabilities: np.ndarray
    """Regime probabilities after each row (N, 4)."""
    mode_names: tuple


def rail_track(scenario, horizon_s: float = HORIZON_S) -> RailTrack:
    """Filter a rail scenario from its first measurement; record everything plotted."""
    filt = RailSeriesFilter(load_rail_preset())
    t, z = scenario.t_s, scenario.z[:, 0]
    N, n = t.shape[0], filt.preset.dim_x
    x, P = np.empty((N, n)), np.empty((N, n, n))
    ahead, ahead_P = np.empty((N, n)), np.empty((N, n, n))
    mu = np.empty((N, len(filt.mode_names)))
    previous = None
    for k in range(N):
        if previous is not None:
            filt.predict(float(t[k] - previous))
        filt.update([float(z[k])])
        previous = t[k]
        x[k], P[k] = filt.mean, filt.covariance
        ahead[k], ahead_P[k] = filt.predict_ahead(horizon_s)
        mu[k] = filt.mode_probabilities
    return RailTrack(t.copy(), x, P, ahead, ahead_P, mu, filt.mode_names)


def rail_figures(output_dir: str, seed: int = 0) -> List[str]:
    """Simulate a metro rail run of ``seed``, filter it, write rail.png and rail_run.png."""
    params = dataclasses.replace(family_parameters('metro', seed), duration_s=RAIL_PLOT_S)
    scenario, run = rail_scenario(seed, 'metro', parameters=params)
    track = rail_track(scenario)
    t = track.t_s
    target = t + HORIZON_S
    truth_ahead = run.state_at(target).position_m
    truth = run.state_at(t)
    stops = [arrive for arrive, _ in run.stops if arrive > t[0] + 10.0]
    centre = stops[0] if stops else float(t[t.size // 2])
    window = (target >= centre + WINDOW_S[0]) & (target <= centre + WINDOW_S[1])
    figure, (ax_p, ax_v, ax_mu) = new_figure(3, 1, size=(9.0, 9.0))
    error = track.predicted_x[:, 0] - truth_ahead
    band = 2.0 * np.sqrt(track.predicted_P[:, 0, 0])
    ax_p.fill_between(target[window], -band[window], band[window], color='tab:blue',
                      alpha=0.25, label='±2σ of the 2-s prediction')
    ax_p.plot(target[window], error[window], color='tab:blue',
              label='2-s prediction − truth')
    ax_p.plot(t[window], (track.x[:, 0] - truth.position_m)[window], color='k',
              linewidth=0.8, label='estimate − truth')
    ax_p.axhline(0.0, color='0.5', linewidth=0.6)
    ax_p.set_ylabel('position error [m]')
    ax_p.set_title(f'rail preset, metro run (seed {seed}): the stop at t = {centre:.0f} s, '
                   'predicted 2 s ahead')
    ax_p.legend(loc='upper right', fontsize=8)
    v_band = 2.0 * np.sqrt(track.P[:, 1, 1])
    ax_v.fill_between(t[window], (track.x[:, 1] - v_band)[window],
                      (track.x[:, 1] + v_band)[window], color='tab:orange', alpha=0.3,
                      label='estimate ±2σ')
    ax_v.plot(t[window], truth.velocity_mps[window], color='k', linewidth=0.8,
              label='truth')
    ax_v.set_ylabel('velocity [m/s]')
    ax_v.legend(loc='upper right', fontsize=8)
    ax_mu.stackplot(t[window], track.probabilities[window].T, labels=track.mode_names,
                    colors=MODE_COLOURS, alpha=0.8)
    ax_mu.set_ylim(0.0, 1.0)
    ax_mu.set_xlabel('t [s]')
    ax_mu.set_ylabel('regime probability')
    ax_mu.legend(loc='upper right', fontsize=8, ncol=4)
    paths = [save(figure, os.path.join(output_dir, 'rail.png'))]
    whole, (ax_speed, ax_error) = new_figure(2, 1, size=(9.0, 6.5))
    ax_speed.plot(t, truth.velocity_mps, color='k', linewidth=0.8, label='truth')
    ax_speed.plot(t, track.x[:, 1], color='tab:orange', linewidth=0.8, label='estimate')
    ax_speed.set_ylabel('velocity [m/s]')
    ax_speed.set_title(f'rail preset over the whole run (seed {seed})')
    ax_speed.legend(loc='upper right', fontsize=8)
    scored = t >= t[0] + 10.0
    coverage = float(np.mean(np.abs(error[scored]) <= band[scored]))
    rmse = float(np.sqrt(np.mean(error[scored] ** 2)))
    ax_error.fill_between(target, -band, band, color='tab:blue', alpha=0.25, label='±2σ')
    ax_error.plot(target, error, color='tab:blue', linewidth=0.7,
                  label=f'2-s prediction − truth (RMSE {rmse:.2f} m, 2σ coverage '
                        f'{100 * coverage:.0f} % after 10 s)')
    ax_error.set_ylim(-6.0, 6.0)
    ax_error.set_xlabel('t [s]')
    ax_error.set_ylabel('position error [m]')
    ax_error.legend(loc='upper right', fontsize=8)
    paths.append(save(whole, os.path.join(output_dir, 'rail_run.png')))
    return paths
