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

Input contract: :meth:`TrainEstimator.process` raises :class:`Rejected` (a
``ValueError``) with a ``reason`` from :data:`REJECTION_REASONS` for a measurement it
will not fuse, and the filter state (x, P, last stamp, history) is then exactly as
before, unless the rejection itself triggered a reset (``Rejected.reset``). The
checks, cheapest first:

* ``wrong_frame``: ``expected_frame_id`` is set and the measurement's frame differs;
* ``non_finite``: NaN or Inf in the position or the message's variance;
* ``bad_variance``: the variance in use (the override, else the message's) <= 0;
* ``zero_stamp``: a stamp <= 0 (an unset header);
* ``future_stamp``: more than ``max_future_s`` after ``now_ns``, when that is given;
* ``duplicate_stamp``: a stamp already fused;
* ``stale_stamp``: older than the newest fused one by ``history_s`` or more;
* ``outlier``: the NIS exceeds the χ² gate (``gate_probability``);
* ``numerical``: the update could not be computed in floating point.

Time handling:

* A measurement older than the newest fused one but by less than ``history_s`` is
  fused out of sequence: the filter rewinds to the state after the last measurement
  before it, fuses it, and replays the later measurements (each with the R and model
  it was first fused with). The result equals in-order processing to rounding.
  Replayed measurements are not gated again. A measurement older than the first one
  since (re)initialisation re-initialises from it and replays everything, as
  in-order processing would have.
* ``restart_after_stale`` consecutive stale measurements mean the stream restarted
  (a bag loop, a restarted sensor): the filter resets and initialises from the last
  of them.
* ``max_consecutive_outliers`` consecutive gate (or numerical) rejections reset the
  filter; the next measurement initialises it, from the measurement itself as in
  ``first_measurement`` mode even in ``prior`` mode (the prior is what the data
  contradicted). The initialising measurement is never gated, so the filter cannot
  stay locked out. Other resets re-initialise in the configured mode.

Every rejection and reset is counted by reason (:attr:`TrainEstimator.rejection_counts`,
:attr:`TrainEstimator.reset_counts`).
"""

import bisect
import collections
from dataclasses import dataclass
import math
from typing import Dict, NamedTuple, Optional, Sequence, Tuple

from kf_train.core.chi2 import chi2_quantile
from kf_train.core.kalman import UpdateResult
from kf_train.core.models import constant_velocity_model, LinearModel, WhiteNoiseAcceleration
from kf_train.core.validation import as_covariance, as_finite_array, as_vector
import numpy as np

INITIALIZATIONS = ('first_measurement', 'prior')
# What the filter arithmetic raises for inputs it cannot handle in double precision
# (kalman raises ValueError for a non-finite result; Python float arithmetic may
# raise OverflowError first).
_NUMERICAL_ERRORS = (ValueError, ArithmeticError)
NS_PER_S = 1_000_000_000

REJECTION_REASONS = ('wrong_frame', 'non_finite', 'bad_variance', 'zero_stamp',
                     'future_stamp', 'duplicate_stamp', 'stale_stamp', 'outlier', 'numerical')
"""Why a measurement was not fused; keys of :attr:`TrainEstimator.rejection_counts`."""

RESET_REASONS = ('manual', 'set_state', 'clock_jump', 'stream_restart', 'outlier_lockout',
                 'non_finite')
"""Why the filter was reset; keys of :attr:`TrainEstimator.reset_counts`."""

# Ranges shared with the node's parameter descriptors.
GATE_PROBABILITY_RANGE = (0.5, 1.0)
HISTORY_S_RANGE = (0.0, 60.0)
MAX_CONSECUTIVE_OUTLIERS_RANGE = (1, 1_000_000)
RESTART_AFTER_STALE_RANGE = (2, 1_000_000)
MAX_FUTURE_S_RANGE = (0.0, 1e9)


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


def _check_float_range(name: str, value, low: float, high: float) -> float:
    """Return value as a float, or raise naming ``name`` and the range [low, high]."""
    array = as_finite_array(name, value)
    if array.ndim != 0 or not low <= float(array) <= high:
        raise ValueError(f'{name} must be a number in [{low:g}, {high:g}], got {value!r}')
    return float(array)


def _check_int_range(name: str, value, low: int, high: int) -> int:
    """Return value as an int, or raise naming ``name`` and the range [low, high]."""
    if (not isinstance(value, (int, np.integer)) or isinstance(value, bool)
            or not low <= value <= high):
        raise ValueError(f'{name} must be an integer in [{low}, {high}], got {value!r}')
    return int(value)


@dataclass(frozen=True)
class EstimatorSettings:
    """
    Everything that configures a :class:`TrainEstimator`, with seed-000 defaults.

    The defaults reproduce the seed exactly: no gate and no out-of-sequence fusion.
    The estimator node turns both on by default (see its parameters).
    """

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
    history_s: float = 0.0
    """Out-of-sequence window [s]: older measurements are fused by replay; 0 = off."""
    gate_probability: float = 1.0
    """χ² gate on the NIS: reject when P(χ²(m) <= NIS) exceeds this; 1 = no gate."""
    max_consecutive_outliers: int = 10
    """Consecutive gate (or numerical) rejections after which the filter resets."""
    restart_after_stale: int = 3
    """Consecutive stale measurements after which the stream counts as restarted."""
    max_future_s: float = 1.0
    """How far [s] a stamp may lie ahead of ``now_ns`` (when process() is given it)."""
    expected_frame_id: str = ''
    """The measurements' required frame_id; '' accepts any."""

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
        _check_float_range('history_s', self.history_s, *HISTORY_S_RANGE)
        _check_float_range('gate_probability', self.gate_probability,
                           *GATE_PROBABILITY_RANGE)
        _check_float_range('max_future_s', self.max_future_s, *MAX_FUTURE_S_RANGE)
        _check_int_range('max_consecutive_outliers', self.max_consecutive_outliers,
                         *MAX_CONSECUTIVE_OUTLIERS_RANGE)
        _check_int_range('restart_after_stale', self.restart_after_stale,
                         *RESTART_AFTER_STALE_RANGE)
        if not isinstance(self.expected_frame_id, str):
            raise ValueError(
                f'expected_frame_id must be a string, got {self.expected_frame_id!r}')
        return self


class EstimateStep(NamedTuple):
    """The filter's output after one measurement."""

    stamp_ns: int
    """Time of x and P: the newest fused stamp (later than the measurement's if replayed)."""
    x: np.ndarray
    P: np.ndarray
    update: Optional[UpdateResult]
    """The measurement's innovation; None when it initialised the filter (first_measurement)."""
    prediction_stamp_ns: int
    predicted_x: np.ndarray
    predicted_P: np.ndarray
    measurement_stamp_ns: int = 0
    """The fused measurement's own stamp."""
    replayed: int = 0
    """How many later measurements were replayed after this out-of-sequence one."""
    reset: Optional[str] = None
    """A reset this measurement triggered before initialising the filter (stream_restart)."""


class Rejected(ValueError):
    """A measurement the estimator did not fuse; ``reason`` is from REJECTION_REASONS."""

    def __init__(self, reason: str, message: str, reset: Optional[str] = None,
                 update: Optional[UpdateResult] = None):
        """Record why; ``reset`` names a reset it caused, ``update`` a gated innovation."""
        super().__init__(message)
        self.reason = reason
        self.reset = reset
        self.update = update


class _Entry(NamedTuple):
    """One fused measurement and the state right after it, for out-of-sequence replay."""

    stamp_ns: int
    z: np.ndarray
    R: np.ndarray
    model: LinearModel
    x: np.ndarray
    P: np.ndarray
    kind: str
    """'init' (initialised the filter), 'update', or 'set' / 'reinit' (set_state, the
    re-initialisation after a lock-out: no rewinding past them)."""


class TrainEstimator:
    """Fuses stamped position measurements of a constant-velocity train."""

    def __init__(self, settings: EstimatorSettings = EstimatorSettings()):
        """Validate ``settings``; the filter starts uninitialised."""
        self._x: Optional[np.ndarray] = None
        self._P: Optional[np.ndarray] = None
        self._last_stamp_ns: Optional[int] = None
        self._history = collections.deque()
        self._consecutive_outliers = 0
        self._stale_streak = 0
        self._locked_out = False
        self._rejections = dict.fromkeys(REJECTION_REASONS, 0)
        self._resets = dict.fromkeys(RESET_REASONS, 0)
        self._fused = 0
        self._out_of_sequence = 0
        self._apply(settings.validated())

    def _apply(self, settings: EstimatorSettings) -> None:
        """Install validated settings and everything derived from them."""
        self.model = self._make_model(settings)
        self.settings = settings
        self._history_ns = seconds_to_ns(settings.history_s)
        self._max_future_ns = seconds_to_ns(settings.max_future_s)
        self._horizon_ns = seconds_to_ns(settings.horizon_s)
        self._gate_threshold = chi2_quantile(settings.gate_probability, self.model.dim_z)
        self._initial_covariance = covariance_from_list(
            'initial_covariance', settings.initial_covariance, 2)
        if self._history_ns == 0:
            self._history.clear()

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
        """Return the stamp of the newest fused measurement, or None."""
        return self._last_stamp_ns

    @property
    def state(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """Return a copy of (x, P), or None before the first measurement."""
        if self._x is None:
            return None
        return self._x.copy(), self._P.copy()

    @property
    def gate_threshold(self) -> float:
        """Return the NIS above which a measurement is an outlier (inf: no gate)."""
        return self._gate_threshold

    @property
    def rejection_counts(self) -> Dict[str, int]:
        """Return how many measurements were rejected, by reason, since construction."""
        return dict(self._rejections)

    @property
    def reset_counts(self) -> Dict[str, int]:
        """Return how many times the filter was reset, by reason, since construction."""
        return dict(self._resets)

    @property
    def fused_count(self) -> int:
        """Return how many measurements were fused (initialisations included)."""
        return self._fused

    @property
    def out_of_sequence_count(self) -> int:
        """Return how many of the fused measurements came out of sequence."""
        return self._out_of_sequence

    @property
    def history_length(self) -> int:
        """Return how many fused states are kept for out-of-sequence replay."""
        return len(self._history)

    def reconfigure(self, settings: EstimatorSettings) -> None:
        """
        Use new settings from the next measurement on; the current state is kept.

        Initial state, covariance and initialisation mode matter again only at the
        next (re)initialisation. Measurements already fused keep the model and R they
        were fused with when they are replayed.
        """
        self._apply(settings.validated())

    def reset(self, reason: str = 'manual') -> None:
        """Forget the state; the next measurement initialises the filter again."""
        if reason not in self._resets:
            raise ValueError(f'reason must be one of {RESET_REASONS}, got {reason!r}')
        self._x = self._P = None
        self._last_stamp_ns = None
        self._history.clear()
        self._consecutive_outliers = 0
        self._stale_streak = 0
        self._locked_out = reason == 'outlier_lockout'
        self._resets[reason] += 1

    def set_state(self, stamp_ns: int, x, P) -> None:
        """
        Replace the state with (x, P) valid at ``stamp_ns``; on ValueError nothing changes.

        Counted as a ``set_state`` reset: the history is dropped, and measurements
        older than ``stamp_ns`` are then stale.
        """
        if (not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool)
                or stamp_ns <= 0):
            raise ValueError(f'stamp_ns must be a positive integer, got {stamp_ns!r}')
        x = as_vector('x', x, self.model.dim_x)
        P = as_covariance('P', P, self.model.dim_x)
        self.reset('set_state')
        self._x, self._P, self._last_stamp_ns = x, P, int(stamp_ns)
        if self._history_ns > 0:
            self._history.append(_Entry(int(stamp_ns), None, None, self.model, x, P, 'set'))

    def measurement_variance(self, message_variance_m2: float) -> float:
        """Return R: the override when set, else the message's own variance."""
        if self.settings.measurement_variance > 0.0:
            return float(self.settings.measurement_variance)
        return float(message_variance_m2)

    def _reject(self, reason: str, message: str, reset: Optional[str] = None,
                update: Optional[UpdateResult] = None) -> None:
        """Count a rejection and raise it."""
        self._rejections[reason] += 1
        raise Rejected(reason, message, reset, update)

    def _reject_update(self, reason: str, message: str,
                       update: Optional[UpdateResult] = None) -> None:
        """Reject an outlier or a numerical failure; enough in a row reset the filter."""
        self._consecutive_outliers += 1
        reset = None
        if self._consecutive_outliers >= self.settings.max_consecutive_outliers:
            reset = 'outlier_lockout'
            message += (f'; {self._consecutive_outliers} consecutive rejections: filter '
                        'reset, the next measurement initialises it')
            self.reset(reset)
        self._reject(reason, message, reset, update)

    def process(self, stamp_ns: int, position_m: float, variance_m2: float, *,
                frame_id: Optional[str] = None, now_ns: Optional[int] = None) -> EstimateStep:
        """
        Fuse one measurement; on ValueError the estimator state is unchanged.

        ``frame_id`` is checked against ``expected_frame_id`` when both are given;
        ``now_ns`` (the receiver's clock; None or 0 when unknown) bounds future stamps.
        Raises :class:`Rejected` for a measurement that breaks the input contract, a
        plain ValueError for a stamp that is not an integer.
        """
        if not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool):
            raise ValueError(f'stamp_ns must be an integer, got {stamp_ns!r}')
        stamp_ns = int(stamp_ns)
        s = self.settings
        if s.expected_frame_id and frame_id is not None and frame_id != s.expected_frame_id:
            self._reject('wrong_frame', f'frame_id {frame_id!r} is not the expected '
                         f'{s.expected_frame_id!r}')
        try:
            position_m = float(position_m)
            variance_m2 = float(variance_m2)
        except (TypeError, ValueError):
            raise ValueError(
                f'position and variance must be numbers, got {position_m!r}, {variance_m2!r}'
            ) from None
        if not math.isfinite(position_m):
            self._reject('non_finite', f'position must be finite, got {position_m}')
        if not math.isfinite(variance_m2):
            self._reject('non_finite', f'measurement variance must be finite, got {variance_m2}')
        R = self.measurement_variance(variance_m2)
        if R <= 0.0:
            self._reject('bad_variance', f'measurement variance must be > 0, got {R}')
        if stamp_ns <= 0:
            self._reject('zero_stamp', f'stamp must be > 0 (a set header stamp), got {stamp_ns}')
        if now_ns and stamp_ns - now_ns > self._max_future_ns:
            self._reject('future_stamp', f'stamp {stamp_ns} ns is {(stamp_ns - now_ns) / 1e9:.3f}'
                         f' s ahead of the clock, more than max_future_s = {s.max_future_s}')
        z = np.array([position_m])
        R_matrix = np.array([[R]])
        newest = self._last_stamp_ns
        if self._x is None:
            return self._initialise(stamp_ns, z, R_matrix)
        if stamp_ns > newest:
            return self._fuse_in_order(stamp_ns, z, R_matrix)
        if stamp_ns == newest:
            self._reject('duplicate_stamp', f'measurement stamp {stamp_ns} ns is not newer than '
                         f'the last fused one, {newest} ns (a duplicate)')
        if newest - stamp_ns < self._history_ns:
            return self._fuse_out_of_sequence(stamp_ns, z, R_matrix)
        return self._stale(stamp_ns, z, R_matrix)

    def _stale(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Reject a stale measurement, or restart from it after enough in a row."""
        self._stale_streak += 1
        if self._stale_streak >= self.settings.restart_after_stale:
            self.reset('stream_restart')
            return self._initialise(stamp_ns, z, R)._replace(reset='stream_restart')
        newest = self._last_stamp_ns
        self._reject('stale_stamp', (
            f'measurement stamp {stamp_ns} ns is not newer than the last fused one, '
            f'{newest} ns, and {(newest - stamp_ns) / NS_PER_S:.6f} s older: beyond '
            f'history_s = {self.settings.history_s}'))

    def _init_state(self, stamp_ns: int, z: np.ndarray, R: np.ndarray, model: LinearModel):
        """Return (x, P, update result or None) of the filter initialised by z."""
        s = self.settings
        if s.initialization == 'prior' and not self._locked_out:
            x, P = model.predict(s.initial_state, self._initial_covariance,
                                 s.nominal_period_s)
            return model.update(x, P, z, R)
        x = np.array([z[0], s.initial_state[1]], dtype=float)
        P = np.diag([R[0, 0], s.first_velocity_std_mps ** 2])
        return x, P, None

    def _initialise(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Start the filter from this measurement (never gated)."""
        try:
            x, P, result = self._init_state(stamp_ns, z, R, self.model)
            predicted = self._predict_ahead(x, P)
        except _NUMERICAL_ERRORS as error:
            self._reject('numerical', f'initialisation failed: {error}')
        self._history.clear()
        # After a lock-out the state starts from the measurement: no rewinding past it.
        self._commit(stamp_ns, x, P, 'reinit' if self._locked_out else 'init', z, R)
        self._locked_out = False
        return self._step(stamp_ns, x, P, result, predicted, stamp_ns)

    def _fuse_in_order(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Predict from the newest state to the stamp, gate, update, commit."""
        dt_s = (stamp_ns - self._last_stamp_ns) / NS_PER_S
        x, P, result, predicted = self._gated_update(self._x, self._P, dt_s, z, R)
        self._commit(stamp_ns, x, P, 'update', z, R)
        return self._step(stamp_ns, x, P, result, predicted, stamp_ns)

    def _gated_update(self, x0, P0, dt_s: float, z: np.ndarray, R: np.ndarray):
        """Return (x, P, result, prediction ahead) or reject as outlier/numerical."""
        try:
            x, P = self.model.predict(x0, P0, dt_s)
            x, P, result = self.model.update(x, P, z, R)
        except _NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'update failed: {error}')
        if result.nis > self._gate_threshold:
            self._reject_update('outlier', (
                f'NIS {result.nis:.6g} exceeds the gate {self._gate_threshold:.6g} '
                f'(gate_probability {self.settings.gate_probability}); innovation '
                f'{result.innovation[0]:.6g}'), result)
        try:
            predicted = self._predict_ahead(x, P)
        except _NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'prediction failed: {error}')
        return x, P, result, predicted

    def _fuse_out_of_sequence(self, stamp_ns: int, z: np.ndarray,
                              R: np.ndarray) -> EstimateStep:
        """Rewind to the last state before stamp_ns, fuse, replay the later ones."""
        entries = list(self._history)
        stamps = [entry.stamp_ns for entry in entries]
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            self._reject('duplicate_stamp', f'measurement stamp {stamp_ns} ns was fused already')
        if i == 0 and (not entries or entries[0].kind != 'init'):
            what = 'the state was set' if entries else 'no state is kept (history_s)'
            self._reject('stale_stamp', (
                f'measurement stamp {stamp_ns} ns is not newer than the last fused one, '
                f'{self._last_stamp_ns} ns, and older than the oldest state to rewind to: '
                f'{what}'))
        if i == 0:
            # Older than the initialising measurement: in order, this one would have
            # initialised the filter and the old first one been an update.
            try:
                x, P, result = self._init_state(stamp_ns, z, R, self.model)
            except _NUMERICAL_ERRORS as error:
                self._reject('numerical', f'initialisation failed: {error}')
            kind = 'init'
        else:
            anchor = entries[i - 1]
            x, P, result, _ = self._gated_update(
                anchor.x, anchor.P, (stamp_ns - anchor.stamp_ns) / NS_PER_S, z, R)
            kind = 'update'
        rebuilt = entries[:i] + [_Entry(stamp_ns, z, R, self.model, x, P, kind)]
        try:
            for entry in entries[i:]:
                dt_s = (entry.stamp_ns - rebuilt[-1].stamp_ns) / NS_PER_S
                x, P = entry.model.predict(x, P, dt_s)
                x, P, _ = entry.model.update(x, P, entry.z, entry.R)
                rebuilt.append(entry._replace(x=x, P=P, kind='update'))
            predicted = self._predict_ahead(x, P)
        except _NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'replay failed: {error}')
        self._history = collections.deque(rebuilt)
        self._x, self._P = x, P
        self._after_fusion()
        self._out_of_sequence += 1
        return self._step(self._last_stamp_ns, x, P, result, predicted, stamp_ns,
                          replayed=len(entries) - i)

    def _predict_ahead(self, x: np.ndarray, P: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Return the state horizon_s after (x, P)."""
        return self.model.predict(x, P, self.settings.horizon_s)

    def _commit(self, stamp_ns: int, x: np.ndarray, P: np.ndarray, kind: str,
                z: np.ndarray, R: np.ndarray) -> None:
        """Make (x, P) at stamp_ns the newest state and keep it for replay."""
        self._x, self._P, self._last_stamp_ns = x, P, stamp_ns
        if self._history_ns > 0:
            history = self._history
            history.append(_Entry(stamp_ns, z, R, self.model, x, P, kind))
            # Keep every state younger than history_s plus one older one to rewind to.
            oldest_needed = stamp_ns - self._history_ns
            while len(history) > 1 and history[1].stamp_ns <= oldest_needed:
                history.popleft()
        self._after_fusion()

    def _after_fusion(self) -> None:
        """Count a fused measurement; it ends any run of outliers or stale stamps."""
        self._fused += 1
        self._consecutive_outliers = 0
        self._stale_streak = 0

    def _step(self, stamp_ns: int, x: np.ndarray, P: np.ndarray,
              result: Optional[UpdateResult], predicted, measurement_stamp_ns: int,
              replayed: int = 0) -> EstimateStep:
        """Return the public EstimateStep (copies of the kept arrays)."""
        return EstimateStep(stamp_ns, x.copy(), P.copy(), result,
                            stamp_ns + self._horizon_ns, predicted[0], predicted[1],
                            measurement_stamp_ns, replayed)
