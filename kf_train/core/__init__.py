"""kf_train's pure-Python core: numpy only, no ROS imports."""

from kf_train.estimator.estimator import EstimateStep, EstimatorSettings, TrainEstimator
from kf_train.filters.kalman import KalmanFilter, predict, update, UpdateResult
from kf_train.filters.models import (
    constant_velocity_F, constant_velocity_model, ConstantVelocityModel, LinearModel,
    PerStepNoise, POSITION_H, WhiteNoiseAcceleration)
from kf_train.sim.simulation import TrainSample, TrainSeries, TrainSimulation

__all__ = [
    'ConstantVelocityModel', 'EstimateStep', 'LinearModel', 'EstimatorSettings', 'KalmanFilter',
    'PerStepNoise', 'POSITION_H', 'TrainEstimator', 'TrainSample', 'TrainSeries',
    'TrainSimulation', 'UpdateResult', 'WhiteNoiseAcceleration', 'constant_velocity_F',
    'constant_velocity_model', 'predict', 'update',
]
