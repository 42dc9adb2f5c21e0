"""
The rail preset: the rail IMM's figures as a YAML file (kf_train/presets/rail.yaml).

:func:`kf_train.presets.loader.load_preset` builds one linear model per preset
(F = I + dt·A with A² = 0, one process noise); the rail preset is an IMM of four
regimes whose motion is a first-order response, so it has its own keys and is read
here. Every key is checked and named in errors, as the preset loader does:

* ``name``, ``description``, [``notes``]: text;
* ``filter: imm`` and ``model: rail_regimes``: what this file describes;
* ``states``, ``measurements``, ``modes``: must be the rail model's (they document
  the columns and regime names);
* ``R``: [[σ²]], the position noise (RailModelParameters.noise_std_m = σ);
* ``nominal_period_s``, ``horizon_s``: as in every preset;
* ``parameters``: any fields of :class:`~kf_train.filters.rail_model.RailModelParameters`
  (the rest keep their defaults).
"""

import math
import os
from typing import Any, Mapping, NamedTuple, Optional, Tuple

from kf_train.filters import (
    MODE_NAMES, rail_model, RailModel, RailModelParameters, STATE_NAMES)
from kf_train.presets.loader import check_keys, PRESET_DIR, read_yaml_file
import numpy as np

RAIL_PRESET_NAME = 'rail'
RAIL_PRESET_PATH = os.path.join(PRESET_DIR, 'rail.yaml')
RAIL_MODEL_KEY = 'rail_regimes'
"""The value of ``model`` that marks a YAML file as a rail preset."""
_KEYS = {'name', 'description', 'notes', 'filter', 'model', 'states', 'measurements', 'modes',
         'R', 'nominal_period_s', 'horizon_s', 'parameters'}


SPEED_COLUMN = 'z_velocity'
"""The offline column of a measured speed along the track [m/s] (a GNSS Doppler)."""
SPEED_VARIANCE_COLUMN = 'var_' + SPEED_COLUMN
"""Its variance [m²/s²] (``var_<column>``, as the outputs name a variance)."""
SPEED_MEASUREMENTS = ('position', 'velocity', 'velocity_variance')


class RailPreset(NamedTuple):
    """
    The rail preset as read from its file.

    Besides its fields it answers what the tools ask a linear
    :class:`~kf_train.presets.Preset` (state, measurement and control names and
    counts, initial state and covariance, CSV columns), so the streaming estimator
    and the replay treat both alike; :meth:`model` builds the IMM.
    """

    name: str
    description: str
    parameters: RailModelParameters
    nominal_period_s: float
    horizon_s: Optional[float]
    source: str
    speed: bool = False
    """Offline with measured speeds (:meth:`with_speed`): each row holds a position, a
    speed and its variance (``z_position``, ``z_velocity``, ``var_z_velocity``), each
    cell may be empty."""

    linear = False
    """The motion is a mixture of regimes, not one linear model."""
    seed = ''
    """Not a seed tutorial."""
    notes = 'docs/rail.md'

    @property
    def state_names(self) -> Tuple[str, ...]:
        """Return [position, velocity, acceleration, commanded, capabilities A and B]."""
        return STATE_NAMES

    @property
    def measurement_names(self) -> Tuple[str, ...]:
        """Return ('position',), with speeds ('position', 'velocity', 'velocity_variance')."""
        return SPEED_MEASUREMENTS if self.speed else ('position',)

    @property
    def control_names(self) -> Tuple[str, ...]:
        """Return () (no control input)."""
        return ()

    @property
    def mode_names(self) -> Tuple[str, ...]:
        """Return the regimes: stand, accelerate, cruise, brake."""
        return MODE_NAMES

    @property
    def dim_x(self) -> int:
        """Return the number of states (6)."""
        return len(STATE_NAMES)

    @property
    def dim_z(self) -> int:
        """Return 1 (the position), with speeds 3 (position, speed, its variance)."""
        return len(self.measurement_names)

    @property
    def dim_u(self) -> int:
        """Return 0."""
        return 0

    @property
    def H(self) -> np.ndarray:
        """Return the measurement matrix [1, 0, 0, 0, 0, 0] (a new array)."""
        H = np.zeros((1, len(STATE_NAMES)))
        H[0, 0] = 1.0
        return H

    @property
    def R(self) -> np.ndarray:
        """Return the default position variance [[σ²]] (a new array)."""
        return np.array([[self.parameters.noise_std_m ** 2]])

    @property
    def initial_state(self) -> np.ndarray:
        """Return [0, 0, 0, 0, A, B]: standing at 0 with the prior capabilities."""
        params = self.parameters
        return np.array([0.0, 0.0, 0.0, 0.0, params.accelerate_mps2, params.brake_mps2])

    @property
    def initial_covariance(self) -> np.ndarray:
        """Return the covariance at a first position fix of variance σ² (its priors)."""
        return self.parameters.initial_covariance(self.parameters.noise_std_m ** 2)

    def measurement_columns(self) -> Tuple[Tuple[str, ...], ...]:
        """Return the CSV columns of the measurement: (('z_position',),), plus the speed's."""
        if self.speed:
            return (('z_position',), (SPEED_COLUMN,), (SPEED_VARIANCE_COLUMN,))
        return (('z_position',),)

    def with_speed(self) -> 'RailPreset':
        """Return this preset reading measured speeds too (offline: the speed's columns)."""
        return self._replace(speed=True)

    def control_columns(self) -> Tuple[str, ...]:
        """Return () (no control input)."""
        return ()

    def model(self, jit: Optional[bool] = None) -> RailModel:
        """Return the four-regime IMM of these parameters (compiled if ``jit``: rail_model)."""
        return rail_model(self.parameters, jit)

    @property
    def dynamics(self) -> 'MovingDynamics':
        """Return the moving regimes' transition (for series results; see MovingDynamics)."""
        return MovingDynamics(self.parameters)


class MovingDynamics(NamedTuple):
    """
    F(dt) of the rail model's moving regimes (the relaxation; A and B held).

    A series result carries each row's F for the RTS smoother; an IMM has no single
    F, so this is the moving regimes' (what stand does is F = diag(1, 0, 0, 0, 1, 1)),
    and the tools refuse to smooth the rail preset.
    """

    parameters: RailModelParameters

    def F_batch(self, dt_s) -> np.ndarray:
        """Return F for each dt: shape (k, 6, 6)."""
        moving = RailModel(self.parameters).modes[1]
        return np.array([moving.F(float(dt)) for dt in np.atleast_1d(dt_s)]).reshape(
            (-1, len(STATE_NAMES), len(STATE_NAMES)))


def load_rail_preset(path: str = RAIL_PRESET_PATH) -> RailPreset:
    """Return the rail preset in a YAML file; errors name the file and the key."""
    data = read_yaml_file(path)
    try:
        return rail_preset_from_mapping(data, path)
    except ValueError as error:
        raise ValueError(f'{path}: {error}') from None


def is_rail_preset_file(path: str) -> bool:
    """Return whether a YAML file says ``model: rail_regimes`` (False if unreadable)."""
    import yaml
    try:
        with open(path, encoding='utf-8') as stream:
            data = yaml.safe_load(stream)
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(data, Mapping) and data.get('model') == RAIL_MODEL_KEY


def _positive(key: str, value) -> float:
    """Return a finite number > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"'{key}' must be a number > 0, got {value!r}")
    return float(value)


def rail_preset_from_mapping(data: Mapping[str, Any], source: str = '<mapping>') -> RailPreset:
    """Return the rail preset a mapping (the parsed YAML) describes."""
    check_keys(data, _KEYS)
    expected = {'filter': 'imm', 'model': RAIL_MODEL_KEY, 'states': list(STATE_NAMES),
                'measurements': ['position'], 'modes': list(MODE_NAMES)}
    for key, value in expected.items():
        if data.get(key) != value:
            raise ValueError(f"'{key}' must be {value!r}, got {data.get(key)!r}")
    R = data.get('R')
    if not (isinstance(R, list) and len(R) == 1 and isinstance(R[0], list) and len(R[0]) == 1):
        raise ValueError(f"'R' must be [[variance]], got {R!r}")
    fields = data.get('parameters') or {}
    if not isinstance(fields, Mapping):
        raise ValueError(f"'parameters' must be a mapping, got {fields!r}")
    known = RailModelParameters.__dataclass_fields__
    for key in fields:
        if key not in known or key == 'noise_std_m':
            raise ValueError(f"unknown key 'parameters.{key}' (noise_std_m comes from R)")
    try:
        parameters = RailModelParameters(
            noise_std_m=math.sqrt(_positive('R', R[0][0])), **fields)
    except ValueError as error:
        raise ValueError(f'parameters: {error}') from None
    horizon = data.get('horizon_s')
    name = data.get('name')
    if not isinstance(name, str) or not name:
        raise ValueError(f"'name' must be text, got {name!r}")
    return RailPreset(name, str(data.get('description', '')), parameters,
                      _positive('nominal_period_s', data.get('nominal_period_s')),
                      None if horizon is None else _positive('horizon_s', horizon), source)
