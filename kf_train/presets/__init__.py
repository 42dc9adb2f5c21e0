"""
Floor 2, the presets: named, fully specified filters, and their loader.

Every seed tutorial is a preset YAML beside this file that reproduces the seed's
numbers exactly (docs/presets.md); :func:`load_preset` builds one, on top of
:mod:`kf_train.filters` only.
"""

from kf_train.presets.loader import (
    available_presets, ControlMatrix, DtExpression, Dynamics, load_preset, load_preset_file,
    MOTIONS, Preset, PRESET_DIR, preset_from_mapping, PRESET_NAMES, preset_path)

__all__ = [
    'available_presets', 'ControlMatrix', 'DtExpression', 'Dynamics', 'load_preset',
    'load_preset_file', 'MOTIONS', 'Preset', 'PRESET_DIR', 'preset_from_mapping',
    'PRESET_NAMES', 'preset_path',
]
