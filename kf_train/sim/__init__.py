"""
Floor 3, simulation: the truth, the seeds' scenarios, live streams, faults, baselines.

:class:`TrainSimulation` is seed 000's train; :func:`scenario_for_preset` gives each
shipped preset its seed scenario (truth plus seeded noise); :func:`make_stream` the
simulator node's live streams (:data:`SCENARIOS`, the rail run of
:mod:`~kf_train.sim.rail` among them, :mod:`~kf_train.sim.rail_stream`); the rail
scoring (:mod:`~kf_train.sim.rail_eval`) and its hindsight-tuned CV/CA baselines
(:mod:`~kf_train.sim.rail_baselines`); :class:`FaultInjector` its seeded
faults; :mod:`~kf_train.sim.baselines` the seeds' naive estimators;
runs drawn from the rail IMM itself (:func:`sample_rail_model`); the rail scenario's GNSS
receiver error model (:mod:`~kf_train.sim.gnss_receiver`,
:mod:`~kf_train.sim.gnss_error`);
:func:`white_noise_acceleration_scenario` a train under random force with known q and
R (the data of the noise-estimation tests). Built on
:mod:`kf_train.filters` and :mod:`kf_train.presets` only.
"""

from kf_train.sim import baselines
from kf_train.sim.baselines import extrapolate, raw_difference_velocity, running_average
from kf_train.sim.faults import Delivery, FAULT_STREAM, FaultInjector, FaultSettings
from kf_train.sim.gnss_receiver import (
    DEFAULT_GNSS_MODEL, GNSS_MODELS, GnssFix, GnssReceiver, GnssReceiverParameters,
    structure_function)
from kf_train.sim.noise_simulation import white_noise_acceleration_scenario
from kf_train.sim.rail import DEFAULT_FAMILY as DEFAULT_RAIL_FAMILY
from kf_train.sim.rail import FAMILIES as RAIL_FAMILY_RANGES
from kf_train.sim.rail import (
    family_parameters, rail_run, rail_scenario, RailParameters, RailRun)
from kf_train.sim.rail_baselines import PolynomialKF, tuned_baselines, TunedBaseline
from kf_train.sim.rail_eval import HORIZON_S as RAIL_HORIZON_S
from kf_train.sim.rail_eval import Score, Track, WARMUP_S as RAIL_WARMUP_S
from kf_train.sim.rail_eval import score as score_predictions
from kf_train.sim.rail_model_sample import sample_rail_model
from kf_train.sim.rail_stream import RAIL_FAMILIES, rail_parameters, RailStream
from kf_train.sim.sample import ScenarioSample
from kf_train.sim.scenario_streams import (
    ACCELERATION_SCENARIOS, CAR_ACCELERATION_MPS2, CarStream, CONTROL_NAMES,
    DEFAULT_INITIAL_STATE, DEFAULT_NOISE_STD_M,
    make_stream, ROBOT_SPEED_STD_MPS, RobotStream, SCENARIOS, TrainStream)
from kf_train.sim.scenarios import (
    car_scenario, cv_position_scenario, cv_position_velocity_scenario, PRESET_SCENARIOS,
    range_bearing_scenario, robot_position_m, robot_scenario, Scenario, scenario_for_preset,
    train_scenario)
from kf_train.sim.simulation import TrainSample, TrainSeries, TrainSimulation

__all__ = [
    'ACCELERATION_SCENARIOS', 'DEFAULT_GNSS_MODEL', 'DEFAULT_RAIL_FAMILY', 'GNSS_MODELS',
    'GnssFix', 'GnssReceiver', 'GnssReceiverParameters', 'structure_function',
    'PolynomialKF', 'RAIL_FAMILIES',
    'RAIL_FAMILY_RANGES',
    'RAIL_HORIZON_S', 'rail_parameters', 'rail_run', 'rail_scenario', 'RAIL_WARMUP_S',
    'RailParameters', 'RailRun', 'RailStream', 'sample_rail_model', 'Score',
    'score_predictions', 'Track',
    'tuned_baselines', 'TunedBaseline', 'baselines', 'CAR_ACCELERATION_MPS2', 'car_scenario',
    'CarStream', 'CONTROL_NAMES',
    'cv_position_scenario', 'cv_position_velocity_scenario', 'DEFAULT_INITIAL_STATE',
    'DEFAULT_NOISE_STD_M', 'Delivery', 'extrapolate', 'FAULT_STREAM', 'FaultInjector',
    'FaultSettings', 'family_parameters', 'make_stream', 'PRESET_SCENARIOS',
    'range_bearing_scenario',
    'raw_difference_velocity', 'ROBOT_SPEED_STD_MPS', 'robot_position_m', 'robot_scenario',
    'RobotStream', 'running_average', 'Scenario', 'scenario_for_preset', 'ScenarioSample',
    'SCENARIOS', 'train_scenario', 'TrainSample', 'TrainSeries', 'TrainSimulation',
    'TrainStream', 'white_noise_acceleration_scenario',
]
