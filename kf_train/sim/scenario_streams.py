"""
The seeds' 1-D scenarios as sample-by-sample streams, for the simulator node.

:mod:`kf_train.sim.scenarios` draws a whole series at once; a live simulator needs
one sample at a time, for as long as it runs. These streams follow the same truth
models. Sample k (k = 1, 2, …) is taken at t_k = k·dt (dt = 1 / rate_hz) and carries
the control of the interval (t_{k-1}, t_k] that ends at it (the seeds' convention:
docs/presets.md), or None.

* ``train`` (seed 000): :class:`kf_train.sim.simulation.TrainSimulation`,
  x(t) = x0 + v·t.
* ``car`` / ``car-exact`` (seed 001): the seed's random walk driven by a commanded
  acceleration u, x_k = F(dt) x_{k-1} + B(dt) u + w_k, with F, B and Q(dt) of the
  ``car`` / ``car-exact`` preset (B = [0, dt], the seed's, or [dt²/2, dt]; w ~ N(0,
  Q(dt)), Q(0.1 s) = diag(0, 0.05)); the control is u. At dt = 0.1 s, x0 = [0.2, 0],
  u = 1 and σ = 1 the stream gives exactly the numbers of
  ``scenarios.car_scenario(seed)`` (same generator, same order of draws).
* ``robot`` / ``robot-exact`` (seed 002): x(t) = x0 + 0.05·t·cos(2t) (x0 = 0 in the
  seed). A speed sensor reads the mean velocity over the interval ending at sample k,
  (x_k − x_{k−1}) / dt, plus N(0, σ_s²) (at t = 0 it reads 0 + noise); a range finder
  measures z_k = x_k − N(0, σ²) (the seed's sign). ``robot``'s control for
  (t_{k-1}, t_k] is the reading taken at t_{k-1}, as the seed applies it (u(i-1));
  ``robot-exact``'s is the reading of that interval itself, taken at t_k. Streamed
  noise is drawn sample by sample (speed, then range), so it is not the series
  ``scenarios.robot_scenario`` draws all at once.
* ``rail`` (issue 11): :class:`kf_train.sim.rail_stream.RailStream`, a jerk-limited
  run through stations (accelerate, cruise, slow zones, brake, dwell), starting at a
  station; its values drawn by ``rail_family`` from the seed unless given (``rail``:
  the keyword arguments of :func:`kf_train.sim.rail_stream.rail_parameters`). Its
  samples carry the true acceleration. ``gnss_model`` (in ``rail``) measures the
  position with white noise ('white', the default here) or with the GNSS receiver
  of :mod:`kf_train.sim.gnss_receiver` ('receiver': hAcc², Doppler speed and
  speedAcc² on each sample, no position at an epoch without a fix).
"""

from typing import Mapping, Optional

from kf_train.filters import as_non_negative, as_positive, as_scalar
from kf_train.presets import load_preset
from kf_train.sim.rail_stream import DEFAULT_FAMILY, rail_parameters, RailStream
from kf_train.sim.sample import ScenarioSample
from kf_train.sim.scenarios import robot_position_m
from kf_train.sim.simulation import TrainSimulation
import numpy as np

SCENARIOS = ('train', 'car', 'car-exact', 'robot', 'robot-exact', 'rail')
"""The scenarios a stream (and the simulator node) can run."""
CONTROL_NAMES = {'train': None, 'car': 'acceleration', 'car-exact': 'acceleration',
                 'robot': 'velocity', 'robot-exact': 'velocity', 'rail': None}
"""Each scenario's control: acceleration [m/s²], velocity [m/s], or None."""
ACCELERATION_SCENARIOS = ('rail',)
"""The scenarios whose samples carry the true acceleration."""
DEFAULT_NOISE_STD_M = {'train': 1.0, 'car': 1.0, 'car-exact': 1.0, 'robot': 0.03,
                       'robot-exact': 0.03, 'rail': 1.0}
"""Each scenario's measurement noise σ [m] (the seeds': R = 1, robot R = 0.03²)."""
DEFAULT_INITIAL_STATE = {'train': (0.0, 10.0), 'car': (0.2, 0.0), 'car-exact': (0.2, 0.0),
                         'robot': (0.0, 0.0), 'robot-exact': (0.0, 0.0), 'rail': (0.0, 0.0)}
"""Each scenario's (initial position m, velocity m/s); the robot's velocity follows x(t),
the rail run starts standing."""
CAR_ACCELERATION_MPS2 = 1.0
"""Seed 001's commanded acceleration."""
ROBOT_SPEED_STD_MPS = 0.2
"""Seed 002's speed sensor σ."""


def _sqrt_psd(Q: np.ndarray) -> np.ndarray:
    """Return L with L Lᵀ = Q: sqrt of the diagonal when Q is diagonal (as the seed draws)."""
    if np.count_nonzero(Q - np.diag(np.diag(Q))) == 0:
        return np.diag(np.sqrt(np.diag(Q)))
    w, V = np.linalg.eigh(Q)
    return V * np.sqrt(np.clip(w, 0.0, None))


class CarStream:
    """Seed 001's car: a random walk under a commanded acceleration, position measured."""

    def __init__(self, rate_hz: float, seed: Optional[int], noise_std_m: float = 1.0,
                 initial_position_m: float = 0.2, initial_velocity_mps: float = 0.0,
                 acceleration_mps2: float = CAR_ACCELERATION_MPS2, exact: bool = False):
        """Set up the truth x0 = [position, velocity] and the seeded generator."""
        self.rate_hz = as_positive('rate_hz', rate_hz)
        self.noise_std_m = as_non_negative('noise_std_m', noise_std_m)
        self.acceleration_mps2 = as_scalar('acceleration_mps2', acceleration_mps2)
        dynamics = load_preset('car-exact' if exact else 'car').dynamics
        dt = 1.0 / self.rate_hz
        self._F = dynamics.F(dt)
        self._Bu = dynamics.control(dt)[:, 0] * self.acceleration_mps2
        self._L = _sqrt_psd(dynamics.Q(dt))
        self._x = np.array([as_scalar('initial_position_m', initial_position_m),
                            as_scalar('initial_velocity_mps', initial_velocity_mps)])
        self._rng = np.random.default_rng(seed)
        self._index = 0

    def next_sample(self) -> ScenarioSample:
        """Advance one period and return the sample."""
        self._index += 1
        # x_k = F x_{k-1} + B u + w_k, w ~ N(0, Q(dt)); then z = x + σ·n
        noise = self._L @ self._rng.standard_normal(2)
        self._x = self._F @ self._x + self._Bu + noise
        z = self._x[0] + self.noise_std_m * self._rng.standard_normal()
        return ScenarioSample(self._index, self._index / self.rate_hz, float(self._x[0]),
                              float(self._x[1]), float(z), self.acceleration_mps2)


class RobotStream:
    """Seed 002's robot: x = x0 + 0.05·t·cos(2t), a range finder and a noisy speed sensor."""

    def __init__(self, rate_hz: float, seed: Optional[int], noise_std_m: float = 0.03,
                 initial_position_m: float = 0.0,
                 speed_noise_std_mps: float = ROBOT_SPEED_STD_MPS, seed_lag: bool = True):
        """Set up the trajectory, the sensors and the seeded generator."""
        self.rate_hz = as_positive('rate_hz', rate_hz)
        self.noise_std_m = as_non_negative('noise_std_m', noise_std_m)
        self.speed_noise_std_mps = as_non_negative('speed_noise_std_mps', speed_noise_std_mps)
        self.initial_position_m = as_scalar('initial_position_m', initial_position_m)
        self.seed_lag = bool(seed_lag)
        self._rng = np.random.default_rng(seed)
        self._index = 0
        # The reading at t = 0: the seed's [0, diff(x)/dt] starts with 0, plus noise.
        self._last_reading = self.speed_noise_std_mps * self._rng.standard_normal()

    def position(self, t_s: float) -> float:
        """Return the true position x0 + 0.05·t·cos(2t) [m]."""
        return self.initial_position_m + float(robot_position_m(t_s))

    @staticmethod
    def velocity(t_s: float) -> float:
        """Return the true velocity d/dt (0.05·t·cos 2t) = 0.05 cos 2t − 0.1 t sin 2t."""
        return 0.05 * np.cos(2.0 * t_s) - 0.1 * t_s * np.sin(2.0 * t_s)

    def next_sample(self) -> ScenarioSample:
        """Advance one period and return the sample."""
        self._index += 1
        dt = 1.0 / self.rate_hz
        t, t_before = self._index / self.rate_hz, (self._index - 1) / self.rate_hz
        x, x_before = self.position(t), self.position(t_before)
        # Mean velocity over (t_{k-1}, t_k] plus the speed sensor's noise.
        reading = (x - x_before) / dt + self.speed_noise_std_mps * self._rng.standard_normal()
        z = x - self.noise_std_m * self._rng.standard_normal()   # z = x − σ·n, as the seed
        control = self._last_reading if self.seed_lag else reading
        self._last_reading = reading
        return ScenarioSample(self._index, t, x, float(self.velocity(t)), float(z),
                              float(control))


class TrainStream:
    """Seed 000's train (TrainSimulation) as a stream without control input."""

    def __init__(self, simulation: TrainSimulation):
        """Wrap the simulation."""
        self.simulation = simulation

    @property
    def noise_std_m(self) -> float:
        """Return the measurement noise σ [m]."""
        return self.simulation.noise_std_m

    @noise_std_m.setter
    def noise_std_m(self, value: float) -> None:
        """Set the measurement noise σ [m] for the next samples."""
        self.simulation.noise_std_m = as_non_negative('noise_std_m', value)

    def next_sample(self) -> ScenarioSample:
        """Return the next train sample."""
        s = self.simulation.next_sample()
        return ScenarioSample(s.index, s.t_s, s.true_position_m, s.true_velocity_mps,
                              s.measured_position_m, None)


def _rail_seed(seed: Optional[int]) -> int:
    """Return the seed of a rail run: the given one, or one drawn from fresh entropy."""
    return int(np.random.SeedSequence().entropy % 2 ** 63) if seed is None else int(seed)


def make_stream(scenario: str, rate_hz: float, seed: Optional[int], *,
                noise_std_m: Optional[float] = None,
                initial_position_m: Optional[float] = None,
                velocity_mps: Optional[float] = None,
                acceleration_mps2: float = CAR_ACCELERATION_MPS2,
                speed_noise_std_mps: float = ROBOT_SPEED_STD_MPS,
                rail: Optional[Mapping] = None):
    """
    Return the stream of a scenario; None arguments take the scenario's defaults.

    ``velocity_mps`` is the train's constant velocity or the car's initial one (the
    robot's follows its trajectory, the rail run's its plan). ``seed`` None draws fresh
    entropy. ``rail``: ``family``, ``gnss_model`` ('white' or 'receiver'), ``receiver``
    (its GnssReceiverParameters) and the keyword arguments of
    :func:`kf_train.sim.rail_stream.rail_parameters` (rail only).
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {scenario!r}")
    if seed is not None and (not isinstance(seed, (int, np.integer)) or seed < 0):
        raise ValueError(f'seed must be a non-negative integer or None, got {seed!r}')
    noise = DEFAULT_NOISE_STD_M[scenario] if noise_std_m is None else noise_std_m
    position, velocity = DEFAULT_INITIAL_STATE[scenario]
    position = position if initial_position_m is None else initial_position_m
    velocity = velocity if velocity_mps is None else velocity_mps
    if scenario == 'rail':
        rail = dict(rail or {})
        family = rail.pop('family', DEFAULT_FAMILY)
        gnss_model = rail.pop('gnss_model', 'white')
        receiver = rail.pop('receiver', None)
        seed = _rail_seed(seed)
        return RailStream(rate_hz, seed, noise, position,
                          rail_parameters(family, seed, **rail), gnss_model=gnss_model,
                          receiver=receiver)
    if scenario == 'train':
        return TrainStream(TrainSimulation(position, velocity, noise, rate_hz, seed))
    if scenario in ('car', 'car-exact'):
        return CarStream(rate_hz, seed, noise, position, velocity, acceleration_mps2,
                         exact=scenario == 'car-exact')
    return RobotStream(rate_hz, seed, noise, position, speed_noise_std_mps,
                       seed_lag=scenario == 'robot')
