"""
The train estimator as a pure state machine: stamped measurements in, estimates out.

Time is kept in integer nanoseconds (as ROS stamps are), so that dt between two
stamps is exact: a float of epoch seconds has only ~0.2 µs resolution, which alone
would move the estimate by more than 1e-9.

Initialisation:

* ``prior`` (seed 000's mode): the configured initial state and covariance hold one
  nominal period before the first measurement's stamp; every measurement, the first
  included, is then a predict and an update.
* ``first_measurement`` (default): the first measurement sets the position with its
  own variance; the velocity comes from the configured initial state with a wide
  variance, so the filter converges within a few samples even when it joins a train
  that is far down the track. (With Q = 0 the seed's prior would lock the filter
  onto its wrong initial velocity.)
"""

from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence, Tuple

from kf_train.core.kalman import UpdateResult
from kf_train.core.models import constant_velocity_model, LinearModel, WhiteNoiseAcceleration
from kf_train.core.validation import as_covariance, as_finite_array, as_vector
import numpy as np

INITIALIZATIONS = ('first_measurement', 'prior')
NS_PER_S = 1_000_000_000


def seconds_to_ns(seconds: float) -> int:
    """Return a duration in whole nanoseconds, rounded to nearest."""
    return int(round(seconds * NS_PER_S))


def covariance_from_list(name: str, values: Sequence[float], dim: int) -> np.ndarray:
    """Return a covariance from its diagonal (dim values) or row-major entries (dim²)."""
    flat = as_vector(name, values)
    if flat.shape[0] == dim:
        return as_covariance(name, np.diag(flat), dim)
    if flat.shape[0] == dim * dim:
        return as_covariance(name, flat.reshape(dim, dim), dim)
    raise ValueError(
        f'{name} must have {dim} (diagonal) or {dim * dim} (full) entries, '
        f'got {flat.shape[0]}')


@dataclass(frozen=True)
class EstimatorSettings:
    """Everything that configures a :class:`TrainEstimator`, with seed-000 defaults."""

    initial_state: Tuple[float, ...] = (0.0, 5.0)
    """[position m, velocity m/s]; seed 000 starts at half the true speed."""
    initial_covariance: Tuple[float, ...] = (1.0, 1.0)
    """Diagonal (2 values) or row-major full matrix (4 values)."""
    process_noise_density: float = 0.0
    """White-noise acceleration density q [m²/s³]; 0 as in seed 000."""
    measurement_variance: float = 0.0
    """R [m²] overriding the message's variance; 0 uses the message's."""
    horizon_s: float = 2.0
    initialization: str = 'first_measurement'
    nominal_period_s: float = 0.1
    """Prior mode: how long before the first stamp the prior holds."""
    first_velocity_std_mps: float = 100.0
    """first_measurement mode: standard deviation of the initial velocity."""

    def validated(self) -> 'EstimatorSettings':
        """Return self after checking every field; raise ValueError naming the field."""
        as_vector('initial_state', self.initial_state, 2)
        covariance_from_list('initial_covariance', self.initial_covariance, 2)
        for name in ('process_noise_density', 'measurement_variance', 'horizon_s',
                     'nominal_period_s', 'first_velocity_std_mps'):
            value = as_finite_array(name, getattr(self, name))
            if value.ndim != 0 or float(value) < 0.0:
                raise ValueError(f'{name} must be a finite number >= 0, got {value}')
        if self.nominal_period_s <= 0.0:
            raise ValueError(f'nominal_period_s must be > 0, got {self.nominal_period_s}')
        if self.first_velocity_std_mps <= 0.0:
            raise ValueError(
                f'first_velocity_std_mps must be > 0, got {self.first_velocity_std_mps}')
        if self.initialization not in INITIALIZATIONS:
            raise ValueError(
                f'initialization must be one of {INITIALIZATIONS}, '
                f'got {self.initialization!r}')
        return self


class EstimateStep(NamedTuple):
    """The filter's output after one measurement."""

    stamp_ns: int
    x: np.ndarray
    P: np.ndarray
    update: Optional[UpdateResult]
    """None for the measurement that initialised the filter in first_measurement mode."""
    prediction_stamp_ns: int
    predicted_x: np.ndarray
    predicted_P: np.ndarray


class TrainEstimator:
    """Fuses stamped position measurements of a constant-velocity train."""

    def __init__(self, settings: EstimatorSettings = EstimatorSettings()):
        """Validate ``settings``; the filter starts uninitialised."""
        self.settings = settings.validated()
        self.model = self._make_model(settings)
        self._x: Optional[np.ndarray] = None
        self._P: Optional[np.ndarray] = None
        self._last_stamp_ns: Optional[int] = None

    @staticmethod
    def _make_model(settings: EstimatorSettings) -> LinearModel:
        """Return the constant-velocity model the settings describe."""
        return constant_velocity_model(
            WhiteNoiseAcceleration(settings.process_noise_density))

    @property
    def initialized(self) -> bool:
        """Return whether a measurement has been fused since start or reset."""
        return self._x is not None

    @property
    def last_stamp_ns(self) -> Optional[int]:
        """Return the stamp of the last fused measurement, or None."""
        return self._last_stamp_ns

    @property
    def state(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """Return a copy of (x, P), or None before the first measurement."""
        if self._x is None:
            return None
        return self._x.copy(), self._P.copy()

    def reconfigure(self, settings: EstimatorSettings) -> None:
        """
        Use new settings from the next measurement on; the current state is kept.

        Initial state, covariance and initialisation mode matter again only at the
        next (re)initialisation.
        """
        settings = settings.validated()
        self.model = self._make_model(settings)
        self.settings = settings

    def reset(self) -> None:
        """Forget the state; the next measurement initialises the filter again."""
        self._x = self._P = None
        self._last_stamp_ns = None

    def measurement_variance(self, message_variance_m2: float) -> float:
        """Return R: the override when set, else the message's own variance."""
        if self.settings.measurement_variance > 0.0:
            return float(self.settings.measurement_variance)
        return float(message_variance_m2)

    def process(self, stamp_ns: int, position_m: float,
                variance_m2: float) -> EstimateStep:
        """Fuse one measurement; on ValueError the estimator is unchanged."""
        if not isinstance(stamp_ns, (int, np.integer)):
            raise ValueError(f'stamp_ns must be an integer, got {stamp_ns!r}')
        R = self.measurement_variance(variance_m2)
        if not np.isfinite(R) or R <= 0.0:
            raise ValueError(f'measurement variance must be finite and > 0, got {R}')
        if not np.isfinite(position_m):
            raise ValueError(f'position must be finite, got {position_m}')
        s = self.settings
        R_matrix = np.array([[R]])
        update_result = None
        if self._x is None:
            if s.initialization == 'prior':
                x, P = self.model.predict(
                    s.initial_state,
                    covariance_from_list('initial_covariance', s.initial_covariance, 2),
                    s.nominal_period_s)
                x, P, update_result = self.model.update(x, P, [position_m], R_matrix)
            else:
                x = np.array([position_m, s.initial_state[1]], dtype=float)
                P = np.diag([R, s.first_velocity_std_mps ** 2])
        else:
            if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
                raise ValueError(
                    f'measurement stamp {stamp_ns} ns is not newer than the last fused '
                    f'one, {self._last_stamp_ns} ns')
            dt_s = (stamp_ns - self._last_stamp_ns) / NS_PER_S
            x, P = self.model.predict(self._x, self._P, dt_s)
            x, P, update_result = self.model.update(x, P, [position_m], R_matrix)
        predicted_x, predicted_P = self.model.predict(x, P, s.horizon_s)
        # Commit only now: every failure above left the old state in place.
        self._x, self._P, self._last_stamp_ns = x, P, int(stamp_ns)
        return EstimateStep(int(stamp_ns), x.copy(), P.copy(), update_result,
                            int(stamp_ns) + seconds_to_ns(s.horizon_s),
                            predicted_x, predicted_P)
