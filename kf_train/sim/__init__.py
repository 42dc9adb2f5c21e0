"""
Floor 3, simulation: the truth, the seeds' scenarios, live streams, faults, baselines.

:class:`TrainSimulation` is seed 000's train; :func:`scenario_for_preset` gives each
shipped preset its seed scenario (truth plus seeded noise); :func:`make_stream` the
simulator node's live streams (:data:`SCENARIOS`); :class:`FaultInjector` its seeded
faults; :mod:`~kf_train.sim.baselines` the seeds' naive estimators;
:func:`white_noise_acceleration_scenario` a train under random force with known q and
R (the data of the noise-estimation tests). Built on
:mod:`kf_train.filters` and :mod:`kf_train.presets` only.
"""

from kf_train.sim import baselines
from kf_train.sim.baselines import extrapolate, raw_difference_velocity, running_average
from kf_train.sim.faults import Delivery, FAULT_STREAM, FaultInjector, FaultSettings
from kf_train.sim.noise_simulation import white_noise_acceleration_scenario
from kf_train.sim.rail import family_parameters, rail_run, rail_scenario, RailParameters, RailRun
from kf_train.sim.scenario_streams import (
    CAR_ACCELERATION_MPS2, CarStream, CONTROL_NAMES, DEFAULT_INITIAL_STATE, DEFAULT_NOISE_STD_M,
    make_stream, ROBOT_SPEED_STD_MPS, RobotStream, SCENARIOS, ScenarioSample, TrainStream)
from kf_train.sim.scenarios import (
    car_scenario, cv_position_scenario, cv_position_velocity_scenario, PRESET_SCENARIOS,
    range_bearing_scenario, robot_position_m, robot_scenario, Scenario, scenario_for_preset,
    train_scenario)
from kf_train.sim.simulation import TrainSample, TrainSeries, TrainSimulation

__all__ = [
    'baselines', 'CAR_ACCELERATION_MPS2', 'car_scenario', 'CarStream', 'CONTROL_NAMES',
    'cv_position_scenario', 'cv_position_velocity_scenario', 'DEFAULT_INITIAL_STATE',
    'DEFAULT_NOISE_STD_M', 'Delivery', 'extrapolate', 'FAULT_STREAM', 'FaultInjector',
    'FaultSettings', 'family_parameters', 'make_stream', 'rail_run', 'rail_scenario',
    'RailParameters', 'RailRun', 'PRESET_SCENARIOS', 'range_bearing_scenario',
    'raw_difference_velocity', 'ROBOT_SPEED_STD_MPS', 'robot_position_m', 'robot_scenario',
    'RobotStream', 'running_average', 'Scenario', 'scenario_for_preset', 'ScenarioSample',
    'SCENARIOS', 'train_scenario', 'TrainSample', 'TrainSeries', 'TrainSimulation',
    'TrainStream', 'white_noise_acceleration_scenario',
]
