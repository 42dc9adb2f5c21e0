"""
Floor 6, figures: PNGs drawn on matplotlib's Agg canvas (no pyplot, no display).

matplotlib (the extra ``[plot]``) is imported when a figure is made
(:func:`new_figure`), so importing this package does not need it.

* :mod:`~kf_train.plots.figures`: the seeds' filters, a preset's scenario, a replay output;
* :mod:`~kf_train.plots.replay_figure`: a replay with a prediction (error against the
  later fix, regimes, NIS, the longest stop);
* :mod:`~kf_train.plots.rail`: the rail IMM over a stop and a whole run;
* :mod:`~kf_train.plots.rail_figure`: the rail demo's stop figure;
* :mod:`~kf_train.plots.compare_figure`: ``kf-train compare``'s RMSE and ANEES.
"""

from kf_train.plots.compare_figure import comparison_figure
from kf_train.plots.figures import (
    build_seed000_figures, measured_states, new_figure, preset_figure, replay_figure_paths,
    save, scenario_figures, seed000_figures, track_figure)
from kf_train.plots.rail import rail_figures, rail_track, RailTrack
from kf_train.plots.rail_figure import rail_figure

__all__ = [
    'build_seed000_figures', 'comparison_figure', 'measured_states', 'new_figure',
    'preset_figure', 'rail_figure', 'rail_figures', 'rail_track', 'RailTrack',
    'replay_figure_paths', 'save', 'scenario_figures', 'seed000_figures', 'track_figure',
]
