"""
The streaming estimator's contract: what a step returns, why an input is refused.

:func:`check_measurement` and :func:`check_control` apply the input contract, cheapest
check first (see :mod:`kf_train.estimator.estimator`); they change nothing and raise
:class:`Rejected` with a ``reason`` from :data:`REJECTION_REASONS` (or
:data:`CONTROL_REJECTION_REASONS`), or a plain ``ValueError`` for a call that is
wrong rather than a measurement that is bad. :class:`Counters` counts what happened;
:class:`EstimatorStats` is its snapshot, :meth:`StreamEstimator.stats`.
"""

import math
from typing import Dict, NamedTuple, Optional, Tuple

from kf_train.filters import UpdateResult
import numpy as np

# What the filter arithmetic raises for inputs it cannot handle in double precision
# (kalman raises ValueError for a non-finite result; Python float arithmetic may
# raise OverflowError first).
NUMERICAL_ERRORS = (ValueError, ArithmeticError)

REJECTION_REASONS = ('wrong_frame', 'non_finite', 'bad_variance', 'zero_stamp',
                     'future_stamp', 'duplicate_stamp', 'stale_stamp', 'outlier', 'repeated',
                     'numerical')
"""
Why a measurement was not fused; keys of :attr:`EstimatorStats.rejections`.

``repeated``: a receiver's repeated epoch, the newest fused position again while the
track has moved beyond the gate on the R in use (``Fusion._reject_repeat``); repeats
count toward a lock-out as outliers do (a receiver holding one position says the train
stands there).
"""

CONTROL_REJECTION_REASONS = ('non_finite', 'zero_stamp', 'future_stamp', 'stale_stamp',
                             'numerical')
"""Why a control was not used; keys of :attr:`EstimatorStats.control_rejections`."""

VELOCITY_REJECTION_REASONS = ('non_finite', 'bad_variance', 'zero_stamp', 'future_stamp',
                              'no_state', 'duplicate_stamp', 'stale_stamp', 'outlier',
                              'numerical')
"""Why a speed measurement (:meth:`StreamEstimator.process_velocity`) was not fused; keys
of :attr:`EstimatorStats.velocity_rejections` (``no_state``: no position fused yet)."""

RESET_REASONS = ('manual', 'set_state', 'clock_jump', 'stream_restart', 'outlier_lockout',
                 'non_finite')
"""Why the filter was reset; keys of :attr:`EstimatorStats.resets`."""


class _EstimateStepFields(NamedTuple):
    """The fields of :class:`EstimateStep`, in their (internal) order."""

    stamp_ns: int
    """Time of x and P: the newest fused stamp (later than the measurement's if replayed)."""
    x: np.ndarray
    """The estimate at ``stamp_ns``."""
    P: np.ndarray
    """Its covariance."""
    update: Optional[UpdateResult]
    """The measurement's innovation; None when it initialised the filter (first_measurement)
    or when a late control caused the step."""
    prediction_stamp_ns: int
    """Time of the prediction: ``stamp_ns`` plus the horizon."""
    predicted_x: np.ndarray
    """The estimate predicted to ``prediction_stamp_ns`` (the model's predict_ahead)."""
    predicted_P: np.ndarray
    """Its covariance."""
    measurement_stamp_ns: int
    """The fused measurement's own stamp (0 for a step caused by a control)."""
    replayed: int
    """How many fused measurements were replayed after this out-of-sequence one (or
    recomputed with a late control)."""
    reset: Optional[str]
    """A reset this measurement triggered before initialising the filter (stream_restart)."""
    control_stamp_ns: int
    """The late control that caused this step, or 0 for a measurement's step."""


class EstimateStep(_EstimateStepFields):
    """
    The filter's output after one measurement (or one late control), built by keywords.

    Fields are read by name (``step.x``, ``step.predicted_P``, ...); ``_replace``
    returns a changed copy. The last four default to 0, 0, None and 0.
    """

    __slots__ = ()

    def __new__(cls, *, stamp_ns: int, x: np.ndarray, P: np.ndarray,
                update: Optional[UpdateResult], prediction_stamp_ns: int,
                predicted_x: np.ndarray, predicted_P: np.ndarray,
                measurement_stamp_ns: int = 0, replayed: int = 0, reset: Optional[str] = None,
                control_stamp_ns: int = 0) -> 'EstimateStep':
        """Return the step of these fields (keywords only: 11 positions are unreadable)."""
        return tuple.__new__(cls, (stamp_ns, x, P, update, prediction_stamp_ns, predicted_x,
                                   predicted_P, measurement_stamp_ns, replayed, reset,
                                   control_stamp_ns))


class Rejected(ValueError):
    """A measurement the estimator did not fuse; ``reason`` is from REJECTION_REASONS."""

    def __init__(self, reason: str, message: str, reset: Optional[str] = None,
                 update: Optional[UpdateResult] = None):
        """Record why; ``reset`` names a reset it caused, ``update`` a gated innovation."""
        super().__init__(message)
        self.reason = reason
        self.reset = reset
        self.update = update


class EstimatorStats(NamedTuple):
    """What an estimator has done since construction: one consistent snapshot."""

    fused: int
    """Measurements fused (initialisations included)."""
    out_of_sequence: int
    """Of those, how many came out of sequence."""
    rejections: Dict[str, int]
    """Measurements rejected, by reason (:data:`REJECTION_REASONS`)."""
    control_rejections: Dict[str, int]
    """Controls rejected, by reason (:data:`CONTROL_REJECTION_REASONS`)."""
    resets: Dict[str, int]
    """Resets, by reason (:data:`RESET_REASONS`)."""
    controls: Dict[str, int]
    """``accepted``: controls taken; ``late``: of those, how many came after fused
    estimates that they apply to, and were applied by rewinding and replaying;
    ``provisional``: fusions that had to use another interval's control (or 0)
    because their own had not arrived (yet)."""
    history_length: int
    """Fused states kept for out-of-sequence replay."""
    control_count: int
    """Controls kept (by stamp)."""
    velocities: Dict[str, int]
    """Speed measurements (:meth:`StreamEstimator.process_velocity`): ``fused``, and
    ``out_of_sequence`` (of those, how many were fused by rewinding and replaying)."""
    velocity_rejections: Dict[str, int]
    """Speed measurements rejected, by reason (:data:`VELOCITY_REJECTION_REASONS`); they
    never count toward the positions' lock-out."""
    reacquisitions: int = 0
    """Lock-outs that kept the track (``lockout`` reacquire): the track widened by the
    rejected group's disagreement and the group fused (its last fix counted as fused, the
    others as rejected). A lock-out with ``lockout`` reset counts in ``resets``."""
    holds: int = 0
    """Of the fused measurements, the held positions fused as a standstill (the rail
    preset: ``hold_speed_std_mps``, docs/rail.md)."""


class Counters:
    """The running counts behind :class:`EstimatorStats`."""

    def __init__(self):
        """Start every count at zero."""
        self.rejections = dict.fromkeys(REJECTION_REASONS, 0)
        self.control_rejections = dict.fromkeys(CONTROL_REJECTION_REASONS, 0)
        self.resets = dict.fromkeys(RESET_REASONS, 0)
        self.fused = 0
        self.out_of_sequence = 0
        self.controls_accepted = 0
        self.controls_late = 0
        self.provisional = 0
        self.velocity_rejections = dict.fromkeys(VELOCITY_REJECTION_REASONS, 0)
        self.velocities_fused = 0
        self.velocities_out_of_sequence = 0
        self.reacquisitions = 0
        self.holds = 0

    def snapshot(self, history_length: int, control_count: int) -> EstimatorStats:
        """Return the counts as an :class:`EstimatorStats` (copies of the dicts)."""
        return EstimatorStats(
            self.fused, self.out_of_sequence, dict(self.rejections),
            dict(self.control_rejections), dict(self.resets),
            {'accepted': self.controls_accepted, 'late': self.controls_late,
             'provisional': self.provisional}, history_length, control_count,
            {'fused': self.velocities_fused,
             'out_of_sequence': self.velocities_out_of_sequence},
            dict(self.velocity_rejections), self.reacquisitions, self.holds)


def override_variance(override: float, message_variance: float) -> float:
    """Return the variance in use: ``override`` when it is set (> 0), else the message's."""
    if override > 0.0:
        return float(override)
    return float(message_variance)


def measurement_noise(settings, variance_m2: float,
                      velocity_variance_m2s2: Optional[float] = None) -> np.ndarray:
    """
    Return the R (m, m) a message's variances are fused with: THE estimator's R.

    Each override (``measurement_variance``, ``measurement_velocity_variance``, when
    > 0) replaces the message's variance; a velocity variance makes R 2x2 (diagonal).
    This array, checked by :func:`check_measurement`, is what the model's update gets.
    """
    R = override_variance(settings.measurement_variance, variance_m2)
    if velocity_variance_m2s2 is None:
        return np.array([[R]])
    return np.array([[R, 0.0], [0.0, override_variance(
        settings.measurement_velocity_variance, velocity_variance_m2s2)]])


def check_stamp(stamp_ns) -> int:
    """Return the stamp as an int; raise ValueError unless it is an integer."""
    if not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool):
        raise ValueError(f'stamp_ns must be an integer, got {stamp_ns!r}')
    return int(stamp_ns)


def check_measurement(settings, model, preset_name: str, max_future_ns: int,
                      stamp_ns: int, position_m, variance_m2, frame_id: Optional[str],
                      now_ns: Optional[int], velocity_mps,
                      velocity_variance_m2s2) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return (z, R) of a measurement, or raise Rejected (or ValueError) as documented.

    A ``model`` with two measurements measures the velocity too. ``stamp_ns`` is
    already an int (:func:`check_stamp`).
    """
    measures_velocity = model.dim_z == 2
    if measures_velocity != (velocity_mps is not None) or (
            (velocity_mps is None) != (velocity_variance_m2s2 is None)):
        raise ValueError(
            f'preset {preset_name!r} measures {list(model.measurement_names)}:'
            ' velocity_mps and velocity_variance_m2s2 must be given '
            + ('both' if measures_velocity else 'neither'))
    s = settings
    if s.expected_frame_id and frame_id is not None and frame_id != s.expected_frame_id:
        raise Rejected('wrong_frame', f'frame_id {frame_id!r} is not the expected '
                       f'{s.expected_frame_id!r}')
    try:
        values = [float(position_m), float(variance_m2)]
        if measures_velocity:
            values += [float(velocity_mps), float(velocity_variance_m2s2)]
    except (TypeError, ValueError):
        raise ValueError(
            f'position, velocity and variances must be numbers, got {position_m!r}, '
            f'{variance_m2!r}, {velocity_mps!r}, {velocity_variance_m2s2!r}') from None
    position_m, variance_m2 = values[:2]
    # R is built once, in the shape the update takes, and checked here (non-finite
    # message variances are rejected before R is read).
    R = measurement_noise(s, variance_m2, values[3] if measures_velocity else None)
    if not math.isfinite(position_m):
        raise Rejected('non_finite', f'position must be finite, got {position_m}')
    if not math.isfinite(variance_m2):
        raise Rejected('non_finite', f'measurement variance must be finite, got {variance_m2}')
    if R.item(0) <= 0.0:
        raise Rejected('bad_variance', f'measurement variance must be > 0, got {R.item(0)}')
    if measures_velocity:
        velocity_mps, velocity_variance = values[2:]
        if not math.isfinite(velocity_mps):
            raise Rejected('non_finite', f'velocity must be finite, got {velocity_mps}')
        if not math.isfinite(velocity_variance):
            raise Rejected('non_finite',
                           f'velocity variance must be finite, got {velocity_variance}')
        if R.item(3) <= 0.0:
            raise Rejected('bad_variance', f'velocity variance must be > 0, got {R.item(3)}')
        _check_time('', stamp_ns, now_ns, max_future_ns, s.max_future_s)
        return np.array([position_m, velocity_mps]), R
    _check_time('', stamp_ns, now_ns, max_future_ns, s.max_future_s)
    return np.array([position_m]), R


def check_velocity(settings, max_future_ns: int, stamp_ns: int, velocity_mps,
                   variance_m2s2, now_ns: Optional[int]) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return (z, R) of a speed measurement, or raise Rejected (or ValueError).

    The checks and their order are a position's: numbers, finite, R > 0 (the
    ``measurement_velocity_variance`` override, when set, else the message's),
    stamp > 0, not too far ahead of ``now_ns``.
    """
    try:
        velocity_mps, variance_m2s2 = float(velocity_mps), float(variance_m2s2)
    except (TypeError, ValueError):
        raise ValueError(f'velocity and its variance must be numbers, got {velocity_mps!r}, '
                         f'{variance_m2s2!r}') from None
    if not math.isfinite(velocity_mps):
        raise Rejected('non_finite', f'velocity must be finite, got {velocity_mps}')
    if not math.isfinite(variance_m2s2):
        raise Rejected('non_finite', f'velocity variance must be finite, got {variance_m2s2}')
    R = override_variance(settings.measurement_velocity_variance, variance_m2s2)
    if R <= 0.0:
        raise Rejected('bad_variance', f'velocity variance must be > 0, got {R}')
    _check_time('velocity ', stamp_ns, now_ns, max_future_ns, settings.max_future_s)
    return np.array([velocity_mps]), np.array([[R]])


def check_control(preset, max_future_ns: int, max_future_s: float, stamp_ns: int, u,
                  now_ns: Optional[int]) -> np.ndarray:
    """Return the control as a read-only vector, or raise Rejected (or ValueError)."""
    try:
        u = np.array(u, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f'u must be numeric, got {u!r}') from None
    if u.shape != (preset.dim_u,):
        raise ValueError(f'u must have {preset.dim_u} entries '
                         f'({", ".join(preset.control_names)}), got {u.shape[0]}')
    if not np.all(np.isfinite(u)):
        raise Rejected('non_finite', f'control must be finite, got {u.tolist()}')
    _check_time('control ', stamp_ns, now_ns, max_future_ns, max_future_s)
    u.setflags(write=False)
    return u


def _check_time(what: str, stamp_ns: int, now_ns: Optional[int], max_future_ns: int,
                max_future_s: float) -> None:
    """Raise Rejected for a zero stamp or one too far ahead of ``now_ns``."""
    if stamp_ns <= 0:
        raise Rejected('zero_stamp',
                       f'{what}stamp must be > 0 (a set header stamp), got {stamp_ns}')
    if now_ns and stamp_ns - now_ns > max_future_ns:
        raise Rejected('future_stamp', (
            f'{what}stamp {stamp_ns} ns is {(stamp_ns - now_ns) / 1e9:.3f} s ahead of the '
            f'clock, more than max_future_s = {max_future_s}'))
