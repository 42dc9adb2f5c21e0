"""
The rail IMM as it was first written (branch rail2, d5ae099): a slow reference.

kf_train.filters.imm and kf_train.filters.rail_model now compute the modes as one
stack (kf_train.filters.imm_stack) and keep per-dt matrices; this is the original
mode-by-mode algorithm, transcribed, for test/unit/test_imm_stack.py to compare with.
It builds its regimes from the same public pieces (relaxation_transition,
relaxation_noise, the parameters) and runs them through kf_train.filters.kalman.
Only the class names differ (ReferenceIMM, ReferenceRailModel). Added since: the
acceleration bound and no-reversal projection of each regime's updated mean
(rail_model.bound_acceleration, hold_velocity),
written out regime by regime; the learned noise scale is not here, so the tests
compare with a RailModel whose noise_window is 0.
"""

import math
from typing import Callable, Dict, Optional, Sequence, Tuple

from kf_train.filters.imm import (
    check_transition_matrix, IMMState, make_state, RateTransition)
from kf_train.filters.kalman import UpdateResult
from kf_train.filters.models import LinearModel
from kf_train.filters.rail_dynamics import _phi, relaxation_noise, relaxation_transition
from kf_train.filters.rail_model import (
    ACCELERATE, ACCELERATION_LIMIT_MPS2, BRAKE, CRUISE, DIM_X, MODE_NAMES, RailModelParameters,
    STAND, STATE_NAMES)
from kf_train.filters.validation import as_covariance, as_duration, as_vector
import numpy as np

_LOG_2PI = math.log(2.0 * math.pi)
_H = np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
_CACHE_SIZE = 64


def _read_only(array: np.ndarray) -> np.ndarray:
    """Return ``array`` marked read-only."""
    array.flags.writeable = False
    return array


def combine(means: np.ndarray, covariances: np.ndarray,
            probabilities: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Return the moment-matched (x, P) of a Gaussian mixture."""
    x = probabilities.dot(means)                                    # x = Σ μ_j x_j
    d = means - x
    P = np.einsum('j,jab->ab', probabilities, covariances) + \
        np.einsum('j,ja,jb->ab', probabilities, d, d)                # P = Σ μ_j (P_j + d dᵀ)
    return x, 0.5 * (P + P.T)


def log_likelihood(result: UpdateResult) -> float:
    """Return log N(y; 0, S) of an update's innovation: -(NIS + log det(2π S)) / 2."""
    S = result.innovation_covariance
    if S.shape == (1, 1):
        log_det = math.log(float(S[0, 0]))
    else:
        sign, log_det = np.linalg.slogdet(S)
        if sign <= 0.0:
            raise ValueError(f'innovation covariance is not positive definite: {S.tolist()}')
    return -0.5 * (result.nis + log_det + S.shape[0] * _LOG_2PI)


class ReferenceIMM:
    """
    The IMM's models and arithmetic; every method is pure (states in, states out).

    ``modes``: one model per mode, each with ``predict(x, P, dt_s, u)`` and
    ``update(x, P, z, R)`` returning ``(x, P, UpdateResult)``. ``transition``: a
    callable ``(dt_s, state) -> Π`` (:class:`FixedTransition`,
    :class:`RateTransition` or a model's own). ``entry``: optional
    ``(j, x, P) -> (x, P)`` applied to each component that switches into mode j.
    """

    def __init__(self, modes: Sequence, transition: Callable, mode_names=None,
                 entry: Optional[Callable] = None):
        """Keep the models; names default to mode0, mode1, …."""
        if len(modes) < 1:
            raise ValueError('an IMM needs at least one mode')
        self.modes = tuple(modes)
        self.transition = transition
        self.entry = entry
        names = tuple(mode_names) if mode_names is not None else tuple(
            f'mode{i}' for i in range(len(self.modes)))
        if len(names) != len(self.modes) or len(set(names)) != len(names):
            raise ValueError(f'mode_names must be {len(self.modes)} distinct names, got '
                             f'{names!r}')
        self.mode_names = names

    @property
    def mode_count(self) -> int:
        """Return the number of modes N."""
        return len(self.modes)

    def initial_state(self, x0, P0, probabilities=None) -> IMMState:
        """Return every mode at (x0, P0), with ``probabilities`` (uniform by default)."""
        x0 = as_vector('x0', x0)
        P0 = as_covariance('P0', P0, x0.shape[0])
        count = self.mode_count
        if probabilities is None:
            probabilities = np.full(count, 1.0 / count)
        return make_state(np.tile(x0, (count, 1)), np.tile(P0, (count, 1, 1)), probabilities)

    def estimate(self, state: IMMState) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) of a state."""
        return combine(state.means, state.covariances, state.probabilities)

    def mix(self, state: IMMState, matrix: np.ndarray):
        """Return (c̄, mixed means, mixed covariances) for transition matrix Π."""
        mu, means, covs = state.probabilities, state.means, state.covariances
        count = self.mode_count
        matrix = check_transition_matrix(matrix, count)
        cbar = mu.dot(matrix)                                   # c̄_j = Σ_i Π_ij μ_i
        mixed_x = np.empty_like(means)
        mixed_P = np.empty_like(covs)
        for j in range(count):
            if cbar[j] > 0.0:
                weights = matrix[:, j] * mu / cbar[j]           # ω_ij = Π_ij μ_i / c̄_j
            else:  # unreachable mode: keep its own estimate (its probability is 0)
                weights = np.zeros(count)
                weights[j] = 1.0
            xs, Ps = self._entering(j, means, covs, weights)
            mixed_x[j], mixed_P[j] = combine(xs, Ps, weights)  # x0_j, P0_j
        return cbar, mixed_x, mixed_P

    def _entering(self, j: int, means: np.ndarray, covs: np.ndarray, weights: np.ndarray):
        """Return the components as they enter mode j (the entry hook for i != j)."""
        if self.entry is None:
            return means, covs
        xs, Ps = means.copy(), covs.copy()
        for i in range(self.mode_count):
            if i != j and weights[i] > 0.0:
                xs[i], Ps[i] = self.entry(j, means[i], covs[i])
        return xs, Ps

    def predict(self, state: IMMState, dt_s: float, u=None) -> IMMState:
        """Return the state predicted over dt_s: mixing, then each mode's prediction."""
        dt_s = as_duration('dt_s', dt_s)
        cbar, mixed_x, mixed_P = self.mix(state, self.transition(dt_s, state))
        means = np.empty_like(mixed_x)
        covs = np.empty_like(mixed_P)
        for j, mode in enumerate(self.modes):
            means[j], covs[j] = mode.predict(mixed_x[j], mixed_P[j], dt_s, u)
        return IMMState(_read_only(means), _read_only(covs), _read_only(cbar / cbar.sum()))

    def predict_ahead(self, state: IMMState, dt_s: float, u=None
                      ) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) dt_s ahead: one IMM prediction, moment-matched."""
        return self.estimate(self.predict(state, dt_s, u))

    def update(self, state: IMMState, z, R=None) -> Tuple[IMMState, UpdateResult]:
        """
        Return the state corrected by z, and the innovation of the whole mixture.

        The returned UpdateResult is the moment-matched one: predicted measurement
        ẑ = Σ c̄_j ẑ_j, S = Σ c̄_j (S_j + (ẑ_j - ẑ)(ẑ_j - ẑ)ᵀ), NIS = yᵀ S⁻¹ y, and the
        gain P_xz S⁻¹, so that a χ² gate treats the IMM like one filter.
        """
        prior_mu = state.probabilities
        means = np.empty_like(state.means)
        covs = np.empty_like(state.covariances)
        results = []
        for j, mode in enumerate(self.modes):
            means[j], covs[j], result = mode.update(
                state.means[j], state.covariances[j], z, R)
            results.append(result)
        logs = np.array([log_likelihood(result) for result in results])
        with np.errstate(divide='ignore'):
            weights = np.log(prior_mu) + logs                  # log(c̄_j Λ_j)
        weights = np.exp(weights - np.max(weights))
        posterior = weights / weights.sum()                    # μ_j = c̄_j Λ_j / Σ
        new_state = IMMState(_read_only(means), _read_only(covs), _read_only(posterior))
        return new_state, self._mixture_innovation(state, results)

    @staticmethod
    def _mixture_innovation(prior: IMMState, results) -> UpdateResult:
        """Return the moment-matched innovation statistics of the prior mixture."""
        c = prior.probabilities
        y_modes = np.array([r.innovation for r in results])             # y_j = z - ẑ_j
        y = c.dot(y_modes)                                              # y = z - Σ c̄_j ẑ_j
        d = y_modes - y
        S = np.einsum('j,jab->ab', c, np.array([r.innovation_covariance for r in results]))
        S = S + np.einsum('j,ja,jb->ab', c, d, d)
        S = 0.5 * (S + S.T)
        x_bar = c.dot(prior.means)
        # P_xz = Σ c̄_j (P_j Hᵀ + (x_j - x̄)(ẑ_j - ẑ)ᵀ), with P_j Hᵀ = K_j S_j
        # and ẑ_j - ẑ = -(y_j - y).
        Pxz = sum(cj * (r.gain.dot(r.innovation_covariance) - np.outer(xj - x_bar, dj))
                  for cj, r, xj, dj in zip(c, results, prior.means, d))
        gain = np.linalg.solve(S, Pxz.T).T                              # K = P_xz S⁻¹
        nis = float(y.dot(np.linalg.solve(S, y)))                       # yᵀ S⁻¹ y
        return UpdateResult(y, S, nis, gain)


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
            value = self.function(as_duration('dt', dt_s))
            value.flags.writeable = False
            if len(self.values) >= _CACHE_SIZE:
                self.values.pop(next(iter(self.values)))
            self.values[dt_s] = value
        return value


def _stand_model(params: RailModelParameters) -> LinearModel:
    """Return the stand regime: p held (plus stand_noise), v = a = ℓ = 0 exactly, A, B kept."""
    F = np.diag([1.0, 0.0, 0.0, 0.0, 1.0, 1.0])
    F.flags.writeable = False
    q = params.capability_noise
    return LinearModel(lambda dt: F,
                       _Cached(lambda dt: np.diag([params.stand_noise * dt, 0.0, 0.0, 0.0,
                                                   q * dt, q * dt])),
                       _H, [[params.noise_std_m ** 2]], state_names=STATE_NAMES)


def _moving_transition(dt_s: float, tau_s: float) -> np.ndarray:
    """Return the 6x6 F(dt) of a moving regime: the relaxation, A and B held."""
    F = np.eye(DIM_X)
    F[:4, :4] = relaxation_transition(dt_s, tau_s)[0]
    return F


def _moving_noise(dt_s: float, params: RailModelParameters) -> np.ndarray:
    """Return the 6x6 Q(dt) of a moving regime: the relaxation's, and A, B's drift."""
    Q = np.zeros((DIM_X, DIM_X))
    Q[:4, :4] = relaxation_noise(dt_s, params.response_time_s, params.acceleration_noise,
                                 params.command_noise)
    Q[4, 4] = Q[5, 5] = params.capability_noise * dt_s
    return Q


def _moving_model(params: RailModelParameters) -> LinearModel:
    """Return a moving regime's Kalman model (all three share the dynamics)."""
    tau = params.response_time_s
    return LinearModel(_Cached(lambda dt: _moving_transition(dt, tau)),
                       _Cached(lambda dt: _moving_noise(dt, params)),
                       _H, [[params.noise_std_m ** 2]], state_names=STATE_NAMES)


def _normal_cdf(x: float) -> float:
    """Return Φ(x), the standard normal distribution function."""
    return 0.5 * math.erfc(-x / math.sqrt(2.0))


class ReferenceRailModel(ReferenceIMM):
    """The four-regime rail IMM (pure: states in, states out); see the module docstring."""

    def __init__(self, parameters: RailModelParameters = RailModelParameters()):
        """Build the regimes from ``parameters``."""
        self.parameters = parameters
        moving = _moving_model(parameters)
        self._rates = RateTransition(parameters.rates())
        super().__init__((_stand_model(parameters), moving, moving, moving), self._transition,
                         MODE_NAMES, self.entry)

    def _transition(self, dt_s: float, state: IMMState) -> np.ndarray:
        """Return Π(dt): the fixed rates plus brake -> stand, scaled by P(v <= stop speed)."""
        params = self.parameters
        rates = self._rates.rates.copy()
        for regime in (ACCELERATE, CRUISE, BRAKE):  # added since: any slow train may stop
            v = state.means[regime, 1]
            std = math.sqrt(max(state.covariances[regime, 1, 1], 0.0))
            slow = (1.0 if v <= params.stop_speed_mps else 0.0) if std == 0.0 else \
                _normal_cdf((params.stop_speed_mps - v) / std)
            rates[regime, STAND] = params.stop_rate_hz * slow
        return self._rates.matrix(dt_s, rates)

    def update(self, state: IMMState, z, R=None) -> Tuple[IMMState, UpdateResult]:
        """Return the IMM update, each regime's mean bounded in a, then held at v >= 0."""
        state, result = super().update(state, z, R)
        means = np.array(state.means)
        for j in range(means.shape[0]):
            a, P = means[j, 2], state.covariances[j]
            limit = min(max(a, -ACCELERATION_LIMIT_MPS2), ACCELERATION_LIMIT_MPS2)
            if a != limit:
                if P[2, 2] > 0.0:
                    means[j] = means[j] - P[:, 2] * ((a - limit) / P[2, 2])
                means[j, 2] = limit
            if means[j, 1] < 0.0:
                P = state.covariances[j]
                if P[1, 1] > 0.0:
                    means[j] = means[j] - P[:, 1] * (means[j, 1] / P[1, 1])
                means[j, 1] = 0.0
        return state._replace(means=_read_only(means)), result

    def entry(self, j: int, x: np.ndarray, P: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return a component entering mode j with its new commanded acceleration ℓ.

        accelerate: ℓ = A + w, brake: ℓ = -B + w, w ~ N(0, plateau_std²) independent;
        as x' = T x + w this is exact: ℓ's row and column become A's (or -B's) and its
        variance Var(A) + plateau_std². cruise: ℓ ~ N(0, cruise_std²), independent of
        the rest; stand: ℓ = 0.
        """
        x, P = x.copy(), P.copy()
        params = self.parameters
        if j in (ACCELERATE, BRAKE):
            source, sign = (4, 1.0) if j == ACCELERATE else (5, -1.0)
            x[3] = sign * x[source]
            P[3, :] = sign * P[source, :]
            P[:, 3] = sign * P[:, source]
            P[3, 3] = P[source, source] + params.plateau_std_mps2 ** 2
        else:
            x[3] = 0.0
            P[3, :] = 0.0
            P[:, 3] = 0.0
            P[3, 3] = params.cruise_std_mps2 ** 2 if j == CRUISE else 0.0
        return x, P

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
        dt_s = as_duration('dt_s', dt_s)
        means = np.empty_like(state.means)
        covs = np.empty_like(state.covariances)
        for j, mode in enumerate(self.modes):
            means[j], covs[j] = mode.predict(state.means[j], state.covariances[j], dt_s, u)
            if j != STAND:
                means[j] = self._no_reversal(state.means[j], means[j], dt_s)
        return combine(means, covs, state.probabilities)

    def _horizon_phi(self, dt_s: float) -> Tuple[float, float, float]:
        """Return (φ1, φ2, φ3) at x = dt_s/τ, remembered for the last dt_s."""
        if getattr(self, '_phi_cache', (None,))[0] != dt_s:
            values = _phi(np.array([dt_s / self.parameters.response_time_s]))
            self._phi_cache = (dt_s, tuple(float(v[0]) for v in values))
        return self._phi_cache[1]

    def _no_reversal(self, start: np.ndarray, predicted: np.ndarray,
                     dt_s: float) -> np.ndarray:
        """
        Return the predicted mean with the train held where its mean velocity reaches 0.

        The mean path from ``start`` (velocity clipped at 0) is v(t) = v + τφ1 a + τφ2 ℓ.
        If it reaches 0 within dt_s, the first root is bracketed on a 40-step grid,
        then on a 40-step grid within that step (to dt_s/1600), and the train stands
        from then on (v = a = 0) at the position it reached.
        """
        p, v, a, command = start[:4]
        tau = self.parameters.response_time_s
        if v >= 0.0:
            # φ1, φ2 grow with t, so v(t) >= v + τ φ1(T/τ) min(a, 0) + τ φ2(T/τ) min(ℓ, 0):
            # if that is positive the mean path never stops and the prediction stands.
            phi1, phi2, _ = self._horizon_phi(dt_s)
            if v + tau * (phi1 * min(a, 0.0) + phi2 * min(command, 0.0)) > 0.0:
                return predicted
        state = np.array([p, max(v, 0.0), a, command])
        low, high = 0.0, dt_s
        for _ in range(2):
            grid = np.linspace(low, high, 41)
            path = relaxation_transition(grid, tau).dot(state)       # (41, 4) mean path
            below = np.nonzero(path[:, 1] <= 0.0)[0]
            if below.size == 0:
                if v >= 0.0:
                    return predicted
                held = predicted.copy()  # started below 0: follow the clipped path
                held[:3] = path[-1, :3]
                return held
            high = grid[below[0]]
            if below[0] == 0:
                break  # standing with a <= 0 already: it stays where it is
            low = grid[below[0] - 1]
        stop = relaxation_transition(high, tau)[0].dot(state)
        held = predicted.copy()
        held[0], held[1], held[2] = max(stop[0], p), 0.0, 0.0
        return held
