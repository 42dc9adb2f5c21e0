"""
Floor 2, the presets: named, fully specified filters, and their loader.

Every seed tutorial is a preset YAML beside this file that reproduces the seed's
numbers exactly (docs/presets.md); :func:`load_preset` builds one, on top of
:mod:`kf_train.filters` only. The rail preset (:mod:`.rail`, docs/rail.md), an IMM of
four regimes, has its own reader, :func:`load_rail_preset`.
"""

from kf_train.presets.loader import (
    available_presets, ControlMatrix, DtExpression, Dynamics, load_preset, load_preset_file,
    MOTIONS, Preset, PRESET_DIR, preset_from_mapping, PRESET_NAMES, preset_path)
from kf_train.presets.rail import (
    is_rail_preset_file, load_rail_preset, rail_preset_from_mapping, RAIL_PRESET_NAME,
    RAIL_PRESET_PATH, RailPreset, SPEED_COLUMN, SPEED_VARIANCE_COLUMN)
from kf_train.presets.structure import INITIALIZATIONS, is_constant_velocity, measured_states

__all__ = [
    'available_presets', 'ControlMatrix', 'DtExpression', 'Dynamics', 'load_preset',
    'load_preset_file', 'MOTIONS', 'Preset', 'PRESET_DIR', 'preset_from_mapping',
    'PRESET_NAMES', 'preset_path', 'is_rail_preset_file', 'load_rail_preset',
    'RAIL_PRESET_NAME', 'RAIL_PRESET_PATH', 'rail_preset_from_mapping', 'RailPreset',
    'SPEED_COLUMN', 'SPEED_VARIANCE_COLUMN',
    'INITIALIZATIONS', 'is_constant_velocity', 'measured_states',
]
