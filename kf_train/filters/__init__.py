"""
Floor 1, the filter mathematics: numpy only, no ROS, no command line.

Kalman predict/update in Joseph form (:mod:`.kalman`), the motion models and THE
white-noise Q(dt) (:mod:`.models`), the 2-state step in closed form
(:mod:`.closed_form`) and the filter built on it (:mod:`.fast`), the EKF
(:mod:`.ekf`), UKF (:mod:`.ukf`), particle filters (:mod:`.particle`, the bootstrap
one, and :mod:`.regularised_pf`, the one that tracks range-bearing), the χ²
distribution (:mod:`.chi2`), the input checks (:mod:`.validation`), time units
(:mod:`.units`), the family behind one interface (:mod:`.family`, make_filter), and
the model contract the streaming estimator runs (:mod:`.contract`, StepModel); the
rail IMM (:mod:`.rail_model`) and its compiled form (:mod:`.rail_fast`, whose numba
kernels, :mod:`.rail_kernels`, load on first use, as does the tuner's compiled
likelihood, :mod:`.rail_likelihood_kernel`). Other floors import from here, never
from the modules.
"""

import importlib

from kf_train.filters import closed_form, kalman
from kf_train.filters.chi2 import chi2_cdf, chi2_mean_bounds, chi2_quantile, chi2_sf
from kf_train.filters.closed_form import FastUpdate, noise_terms_function, NoiseModel
from kf_train.filters.contract import PredictThenUpdate, regime_columns, StepModel
from kf_train.filters.ekf import (
    ekf_update, ExtendedKalmanFilter, ExtendedModel, FunctionMeasurement, RangeBearing, TWO_PI,
    wrap_angle)
from kf_train.filters.error_walk import ErrorWalk, position_walked
from kf_train.filters.family import (
    check_kind, DEFAULT_PARTICLES, Filter, FILTER_KINDS, FilterOptions, gaussian_model,
    GaussianFilter, make_filter, PARTICLE_KINDS, ParticlePresetFilter)
from kf_train.filters.fast import FastRun, FastTrainFilter
from kf_train.filters.imm import (
    check_transition_matrix, combine, first_jump_row, FixedTransition, IMM, IMMFilter, IMMState,
    make_state, RateTransition)
from kf_train.filters.kalman import KalmanFilter, LOG_2PI, predict, update, UpdateResult
from kf_train.filters.models import (
    constant_velocity_F, constant_velocity_model, ConstantVelocityModel, LinearDynamicsModel,
    LinearModel, per_step_noise_terms, per_step_periods, per_step_weights, PerStepNoise,
    POSITION_H, ProcessNoise, white_noise_integrals, white_noise_terms,
    WhiteNoiseAcceleration)
from kf_train.filters.noise_adaptation import NoiseAdaptation, NoiseScale
from kf_train.filters.particle import (
    check_particles, check_seed, DEFAULT_RESAMPLE_THRESHOLD, log_normalise, MAX_PARTICLES,
    ParticleFilter, psd_factor, Snapshot, systematic_resample)
from kf_train.filters.rail_fast import (
    FastRailModel, jit_enabled, JIT_VARIABLE, numba_available, rail_model)
from kf_train.filters.rail_model import (
    bound_acceleration, hold_velocity, make_rail_filter, MODE_NAMES, moved_past, RailModel,
    RailModelParameters, STATE_NAMES, stop_probability, STOPPING)
from kf_train.filters.regularised_pf import (
    kernel_draws, KERNELS, optimal_bandwidth, regularisation_jitter, RegularisedParticleFilter,
    RegularisedSnapshot, tempering_step)
from kf_train.filters.ukf import (
    batch_measurement, BatchMeasurement, DEFAULT_ALPHA, DEFAULT_BETA, DEFAULT_KAPPA,
    keep_positive_definite, MerweScaledSigmaPoints, robust_cholesky, SquareRoot, Transformed,
    unscented_moments, unscented_predict, unscented_update, UnscentedModel)
from kf_train.filters.units import NS_PER_S, seconds_to_ns, seconds_to_ns_array
from kf_train.filters.validation import (
    as_covariance, as_duration, as_finite_array, as_matrix, as_non_negative, as_positive,
    as_scalar, as_vector, COVARIANCE_RTOL)

__all__ = [
    'as_covariance', 'as_duration', 'as_finite_array', 'as_matrix', 'as_non_negative',
    'as_positive', 'as_scalar', 'as_vector',
    'batch_measurement', 'BatchMeasurement', 'check_kind', 'check_particles', 'check_seed',
    'check_transition_matrix', 'chi2_cdf', 'chi2_mean_bounds', 'chi2_quantile', 'chi2_sf',
    'closed_form', 'combine', 'constant_velocity_F', 'constant_velocity_model',
    'ConstantVelocityModel', 'COVARIANCE_RTOL', 'DEFAULT_ALPHA', 'DEFAULT_BETA', 'DEFAULT_KAPPA',
    'DEFAULT_PARTICLES', 'DEFAULT_RESAMPLE_THRESHOLD', 'ekf_update', 'ErrorWalk',
    'ExtendedKalmanFilter', 'ExtendedModel', 'FastRailModel', 'FastRun', 'FastTrainFilter',
    'FastUpdate', 'Filter',
    'FILTER_KINDS', 'first_jump_row',
    'FilterOptions', 'FixedTransition', 'FunctionMeasurement', 'gaussian_model', 'GaussianFilter',
    'bound_acceleration', 'hold_velocity', 'IMM', 'IMMFilter', 'IMMState', 'jit_enabled',
    'JIT_VARIABLE', 'kalman',
    'KalmanFilter', 'keep_positive_definite',
    'kernel_draws', 'KERNELS', 'LOG_2PI', 'LinearDynamicsModel', 'LinearModel', 'log_normalise',
    'make_filter', 'make_rail_filter', 'make_state', 'MAX_PARTICLES', 'MerweScaledSigmaPoints',
    'NoiseAdaptation', 'NoiseScale', 'numba_available',
    'MODE_NAMES', 'moved_past', 'noise_terms_function', 'NoiseModel', 'NS_PER_S',
    'optimal_bandwidth',
    'PARTICLE_KINDS', 'ParticleFilter', 'ParticlePresetFilter', 'per_step_noise_terms',
    'position_walked',
    'per_step_periods', 'per_step_weights', 'PerStepNoise', 'POSITION_H', 'predict',
    'PredictThenUpdate',
    'ProcessNoise', 'psd_factor', 'rail_model', 'RailModel', 'RailModelParameters',
    'RangeBearing', 'RateTransition', 'regime_columns', 'regularisation_jitter',
    'RegularisedParticleFilter', 'RegularisedSnapshot',
    'robust_cholesky', 'seconds_to_ns', 'seconds_to_ns_array', 'Snapshot', 'SquareRoot',
    'STATE_NAMES', 'StepModel', 'stop_probability', 'STOPPING',
    'systematic_resample', 'tempering_step', 'Transformed', 'TWO_PI', 'unscented_moments',
    'unscented_predict', 'unscented_update', 'UnscentedModel', 'update', 'UpdateResult',
    'white_noise_integrals', 'white_noise_terms',
    'WhiteNoiseAcceleration', 'wrap_angle',
]

# numba compiles these on import (the jit extra): loaded on first use.
_LAZY = ('rail_kernels', 'rail_likelihood_kernel')


def __getattr__(name: str):
    """Import the compiled rail modules on first use (PEP 562): they need numba."""
    if name in _LAZY:
        return importlib.import_module(f'kf_train.filters.{name}')
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
