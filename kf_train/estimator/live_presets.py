"""
Which presets the live estimator runs, and what a preset contributes to its settings.

A preset is named (a shipped one) or given as the path of a YAML file; files are read
again only when they change. :func:`resolve_preset` raises ``ValueError`` naming
``preset`` for anything the live estimator cannot run (:func:`check_live_preset`).
Besides the 1-D linear presets it runs the rail preset (``rail``, or a YAML file with
``model: rail_regimes``): a :class:`~kf_train.presets.RailPreset`, the four-regime IMM
of docs/rail.md.
"""

import os
from typing import Dict, Sequence, Tuple, Union

from kf_train.filters import as_covariance, as_vector
from kf_train.presets import (
    is_rail_preset_file, load_preset, load_preset_file, load_rail_preset, Preset, PRESET_NAMES,
    RAIL_PRESET_NAME, RailPreset)
import numpy as np

LivePreset = Union[Preset, RailPreset]
"""What the live estimator runs: a linear 1-D preset or the rail preset."""

LIVE_STATES = (('position', 'velocity'), ('position',))
"""State names a live preset may have: 1-D constant velocity, or position alone."""
LIVE_MEASUREMENTS = (('position',), ('position', 'velocity'))
"""Measurement names a live preset may have."""
LIVE_CONTROLS = ((), ('acceleration',), ('velocity',))
"""Control names a live preset may have (at most one: acceleration or velocity)."""
LIVE_PRESETS = ('rail', 'train', 'car', 'car-exact', 'robot', 'robot-exact', 'cv-position',
                'cv-position-velocity')
"""The shipped presets the live estimator runs (range-bearing is 2-D: offline only)."""
LINEAR_LIVE_PRESETS = LIVE_PRESETS[1:]
"""Those that are one linear model (every filter kind runs them): all but rail."""

_PRESET_CACHE: Dict[Tuple[str, int], LivePreset] = {}


def covariance_from_list(name: str, values: Sequence[float], dim: int) -> np.ndarray:
    """Return a covariance from its diagonal (dim values) or row-major entries (dim²)."""
    flat = as_vector(name, values)
    if flat.shape[0] == dim:
        return as_covariance(name, np.diag(flat), dim)
    if flat.shape[0] == dim * dim:
        return as_covariance(name, flat.reshape(dim, dim), dim)
    raise ValueError(
        f'{name} must have {dim} (diagonal) or {dim * dim} (full) entries, '
        f'got {flat.shape[0]}')


def covariance_to_list(P: np.ndarray) -> Tuple[float, ...]:
    """Return a covariance as covariance_from_list takes it: the diagonal if P is diagonal."""
    P = np.asarray(P, dtype=float)
    if np.count_nonzero(P - np.diag(np.diag(P))) == 0:
        return tuple(float(v) for v in np.diag(P))
    return tuple(float(v) for v in P.ravel())


def resolve_preset(spec: str) -> LivePreset:
    """
    Return the preset ``spec`` names: a shipped one, or a YAML file (a path).

    A value ending in .yaml/.yml or containing a path separator is a file; one with
    ``model: rail_regimes`` is read as a rail preset. Files are read again only when
    they change. Raises ValueError naming ``preset``.
    """
    if not isinstance(spec, str) or not spec:
        raise ValueError(f'preset must be a preset name or a YAML file, got {spec!r}')
    is_file = spec.endswith(('.yaml', '.yml')) or os.sep in spec or '/' in spec
    if not is_file and spec not in PRESET_NAMES + (RAIL_PRESET_NAME,):
        raise ValueError(f"preset must be one of {', '.join(LIVE_PRESETS)} or the path of a "
                         f'preset YAML file, got {spec!r}')
    try:
        key = (spec, os.stat(spec).st_mtime_ns if is_file else 0)
    except OSError as error:
        raise ValueError(f'preset must be a readable file: {spec}: {error.strerror}') from None
    if key not in _PRESET_CACHE:
        try:
            preset = _load(spec, is_file)
        except ValueError as error:
            raise ValueError(f'preset must be a valid preset file: {error}') from None
        check_live_preset(preset)
        if len(_PRESET_CACHE) > 32:
            _PRESET_CACHE.clear()
        _PRESET_CACHE[key] = preset
    return _PRESET_CACHE[key]


def _load(spec: str, is_file: bool) -> LivePreset:
    """Return the preset of a name or a file (a rail preset by name or by its model key)."""
    if spec == RAIL_PRESET_NAME:
        return load_rail_preset()
    if not is_file:
        return load_preset(spec)
    return load_rail_preset(spec) if is_rail_preset_file(spec) else load_preset_file(spec)


def check_live_preset(preset: LivePreset) -> None:
    """
    Raise ValueError unless the live estimator can run ``preset``.

    A rail preset runs (it is checked when read). Any other needs a linear model of
    a 1-D position (states [position, velocity] or [position]), measuring the
    position (and optionally the velocity), with at most one control named
    acceleration [m/s²] or velocity [m/s], and with process noise that does not
    depend on the dt's history (any preset file qualifies).
    """
    if isinstance(preset, RailPreset):
        return
    problems = []
    if not preset.linear:
        problems.append('its measurement model is not linear')
    if preset.state_names not in LIVE_STATES:
        problems.append(f'its states are {list(preset.state_names)}, not [position, '
                        'velocity] or [position]')
    if preset.measurement_names not in LIVE_MEASUREMENTS:
        problems.append(f'it measures {list(preset.measurement_names)}, not [position] or '
                        '[position, velocity]')
    if preset.control_names not in LIVE_CONTROLS:
        problems.append(f'its controls are {list(preset.control_names)}, not none, '
                        '[acceleration] or [velocity]')
    if problems:
        raise ValueError(f'preset must be a 1-D preset for the live estimator; '
                         f'{preset.name!r} cannot run live: {"; ".join(problems)} '
                         '(use kf-train replay for it)')


def preset_defaults(spec: str) -> Dict[str, object]:
    """Return the settings a preset supplies: initial state and covariance, period, horizon."""
    preset = resolve_preset(spec)
    return {
        'initial_state': tuple(float(v) for v in preset.initial_state),
        'initial_covariance': covariance_to_list(preset.initial_covariance),
        'nominal_period_s': float(preset.nominal_period_s),
        'horizon_s': float(preset.horizon_s or 0.0),
    }


def is_rail(preset: LivePreset) -> bool:
    """Return whether ``preset`` is a rail preset (an IMM of regimes)."""
    return isinstance(preset, RailPreset)
