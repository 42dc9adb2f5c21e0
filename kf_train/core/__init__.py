"""
The old flat core's public API, re-exported for one release: import from the floors.

kf_train.core was 20 flat modules; they now live in :mod:`kf_train.filters`,
:mod:`kf_train.presets`, :mod:`kf_train.estimator`, :mod:`kf_train.batch`,
:mod:`kf_train.sim` and :mod:`kf_train.io` (README, "The floors"). This module only
re-exports what ``kf_train.core`` exported, under the same names; ``TrainEstimator``
is :class:`kf_train.estimator.StreamEstimator`, kept under its old name here and
nowhere else. Nothing inside kf_train imports this module; it goes in the next release.
"""

from kf_train.estimator import EstimateStep, EstimatorSettings, StreamEstimator
from kf_train.filters import (
    constant_velocity_F, constant_velocity_model, ConstantVelocityModel, KalmanFilter,
    LinearModel, PerStepNoise, POSITION_H, predict, update, UpdateResult,
    WhiteNoiseAcceleration)
from kf_train.sim import TrainSample, TrainSeries, TrainSimulation

TrainEstimator = StreamEstimator
"""The old name of :class:`kf_train.estimator.StreamEstimator` (it runs every preset)."""

__all__ = [
    'ConstantVelocityModel', 'EstimateStep', 'LinearModel', 'EstimatorSettings', 'KalmanFilter',
    'PerStepNoise', 'POSITION_H', 'StreamEstimator', 'TrainEstimator', 'TrainSample',
    'TrainSeries', 'TrainSimulation', 'UpdateResult', 'WhiteNoiseAcceleration',
    'constant_velocity_F', 'constant_velocity_model', 'predict', 'update',
]
