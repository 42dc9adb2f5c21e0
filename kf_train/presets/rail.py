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
from typing import Any, Mapping, NamedTuple, Optional

from kf_train.filters import MODE_NAMES, RailModelParameters, STATE_NAMES
from kf_train.presets.loader import PRESET_DIR

RAIL_PRESET_PATH = os.path.join(PRESET_DIR, 'rail.yaml')
_KEYS = {'name', 'description', 'notes', 'filter', 'model', 'states', 'measurements', 'modes',
         'R', 'nominal_period_s', 'horizon_s', 'parameters'}


class RailPreset(NamedTuple):
    """The rail preset as read from its file."""

    name: str
    description: str
    parameters: RailModelParameters
    nominal_period_s: float
    horizon_s: Optional[float]
    source: str


def load_rail_preset(path: str = RAIL_PRESET_PATH) -> RailPreset:
    """Return the rail preset in a YAML file; errors name the file and the key."""
    import yaml
    try:
        with open(path, encoding='utf-8') as stream:
            data = yaml.safe_load(stream)
    except OSError as error:
        raise ValueError(f'{path}: cannot read: {error.strerror}') from None
    except yaml.YAMLError as error:
        raise ValueError(f'{path}: not valid YAML: {" ".join(str(error).split())}') from None
    try:
        return rail_preset_from_mapping(data, path)
    except ValueError as error:
        raise ValueError(f'{path}: {error}') from None


def _positive(key: str, value) -> float:
    """Return a finite number > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"'{key}' must be a number > 0, got {value!r}")
    return float(value)


def rail_preset_from_mapping(data: Mapping[str, Any], source: str = '<mapping>') -> RailPreset:
    """Return the rail preset a mapping (the parsed YAML) describes."""
    if not isinstance(data, Mapping):
        raise ValueError(f'a preset must be a mapping of keys, got {type(data).__name__}')
    unknown = sorted(str(k) for k in data if k not in _KEYS)
    if unknown:
        raise ValueError(f"unknown key '{unknown[0]}'; the keys are {', '.join(sorted(_KEYS))}")
    expected = {'filter': 'imm', 'model': 'rail_regimes', 'states': list(STATE_NAMES),
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
