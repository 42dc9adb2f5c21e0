"""
A train's motion as four regimes (stand, accelerate, cruise, brake) in one IMM.

What is known about trains, and how the model uses it:

* **Acceleration changes smoothly** (jerk-limited). Every moving regime has the state
  [position p, velocity v, acceleration a, commanded acceleration ℓ]: the drive or the
  brake settles a on ℓ with a response time τ, ȧ = (ℓ - a)/τ, and ℓ itself holds
  (ℓ̇ = 0). A white noise q_a on ȧ and a random walk q_ℓ on ℓ absorb what this does
  not describe (coasting, gradients, a driver's notches). The dynamics are linear,
  with the exact transition F(dt) below, so each regime is a Kalman filter
  (:class:`~kf_train.filters.models.LinearModel`, Joseph-form update).
* **Regimes have their own acceleration, and a train its own capabilities.** A train
  that starts to accelerate commands about its traction capability A, one that
  brakes about its service braking -B, a cruising one about 0. A and B are states
  too (constant but for a slow drift, prior N(0.8, 0.35²) and N(0.9, 0.35²) m/s²):
  when a mixture component switches into 'accelerate', its ℓ becomes A plus a
  N(0, plateau_std²) difference (:meth:`RailModel.entry`, an exact linear
  transformation of the Gaussian, so ℓ stays correlated with A); p, v and a carry
  over, because a switch changes the command, not the motion. Each acceleration or
  braking phase then teaches the filter A or B through that correlation, and the
  next departure or brake is recognised sooner.
* **Stopped means stopped.** The stand regime holds p and sets v = a = ℓ = 0 with no
  uncertainty (F = diag(1, 0, 0, 0, 1, 1)). Only a slow train can stop: a moving
  regime's rate of switching to stand (stop_rate_hz) is scaled by
  P(v <= stop_speed_mps) under its own estimate, so a noisy measurement cannot 'stop' a
  train at speed, and a regime that holds no speed (an 'accelerating' or 'cruising'
  train that does not move, at a dwell) drains into stand (:data:`STOPPING`; before,
  only brake could, and at real dwells P(stand) stayed near 0.7).
* **The receiver's noise is learned.** R in use is a scale times the variance given,
  the scale learned from the innovations (:mod:`~kf_train.filters.noise_adaptation`,
  ``noise_window``); a fix is gated with the variance given, so only a fix the
  receiver's own accuracy cannot explain is an outlier.
* **The receiver's error is slow.** After a fix weighed with R = s r the measured
  position walks by c · s r per second in every regime, c learned from whether
  successive innovations agree (:mod:`~kf_train.filters.error_walk`,
  ``error_walk_rate_hz``): a receiver that filters its output is followed, white
  noise is not.
* **Trains do not reverse.** The prediction ahead (:meth:`RailModel.predict_ahead`)
  follows each regime's mean path and holds the train where its velocity reaches 0,
  so no regime predicts going backwards, and the mixture's predicted position is
  never behind its current one.

The state is [p, v, a, ℓ, A, B]. The 2-s prediction is the whole model's: each
regime's own prediction from its current estimate, held on the no-reversal path, and
the moment-matched mixture of them with the current regime probabilities (mean and
covariance). A switch of regime within the horizon is left to each regime's process
noise rather than mixed in at the start of the horizon: mixing a switch at t = 0
counts it at its full 2-s effect, when on average it acts for a fraction of that;
measured on the development runs that costs 1-2 % of RMSE (docs/rail.md).
:class:`RailModelParameters` holds the defaults; they are physical figures for
passenger trains, not tuned to one run (docs/rail.md).
"""

from dataclasses import asdict, dataclass
import math
from typing import Dict, Optional, Tuple

from kf_train.filters import imm_stack
from kf_train.filters.error_walk import ErrorWalk, position_walked
from kf_train.filters.imm import (
    first_jump_row, IMM, IMMFilter, IMMState, noise_in_use, RateTransition)
from kf_train.filters.kalman import UpdateResult
from kf_train.filters.models import LinearModel
from kf_train.filters.noise_adaptation import NoiseAdaptation
from kf_train.filters.rail_dynamics import (
    _phi, moving_noise, moving_transition, relaxation_transition, RelaxationNoise, stand_noise,
    STAND_TRANSITION)
from kf_train.filters.rail_mixing import EntryGather
from kf_train.filters.rail_stop import StopFinder
import numpy as np

MODE_NAMES = ('stand', 'accelerate', 'cruise', 'brake')
STATE_NAMES = ('position', 'velocity', 'acceleration', 'commanded_acceleration',
               'acceleration_capability', 'braking_capability')
DIM_X = len(STATE_NAMES)
STAND, ACCELERATE, CRUISE, BRAKE = range(4)
STOPPING = (ACCELERATE, CRUISE, BRAKE)
"""The regimes a slow train may stop from: braking to a halt, or 'cruising' at a crawl
(a train that holds no speed is standing, whatever the regime it came from)."""
VELOCITY = STATE_NAMES.index('velocity')
ACCELERATION = STATE_NAMES.index('acceleration')
ACCELERATION_LIMIT_MPS2 = 3.0
"""No train accelerates or brakes harder [m/s²]: traction gives up to ~1.3 m/s², service
brakes ~1, emergency brakes 1.2-1.5 on main lines and up to ~2.7 on trams with track
brakes. A regime mean beyond it is a receiver's jump read as motion
(:func:`bound_acceleration`)."""
_H = np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
_CACHE_SIZE = 64


@dataclass(frozen=True)
class RailModelParameters:
    """The rail model's figures; the defaults are for passenger trains (docs/rail.md)."""

    noise_std_m: float = 1.0
    """Measurement noise σ (R = σ²) when an update gives no R [m]."""
    response_time_s: float = 0.7
    """τ: how fast a settles on the commanded acceleration (jerk-limited ramps) [s]."""
    acceleration_noise: float = 1e-4
    """q_a: white noise on ȧ [m²/s⁵]."""
    command_noise: float = 1e-4
    """q_ℓ: random walk of the commanded acceleration [m²/s⁵]."""
    accelerate_mps2: float = 0.8
    """Prior mean of the traction capability A [m/s²]."""
    accelerate_std_mps2: float = 0.35
    """Its prior standard deviation [m/s²]."""
    brake_mps2: float = 0.9
    """Prior mean of the service braking B (ℓ = -B when braking) [m/s²]."""
    brake_std_mps2: float = 0.35
    """Its prior standard deviation [m/s²]."""
    plateau_std_mps2: float = 0.1
    """How far one phase's commanded acceleration may be from A (or -B) [m/s²]."""
    cruise_std_mps2: float = 0.05
    """Prior standard deviation of the commanded acceleration in 'cruise' (mean 0)."""
    capability_noise: float = 1e-6
    """Random walk of A and B (load, adhesion) [m²/s⁵]."""

    departure_rate_hz: float = 1.0 / 30.0
    """stand -> accelerate: one over a typical dwell [1/s]."""
    accelerate_to_cruise_rate_hz: float = 1.0 / 15.0
    """accelerate -> cruise: line speed reached [1/s]."""
    accelerate_to_brake_rate_hz: float = 1.0 / 200.0
    """accelerate -> brake: rare (a signal) [1/s]."""
    cruise_to_accelerate_rate_hz: float = 1.0 / 100.0
    """cruise -> accelerate: after a slow zone [1/s]."""
    cruise_to_brake_rate_hz: float = 1.0 / 60.0
    """cruise -> brake: for a station or a slow zone, the usual end of a cruise [1/s]."""
    brake_to_cruise_rate_hz: float = 1.0 / 30.0
    """brake -> cruise: a slow zone's speed reached [1/s]."""
    brake_to_accelerate_rate_hz: float = 1.0 / 100.0
    """brake -> accelerate: rare [1/s]."""
    stop_rate_hz: float = 1.0
    """accelerate, cruise, brake -> stand, for a train slower than stop_speed_mps [1/s]."""
    stop_speed_mps: float = 0.3
    """Speed below which a braking train may be standing [m/s]."""
    stand_noise: float = 0.0
    """Random walk of a standing train's position [m²/s] (0: it does not move)."""
    initial_velocity_std_mps: float = 20.0
    """Standard deviation of the velocity at the first measurement [m/s]."""
    initial_acceleration_std_mps2: float = 1.0
    """Standard deviation of a and ℓ at the first measurement [m/s²]."""
    noise_window: float = 50.0
    """Memory of the learned measurement-noise scale [measurements]; 0: R as given."""
    noise_scale_min: float = NoiseAdaptation.scale_min
    """Lower bound of the learned scale on R."""
    noise_scale_max: float = NoiseAdaptation.scale_max
    """Upper bound of the learned scale on R."""
    error_walk_rate_hz: float = ErrorWalk.rate_hz
    """
    The receiver's slow error: the measured position walks by c · s r per second after
    a fix weighed with R = s r, c starting here and learned [1/s]; 0: the error is white
    (:mod:`~kf_train.filters.error_walk`).
    """
    error_walk_learning_rate: float = ErrorWalk.learning_rate
    """η: how fast c is learned from successive innovations (0: c stays where it starts)."""
    error_walk_rate_min_hz: float = ErrorWalk.rate_min_hz
    """Lower bound of the learned c [1/s]."""
    error_walk_rate_max_hz: float = ErrorWalk.rate_max_hz
    """Upper bound of the learned c [1/s]."""
    hold_speed_std_mps: float = 0.3
    """
    A receiver's held position (the last fused fix repeated exactly) is fused as a speed
    of 0 with this σ, the speed below which receivers hold [m/s]; 0: fused as a position.
    """
    hold_max_variance_m2: float = 100.0
    """A hold counts only with a variance given up to this (not a cold start's) [m²]."""
    absolute_error_scale: float = 6.0
    """
    The receiver's slow error that no fix reveals, as a multiple of the variance given:
    a band about the truth adds this times the newest fix's variance to the position's
    (``StreamEstimator.absolute``; 0: the fixes' frame is the truth's).
    """

    def __post_init__(self):
        """Check every figure: finite, >= 0, and > 0 where it divides."""
        for name, value in asdict(self).items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value) or value < 0.0:
                raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
            object.__setattr__(self, name, float(value))
        for name in ('noise_std_m', 'response_time_s', 'stop_speed_mps'):
            if getattr(self, name) <= 0.0:
                raise ValueError(f'{name} must be > 0, got {getattr(self, name)}')
        if not self.noise_window.is_integer():
            raise ValueError(f'noise_window must be a whole number, got {self.noise_window}')
        self.adaptation()  # raises ValueError for bounds out of order
        self.error_walk()

    def adaptation(self) -> NoiseAdaptation:
        """Return how the measurement-noise scale is learned (noise_window 0: not at all)."""
        return NoiseAdaptation(window=int(self.noise_window), scale_min=self.noise_scale_min,
                               scale_max=self.noise_scale_max)

    def error_walk(self) -> ErrorWalk:
        """Return how the receiver's error walks (error_walk_rate_hz 0: not at all)."""
        return ErrorWalk(self.error_walk_rate_hz, self.error_walk_learning_rate,
                         self.error_walk_rate_min_hz, self.error_walk_rate_max_hz)

    def rates(self) -> np.ndarray:
        """Return the switching rates [1/s], rates[i, j] from mode i to j (stop excluded)."""
        rates = np.zeros((4, 4))
        rates[STAND, ACCELERATE] = self.departure_rate_hz
        rates[ACCELERATE, CRUISE] = self.accelerate_to_cruise_rate_hz
        rates[ACCELERATE, BRAKE] = self.accelerate_to_brake_rate_hz
        rates[CRUISE, ACCELERATE] = self.cruise_to_accelerate_rate_hz
        rates[CRUISE, BRAKE] = self.cruise_to_brake_rate_hz
        rates[BRAKE, CRUISE] = self.brake_to_cruise_rate_hz
        rates[BRAKE, ACCELERATE] = self.brake_to_accelerate_rate_hz
        return rates

    def initial_covariance(self, position_variance_m2: float) -> np.ndarray:
        """Return P at a first position measurement with variance position_variance_m2."""
        a = self.initial_acceleration_std_mps2 ** 2
        return np.diag([position_variance_m2, self.initial_velocity_std_mps ** 2, a, a,
                        self.accelerate_std_mps2 ** 2, self.brake_std_mps2 ** 2])


class _Cached:
    """dt -> matrix, remembering the last few dt values (a stream repeats its period)."""

    def __init__(self, function):
        """Wrap ``function(dt) -> read-only matrix``."""
        self.function = function
        self.values: Dict[float, np.ndarray] = {}

    def __call__(self, dt_s: float) -> np.ndarray:
        """Return function(dt_s), computed once per dt."""
        value = self.values.get(dt_s)
        if value is None:
            value = self.function(imm_stack.duration(dt_s))
            value.flags.writeable = False
            if len(self.values) >= _CACHE_SIZE:
                self.values.pop(next(iter(self.values)))
            self.values[dt_s] = value
        return value


def _stand_model(params: RailModelParameters) -> LinearModel:
    """Return the stand regime: p held (plus stand_noise), v = a = ℓ = 0 exactly, A, B kept."""
    return LinearModel(lambda dt: STAND_TRANSITION,
                       _Cached(lambda dt: stand_noise(dt, params.stand_noise,
                                                      params.capability_noise)),
                       _H, [[params.noise_std_m ** 2]], state_names=STATE_NAMES)


def _moving_model(params: RailModelParameters) -> LinearModel:
    """Return a moving regime's Kalman model (all three share the dynamics)."""
    tau = params.response_time_s
    relaxation = RelaxationNoise(tau, params.acceleration_noise, params.command_noise)
    return LinearModel(_Cached(lambda dt: moving_transition(dt, tau)),
                       _Cached(lambda dt: moving_noise(dt, relaxation,
                                                       params.capability_noise)),
                       _H, [[params.noise_std_m ** 2]], state_names=STATE_NAMES)


def _normal_cdf(x: float) -> float:
    """Return Φ(x), the standard normal distribution function."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


def stop_probability(v, std, stop_speed_mps: float):
    """
    Return P(velocity <= stop_speed_mps) for a velocity ~ N(v, std²): THE stop rule.

    A braking train switches to stand at stop_rate_hz times this. ``v`` and ``std``
    are floats, or arrays (one per setting, the tuner's), computed element by element
    with the same float arithmetic.
    """
    if type(v) is not float:
        return np.array([stop_probability(a, b, stop_speed_mps)
                         for a, b in zip(v.tolist(), std.tolist())])
    return (1.0 if v <= stop_speed_mps else 0.0) if std == 0.0 else \
        _normal_cdf((stop_speed_mps - v) / std)


def moved_past(speed_mps: float, speed_variance: float, dt_s: float,
               position_variance_m2: float, threshold: float) -> bool:
    """
    Return whether a train at this speed must have moved past a fix's reach in dt_s.

    The speed's lower bound at the gate's own width, v⁻ = v - √(γ σ_v²), braking at
    once at ACCELERATION_LIMIT_MPS2 = a covers at least d = v⁻ dt - ½ a dt² (v⁻²/2a if
    it stops within dt); True when d² > γ (P_pp + s r), beyond the gate on the
    position's variance. It tells a receiver's repeated epoch from a standing train's
    held position whatever the gap (Fusion._reject_repeat): after a 30-s outage the
    IMM's regimes spread over hundreds of metres, so a repeat of the last fix passes
    the gate on the prediction, but a train that was doing 18 m/s cannot be there.
    Plain floats and ``math`` only: the tuner's compiled likelihood compiles it as is.
    """
    lower = speed_mps - math.sqrt(threshold * speed_variance)             # v⁻
    if not lower > 0.0:
        return False
    if lower <= ACCELERATION_LIMIT_MPS2 * dt_s:
        travel = 0.5 * lower * lower / ACCELERATION_LIMIT_MPS2            # stops within dt
    else:
        travel = (lower - 0.5 * ACCELERATION_LIMIT_MPS2 * dt_s) * dt_s     # v⁻ dt - ½ a dt²
    return travel * travel > threshold * position_variance_m2


def bound_acceleration(means: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """
    Return the means with every acceleration beyond ±ACCELERATION_LIMIT_MPS2 projected onto it.

    A receiver's along-track jump of a few metres, fused at a regime's onset, reads as
    an acceleration of 10 m/s² or more: on a real log (tp-lib 29584) one such fix made
    a regime's mean 78 m/s and 14 m/s², its next 2-s predictions hundreds of metres off.
    As :func:`hold_velocity` does for v < 0, such a mean is moved to the limit along
    its own covariance, x - P e (a - a_limit) / P_aa (the conditional mean given the
    limit; Simon 2010), so position and velocity move with it; P is kept. ``means``
    itself is returned when every acceleration is within the limit.
    """
    acceleration = means[..., ACCELERATION]
    if not np.abs(acceleration).max() > ACCELERATION_LIMIT_MPS2:
        return means
    column = covariances[..., :, ACCELERATION]                           # P e
    variance = column[..., ACCELERATION]                                 # P_aa
    limit = np.clip(acceleration, -ACCELERATION_LIMIT_MPS2, ACCELERATION_LIMIT_MPS2)
    beyond = acceleration != limit
    shift = np.where(beyond & (variance > 0.0),
                     (acceleration - limit) / np.where(variance > 0.0, variance, 1.0), 0.0)
    bounded = means - column * shift[..., None]                       # x - P e Δa / P_aa
    bounded[..., ACCELERATION] = limit
    return bounded


def hold_velocity(means: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """
    Return the means with every mean velocity below 0 projected onto v = 0: THE rule.

    A train does not reverse, so a regime whose updated mean velocity is negative (a
    receiver's drift at a stop, a fix that jumps back) has its mean moved to v = 0
    along its own covariance: x - P e (v / P_vv), e the velocity axis, the conditional
    mean given v = 0 (Simon 2010, estimate projection). P is kept, so the velocity's
    doubt is not understated. ``means`` (..., n) and ``covariances`` (..., n, n), one
    regime, a stack of them or the tuner's settings × regimes; ``means`` itself is
    returned when no velocity is negative, else a new array.
    """
    velocity = means[..., 1]
    if not velocity.min() < 0.0:
        return means
    column = covariances[..., :, 1]                                   # P e
    variance = column[..., 1]                                         # P_vv
    backwards = velocity < 0.0
    shift = np.where(backwards & (variance > 0.0),
                     velocity / np.where(variance > 0.0, variance, 1.0), 0.0)
    held = means - column * shift[..., None]                          # x - P e v / P_vv
    held[..., 1] = np.where(backwards, 0.0, held[..., 1])
    return held


class RailModel(IMM):
    """
    The four-regime rail IMM (pure: states in, states out); see the module docstring.

    It specialises the :class:`~kf_train.filters.imm.IMM` through its public hooks
    only, each of them a method here and the one code that runs: :meth:`transition`
    (Π(dt) with the state's -> stand rates), :meth:`mix_entering` (the mixing,
    components entering a regime by :meth:`entry`'s rule) and :meth:`matrices` (the
    regimes' stacked F, Q); and it has its own :meth:`predict_ahead` (no reversal), and
    :meth:`predict` and :meth:`finish_update` for the receiver's error walk
    (:mod:`~kf_train.filters.error_walk`).
    """

    def __init__(self, parameters: RailModelParameters = RailModelParameters()):
        """Build the regimes from ``parameters``."""
        self.parameters = parameters
        moving = _moving_model(parameters)
        self._rates = RateTransition(parameters.rates())
        self._entry = _entry_transformation(parameters)
        self._per_dt: Dict[float, tuple] = {}
        # Π is row-stochastic by construction (first_jump_row), so not re-checked.
        super().__init__((_stand_model(parameters), moving, moving, moving), self.transition,
                         MODE_NAMES, self.entry, mixing=self.mix_entering,
                         matrices=self.matrices, stochastic=True,
                         adaptation=parameters.adaptation())
        self.error_walk = parameters.error_walk()
        self._stops = StopFinder(parameters.response_time_s, relaxation_transition, _phi)

    def _slow(self, state: IMMState, regime: int) -> float:
        """Return P(v <= stop_speed_mps) under a regime's estimate."""
        return stop_probability(float(state.means[regime, 1]),
                                math.sqrt(max(float(state.covariances[regime, 1, 1]), 0.0)),
                                self.parameters.stop_speed_mps)

    @property
    def stop_finder(self) -> StopFinder:
        """Return the no-reversal hold of the regimes' mean paths (:meth:`hold_paths`)."""
        return self._stops

    @property
    def entry_rule(self) -> EntryGather:
        """Return the entry rule's tables (sources, factors, noises of ℓ per regime)."""
        return self._entry

    def _for_dt(self, dt_s: float) -> tuple:
        """Return (F, Q, Fᵀ, Π without the -> stand rates) for dt_s, computed once per dt_s."""
        kept = self._per_dt.get(dt_s)
        if kept is None:
            # Stacked straight from the regimes' own F and Q, unchecked: they are built
            # here from checked parameters (finite and positive semi-definite for any
            # finite dt, tested), and a prediction that overflows still raises. A sensor
            # with jittered stamps brings a new dt at every step, so this is kept cheap.
            stand, moving = self.modes[STAND], self.modes[ACCELERATE]
            F = np.array((stand.F(dt_s),) + (moving.F(dt_s),) * 3)
            Q = np.array((stand.Q(dt_s),) + (moving.Q(dt_s),) * 3)
            kept = (F, Q, F.swapaxes(1, 2).copy(), self._rates.matrix(dt_s))
            for array in kept:
                array.flags.writeable = False
            if len(self._per_dt) >= _CACHE_SIZE:
                self._per_dt.pop(next(iter(self._per_dt)))
            self._per_dt[dt_s] = kept
        return kept

    def matrices(self, dt_s: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the regimes' stacked F(dt_s), Q(dt_s) and F(dt_s)ᵀ (the IMM's hook)."""
        return self._for_dt(dt_s)[:3]

    def transition(self, dt_s: float, state: IMMState) -> np.ndarray:
        """
        Return Π(dt): the fixed rates plus -> stand, scaled by P(v <= stop speed).

        Only the rows of :data:`STOPPING` depend on the state: the others are kept per
        dt, and each of those is :func:`~kf_train.filters.imm.first_jump_row` of its
        rates with stop_rate_hz · P(v <= stop_speed_mps) to stand (the IMM's hook).
        """
        matrix = self._for_dt(dt_s)[3].copy()
        for regime in STOPPING:
            rates = self._rates.rates[regime].tolist()
            rates[STAND] = self.parameters.stop_rate_hz * self._slow(state, regime)
            matrix[regime] = first_jump_row(rates, regime, dt_s)
        return matrix

    def mix_entering(self, weights: np.ndarray, means: np.ndarray, covs: np.ndarray):
        """
        Return every regime's starting mixture, components entering it by :meth:`entry`.

        x0_j = Σ_i ω_ij x_ji, P0_j = Σ_i ω_ij (P_ji + d dᵀ), d = x_ji - x0_j, where
        (x_ji, P_ji) is component i as it enters regime j: x' = T_j x, P' = T_j P Tⱼᵀ + W_j
        for i ≠ j, itself for i = j. T_j is the identity but for ℓ's row (A's, -B's or
        none), so every entry of x_ji and P_ji is one entry of x_i or P_i times 1, ±1
        or 0: all N² components are gathered at once (:mod:`~kf_train.filters.rail_mixing`,
        exact, as entry's copies are). The IMM's mixing hook.
        """
        return self._entry.mix(weights.T, means, covs)

    def entry(self, j: int, x: np.ndarray, P: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return a component entering mode j with its new commanded acceleration ℓ.

        accelerate: ℓ = A + w, brake: ℓ = -B + w, w ~ N(0, plateau_std²) independent;
        as x' = T x + w this is exact: ℓ's row and column become A's (or -B's) and its
        variance Var(A) + plateau_std². cruise: ℓ ~ N(0, cruise_std²), independent of
        the rest; stand: ℓ = 0. The rule is :func:`_entry_transformation`'s tables,
        which :meth:`mix_entering` applies to all components at once.
        """
        return self._entry.enter(j, x, P)

    def predict(self, state: IMMState, dt_s: float, u=None) -> IMMState:
        """
        Return IMM.predict, the position walking as the state says (``noise.walk_m2_per_s``).

        IMM.predict_update predicts through this method, so a fused step and a
        prediction then an update are the same numbers.
        """
        predicted = super().predict(state, dt_s, u)
        covs = position_walked(predicted.covariances, imm_stack.duration(dt_s),
                               state.noise.walk_m2_per_s)
        if covs is predicted.covariances:
            return predicted
        covs.flags.writeable = False
        return predicted._replace(covariances=covs)

    def finish_update(self, prior: IMMState, means: np.ndarray, covariances: np.ndarray,
                      posterior: np.ndarray, innovation: tuple, reported_m2: float,
                      learn: bool) -> Tuple[IMMState, UpdateResult]:
        """Return IMM.finish_update, a position fix also teaching the error walk."""
        state, result = super().finish_update(prior, means, covariances, posterior,
                                              innovation, reported_m2, learn)
        if learn and self.error_walk.enabled:
            noise = self.error_walk.learn(state.noise, innovation[0], innovation[1],
                                          noise_in_use(reported_m2, prior.noise, True))
            state = IMMState(state.means, state.covariances, state.probabilities, noise)
        return state, result

    def error_walk_rate_hz(self, state: IMMState) -> Optional[float]:
        """Return c, the walk's rate learned up to ``state`` [1/s] (None: no walk)."""
        return self.error_walk.rate(state.noise) if self.error_walk.enabled else None

    def update(self, state: IMMState, z, R=None):
        """Return the IMM's update, every regime's motion held (:meth:`_held`)."""
        return self._held(*super().update(state, z, R))

    def update_component(self, state: IMMState, z, R, index: int):
        """Return the IMM's update by a measurement of state ``index``, velocities held."""
        return self._held(*super().update_component(state, z, R, index))

    def update_velocity(self, state: IMMState, velocity_mps, variance_m2s2):
        """
        Return the state corrected by a measured speed (a Doppler, an odometer) [m/s].

        H = e_1 (the velocity), R = ``variance_m2s2`` as given: the learned scale is
        the position's (:mod:`~kf_train.filters.noise_adaptation`) and a speed neither
        uses nor teaches it. Every regime is corrected and weighed by the speed's
        likelihood (a standing train's v is exactly 0), and no mean velocity stays
        below 0 (:func:`hold_velocity`).
        """
        return self.update_component(state, velocity_mps, [[variance_m2s2]], VELOCITY)

    @staticmethod
    def _held(state: IMMState, result):
        """Return (state, result), each regime's mean bounded in a then held at v >= 0."""
        means = hold_velocity(bound_acceleration(state.means, state.covariances),
                              state.covariances)
        if means is not state.means:
            means.flags.writeable = False
            state = state._replace(means=means)
        return state, result

    def first_estimate(self, position_m: float, variance_m2: float = None) -> IMMState:
        """Return the state after a first position measurement: v, a, ℓ wide, regimes even."""
        params = self.parameters
        variance = params.noise_std_m ** 2 if variance_m2 is None else float(variance_m2)
        x0 = [float(position_m), 0.0, 0.0, 0.0, params.accelerate_mps2, params.brake_mps2]
        return self.initial_state(x0, params.initial_covariance(variance))

    def predict_ahead(self, state: IMMState, dt_s: float, u=None
                      ) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return the combined (x, P) dt_s ahead; no regime goes backwards.

        Each regime predicts from its own estimate (x_j, P_j) with its dynamics; the
        mean of a moving regime is held where its path stops (:meth:`_no_reversal`);
        x = Σ μ_j x_j⁺, P = Σ μ_j (P_j⁺ + (x_j⁺ - x)(x_j⁺ - x)ᵀ).
        """
        dt_s = imm_stack.duration(dt_s)
        if u is not None:
            raise ValueError('u given to a model without control input')
        means, covs = imm_stack.predict(state.means, state.covariances, *self.matrices(dt_s),
                                        final=False)
        covs = position_walked(covs, dt_s, state.noise.walk_m2_per_s)
        self.hold_paths(state, means, dt_s)
        x, P = imm_stack.combine(means, covs, state.probabilities)
        imm_stack.check_finite(x, P, 'prediction')
        return x, P

    def hold_paths(self, state: IMMState, means: np.ndarray, dt_s: float) -> None:
        """Hold each moving regime's predicted mean (``means``, in place) where it stops."""
        starts = state.means[:, :4].tolist()
        stops = self._stops
        for j in (ACCELERATE, CRUISE, BRAKE):
            if stops.may_stop(starts[j], dt_s):
                held = stops.hold(starts[j], means[j], dt_s)
                if held is not means[j]:
                    means[j] = held

    def _no_reversal(self, start: np.ndarray, predicted: np.ndarray,
                     dt_s: float) -> np.ndarray:
        """Return the predicted mean held where its mean velocity reaches 0 (StopFinder)."""
        return self._stops.hold(start, predicted, dt_s)


def _entry_transformation(params: RailModelParameters) -> EntryGather:
    """
    Return the entry rule of the four regimes as gather tables (:meth:`RailModel.entry`).

    Entering regime j is x' = T_j x + w, w ~ N(0, W_j): T_j is the identity with ℓ's
    row replaced by A's (accelerate), -B's (brake) or zeros (cruise, stand); W_j is
    ℓ's new variance (plateau_std², cruise_std² or 0).
    """
    plateau, cruise = params.plateau_std_mps2 ** 2, params.cruise_std_mps2 ** 2
    return EntryGather(sources=(None, 4, None, 5), factors=(0.0, 1.0, 0.0, -1.0),
                       noises=(0.0, plateau, cruise, plateau), dim_x=DIM_X, ell=3)


def make_rail_filter(position_m: float, parameters: RailModelParameters = None,
                     variance_m2: float = None, jit: Optional[bool] = None) -> IMMFilter:
    """Return an IMMFilter of the rail model at a first fix (compiled if ``jit``: rail_model)."""
    from kf_train.filters.rail_fast import rail_model  # it builds on this module
    model = rail_model(parameters or RailModelParameters(), jit)
    state = model.first_estimate(position_m, variance_m2)
    return IMMFilter(model, state.means[0], state.covariances[0], state.probabilities)
