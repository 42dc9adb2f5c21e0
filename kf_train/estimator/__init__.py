"""
Floor 3, the streaming estimator: stamped measurements and controls in, estimates out.

:class:`StreamEstimator` runs any 1-D preset, and the rail preset's IMM, on a stream,
with the input contract,
out-of-sequence replay, controls, the χ² gate and resets (see
:mod:`kf_train.estimator.estimator`). Built on :mod:`kf_train.filters` and
:mod:`kf_train.presets` only; other floors import from here.
"""

from kf_train.estimator.contract import (
    CONTROL_REJECTION_REASONS, EstimateStep, EstimatorStats, Rejected, REJECTION_REASONS,
    RESET_REASONS, VELOCITY_REJECTION_REASONS)
from kf_train.estimator.estimator import StreamEstimator
from kf_train.estimator.live_presets import (
    check_live_preset, covariance_from_list, covariance_to_list, is_rail, LINEAR_LIVE_PRESETS,
    LIVE_CONTROLS, LIVE_MEASUREMENTS, LIVE_PRESETS, LIVE_STATES, LivePreset, preset_defaults,
    resolve_preset)
from kf_train.estimator.settings import (
    DEFAULT_GATE_PROBABILITY, DEFAULT_PRESET, EstimatorSettings, FILTER_SETTINGS,
    GATE_PROBABILITY_RANGE, HISTORY_S_RANGE, INITIALIZATIONS, LOCKOUT_ACTIONS,
    MAX_CONSECUTIVE_OUTLIERS_RANGE,
    MAX_FUTURE_S_RANGE, PF_PARTICLES_RANGE, PF_RESAMPLE_THRESHOLD_RANGE, PF_SEED_RANGE,
    RAIL_FILTER_KINDS, RESTART_AFTER_STALE_RANGE, SEED_SWITCH, UKF_ALPHA_RANGE, UKF_BETA_RANGE,
    UKF_KAPPA_RANGE)
from kf_train.filters import NS_PER_S, seconds_to_ns

__all__ = [
    'check_live_preset', 'CONTROL_REJECTION_REASONS', 'covariance_from_list',
    'DEFAULT_GATE_PROBABILITY', 'DEFAULT_PRESET',
    'covariance_to_list', 'EstimateStep', 'EstimatorSettings', 'EstimatorStats',
    'FILTER_SETTINGS', 'GATE_PROBABILITY_RANGE', 'HISTORY_S_RANGE', 'INITIALIZATIONS', 'is_rail',
    'LINEAR_LIVE_PRESETS', 'LIVE_CONTROLS', 'LIVE_MEASUREMENTS', 'LIVE_PRESETS', 'LIVE_STATES',
    'LivePreset', 'LOCKOUT_ACTIONS', 'MAX_CONSECUTIVE_OUTLIERS_RANGE', 'MAX_FUTURE_S_RANGE',
    'NS_PER_S',
    'PF_PARTICLES_RANGE', 'PF_RESAMPLE_THRESHOLD_RANGE', 'PF_SEED_RANGE', 'preset_defaults',
    'RAIL_FILTER_KINDS', 'Rejected', 'REJECTION_REASONS', 'RESET_REASONS', 'resolve_preset',
    'RESTART_AFTER_STALE_RANGE', 'seconds_to_ns', 'SEED_SWITCH', 'StreamEstimator',
    'UKF_ALPHA_RANGE', 'UKF_BETA_RANGE', 'UKF_KAPPA_RANGE', 'VELOCITY_REJECTION_REASONS',
]
