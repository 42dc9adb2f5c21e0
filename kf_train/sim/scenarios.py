"""
The seeds' scenarios as seeded simulators: truth, measurements and controls.

Each function returns a :class:`Scenario` whose rows are ready for a preset (the same
columns a replay CSV has): times after ``t0_s``, the measurements, the control of the
interval that ends at each row, and the true state at every row and at ``t0_s``.
Noise comes from ``numpy.random.default_rng(seed)``, so a seed gives the same data
every time (not MATLAB's randn stream: the seeds' figures are reproduced in kind,
not sample for sample).

Where a seed's simulation has a quirk that is not physics, the scenario says so:

* car (seed 001): the seed measures the state of the previous step (``yreal = C*x0``
  before ``x0`` is advanced); here row k measures the state at row k.
* cv-position-velocity (seed 003): the seed never fills its first measurement
  column (``Z(:,1) = 0``); here every row is measured.
* robot (seed 002): the seed applies the speed measured at the previous sample; with
  ``seed_lag=True`` (the ``robot`` preset's scenario) row k carries that reading, as
  the seed uses it; with ``seed_lag=False`` row k carries the reading of its own
  interval (the mean velocity over it plus noise).
"""

from typing import NamedTuple, Optional, Tuple

from kf_train.filters import RangeBearing
from kf_train.sim.simulation import TrainSimulation
import numpy as np


class Scenario(NamedTuple):
    """Simulated rows for one preset."""

    name: str
    """The scenario's name (the preset it is made for)."""
    t0_s: float
    """Time of the initial estimate [s]."""
    t_s: np.ndarray
    """Row times (N,) [s]."""
    z: np.ndarray
    """Measurements (N, m), in the preset's measurement order."""
    u: Optional[np.ndarray]
    """Controls (N, p), or None."""
    truth: np.ndarray
    """True state (N, n) at each row, in the preset's state order."""
    truth0: np.ndarray
    """True state (n,) at t0_s."""
    state_names: Tuple[str, ...]
    measurement_names: Tuple[str, ...]


def _rng(seed: int) -> np.random.Generator:
    """Return a generator for a non-negative integer seed."""
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
    return np.random.default_rng(int(seed))


def _count(name: str, value: int) -> int:
    """Return a positive integer count."""
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise ValueError(f'{name} must be a positive integer, got {value!r}')
    return int(value)


def train_scenario(seed: int = 0, n_samples: int = 100, dt_s: float = 0.1,
                   velocity_mps: float = 10.0, noise_std_m: float = 1.0) -> Scenario:
    """Return seed 000: x = v·t from 0, position measured every dt with σ = 1 m."""
    n_samples = _count('n_samples', n_samples)
    _rng(seed)  # the same check of the seed as every scenario
    simulation = TrainSimulation(0.0, velocity_mps, noise_std_m, 1.0 / dt_s, int(seed))
    series = simulation.generate(n_samples)
    truth = np.column_stack([series.true_position_m, series.true_velocity_mps])
    return Scenario('train', 0.0, series.t_s, series.measured_position_m[:, None], None,
                    truth, np.array([0.0, velocity_mps]), ('position', 'velocity'),
                    ('position',))


def car_scenario(seed: int = 0, n_samples: int = 100, dt_s: float = 0.1,
                 acceleration_mps2: float = 1.0, exact: bool = False) -> Scenario:
    """
    Return seed 001: a car under a constant commanded acceleration, from x = [0.2, 0].

    The truth is the seed's: x_k = A x_{k−1} + B u + w_k with w ~ N(0, diag(0, 0.05))
    and B = [0, dt] (the seed's), or B = [dt²/2, dt] with ``exact`` (the physics of a
    constant acceleration over the step). Position measured with R = 1.
    """
    rng = _rng(seed)
    n_samples = _count('n_samples', n_samples)
    A = np.array([[1.0, dt_s], [0.0, 1.0]])
    B = np.array([dt_s ** 2 / 2.0 if exact else 0.0, dt_s])
    noise_std = np.sqrt(np.array([0.0, 0.05]))  # sqrt(Q), Q = diag(0, 0.05)
    x = np.array([0.2, 0.0])
    truth0 = x.copy()
    truth = np.empty((n_samples, 2))
    z = np.empty(n_samples)
    for k in range(n_samples):
        x = A @ x + B * acceleration_mps2 + noise_std * rng.standard_normal(2)
        truth[k] = x
        z[k] = x[0] + rng.standard_normal()  # R = 1
    t = np.arange(1, n_samples + 1) * dt_s
    return Scenario('car-exact' if exact else 'car', 0.0, t, z[:, None],
                    np.full((n_samples, 1), float(acceleration_mps2)), truth, truth0,
                    ('position', 'velocity'), ('position',))


def robot_position_m(t_s):
    """Return seed 002's trajectory x = 0.05·t·cos(2t) [m]."""
    t = np.asarray(t_s, dtype=float)
    return 0.05 * t * np.cos(2.0 * t)


def robot_scenario(seed: int = 0, duration_s: float = 10.0, dt_s: float = 0.1,
                   range_std_m: float = 0.03, speed_std_mps: float = 0.2,
                   seed_lag: bool = True) -> Scenario:
    """
    Return seed 002: x = 0.05·t·cos(2t), a range finder and a noisy speed sensor.

    The speed reading at sample i is the mean velocity over the interval ending there,
    (x_i − x_{i−1}) / dt, plus noise (0 + noise at t = 0), as the seed simulates it.
    Rows are the samples after t = 0; row i carries reading i − 1 with ``seed_lag``
    (the seed applies the previous sample's speed), else reading i.
    """
    rng = _rng(seed)
    n = int(round(duration_s / dt_s)) + 1
    t = np.arange(n) * dt_s
    x = robot_position_m(t)
    speed = np.concatenate([[0.0], np.diff(x) / dt_s]) + speed_std_mps * rng.standard_normal(n)
    z = x - range_std_m * rng.standard_normal(n)
    u = speed[:-1] if seed_lag else speed[1:]
    return Scenario('robot' if seed_lag else 'robot-exact', 0.0, t[1:], z[1:, None],
                    u[:, None], x[1:, None], x[:1].copy(), ('position',), ('position',))


def cv_position_scenario(seed: int = 0, n_samples: int = 100) -> Scenario:
    """Return seed 003 example 1: x = 2t − 1 at t = 1..N s, position measured, σ = 1."""
    rng = _rng(seed)
    n_samples = _count('n_samples', n_samples)
    t = np.arange(1, n_samples + 1, dtype=float)
    x = 2.0 * t - 1.0                                   # trueX = 1:2:200
    z = x + rng.standard_normal(n_samples)
    truth = np.column_stack([x, np.full(n_samples, 2.0)])
    return Scenario('cv-position', 0.0, t, z[:, None], None, truth, np.array([-1.0, 2.0]),
                    ('position', 'velocity'), ('position',))


def cv_position_velocity_scenario(seed: int = 0, n_samples: int = 100) -> Scenario:
    """Return seed 003's variant: a CV random walk from [1, 2], both states measured."""
    rng = _rng(seed)
    n_samples = _count('n_samples', n_samples)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    truth = np.empty((n_samples, 2))
    truth[0] = [1.0, 2.0]
    for k in range(1, n_samples):
        truth[k] = F @ truth[k - 1] + 0.1 * rng.standard_normal(2)  # sqrt(diag(.01, .01))
    z = truth + 10.0 * rng.standard_normal((n_samples, 2))          # sqrt(diag(100, 100))
    t = np.arange(1, n_samples + 1, dtype=float)
    return Scenario('cv-position-velocity', 0.0, t, z, None, truth,
                    np.linalg.solve(F, truth[0]), ('position', 'velocity'),
                    ('position', 'velocity'))


def range_bearing_scenario(seed: int = 0, duration_s: float = 20.0,
                           dt_s: float = 0.2) -> Scenario:
    """Return seed 003 example 3: 2-D CV from [30, 1, 40, 1], bearing and range."""
    rng = _rng(seed)
    n = int(round(duration_s / dt_s))
    F = np.eye(4) + dt_s * np.diag([1.0, 0.0, 1.0], k=1)
    noise_std = np.sqrt(np.array([0.0, 0.01, 0.0, 0.01]))   # processNoise
    meas_std = np.sqrt(np.array([2e-6, 1.0]))              # measureNoise
    measurement = RangeBearing()
    x = np.array([30.0, 1.0, 40.0, 1.0])
    truth0 = x.copy()
    truth, z = np.empty((n, 4)), np.empty((n, 2))
    for k in range(n):
        x = F @ x + noise_std * rng.standard_normal(4)
        truth[k] = x
        z[k] = measurement.h(x) + meas_std * rng.standard_normal(2)
    t = np.arange(1, n + 1) * dt_s
    return Scenario('range-bearing', 0.0, t, z, None, truth, truth0, ('x', 'vx', 'y', 'vy'),
                    ('bearing', 'range'))


PRESET_SCENARIOS = {
    'train': train_scenario,
    'car': lambda seed=0: car_scenario(seed, exact=False),
    'car-exact': lambda seed=0: car_scenario(seed, exact=True),
    'robot': lambda seed=0: robot_scenario(seed, seed_lag=True),
    'robot-exact': lambda seed=0: robot_scenario(seed, seed_lag=False),
    'cv-position': cv_position_scenario,
    'cv-position-velocity': cv_position_velocity_scenario,
    'range-bearing': range_bearing_scenario,
}


def scenario_for_preset(name: str, seed: int = 0) -> Scenario:
    """Return the seed scenario made for a shipped preset."""
    if name not in PRESET_SCENARIOS:
        raise ValueError(f"no scenario for {name!r}; choose one of: {', '.join(PRESET_SCENARIOS)}")
    return PRESET_SCENARIOS[name](seed)
