"""
What a preset's model is, read from its names and matrices: one home for both floors.

:data:`INITIALIZATIONS` are the two ways a preset's filter starts, live or in the fit.

The live estimator's settings (:mod:`kf_train.estimator.settings`) and the noise fit
(:mod:`kf_train.batch.noise_likelihood`) ask the same two questions of a preset, a
:class:`~kf_train.presets.Preset` or a :class:`~kf_train.presets.RailPreset`.
"""

from typing import Optional, Tuple, Union

from kf_train.presets.loader import Preset
from kf_train.presets.rail import RailPreset
import numpy as np

INITIALIZATIONS = ('first_measurement', 'prior')
"""How a filter starts: from the first measurement, or from the preset's prior (x0, P0)."""


def is_constant_velocity(preset: Union[Preset, RailPreset]) -> bool:
    """Return whether the states are [position, velocity], F = [[1, dt], [0, 1]]: q applies."""
    return (preset.state_names == ('position', 'velocity')
            and np.array_equal(preset.dynamics.A, [[0.0, 1.0], [0.0, 0.0]]))


def measured_states(preset: Union[Preset, RailPreset]) -> Optional[Tuple[int, ...]]:
    """Return, per measurement, the state it measures when H selects states; else None."""
    # The rail preset's H is its own (building its model to read H would be wasted).
    H = preset.H if isinstance(preset, RailPreset) else preset.model.H
    indices = []
    for row in H:
        hits = np.flatnonzero(row)
        if hits.size != 1 or row[hits[0]] != 1.0:
            return None
        indices.append(int(hits[0]))
    return tuple(indices) if len(set(indices)) == len(indices) else None
