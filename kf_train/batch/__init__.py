"""
Floor 3, batch paths: whole series at once, each tested against the row-by-row reference.

:func:`run_series` and :func:`run_filter_series` filter row by row (the reference);
:func:`run_linear_series` vectorises a linear preset along time; :func:`run_bank`
filters many objects (rows tagged by id) as a vectorised bank, the one engine for many
objects at once; :func:`rts_smooth` / :func:`smooth_series` smooth.
:class:`RailSeriesFilter` runs the rail preset's IMM row by row, started by the first
measurement; :func:`rail_log_likelihoods` is its IMM likelihood for many noise settings in
one pass, which ``kf-train tune --preset rail`` maximises (its innovations too).
:class:`StreamingReplay` filters a table of any length in fixed blocks (bounded
memory), :func:`filter_table` the same on arrays, :func:`filter_partition` one Dask
partition.
:class:`TuningProblem` is the exact likelihood of a noise setting (the innovations of
the estimator node's filter, run as :func:`run_linear_series`), which ``kf-train tune``
maximises over a :class:`NoiseParameterisation`; :func:`nis_consistency` and
:func:`prediction_errors` check a setting; :class:`RunningNoiseEstimate` suggests q from
a stream's recent window (numpy only, for the node's diagnostics).
Built on :mod:`kf_train.filters` and :mod:`kf_train.presets` only.
"""

from kf_train.batch.affine import affine_recursion
from kf_train.batch.bank import (
    bank_time_steps, group_rows, Groups, LOCKSTEP_STEP_S, run_bank, SERIES_CALL_S,
    TimeOrderError)
from kf_train.batch.chunked import (
    DEFAULT_BLOCK_ROWS, Estimates, output_header, OutputBlock, resolve_horizon, RowError, Rows)
from kf_train.batch.linear import CONVERGED_ULPS, predict_ahead, run_linear_series
from kf_train.batch.noise_checks import (
    ConsistencyReport, nis_consistency, prediction_errors, PredictionReport, whitened)
from kf_train.batch.noise_likelihood import (
    Innovations, make_segment, NoiseSetting, noisy_preset, Segment, STATE_UNITS,
    TuningProblem, VARIANCE_PARAMETERS)
from kf_train.batch.noise_parameters import (
    LikelihoodProblem, NoiseParameterisation, Parameter, Parameterisation, VARIANCE_UNITS)
from kf_train.batch.noise_suggestion import NoiseSuggestion, RunningNoiseEstimate
from kf_train.batch.partition import filter_partition, partition_meta
from kf_train.batch.rail_likelihood import (
    rail_log_likelihoods, RAIL_NOISE_FIELDS, RailLikelihoods, RailNoise)
from kf_train.batch.rail_series import RailSeriesFilter
from kf_train.batch.series import (
    MAX_ABS_TIME_S, run_filter_series, run_series, SeriesError, SeriesResult, time_steps_s)
from kf_train.batch.smoother import (
    rts_smooth, smooth_series, SmootherResult, VECTORISED_MAX_STATES)
from kf_train.batch.stream import filter_table, GapsFound, StreamingReplay
# The measured-state helpers live in presets/ (the live estimator asks them too).
from kf_train.presets import is_constant_velocity, measured_states

__all__ = [
    'RailSeriesFilter', 'RAIL_NOISE_FIELDS',
    'rail_log_likelihoods', 'RailLikelihoods', 'RailNoise',
    'affine_recursion', 'bank_time_steps', 'ConsistencyReport', 'CONVERGED_ULPS',
    'DEFAULT_BLOCK_ROWS', 'Estimates', 'filter_partition',
    'filter_table', 'GapsFound', 'group_rows', 'Groups', 'Innovations',
    'is_constant_velocity', 'LikelihoodProblem', 'LOCKSTEP_STEP_S', 'make_segment',
    'MAX_ABS_TIME_S', 'measured_states', 'nis_consistency', 'NoiseParameterisation',
    'NoiseSetting', 'NoiseSuggestion', 'noisy_preset', 'output_header', 'OutputBlock',
    'Parameter', 'Parameterisation', 'partition_meta', 'predict_ahead', 'prediction_errors',
    'PredictionReport', 'resolve_horizon', 'RowError', 'Rows', 'rts_smooth', 'run_bank',
    'run_filter_series', 'run_linear_series', 'run_series', 'RunningNoiseEstimate', 'Segment',
    'SERIES_CALL_S', 'SeriesError', 'SeriesResult', 'smooth_series', 'SmootherResult',
    'STATE_UNITS', 'StreamingReplay', 'time_steps_s', 'TimeOrderError',
    'TuningProblem', 'VARIANCE_PARAMETERS', 'VARIANCE_UNITS',
    'VECTORISED_MAX_STATES', 'whitened',
]
