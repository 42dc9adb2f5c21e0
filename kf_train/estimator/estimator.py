"""
The live estimator as a pure state machine: stamped measurements and controls in, estimates out.

It runs any 1-D preset of :mod:`kf_train.presets.loader` on a stream (``preset``:
``train`` by default, ``car``, ``car-exact``, ``robot``, ``robot-exact``,
``cv-position``, ``cv-position-velocity``, or the path of a preset YAML file of the
same shape; see :func:`check_live_preset`). The preset brings the model, the initial
state and covariance, the nominal period and the horizon; a setting that is not None
overrides the preset's value.

The filter (``filter``, fixed for the estimator's life like the preset) is ``kf``
(default), ``ekf`` (the KF on these linear presets), ``ukf``, ``pf`` (the regularised
particle filter) or ``bootstrap-pf`` (the plain bootstrap filter): each is a pure
``predict(x, P, dt, u)``/``update(x, P, z, R)`` model, so the input contract, the χ²
gate (on the filter's own NIS), the out-of-sequence replay, controls and resets work
alike for all. The particle filter keeps the particles behind every kept mean, so a
rewind restores them and the generator, and a replay repeats its draws bit for bit.
The train's KF runs in closed form (:class:`_FastTrainModel`; equal to the generic
path to rounding, ~4x cheaper).

Time is kept in integer nanoseconds (as ROS stamps are), so that dt between two
stamps is exact: a float of epoch seconds has only ~0.2 µs resolution, which alone
would move the estimate by more than 1e-9.

Initialisation:

* ``prior`` (the seeds' mode): the initial state and covariance hold one nominal
  period before the first measurement's stamp; every measurement, the first
  included, is then a predict and an update.
* ``first_measurement`` (default): the first measurement sets the states it measures
  with its own variance; the other states (the velocity, unless measured) come from
  the initial state with a standard deviation of ``first_velocity_std_mps``, so the
  filter converges within a few samples even when it joins a train that is far down
  the track. (With Q = 0 the seed's prior would lock the filter onto its wrong
  initial velocity.)

Controls (presets with a control input: ``car``, acceleration [m/s²]; ``robot``,
velocity [m/s]), fed by :meth:`TrainEstimator.add_control`:

* A control stamped t_k is the input applied over the interval (t_{k-1}, t_k] that
  *ends* at t_k (SEEDS.md). The latest value received for a stamp is kept.
* A prediction from t_a to t_b is split at every control stamp inside (t_a, t_b):
  each piece uses the control of the interval it lies in. The last piece uses the
  control stamped t_b; if that has not arrived, the control of the interval that
  contains t_b (the first later stamp), else the latest earlier one (zero-order
  hold), else zero. Such a fusion is counted as ``provisional``.
* A control that arrives after a measurement that needed it (the topics are not
  ordered against each other) is applied by rewinding to the last state before it
  and replaying the later measurements, as an out-of-sequence measurement is; the
  result is what in-order arrival would have given, whatever the order. This works
  within ``history_s`` (0 turns it off); a control too old for that is rejected as
  ``stale_stamp``. So the estimate never waits for a control, and is exact once the
  control is in.
* The prediction ``horizon_s`` ahead holds the control of the newest interval.
* Controls are kept while a replay or the next prediction may need them: from the
  oldest state kept for replay on (all of them before the first measurement), at
  most MAX_CONTROLS (the oldest go first).

Input contract: :meth:`TrainEstimator.process` raises :class:`Rejected` (a
``ValueError``) with a ``reason`` from :data:`REJECTION_REASONS` for a measurement it
will not fuse, and the filter state (x, P, last stamp, history) is then exactly as
before, unless the rejection itself triggered a reset (``Rejected.reset``). The
checks, cheapest first:

* ``wrong_frame``: ``expected_frame_id`` is set and the measurement's frame differs;
* ``non_finite``: NaN or Inf in a measured value or the message's variance;
* ``bad_variance``: a variance in use (the override, else the message's) <= 0;
* ``zero_stamp``: a stamp <= 0 (an unset header);
* ``future_stamp``: more than ``max_future_s`` after ``now_ns``, when that is given;
* ``duplicate_stamp``: a stamp already fused;
* ``stale_stamp``: older than the newest fused one by ``history_s`` or more;
* ``outlier``: the NIS exceeds the χ² gate (``gate_probability``);
* ``numerical``: the update could not be computed in floating point.

:meth:`TrainEstimator.add_control` rejects likewise, counted apart by
:data:`CONTROL_REJECTION_REASONS`.

Time handling:

* A measurement older than the newest fused one but by less than ``history_s`` is
  fused out of sequence: the filter rewinds to the state after the last measurement
  before it, fuses it, and replays the later measurements (each with the R and model
  it was first fused with, and the controls known now). The result equals in-order
  processing to rounding. Replayed measurements are not gated again. A measurement
  older than the first one since (re)initialisation re-initialises from it and
  replays everything, as in-order processing would have.
* ``restart_after_stale`` consecutive stale measurements mean the stream restarted
  (a bag loop, a restarted sensor): the filter resets and initialises from the last
  of them.
* ``max_consecutive_outliers`` consecutive gate (or numerical) rejections reset the
  filter; the next measurement initialises it, from the measurement itself as in
  ``first_measurement`` mode even in ``prior`` mode (the prior is what the data
  contradicted). The initialising measurement is never gated, so the filter cannot
  stay locked out. Other resets re-initialise in the configured mode. A clock jump
  or a stream restart also forgets the controls (their stamps belong to the old
  time line).

Every rejection and reset is counted by reason (:attr:`TrainEstimator.rejection_counts`,
:attr:`TrainEstimator.reset_counts`, :attr:`TrainEstimator.control_rejection_counts`).
"""

import bisect
import collections
from dataclasses import dataclass, replace
import math
import os
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple
import weakref

from kf_train.filters.chi2 import chi2_quantile
from kf_train.filters.family import DEFAULT_PARTICLES, FILTER_KINDS, PARTICLE_KINDS
from kf_train.filters.fast import correct, white_noise_terms
from kf_train.filters.kalman import UpdateResult
from kf_train.filters.models import constant_velocity_model, LinearModel, WhiteNoiseAcceleration
from kf_train.filters.particle import DEFAULT_RESAMPLE_THRESHOLD, ParticleFilter
from kf_train.filters.regularised_pf import RegularisedParticleFilter
from kf_train.filters.ukf import DEFAULT_ALPHA, DEFAULT_BETA, DEFAULT_KAPPA, UnscentedModel
from kf_train.filters.validation import as_covariance, as_finite_array, as_vector
from kf_train.presets.loader import load_preset, load_preset_file, Preset, PRESET_NAMES
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

CONTROL_REJECTION_REASONS = ('non_finite', 'zero_stamp', 'future_stamp', 'stale_stamp',
                             'numerical')
"""Why a control was not used; keys of :attr:`TrainEstimator.control_rejection_counts`."""

RESET_REASONS = ('manual', 'set_state', 'clock_jump', 'stream_restart', 'outlier_lockout',
                 'non_finite')
"""Why the filter was reset; keys of :attr:`TrainEstimator.reset_counts`."""

LIVE_STATES = (('position', 'velocity'), ('position',))
"""State names a live preset may have: 1-D constant velocity, or position alone."""
LIVE_MEASUREMENTS = (('position',), ('position', 'velocity'))
"""Measurement names a live preset may have."""
LIVE_CONTROLS = ((), ('acceleration',), ('velocity',))
"""Control names a live preset may have (at most one: acceleration or velocity)."""
LIVE_PRESETS = ('train', 'car', 'car-exact', 'robot', 'robot-exact', 'cv-position',
                'cv-position-velocity')
"""The shipped presets the live estimator runs (range-bearing is 2-D: offline only)."""

# Ranges shared with the node's parameter descriptors.
GATE_PROBABILITY_RANGE = (0.5, 1.0)
HISTORY_S_RANGE = (0.0, 60.0)
MAX_CONSECUTIVE_OUTLIERS_RANGE = (1, 1_000_000)
RESTART_AFTER_STALE_RANGE = (2, 1_000_000)
MAX_FUTURE_S_RANGE = (0.0, 1e9)
UKF_ALPHA_RANGE = (1e-4, 10.0)
UKF_BETA_RANGE = (0.0, 100.0)
UKF_KAPPA_RANGE = (-0.999, 100.0)  # n + kappa > 0 for every live preset (n >= 1)
PF_PARTICLES_RANGE = (1, 1_000_000)
PF_SEED_RANGE = (0, 2 ** 31 - 1)
PF_RESAMPLE_THRESHOLD_RANGE = (0.0, 1.0)
FILTER_SETTINGS = ('filter', 'ukf_alpha', 'ukf_beta', 'ukf_kappa', 'pf_particles', 'pf_seed',
                   'pf_resample_threshold')
"""Settings fixed for an estimator's life (like the preset): they choose the filter."""
# Controls kept at most (a control stream running while no measurement comes).
MAX_CONTROLS = 100_000
# Distinct dt values whose F, Q and B a preset model keeps computed.
_MODEL_CACHE_SIZE = 64


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


def covariance_to_list(P: np.ndarray) -> Tuple[float, ...]:
    """Return a covariance as covariance_from_list takes it: the diagonal if P is diagonal."""
    P = np.asarray(P, dtype=float)
    if np.count_nonzero(P - np.diag(np.diag(P))) == 0:
        return tuple(float(v) for v in np.diag(P))
    return tuple(float(v) for v in P.ravel())


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


# -- presets -----------------------------------------------------------------------------

_PRESET_CACHE: Dict[Tuple[str, int], Preset] = {}


def resolve_preset(spec: str) -> Preset:
    """
    Return the preset ``spec`` names: a shipped one, or a YAML file (a path).

    A value ending in .yaml/.yml or containing a path separator is a file. Files are
    read again only when they change. Raises ValueError naming ``preset``.
    """
    if not isinstance(spec, str) or not spec:
        raise ValueError(f'preset must be a preset name or a YAML file, got {spec!r}')
    is_file = spec.endswith(('.yaml', '.yml')) or os.sep in spec or '/' in spec
    if not is_file and spec not in PRESET_NAMES:
        raise ValueError(f"preset must be one of {', '.join(LIVE_PRESETS)} or the path of a "
                         f'preset YAML file, got {spec!r}')
    try:
        key = (spec, os.stat(spec).st_mtime_ns if is_file else 0)
    except OSError as error:
        raise ValueError(f'preset must be a readable file: {spec}: {error.strerror}') from None
    if key not in _PRESET_CACHE:
        try:
            preset = load_preset_file(spec) if is_file else load_preset(spec)
        except ValueError as error:
            raise ValueError(f'preset must be a valid preset file: {error}') from None
        check_live_preset(preset)
        if len(_PRESET_CACHE) > 32:
            _PRESET_CACHE.clear()
        _PRESET_CACHE[key] = preset
    return _PRESET_CACHE[key]


def check_live_preset(preset: Preset) -> None:
    """
    Raise ValueError unless the live estimator can run ``preset``.

    It needs a linear model of a 1-D position (states [position, velocity] or
    [position]), measuring the position (and optionally the velocity), with at most
    one control named acceleration [m/s²] or velocity [m/s], and with process noise
    that does not depend on the dt's history (any preset file qualifies).
    """
    problems = []
    if not preset.linear:
        problems.append('its measurement model is not linear')
    if preset.state_names not in LIVE_STATES:
        problems.append(f'its states are {list(preset.state_names)}, not [position, '
                        'velocity] or [position]')
    if preset.measurement_names not in LIVE_MEASUREMENTS:
        problems.append(f'it measures {list(preset.measurement_names)}, not [position] or '
                        '[position, velocity]')
    if preset.control_names not in LIVE_CONTROLS:
        problems.append(f'its controls are {list(preset.control_names)}, not none, '
                        '[acceleration] or [velocity]')
    if problems:
        raise ValueError(f'preset must be a 1-D preset for the live estimator; '
                         f'{preset.name!r} cannot run live: {"; ".join(problems)} '
                         '(use kf-train replay for it)')


def preset_defaults(spec: str) -> Dict[str, object]:
    """Return the settings a preset supplies: initial state and covariance, period, horizon."""
    preset = resolve_preset(spec)
    return {
        'initial_state': tuple(float(v) for v in preset.initial_state),
        'initial_covariance': covariance_to_list(preset.initial_covariance),
        'nominal_period_s': float(preset.nominal_period_s),
        'horizon_s': float(preset.horizon_s or 0.0),
    }


class _CachedModel(LinearModel):
    """A preset's linear model with F(dt), Q(dt) and B(dt) computed once per dt."""

    def __init__(self, model: LinearModel, extra_Q: Optional[Callable] = None):
        """Wrap ``model``; ``extra_Q(dt)``, if given, is added to its process noise."""
        base_Q = model.Q
        Q = base_Q if extra_Q is None else (lambda dt: base_Q(dt) + extra_Q(dt))
        super().__init__(self._cached(model.F), self._cached(Q), model.H, model.R,
                         B=None if model.B is None else self._cached(model.B),
                         state_names=model.state_names,
                         measurement_names=model.measurement_names,
                         control_names=model.control_names)

    @staticmethod
    def _cached(function: Callable) -> Callable:
        """Return ``function`` of dt remembering its latest _MODEL_CACHE_SIZE results."""
        cache: Dict[float, np.ndarray] = {}

        def cached(dt):
            key = float(dt)
            value = cache.get(key)
            if value is None:
                value = function(dt)
                value.setflags(write=False)  # shared between calls: never modified
                if len(cache) >= _MODEL_CACHE_SIZE:
                    cache.clear()
                cache[key] = value
            return value
        return cached


def _is_constant_velocity(preset: Preset) -> bool:
    """Return whether the preset's states are [position, velocity] with F = [[1, dt], [0, 1]]."""
    return (preset.state_names == ('position', 'velocity')
            and np.array_equal(preset.dynamics.A, [[0.0, 1.0], [0.0, 0.0]]))


def _selector(preset: Preset) -> Optional[Tuple[int, ...]]:
    """Return, per measurement, the state it measures (H a selection), or None."""
    H = preset.model.H
    indices = []
    for row in H:
        hits = np.flatnonzero(row)
        if hits.size != 1 or row[hits[0]] != 1.0:
            return None
        indices.append(int(hits[0]))
    return tuple(indices) if len(set(indices)) == len(indices) else None


@dataclass(frozen=True)
class EstimatorSettings:
    """
    Everything that configures a :class:`TrainEstimator`, with seed-000 defaults.

    The defaults reproduce the seed exactly: no gate and no out-of-sequence fusion.
    The estimator node turns on out-of-sequence fusion by default (see its
    parameters). ``initial_state``, ``initial_covariance``, ``horizon_s`` and
    ``nominal_period_s`` None take the preset's values.
    """

    initial_state: Optional[Tuple[float, ...]] = None
    """The preset's states [position m, velocity m/s] (or [position m]); None: the
    preset's (train: [0, 5], half the true speed as in seed 000)."""
    initial_covariance: Optional[Tuple[float, ...]] = None
    """Diagonal (n values) or row-major full matrix (n² values); None: the preset's."""
    process_noise_density: float = 0.0
    """White-noise acceleration density q [m²/s³], Q(dt) = q·[[dt³/3, dt²/2], [dt²/2, dt]],
    added to the preset's own process noise (train's is 0, as in seed 000). Only for
    presets with [position, velocity] states."""
    measurement_variance: float = 0.0
    """R of the position [m²] overriding the message's variance; 0 uses the message's."""
    horizon_s: Optional[float] = None
    """How far ahead the prediction is [s]; None: the preset's (0 when it has none)."""
    initialization: str = 'first_measurement'
    nominal_period_s: Optional[float] = None
    """Prior mode: how long before the first stamp the prior holds; None: the preset's."""
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
    preset: str = 'train'
    """The filter: a name from LIVE_PRESETS or the path of a preset YAML file."""
    measurement_velocity_variance: float = 0.0
    """R of a measured velocity [m²/s²] overriding the message's; 0 uses the message's."""
    filter: str = 'kf'  # noqa: A003 (the node parameter's name)
    """The filter kind (:data:`kf_train.filters.family.FILTER_KINDS`): ``kf`` (exact, the
    default), ``ekf`` (the same on these linear presets), ``ukf``, ``pf`` (regularised)
    or ``bootstrap-pf``."""
    ukf_alpha: float = DEFAULT_ALPHA
    """UKF sigma-point spread α > 0."""
    ukf_beta: float = DEFAULT_BETA
    """UKF prior-knowledge weight β (2 is optimal for a Gaussian)."""
    ukf_kappa: float = DEFAULT_KAPPA
    """UKF secondary scaling κ (n + κ > 0)."""
    pf_particles: int = DEFAULT_PARTICLES
    """Particle filter: number of particles."""
    pf_seed: int = 0
    """Particle filter: seed of its generator (restarted from it at every initialisation)."""
    pf_resample_threshold: float = DEFAULT_RESAMPLE_THRESHOLD
    """Particle filter: resample when the effective sample size < this · pf_particles."""

    def resolved(self) -> 'EstimatorSettings':
        """Return a copy with the preset's values where a field is None (see preset_defaults)."""
        defaults = preset_defaults(self.preset)
        return replace(self, **{name: value for name, value in defaults.items()
                                if getattr(self, name) is None})

    def validated(self) -> 'EstimatorSettings':
        """Return self after checking every field; raise ValueError naming the field."""
        preset = resolve_preset(self.preset)
        n = preset.dim_x
        if self.initial_state is not None:
            as_vector('initial_state', self.initial_state, n)
        if self.initial_covariance is not None:
            covariance_from_list('initial_covariance', self.initial_covariance, n)
        for name in ('process_noise_density', 'measurement_variance', 'horizon_s',
                     'nominal_period_s', 'first_velocity_std_mps',
                     'measurement_velocity_variance'):
            if getattr(self, name) is None and name in ('horizon_s', 'nominal_period_s'):
                continue
            value = as_finite_array(name, getattr(self, name))
            if value.ndim != 0 or float(value) < 0.0:
                raise ValueError(f'{name} must be a finite number >= 0, got {value}')
        if self.nominal_period_s is not None and self.nominal_period_s <= 0.0:
            raise ValueError(f'nominal_period_s must be > 0, got {self.nominal_period_s}')
        if self.first_velocity_std_mps <= 0.0:
            raise ValueError(
                f'first_velocity_std_mps must be > 0, got {self.first_velocity_std_mps}')
        if self.process_noise_density > 0.0 and not _is_constant_velocity(preset):
            raise ValueError(
                f'process_noise_density must be 0 for preset {preset.name!r}: a white-noise '
                'acceleration needs [position, velocity] states (edit process_noise in '
                'a preset file instead)')
        if self.initialization not in INITIALIZATIONS:
            raise ValueError(
                f'initialization must be one of {INITIALIZATIONS}, '
                f'got {self.initialization!r}')
        if self.initialization == 'first_measurement' and _selector(preset) is None:
            raise ValueError(
                f'initialization must be prior for preset {preset.name!r}: first_measurement '
                'needs measurements that are states (H selecting them)')
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
        if self.filter not in FILTER_KINDS:
            raise ValueError(f"filter must be one of {', '.join(FILTER_KINDS)}, "
                             f'got {self.filter!r}')
        _check_float_range('ukf_alpha', self.ukf_alpha, *UKF_ALPHA_RANGE)
        _check_float_range('ukf_beta', self.ukf_beta, *UKF_BETA_RANGE)
        _check_float_range('ukf_kappa', self.ukf_kappa, *UKF_KAPPA_RANGE)
        _check_int_range('pf_particles', self.pf_particles, *PF_PARTICLES_RANGE)
        _check_int_range('pf_seed', self.pf_seed, *PF_SEED_RANGE)
        _check_float_range('pf_resample_threshold', self.pf_resample_threshold,
                           *PF_RESAMPLE_THRESHOLD_RANGE)
        return self


class EstimateStep(NamedTuple):
    """The filter's output after one measurement (or one late control)."""

    stamp_ns: int
    """Time of x and P: the newest fused stamp (later than the measurement's if replayed)."""
    x: np.ndarray
    P: np.ndarray
    update: Optional[UpdateResult]
    """The measurement's innovation; None when it initialised the filter (first_measurement)
    or when a late control caused the step."""
    prediction_stamp_ns: int
    predicted_x: np.ndarray
    predicted_P: np.ndarray
    measurement_stamp_ns: int = 0
    """The fused measurement's own stamp (0 for a step caused by a control)."""
    replayed: int = 0
    """How many fused measurements were replayed after this out-of-sequence one (or
    recomputed with a late control)."""
    reset: Optional[str] = None
    """A reset this measurement triggered before initialising the filter (stream_restart)."""
    control_stamp_ns: int = 0
    """The late control that caused this step, or 0 for a measurement's step."""


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


class _FastTrainModel:
    """
    Seed 000's train model with ``predict``/``update`` in closed form on plain floats.

    The same interface and results (to rounding) as the generic LinearModel with
    F(dt) = [[1, dt], [0, 1]], Q(dt) = q·[[dt³/3, dt²/2], [dt²/2, dt]], H = [1, 0],
    at a fraction of the cost: no numpy call but the arrays it returns, and no
    re-validation of the estimator's own, already checked, arrays. The update is
    :func:`kf_train.filters.fast.correct` (the Joseph form reduced for the optimal gain).
    Non-finite results and a zero S raise ValueError as the generic path does.
    """

    def __init__(self, model: LinearModel, q: float):
        """Mirror ``model`` (the generic train model with density q)."""
        self.base = model
        self.state_names = model.state_names
        self.measurement_names = model.measurement_names
        self.control_names = model.control_names
        self.dim_x, self.dim_z = 2, 1
        self.F, self.Q, self.B, self.H, self.R = model.F, model.Q, None, model.H, model.R
        self._q = float(q)
        self._noise = (None, 0.0, 0.0, 0.0)  # (dt, Q00, Q01, Q11) of the latest dt

    def _terms(self, dt_s) -> Tuple[float, float, float, float]:
        """Return (dt, Q00, Q01, Q11) for dt_s, checked and cached for a steady rate."""
        noise = self._noise
        if dt_s == noise[0]:
            return noise
        dt = float(dt_s)
        if not 0.0 <= dt < math.inf:
            raise ValueError(f'dt must be a finite number >= 0, got {dt_s!r}')
        try:
            noise = (dt,) + white_noise_terms(self._q, dt)
        except OverflowError:
            raise ValueError('prediction produced a non-finite state; inputs are too '
                             'large') from None
        self._noise = noise
        return noise

    def predict(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return (x⁻, P⁻) over dt_s: x⁻ = F x, P⁻ = F P Fᵀ + Q."""
        if u is not None:
            raise ValueError('u given to a model without control input')
        dt, q00, q01, q11 = self._terms(dt_s)
        x0, x1 = x.tolist()
        (p00, p01), (p10, p11) = P.tolist()
        p01 = 0.5 * (p01 + p10)  # the generic path symmetrises too
        p01_dt = p01 + dt * p11
        x0 = x0 + dt * x1                       # x⁻ = F x
        p00 = p00 + dt * (p01 + p01_dt) + q00   # P⁻00 = P00 + dt (P01 + P01 + dt P11) + Q00
        p01 = p01_dt + q01                      # P⁻01 = P01 + dt P11 + Q01
        p11 = p11 + q11                         # P⁻11 = P11 + Q11
        if not 0.0 * (x0 + x1 + p00 + p01 + p11) == 0.0:
            raise ValueError('prediction produced a non-finite state; inputs are too large')
        return np.array((x0, x1)), np.array(((p00, p01), (p01, p11)))

    def update(self, x, P, z, R=None) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
        """Return (x, P, UpdateResult) after position measurement z of variance R."""
        x0, x1 = x.tolist()
        (p00, p01), (p10, p11) = P.tolist()
        p01 = 0.5 * (p01 + p10)
        r = float((self.R if R is None else R)[0][0])
        try:
            (y0, y1, n00, n01, n11), result = correct(x0, x1, p00, p01, p11, float(z[0]), r)
        except ZeroDivisionError:
            raise ValueError(f'innovation covariance S = H P Hᵀ + R is singular: '
                             f'[[{p00 + r}]]') from None
        nis = result.nis
        if not (0.0 * (y0 + y1 + n00 + n01 + n11) == 0.0 and 0.0 <= nis < math.inf):
            raise ValueError(f'update produced a non-finite state or an invalid NIS {nis}; '
                             f'S = [[{result.innovation_variance}]]')
        k0, k1 = result.gain
        return (np.array((y0, y1)), np.array(((n00, n01), (n01, n11))),
                UpdateResult(np.array((result.innovation,)),
                             np.array(((result.innovation_variance,),)), nis,
                             np.array(((k0,), (k1,)))))


class _ParticleModel:
    """
    A particle filter behind the pure ``predict(x, P, dt, u)``/``update`` interface.

    The estimator keeps states as (x, P) and rewinds by going back to an older pair.
    Each mean this model returns stands for its particles: their snapshot (particles,
    log-weights, generator state) is kept in ``states`` under the mean's id until
    the mean is garbage-collected. A step restores the snapshot of the mean it is
    given, so rewinding and replaying repeats the same draws bit for bit. A mean that
    has no particles (an initialisation, set_state) is sampled as N(x, P) by a
    generator restarted from the seed: deterministic too.
    """

    def __init__(self, model: LinearModel, particles: int, seed: int,
                 resample_threshold: float, states: Dict[int, object],
                 filter_class=RegularisedParticleFilter):
        """Run ``model`` with ``particles`` particles; keep snapshots in ``states``."""
        self.base = model
        self.state_names = model.state_names
        self.measurement_names = model.measurement_names
        self.control_names = model.control_names
        self.dim_x, self.dim_z = model.dim_x, model.dim_z
        self.F, self.Q, self.B, self.H, self.R = model.F, model.Q, model.B, model.H, model.R
        self.seed = seed
        self.states = states
        n = model.dim_x
        self.filter = filter_class(model, np.zeros(n), np.zeros((n, n)),
                                   n_particles=particles, seed=seed,
                                   resample_threshold=resample_threshold)

    def _load(self, x: np.ndarray, P: np.ndarray) -> None:
        """Make the filter's particles those behind x (drawn from N(x, P) if none)."""
        snapshot = self.states.get(id(x))
        if snapshot is None or snapshot[0]() is not x:
            self.filter.reset(x, P, self.seed)
        else:
            self.filter.restore(snapshot[1])

    def _keep(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return the filter's (mean, covariance), the mean remembering the particles."""
        x, P = self.filter.mean, self.filter.covariance
        key = id(x)
        # A weak reference tells the mean from a later array with the same id; the
        # snapshot goes when the mean is freed (nothing can rewind to it any more).
        self.states[key] = (weakref.ref(x), self.filter.snapshot())
        weakref.finalize(x, self.states.pop, key, None)
        return x, P

    def predict(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the particles' moments after moving them over dt_s."""
        self._load(x, P)
        self.filter.predict(dt_s, u)
        return self._keep()

    def predict_ahead(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the exact moments dt_s ahead of the particles behind x (no draws)."""
        self._load(x, P)
        return self.filter.predict_ahead(dt_s, u)

    def update(self, x, P, z, R=None):
        """Return (mean, covariance, UpdateResult) after weighting by z's likelihood."""
        self._load(x, P)
        result = self.filter.update(z, R)
        x, P = self._keep()
        return x, P, result


class _Controls:
    """Control inputs by stamp (the latest value per stamp), sorted by stamp."""

    def __init__(self, dim_u: int):
        """Start empty; controls have ``dim_u`` components."""
        self.stamps: List[int] = []
        self.values: Dict[int, np.ndarray] = {}
        self.zero = np.zeros(dim_u)
        self.zero.setflags(write=False)

    def __len__(self) -> int:
        """Return how many stamps have a control."""
        return len(self.stamps)

    def previous_stamp(self, stamp_ns: int) -> Optional[int]:
        """Return the latest control stamp before ``stamp_ns``, or None."""
        i = bisect.bisect_left(self.stamps, stamp_ns)
        return self.stamps[i - 1] if i else None

    def put(self, stamp_ns: int, u: np.ndarray) -> Optional[np.ndarray]:
        """Store u at stamp_ns; return the value it replaces (None if new)."""
        old = self.values.get(stamp_ns)
        if old is None:
            if self.stamps and stamp_ns < self.stamps[-1]:
                bisect.insort(self.stamps, stamp_ns)
            else:
                self.stamps.append(stamp_ns)
        self.values[stamp_ns] = u
        return old

    def restore(self, stamp_ns: int, old: Optional[np.ndarray]) -> None:
        """Undo put(stamp_ns, ...) that returned ``old``."""
        if old is None:
            del self.values[stamp_ns]
            self.stamps.remove(stamp_ns)
        else:
            self.values[stamp_ns] = old

    def inside(self, t_a: int, t_b: int) -> List[int]:
        """Return the control stamps c with t_a < c < t_b, in order."""
        stamps = self.stamps
        return stamps[bisect.bisect_right(stamps, t_a):bisect.bisect_left(stamps, t_b)]

    def for_interval_ending(self, stamp_ns: int) -> Tuple[np.ndarray, bool]:
        """
        Return (u, exact): the control of the interval that ends at stamp_ns.

        Exact when a control has that stamp; else the control of the interval that
        contains it (the first later stamp), else the latest earlier one (held), else 0.
        """
        u = self.values.get(stamp_ns)
        if u is not None:
            return u, True
        i = bisect.bisect_right(self.stamps, stamp_ns)
        if i < len(self.stamps):
            return self.values[self.stamps[i]], False
        if i:
            return self.values[self.stamps[i - 1]], False
        return self.zero, False

    def prune(self, cutoff_ns: int) -> None:
        """Forget controls older than cutoff_ns but the latest of them; keep MAX_CONTROLS."""
        stamps = self.stamps
        drop = max(bisect.bisect_left(stamps, cutoff_ns) - 1, len(stamps) - MAX_CONTROLS)
        if drop > 0:
            for stamp_ns in stamps[:drop]:
                del self.values[stamp_ns]
            del stamps[:drop]

    def clear(self) -> None:
        """Forget every control."""
        self.stamps.clear()
        self.values.clear()


class TrainEstimator:
    """Fuses stamped measurements (and controls) of a 1-D preset: the train by default."""

    fast_path = True
    """Run the train's KF in closed form (:class:`_FastTrainModel`); False: generic."""

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
        self._control_rejections = dict.fromkeys(CONTROL_REJECTION_REASONS, 0)
        self._resets = dict.fromkeys(RESET_REASONS, 0)
        self._fused = 0
        self._out_of_sequence = 0
        self._controls_accepted = 0
        self._controls_late = 0
        self._provisional = 0
        self.settings: Optional[EstimatorSettings] = None
        # The particle filter's particles behind each kept mean (see _ParticleModel).
        self._particle_states: Dict[int, object] = {}
        self._apply(settings.validated())
        p = self.preset.dim_u
        self._controls: Optional[_Controls] = _Controls(p) if p else None

    def _apply(self, settings: EstimatorSettings) -> None:
        """Install validated settings and everything derived from them."""
        if self.settings is not None:
            for name in ('preset',) + FILTER_SETTINGS:
                old, new = getattr(self.settings, name), getattr(settings, name)
                if new != old:
                    raise ValueError(f'{name} cannot change on a running estimator '
                                     f'({old!r} -> {new!r}); create a new one')
        preset = resolve_preset(settings.preset)
        model = self._make_model(settings, preset, self._particle_states, self.fast_path)
        initial_state = as_vector('initial_state', preset.initial_state
                                  if settings.initial_state is None
                                  else settings.initial_state, preset.dim_x)
        initial_covariance = (preset.initial_covariance if settings.initial_covariance is None
                              else covariance_from_list('initial_covariance',
                                                        settings.initial_covariance,
                                                        preset.dim_x))
        nominal_period_s = float(preset.nominal_period_s if settings.nominal_period_s is None
                                 else settings.nominal_period_s)
        horizon_s = float((preset.horizon_s or 0.0) if settings.horizon_s is None
                          else settings.horizon_s)
        # Everything is checked: install it.
        self.preset = preset
        self.model = model
        # The particle filter predicts ahead with exact moments (no draws); others predict.
        self._predict_ahead_function = getattr(model, 'predict_ahead', model.predict)
        self.settings = settings
        self.initial_state = initial_state
        self._initial_covariance = initial_covariance
        self.nominal_period_s = nominal_period_s
        self.horizon_s = horizon_s
        self._selector = _selector(preset)
        self._history_ns = seconds_to_ns(settings.history_s)
        self._max_future_ns = seconds_to_ns(settings.max_future_s)
        self._horizon_ns = seconds_to_ns(horizon_s)
        self._nominal_ns = seconds_to_ns(nominal_period_s)
        self._gate_threshold = chi2_quantile(settings.gate_probability, self.model.dim_z)
        if self._history_ns == 0:
            self._history.clear()

    @staticmethod
    def _make_model(settings: EstimatorSettings, preset: Preset,
                    particle_states: Optional[Dict[int, object]] = None, fast: bool = True):
        """
        Return the filter's pure model: the preset's, plus white-noise acceleration q if set.

        ``kf`` and ``ekf`` (an EKF of a linear model is the KF) use the linear model
        itself, ``ukf`` its unscented transform, ``pf`` and ``bootstrap-pf`` a
        :class:`_ParticleModel` on it (keeping its particles in ``particle_states``).
        With ``fast``, the train's KF is :class:`_FastTrainModel`, its closed form.
        """
        q = settings.process_noise_density
        if settings.preset == 'train':
            # Seed 000's model exactly as before presets: F(dt), Q(dt) = q·[...], H = [1, 0].
            model = constant_velocity_model(WhiteNoiseAcceleration(q))
            if fast and settings.filter in ('kf', 'ekf'):
                return _FastTrainModel(model, q)
        else:
            model = _CachedModel(preset.model, WhiteNoiseAcceleration(q) if q > 0.0 else None)
        if settings.filter == 'ukf':
            return UnscentedModel.from_model(model, alpha=settings.ukf_alpha,
                                             beta=settings.ukf_beta, kappa=settings.ukf_kappa)
        if settings.filter in PARTICLE_KINDS:
            return _ParticleModel(model, settings.pf_particles, settings.pf_seed,
                                  settings.pf_resample_threshold,
                                  {} if particle_states is None else particle_states,
                                  RegularisedParticleFilter if settings.filter == 'pf'
                                  else ParticleFilter)
        return model

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
    def control_rejection_counts(self) -> Dict[str, int]:
        """Return how many controls were rejected, by reason, since construction."""
        return dict(self._control_rejections)

    @property
    def control_counts(self) -> Dict[str, int]:
        """
        Return control statistics since construction.

        ``accepted``: controls taken; ``late``: of those, how many came after fused
        estimates that they apply to, and were applied by rewinding and replaying;
        ``provisional``: fusions that had to use another interval's control (or 0)
        because their own had not arrived (yet).
        """
        return {'accepted': self._controls_accepted, 'late': self._controls_late,
                'provisional': self._provisional}

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

    @property
    def has_control(self) -> bool:
        """Return whether the preset has a control input (see add_control)."""
        return self._controls is not None

    @property
    def control_count(self) -> int:
        """Return how many controls are kept (by stamp)."""
        return 0 if self._controls is None else len(self._controls)

    def reconfigure(self, settings: EstimatorSettings) -> None:
        """
        Use new settings from the next measurement on; the current state is kept.

        Initial state, covariance and initialisation mode matter again only at the
        next (re)initialisation. Measurements already fused keep the model and R they
        were fused with when they are replayed. The preset cannot change.
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
        if reason in ('clock_jump', 'stream_restart') and self._controls is not None:
            self._controls.clear()  # stamped on the old time line
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
        """Return R of the position: the override when set, else the message's variance."""
        if self.settings.measurement_variance > 0.0:
            return float(self.settings.measurement_variance)
        return float(message_variance_m2)

    def velocity_variance(self, message_variance_m2s2: float) -> float:
        """Return R of a measured velocity: the override when set, else the message's."""
        if self.settings.measurement_velocity_variance > 0.0:
            return float(self.settings.measurement_velocity_variance)
        return float(message_variance_m2s2)

    def _reject(self, reason: str, message: str, reset: Optional[str] = None,
                update: Optional[UpdateResult] = None) -> None:
        """Count a rejection and raise it."""
        self._rejections[reason] += 1
        raise Rejected(reason, message, reset, update)

    def _reject_control(self, reason: str, message: str) -> None:
        """Count a control rejection and raise it."""
        self._control_rejections[reason] += 1
        raise Rejected(reason, message)

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
                frame_id: Optional[str] = None, now_ns: Optional[int] = None,
                velocity_mps: Optional[float] = None,
                velocity_variance_m2s2: Optional[float] = None) -> EstimateStep:
        """
        Fuse one measurement; on ValueError the estimator state is unchanged.

        ``frame_id`` is checked against ``expected_frame_id`` when both are given;
        ``now_ns`` (the receiver's clock; None or 0 when unknown) bounds future stamps.
        ``velocity_mps`` and its variance are required exactly when the preset
        measures the velocity. Raises :class:`Rejected` for a measurement that breaks
        the input contract, a plain ValueError for a stamp that is not an integer or
        a velocity given to (or missing for) the wrong preset.
        """
        if not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool):
            raise ValueError(f'stamp_ns must be an integer, got {stamp_ns!r}')
        stamp_ns = int(stamp_ns)
        measures_velocity = self.model.dim_z == 2
        if measures_velocity != (velocity_mps is not None) or (
                (velocity_mps is None) != (velocity_variance_m2s2 is None)):
            raise ValueError(
                f'preset {self.preset.name!r} measures {list(self.model.measurement_names)}:'
                ' velocity_mps and velocity_variance_m2s2 must be given '
                + ('both' if measures_velocity else 'neither'))
        s = self.settings
        if s.expected_frame_id and frame_id is not None and frame_id != s.expected_frame_id:
            self._reject('wrong_frame', f'frame_id {frame_id!r} is not the expected '
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
        if not math.isfinite(position_m):
            self._reject('non_finite', f'position must be finite, got {position_m}')
        if not math.isfinite(variance_m2):
            self._reject('non_finite', f'measurement variance must be finite, got {variance_m2}')
        R = self.measurement_variance(variance_m2)
        if R <= 0.0:
            self._reject('bad_variance', f'measurement variance must be > 0, got {R}')
        if measures_velocity:
            velocity_mps, velocity_variance = values[2:]
            if not math.isfinite(velocity_mps):
                self._reject('non_finite', f'velocity must be finite, got {velocity_mps}')
            if not math.isfinite(velocity_variance):
                self._reject('non_finite',
                             f'velocity variance must be finite, got {velocity_variance}')
            R_velocity = self.velocity_variance(velocity_variance)
            if R_velocity <= 0.0:
                self._reject('bad_variance', f'velocity variance must be > 0, got {R_velocity}')
        if stamp_ns <= 0:
            self._reject('zero_stamp', f'stamp must be > 0 (a set header stamp), got {stamp_ns}')
        if now_ns and stamp_ns - now_ns > self._max_future_ns:
            self._reject('future_stamp', f'stamp {stamp_ns} ns is {(stamp_ns - now_ns) / 1e9:.3f}'
                         f' s ahead of the clock, more than max_future_s = {s.max_future_s}')
        if measures_velocity:
            z = np.array([position_m, velocity_mps])
            R_matrix = np.array([[R, 0.0], [0.0, R_velocity]])
        else:
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

    def add_control(self, stamp_ns: int, u, *, now_ns: Optional[int] = None
                    ) -> Optional[EstimateStep]:
        """
        Take the control applied over the interval that ends at ``stamp_ns``.

        Returns the corrected estimate when the control changed fused estimates (it
        came after a measurement that needed it; see the module docs), else None. On
        :class:`Rejected` (``CONTROL_REJECTION_REASONS``) nothing changes; a plain
        ValueError for a preset without control input, a stamp that is not an integer
        or a control of the wrong size.
        """
        if self._controls is None:
            raise ValueError(f'preset {self.preset.name!r} has no control input')
        if not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool):
            raise ValueError(f'stamp_ns must be an integer, got {stamp_ns!r}')
        stamp_ns = int(stamp_ns)
        try:
            u = np.array(u, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f'u must be numeric, got {u!r}') from None
        if u.shape != (self.preset.dim_u,):
            raise ValueError(f'u must have {self.preset.dim_u} entries '
                             f'({", ".join(self.preset.control_names)}), got {u.shape[0]}')
        if not np.all(np.isfinite(u)):
            self._reject_control('non_finite', f'control must be finite, got {u.tolist()}')
        if stamp_ns <= 0:
            self._reject_control('zero_stamp',
                                 f'control stamp must be > 0 (a set header stamp), got {stamp_ns}')
        if now_ns and stamp_ns - now_ns > self._max_future_ns:
            self._reject_control('future_stamp', (
                f'control stamp {stamp_ns} ns is {(stamp_ns - now_ns) / 1e9:.3f} s ahead of '
                f'the clock, more than max_future_s = {self.settings.max_future_s}'))
        u.setflags(write=False)
        controls = self._controls
        newest = self._last_stamp_ns
        if self._x is None or (not self._history and stamp_ns > newest):
            controls.put(stamp_ns, u)
            self._accept_control()
            self._prune_controls()
            return None
        if not self._history:
            self._reject_control('stale_stamp', (
                f'control stamp {stamp_ns} ns is not newer than the last fused measurement, '
                f'{newest} ns, and no state is kept to replay from (history_s = 0)'))
        entries = list(self._history)
        first = entries[0]
        prior_init = first.kind == 'init' and self.settings.initialization == 'prior'
        # Intervals ending after `floor` can be recomputed from the history.
        floor = first.stamp_ns - self._nominal_ns if prior_init else first.stamp_ns
        if stamp_ns <= floor:
            if first.kind == 'update':  # the states it applied to are no longer kept
                self._reject_control('stale_stamp', (
                    f'control stamp {stamp_ns} ns is older than the oldest state kept to '
                    f'replay from ({floor} ns; history_s = {self.settings.history_s})'))
            # It applies to a time before the filter started: kept, but nothing to redo.
            controls.put(stamp_ns, u)
            self._accept_control()
            return None
        previous = controls.previous_stamp(stamp_ns)
        old = controls.put(stamp_ns, u)
        if old is not None and np.array_equal(old, u):
            self._accept_control()
            return None
        # The first fused interval it can change ends after the previous control's stamp
        # (intervals up to there had their own control, or one at least as close).
        stamps = [entry.stamp_ns for entry in entries]
        start = 0 if previous is None else bisect.bisect_right(stamps, previous)
        if start == 0 and not prior_init:
            start = 1  # the first state came from a measurement or set_state, not a prediction
        if start >= len(entries):
            self._accept_control()
            self._prune_controls()
            return None
        try:
            if start == 0:
                x, P, _, u_end, _ = self._init_state(first.stamp_ns, first.z, first.R,
                                                     first.model)
                rebuilt = [first._replace(x=x, P=P)]
                rest = entries[1:]
            else:
                rebuilt, rest, u_end = entries[:start], entries[start:], None
            rebuilt, x, P, u_end = self._replay(rebuilt, rest, u_end)
            predicted = self._predict_ahead(x, P, u_end)
        except _NUMERICAL_ERRORS as error:
            controls.restore(stamp_ns, old)
            self._reject_control('numerical', f'replay with the control failed: {error}')
        self._history = collections.deque(rebuilt)
        self._x, self._P = x, P
        self._accept_control()
        self._controls_late += 1
        self._prune_controls()
        return EstimateStep(newest, x.copy(), P.copy(), None, newest + self._horizon_ns,
                            predicted[0], predicted[1], 0, len(entries) - start, None, stamp_ns)

    def _accept_control(self) -> None:
        """Count an accepted control."""
        self._controls_accepted += 1

    def _prune_controls(self) -> None:
        """Forget controls no replay or prediction can need any more."""
        controls = self._controls
        if controls is None or not controls.stamps:
            return
        if self._history:
            first = self._history[0]
            cutoff = first.stamp_ns - (self._nominal_ns if first.kind == 'init' else 0)
        elif self._last_stamp_ns is not None:
            cutoff = self._last_stamp_ns
        else:
            # Not initialised: the first measurement may need any of them (controls
            # fed ahead of the measurements, offline); only MAX_CONTROLS bounds them.
            cutoff = controls.stamps[0]
        controls.prune(cutoff)

    def _propagate(self, model: LinearModel, x, P, t_a: int, t_b: int,
                   dt_s: Optional[float] = None):
        """
        Return (x, P, u, exact) predicted from stamp t_a to t_b.

        Without control input one step of dt = t_b - t_a (or ``dt_s``). With it, the
        step is split at the control stamps inside (t_a, t_b); ``u`` is the control
        of the last piece, ``exact`` whether it was stamped t_b.
        """
        controls = self._controls
        if controls is None:
            x, P = model.predict(x, P, (t_b - t_a) / NS_PER_S if dt_s is None else dt_s)
            return x, P, None, True
        t = t_a
        for c in controls.inside(t_a, t_b):
            # x⁻ = F x + B u over (t, c], with the control of the interval ending at c
            x, P = model.predict(x, P, (c - t) / NS_PER_S, controls.values[c])
            t = c
        u, exact = controls.for_interval_ending(t_b)
        dt = dt_s if (dt_s is not None and t == t_a) else (t_b - t) / NS_PER_S
        x, P = model.predict(x, P, dt, u)
        return x, P, u, exact

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
        """Return (x, P, update result or None, u, exact) of the filter initialised by z."""
        if self.settings.initialization == 'prior' and not self._locked_out:
            x, P, u, exact = self._propagate(
                model, self.initial_state, self._initial_covariance,
                stamp_ns - self._nominal_ns, stamp_ns, self.nominal_period_s)
            x, P, result = model.update(x, P, z, R)
            return x, P, result, u, exact
        # Measured states from the measurement, the others from the initial state with
        # the wide first_velocity_std_mps.
        x = self.initial_state.copy()
        variances = [self.settings.first_velocity_std_mps ** 2] * x.shape[0]
        for i, j in enumerate(self._selector):
            x[j] = z[i]
            variances[j] = R[i, i]
        P = np.diag(variances)
        for i, j in enumerate(self._selector):
            for k, m in enumerate(self._selector):
                if i != k:
                    P[j, m] = R[i, k]
        u, exact = (None, True) if self._controls is None else (
            self._controls.for_interval_ending(stamp_ns))
        return x, P, None, u, exact

    def _initialise(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Start the filter from this measurement (never gated)."""
        try:
            x, P, result, u, exact = self._init_state(stamp_ns, z, R, self.model)
            predicted = self._predict_ahead(x, P, u)
        except _NUMERICAL_ERRORS as error:
            self._reject('numerical', f'initialisation failed: {error}')
        self._history.clear()
        # After a lock-out the state starts from the measurement: no rewinding past it.
        self._commit(stamp_ns, x, P, 'reinit' if self._locked_out else 'init', z, R)
        self._count_provisional(result is not None and not exact)
        self._locked_out = False
        return self._step(stamp_ns, x, P, result, predicted, stamp_ns)

    def _count_provisional(self, provisional: bool) -> None:
        """Count a fusion that used another interval's control."""
        if provisional:
            self._provisional += 1

    def _fuse_in_order(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Predict from the newest state to the stamp, gate, update, commit."""
        x, P, result, predicted, exact = self._gated_update(
            self._x, self._P, self._last_stamp_ns, stamp_ns, z, R)
        self._commit(stamp_ns, x, P, 'update', z, R)
        self._count_provisional(not exact)
        return self._step(stamp_ns, x, P, result, predicted, stamp_ns)

    def _gated_update(self, x0, P0, t_a: int, t_b: int, z: np.ndarray, R: np.ndarray):
        """Return (x, P, result, prediction ahead, exact) or reject as outlier/numerical."""
        try:
            x, P, u, exact = self._propagate(self.model, x0, P0, t_a, t_b)
            x, P, result = self.model.update(x, P, z, R)
        except _NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'update failed: {error}')
        if result.nis > self._gate_threshold:
            self._reject_update('outlier', (
                f'NIS {result.nis:.6g} exceeds the gate {self._gate_threshold:.6g} '
                f'(gate_probability {self.settings.gate_probability}); innovation '
                f'{np.array2string(result.innovation, precision=6)}'), result)
        try:
            predicted = self._predict_ahead(x, P, u)
        except _NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'prediction failed: {error}')
        return x, P, result, predicted, exact

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
                x, P, result, u, exact = self._init_state(stamp_ns, z, R, self.model)
            except _NUMERICAL_ERRORS as error:
                self._reject('numerical', f'initialisation failed: {error}')
            kind = 'init'
        else:
            anchor = entries[i - 1]
            x, P, result, _, exact = self._gated_update(
                anchor.x, anchor.P, anchor.stamp_ns, stamp_ns, z, R)
            u = None
            kind = 'update'
        rebuilt = entries[:i] + [_Entry(stamp_ns, z, R, self.model, x, P, kind)]
        try:
            # entries[i:] is never empty here: the newest fused stamp is later.
            rebuilt, x, P, u = self._replay(rebuilt, entries[i:], u)
            predicted = self._predict_ahead(x, P, u)
        except _NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'replay failed: {error}')
        self._history = collections.deque(rebuilt)
        self._x, self._P = x, P
        self._after_fusion()
        self._out_of_sequence += 1
        self._count_provisional(result is not None and not exact)
        return self._step(self._last_stamp_ns, x, P, result, predicted, stamp_ns,
                          replayed=len(entries) - i)

    def _replay(self, rebuilt: List[_Entry], rest: Sequence[_Entry], u):
        """Return (entries, x, P, u): ``rest`` re-fused after ``rebuilt``, as first fused."""
        x, P = rebuilt[-1].x, rebuilt[-1].P
        for entry in rest:
            x, P, u, _ = self._propagate(entry.model, x, P, rebuilt[-1].stamp_ns,
                                         entry.stamp_ns)
            x, P, _ = entry.model.update(x, P, entry.z, entry.R)
            rebuilt.append(entry._replace(x=x, P=P, kind='update'))
        if not rest and u is None and self._controls is not None:
            u = self._controls.for_interval_ending(rebuilt[-1].stamp_ns)[0]
        return rebuilt, x, P, u

    def _predict_ahead(self, x: np.ndarray, P: np.ndarray, u=None
                       ) -> Tuple[np.ndarray, np.ndarray]:
        """Return the state horizon_s after (x, P), holding the control u."""
        predict = self._predict_ahead_function
        if self._controls is None:
            return predict(x, P, self.horizon_s)
        return predict(x, P, self.horizon_s, u)

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
        if self._controls is not None:
            self._prune_controls()

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
