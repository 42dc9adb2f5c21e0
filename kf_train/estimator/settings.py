"""
The estimator's settings (:class:`EstimatorSettings`) and what is derived from them.

:func:`configure` turns validated settings into a :class:`Configuration`: the preset,
the filter's pure model (:mod:`kf_train.estimator.adapters`), the initial estimate
and every duration in nanoseconds. A running estimator swaps the whole configuration
at once, so a failed reconfiguration changes nothing.
"""

from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Callable, Dict, NamedTuple, Optional, Tuple

from kf_train.estimator.adapters import make_model
from kf_train.estimator.live_presets import (
    covariance_from_list, is_rail, LivePreset, preset_defaults, resolve_preset)
from kf_train.filters import (
    as_finite_array, as_vector, chi2_quantile, DEFAULT_ALPHA, DEFAULT_BETA, DEFAULT_KAPPA,
    DEFAULT_PARTICLES, DEFAULT_RESAMPLE_THRESHOLD, FILTER_KINDS, seconds_to_ns, StepModel)
from kf_train.presets import INITIALIZATIONS, is_constant_velocity, measured_states
import numpy as np

DEFAULT_PRESET = 'rail'
"""The default preset: a real train (issue 11), not a seed tutorial."""
DEFAULT_GATE_PROBABILITY = 0.9999
"""
The default χ² gate: NIS > 15.14 (χ²(1) at 0.9999) is an outlier.

Any outlier beyond ~4σ of the innovation (about 4.3 m with σ = 1 m on the rail
preset) is rejected and counted; a 10⁶ m one has a NIS of ~10¹². Measured on unseen
rail runs (metro-100/101, regional-100/101, 6000 measurements each): 0.9999
rejected 0-1 valid measurements a run and changed the 2-s RMSE by <= 0.1 %,
while 0.999 (NIS > 10.83) rejected 5-8, never two in a row, at maneuver onsets where
the IMM is least sure, and cost 0.3-1.1 % of RMSE. With either, ten valid
rejections in a row (the lock-out) are out of reach.
"""
SEED_SWITCH = MappingProxyType(
    {'preset': 'train', 'initialization': 'prior', 'gate_probability': 1.0})
"""
The settings that reproduce seed 000's MATLAB iteration exactly, on any measurements:
``EstimatorSettings(**SEED_SWITCH)``, the node's ``-p preset:=train -p
initialization:=prior -p gate_probability:=1.0``.
"""
RAIL_FILTER_KINDS = ('kf', 'ekf')
"""The filter kinds the rail preset runs: its IMM of four Kalman filters (the regimes are
linear, so the EKF is the same); the UKF and the particle filters are refused."""

# Ranges shared with the node's parameter descriptors.
GATE_PROBABILITY_RANGE = (0.5, 1.0)
HISTORY_S_RANGE = (0.0, 60.0)
MAX_CONSECUTIVE_OUTLIERS_RANGE = (1, 1_000_000)
RESTART_AFTER_STALE_RANGE = (2, 1_000_000)
LOCKOUT_ACTIONS = ('reacquire', 'reset')
"""What a lock-out does: keep the track, widened, or forget it (EstimatorSettings.lockout)."""
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
    Everything that configures a :class:`StreamEstimator`, with defaults for real trains.

    The defaults run the rail preset (an IMM of stand/accelerate/cruise/brake;
    docs/rail.md) from the first measurement, with the χ² gate on
    (``gate_probability`` 0.9999), and without out-of-sequence fusion (the estimator
    node turns it on: ``history_s`` 1). :data:`SEED_SWITCH` (preset ``train``,
    ``initialization`` prior, ``gate_probability`` 1) reproduces seed 000's iteration
    exactly on any measurements. ``initial_state``, ``initial_covariance``,
    ``horizon_s`` and ``nominal_period_s`` None take the preset's values.
    """

    initial_state: Optional[Tuple[float, ...]] = None
    """The preset's states (rail: [position m, velocity m/s, acceleration m/s², commanded
    acceleration m/s², capabilities A and B m/s²]; train: [position m, velocity m/s]);
    None: the preset's (train: [0, 5], half the true speed as in seed 000)."""
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
    """first_measurement mode: standard deviation of the initial velocity (not used by
    the rail preset, whose initial covariance holds its priors: 20 m/s)."""
    history_s: float = 0.0
    """Out-of-sequence window [s]: older measurements are fused by replay; 0 = off."""
    gate_probability: float = DEFAULT_GATE_PROBABILITY
    """χ² gate on the NIS: reject when P(χ²(m) <= NIS) exceeds this; 1 = no gate."""
    max_consecutive_outliers: int = 10
    """Consecutive gate (repeated-epoch, numerical) rejections that lock out (``lockout``)."""
    lockout: str = 'reacquire'
    """What a lock-out does (:data:`LOCKOUT_ACTIONS`): ``reacquire`` keeps the track,
    widened by the rejected group's disagreement, and fuses the group; ``reset`` forgets
    it and initialises from the group (kf_train.estimator.reacquire)."""
    restart_after_stale: int = 3
    """Consecutive stale measurements after which the stream counts as restarted."""
    max_future_s: float = 1.0
    """How far [s] a stamp may lie ahead of ``now_ns`` (when process() is given it)."""
    expected_frame_id: str = ''
    """The measurements' required frame_id; '' accepts any."""
    preset: str = DEFAULT_PRESET
    """The filter: a name from LIVE_PRESETS (``rail``: the four-regime IMM of
    docs/rail.md) or the path of a preset YAML file."""
    measurement_velocity_variance: float = 0.0
    """R of a measured velocity [m²/s²] overriding the message's; 0 uses the message's."""
    filter: str = 'kf'  # noqa: A003 (the node parameter's name)
    """The filter kind (:data:`kf_train.filters.FILTER_KINDS`): ``kf`` (exact, the
    default), ``ekf`` (the same on these linear presets), ``ukf``, ``pf`` (regularised)
    or ``bootstrap-pf``. With preset ``rail``, ``kf`` and ``ekf`` are its IMM of four
    Kalman filters (:data:`RAIL_FILTER_KINDS`); the others raise ValueError."""
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
        self._validate_model(preset)
        self._validate_ranges()
        return self

    def _validate_model(self, preset: LivePreset) -> None:
        """Check the settings that must suit the preset's model."""
        if is_rail(preset) and self.filter not in RAIL_FILTER_KINDS:
            raise ValueError(
                f'filter must be kf (or ekf, the same) for preset {preset.name!r}, got '
                f'{self.filter!r}: the rail preset is an IMM of four Kalman filters, one per '
                'regime; ukf, pf and bootstrap-pf run the 1-D linear presets')
        if self.process_noise_density > 0.0 and not is_constant_velocity(preset):
            raise ValueError(
                f'process_noise_density must be 0 for preset {preset.name!r}: a white-noise '
                'acceleration needs [position, velocity] states (edit process_noise in '
                'a preset file instead)')
        if self.initialization not in INITIALIZATIONS:
            raise ValueError(
                f'initialization must be one of {INITIALIZATIONS}, '
                f'got {self.initialization!r}')
        if self.initialization == 'first_measurement' and measured_states(preset) is None:
            raise ValueError(
                f'initialization must be prior for preset {preset.name!r}: first_measurement '
                'needs measurements that are states (H selecting them)')

    def _validate_ranges(self) -> None:
        """Check the settings that have a range, a type or a set of values."""
        _check_float_range('history_s', self.history_s, *HISTORY_S_RANGE)
        _check_float_range('gate_probability', self.gate_probability,
                           *GATE_PROBABILITY_RANGE)
        _check_float_range('max_future_s', self.max_future_s, *MAX_FUTURE_S_RANGE)
        _check_int_range('max_consecutive_outliers', self.max_consecutive_outliers,
                         *MAX_CONSECUTIVE_OUTLIERS_RANGE)
        _check_int_range('restart_after_stale', self.restart_after_stale,
                         *RESTART_AFTER_STALE_RANGE)
        if self.lockout not in LOCKOUT_ACTIONS:
            raise ValueError(f'lockout must be one of {LOCKOUT_ACTIONS}, got {self.lockout!r}')
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


class Configuration(NamedTuple):
    """Validated settings and everything derived from them, installed at once."""

    settings: EstimatorSettings
    preset: LivePreset
    model: StepModel
    """The filter's pure model (:class:`~kf_train.filters.contract.StepModel`)."""
    predict_ahead: Callable
    """``model.predict_ahead`` (the particle filter's without draws, the rail IMM's
    mixture), bound once."""
    initial_state: np.ndarray
    initial_covariance: np.ndarray
    nominal_period_s: float
    horizon_s: float
    selector: Optional[Tuple[int, ...]]
    """The state each measurement measures (:func:`measured_states`)."""
    history_ns: int
    max_future_ns: int
    horizon_ns: int
    nominal_ns: int
    gate_threshold: float
    unmeasured_variances: Tuple[float, ...]
    """first_measurement mode: the initial variance of each state (measured ones are
    replaced by R): first_velocity_std_mps² for the linear presets, the diagonal of the
    initial covariance (its priors) for the rail preset."""
    velocity_model: Optional[StepModel] = None
    """The model measuring the velocity alone (a speed sensor), sharing ``model``'s
    states; None for presets that do not fuse a separate speed (all but ``rail``)."""
    hold: Optional['Hold'] = None
    """How a receiver's held position is fused (:class:`Hold`); None: as a position."""
    absolute_error_scale: float = 0.0
    """The receiver's unseen slow error per unit of the variance given (rail); 0 else."""


class Hold(NamedTuple):
    """A held position fused as a standstill (RailModelParameters.hold_speed_std_mps)."""

    speed_variance_m2s2: float
    """R of the speed of 0 it is fused as [m²/s²]."""
    max_variance_m2: float
    """The largest variance given with which a repeat counts as a hold [m²]."""


def configure(settings: EstimatorSettings, previous: Optional[EstimatorSettings],
              particle_states: Dict[int, object], fast: bool,
              jit: Optional[bool] = None) -> Configuration:
    """
    Return the configuration of validated ``settings``; raise ValueError, changing nothing.

    ``previous`` (the running estimator's settings, or None) must have the same
    preset and filter settings: those fix the filter for an estimator's life.
    ``fast`` and ``jit`` choose the model's code path (:func:`make_model`).
    """
    if previous is not None:
        for name in ('preset',) + FILTER_SETTINGS:
            old, new = getattr(previous, name), getattr(settings, name)
            if new != old:
                raise ValueError(f'{name} cannot change on a running estimator '
                                 f'({old!r} -> {new!r}); create a new one')
    preset = resolve_preset(settings.preset)
    model = make_model(settings, preset, particle_states, fast, jit)
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
    return Configuration(
        settings, preset, model,
        model.predict_ahead,
        initial_state, initial_covariance, nominal_period_s, horizon_s,
        measured_states(preset), seconds_to_ns(settings.history_s),
        seconds_to_ns(settings.max_future_s), seconds_to_ns(horizon_s),
        seconds_to_ns(nominal_period_s), chi2_quantile(settings.gate_probability, model.dim_z),
        tuple(float(v) for v in np.diag(initial_covariance)) if is_rail(preset)
        else (settings.first_velocity_std_mps ** 2,) * preset.dim_x,
        _velocity_model(model), _hold(preset),
        preset.parameters.absolute_error_scale if is_rail(preset) else 0.0)


def _hold(preset: LivePreset) -> Optional[Hold]:
    """Return how the rail preset fuses a held position (None: as a position)."""
    if not is_rail(preset) or preset.parameters.hold_speed_std_mps == 0.0:
        return None
    return Hold(preset.parameters.hold_speed_std_mps ** 2,
                preset.parameters.hold_max_variance_m2)


def _velocity_model(model: StepModel) -> Optional[StepModel]:
    """Return ``model`` measuring its velocity state alone, if it can (the rail IMM)."""
    if 'velocity' not in model.state_names:
        return None
    return model.measuring(model.state_names.index('velocity'))
