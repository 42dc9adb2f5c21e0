"""
The train of seed 000: constant velocity along x, position measured with noise.

Truth: ``x(t) = x0 + v·t``. Sample k (k = 1, 2, …) is taken at ``t_k = k / rate_hz``
and measures ``z_k = x(t_k) + N(0, σ²)``, the noise drawn in order from a seeded
``numpy.random.Generator``, so the same seed gives the same measurements whether
they are drawn one by one (the node) or all at once (offline).
"""

from typing import NamedTuple, Optional

from kf_train.filters import as_non_negative, as_positive, as_scalar
import numpy as np


class TrainSample(NamedTuple):
    """One simulated sample."""

    index: int
    t_s: float
    true_position_m: float
    true_velocity_mps: float
    measured_position_m: float


class TrainSeries(NamedTuple):
    """A batch of simulated samples as arrays of equal length."""

    t_s: np.ndarray
    true_position_m: np.ndarray
    true_velocity_mps: np.ndarray
    measured_position_m: np.ndarray


class TrainSimulation:
    """Generates seed-000 style train samples, reproducibly from a seed."""

    def __init__(self, initial_position_m: float = 0.0, velocity_mps: float = 10.0,
                 noise_std_m: float = 1.0, rate_hz: float = 10.0,
                 seed: Optional[int] = None):
        """Configure the truth and the sensor; ``seed`` None draws fresh entropy."""
        self.initial_position_m = as_scalar('initial_position_m', initial_position_m)
        self.velocity_mps = as_scalar('velocity_mps', velocity_mps)
        self.noise_std_m = as_non_negative('noise_std_m', noise_std_m)
        self.rate_hz = as_positive('rate_hz', rate_hz)
        if seed is not None and (not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ValueError(f'seed must be a non-negative integer or None, got {seed!r}')
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        self._index = 0

    @property
    def period_s(self) -> float:
        """Sample period 1 / rate_hz."""
        return 1.0 / self.rate_hz

    def truth(self, t_s):
        """Return the true position x0 + v·t for a time or an array of times."""
        return self.initial_position_m + self.velocity_mps * np.asarray(t_s, dtype=float)

    def sample_time(self, index) -> float:
        """Return t_k = k / rate_hz for sample index k (exact for integer rates)."""
        return index / self.rate_hz

    def next_sample(self) -> TrainSample:
        """Draw the next sample in sequence."""
        self._index += 1
        t_s = self.sample_time(self._index)
        true_position = float(self.truth(t_s))
        noise = self.noise_std_m * float(self._rng.standard_normal())
        return TrainSample(self._index, t_s, true_position, self.velocity_mps,
                           true_position + noise)

    def generate(self, count: int) -> TrainSeries:
        """Draw the next ``count`` samples at once; same numbers as next_sample()."""
        if not isinstance(count, (int, np.integer)) or count < 0:
            raise ValueError(f'count must be a non-negative integer, got {count!r}')
        indices = np.arange(self._index + 1, self._index + 1 + count)
        self._index += count
        t_s = indices / self.rate_hz
        true_position = self.truth(t_s)
        noise = self.noise_std_m * self._rng.standard_normal(count)
        return TrainSeries(t_s, true_position, np.full(count, self.velocity_mps),
                           true_position + noise)
