"""
Interacting multiple models (IMM): a bank of Kalman filters, one per motion regime.

Notation follows Bar-Shalom, Li and Kirubarajan (2001) and filterpy: N modes, each
with its own model (``predict(x, P, dt_s, u)`` and ``update(x, P, z, R)``, e.g. a
:class:`~kf_train.filters.models.LinearModel`, whose arithmetic is
:mod:`kf_train.filters.kalman`'s, Joseph form); mode probabilities μ (N,); the Markov
transition matrix Π with Π[i, j] = P(mode j now | mode i before) (rows sum to 1,
filterpy's ``M``). One cycle:

* mixing: c̄_j = Σ_i Π_ij μ_i, ω_ij = Π_ij μ_i / c̄_j, and each mode starts from the
  moment-matched mixture x0_j = Σ_i ω_ij x_i, P0_j = Σ_i ω_ij (P_i + d dᵀ),
  d = x_i - x0_j;
* mode-matched prediction of each mode from (x0_j, P0_j); the predicted mode
  probabilities are c̄;
* mode-matched update of each mode; μ_j ∝ c̄_j · N(y_j; 0, S_j);
* the estimate: x = Σ μ_j x_j, P = Σ μ_j (P_j + (x_j - x)(x_j - x)ᵀ).

The state is an immutable :class:`IMMState` (per-mode means, covariances and
probabilities, read-only arrays), so a snapshot for an out-of-sequence rewind is the
state object itself. :class:`IMM` holds the models and computes; :class:`IMMFilter`
holds a state and has the interface of :class:`kf_train.filters.family.Filter`
(predict, update, predict_ahead, mean, covariance, snapshot, restore, reset, copy).

Public hooks let a model use what it knows about its regimes (:class:`IMM`,
:mod:`kf_train.filters.rail_model`): ``transition(dt_s, state)`` may depend on the state,
``entry(j, x, P)`` transforms a component that switches into mode j; ``mixing`` and
``matrices`` give the same numbers in fewer numpy calls. Without them, the IMM is
filterpy's ``IMMEstimator`` to rounding. Π(dt) of switching rates is written once,
:func:`first_jump_row`. Likelihoods are kept as logarithms, so a mode whose likelihood
underflows a float (filterpy then substitutes 2.2e-308) still gets its probability.
"""

import math
from typing import Callable, NamedTuple, Optional, Sequence, Tuple

from kf_train.filters import imm_stack
from kf_train.filters.contract import regime_columns
from kf_train.filters.imm_stack import frozen as _frozen, LinearStack
from kf_train.filters.kalman import LOG_2PI, UpdateResult
from kf_train.filters.noise_adaptation import FIXED, NoiseAdaptation, NoiseScale, Variance
from kf_train.filters.validation import as_covariance, as_finite_array, as_vector
import numpy as np

# Rows of a transition matrix must sum to 1 to within this.
_ROW_SUM_TOLERANCE = 1e-9


def _read_only(array: np.ndarray) -> np.ndarray:
    """Return ``array`` marked read-only (it is owned by an IMMState)."""
    array.setflags(write=False)       # a third cheaper than through array.flags
    return array


class IMMState(NamedTuple):
    """The whole state of an IMM: per-mode estimates and mode probabilities."""

    means: np.ndarray
    """Mode-conditioned means (N, n), read-only."""
    covariances: np.ndarray
    """Mode-conditioned covariances (N, n, n), read-only."""
    probabilities: np.ndarray
    """Mode probabilities (N,), summing to 1, read-only."""
    noise: NoiseScale = FIXED
    """The scale on the measurement noise and what learned it (FIXED: R as given;
    :mod:`~kf_train.filters.noise_adaptation`)."""


def make_state(means, covariances, probabilities, noise: NoiseScale = FIXED) -> IMMState:
    """Return a checked, read-only IMMState (probabilities are normalised)."""
    means = as_finite_array('means', means)
    if means.ndim != 2 or means.shape[0] < 1:
        raise ValueError(f'means must have shape (N, n), got {means.shape}')
    count, n = means.shape
    covariances = as_finite_array('covariances', covariances)
    if covariances.shape != (count, n, n):
        raise ValueError(f'covariances must have shape {(count, n, n)}, got '
                         f'{covariances.shape}')
    covariances = np.array([as_covariance(f'covariances[{i}]', c, n)
                            for i, c in enumerate(covariances)])
    probabilities = as_vector('probabilities', probabilities, count)
    total = float(np.sum(probabilities))
    if np.any(probabilities < 0.0) or not total > 0.0:
        raise ValueError(f'probabilities must be >= 0 with a positive sum, got '
                         f'{probabilities.tolist()}')
    return IMMState(_read_only(means.copy()), _read_only(covariances),
                    _read_only(probabilities / total), noise)


def check_transition_matrix(matrix, count: int) -> np.ndarray:
    """Return a (count, count) row-stochastic matrix, else raise ValueError."""
    matrix = as_finite_array('transition matrix', matrix)
    if matrix.shape != (count, count):
        raise ValueError(f'transition matrix must have shape {(count, count)}, got '
                         f'{matrix.shape}')
    if np.any(matrix < 0.0) or np.max(np.abs(matrix.sum(axis=1) - 1.0)) > _ROW_SUM_TOLERANCE:
        raise ValueError(f'transition matrix must be >= 0 with rows summing to 1, got '
                         f'{matrix.tolist()}')
    return matrix


class FixedTransition:
    """Π the same for every prediction, whatever dt (filterpy's convention)."""

    def __init__(self, matrix):
        """Keep a square row-stochastic matrix."""
        matrix = as_finite_array('transition matrix', matrix)
        self.matrix = _read_only(check_transition_matrix(
            matrix, matrix.shape[0] if matrix.ndim == 2 else 0).copy())

    def __call__(self, dt_s: float, state: IMMState) -> np.ndarray:
        """Return Π."""
        return self.matrix


def first_jump_row(rates, own: int, dt_s: float):
    """
    Return row ``own`` of Π(dt) for the rates out of mode ``own``: THE formula of Π(dt).

    Π_ii = e^(-r_i dt), Π_ij = (1 - e^(-r_i dt)) · r_ij / r_i, r_i = Σ_j r_ij (j ≠ i;
    the entry ``own`` is taken as 0). ``rates`` is one row as a list of floats (a new
    list is returned: math.exp, one mode's row at every step of a jittered stream) or
    K rows as a (K, N) array, one per setting (a new (K, N) array: numpy.exp).
    """
    if type(rates) is list:
        rates[own] = 0.0
        leave = sum(rates)                               # r_i
        stay = math.exp(-leave * dt_s)                   # Π_ii = e^(-r_i dt)
        # Π_ij = (1 - e^(-r_i dt)) r_ij / r_i
        row = [(1.0 - stay) * (r / leave) if leave > 0.0 else 0.0 for r in rates]
        row[own] = stay
        return row
    rates = rates.copy()
    rates[:, own] = 0.0
    leave = rates.sum(axis=1)                            # r_i
    stay = np.exp(-leave * dt_s)                         # Π_ii = e^(-r_i dt)
    share = rates / np.where(leave > 0.0, leave, 1.0)[:, None]  # r_ij / r_i (0 if r_i = 0)
    row = (1.0 - stay)[:, None] * share                  # Π_ij = (1 - e^(-r_i dt)) r_ij / r_i
    row[:, own] = stay
    return row


class RateTransition:
    """
    Π(dt) from switching rates [1/s]: a continuous-time Markov chain, first jump only.

    Mode i is left at rate r_i = Σ_j rates[i, j] (j ≠ i), to j with probability
    rates[i, j] / r_i: Π_ii = e^(-r_i dt), Π_ij = (1 - e^(-r_i dt)) · rates[i, j] / r_i.
    This is stochastic for every dt >= 0 (Π(0) = I) and neglects two switches within
    one dt, which at rates of 1/s and dt = 0.1 s is a 0.5 % effect.
    """

    def __init__(self, rates):
        """Keep a square matrix of rates >= 0 (the diagonal is ignored)."""
        rates = as_finite_array('rates', rates)
        if rates.ndim != 2 or rates.shape[0] != rates.shape[1] or np.any(rates < 0.0):
            raise ValueError(f'rates must be a square matrix of values >= 0, got '
                             f'{rates.tolist()}')
        rates = rates.copy()
        np.fill_diagonal(rates, 0.0)
        self.rates = _read_only(rates)

    def matrix(self, dt_s: float, rates: Optional[np.ndarray] = None) -> np.ndarray:
        """Return Π(dt) for these rates (or ``rates``, e.g. scaled by the state)."""
        # Plain floats: a few modes, and a stream with jittered stamps asks at every step.
        return np.array([first_jump_row(row, i, dt_s) for i, row in
                         enumerate((self.rates if rates is None else rates).tolist())])

    def __call__(self, dt_s: float, state: IMMState) -> np.ndarray:
        """Return Π(dt_s)."""
        return self.matrix(dt_s)


def combine(means: np.ndarray, covariances: np.ndarray,
            probabilities: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Return the moment-matched (x, P) of a Gaussian mixture."""
    return imm_stack.combine(means, covariances, probabilities)  # x = Σ μ_j x_j, P = ...


def log_likelihood(result: UpdateResult) -> float:
    """Return log N(y; 0, S) of an update's innovation: -(NIS + log det(2π S)) / 2."""
    S = result.innovation_covariance
    if S.shape == (1, 1):
        log_det = math.log(float(S[0, 0]))
    else:
        sign, log_det = np.linalg.slogdet(S)
        if sign <= 0.0:
            raise ValueError(f'innovation covariance is not positive definite: {S.tolist()}')
    return -0.5 * (result.nis + log_det + S.shape[0] * LOG_2PI)


def _measurement(z) -> float:
    """Return a scalar measurement z as a float (a finite float passes unconverted)."""
    if type(z) is float and math.isfinite(z):
        return z
    if type(z) is np.ndarray and z.shape == (1,) and z.dtype == np.float64:
        value = float(z[0])
        if math.isfinite(value):
            return value
    z = as_vector('z', z)
    if z.shape[0] != 1:
        raise ValueError(f'z must have length 1, got {z.shape[0]}')
    return float(z[0])


def _noise_row(R) -> np.ndarray:
    """
    Return the row (1,) of a 1x1 measurement noise R, checked as as_covariance does.

    The estimator's checked (1, 1) float R passes as it is (a view of its row), and the
    stacked update broadcasts it over the modes.
    """
    if type(R) is np.ndarray and R.shape == (1, 1) and R.dtype == np.float64 and \
            0.0 <= R.item(0) < math.inf:
        return R[0]
    return as_covariance('R', R, 1)[0]


def noise_in_use(reported: Variance, noise: NoiseScale, learn: bool) -> Variance:
    """Return R = s r, the learned scale on the variance given (exactly r while s is 1)."""
    return reported if noise.scale == 1.0 or not learn else reported * noise.scale


class IMM:
    """
    The IMM's models and arithmetic; every method is pure (states in, states out).

    ``modes``: one model per mode, each with ``predict(x, P, dt_s, u)`` and
    ``update(x, P, z, R)`` returning ``(x, P, UpdateResult)``. When every mode is a
    plain LinearModel measuring a scalar, the modes are computed as one stack
    (:mod:`kf_train.filters.imm_stack`); otherwise mode by mode through their own
    ``predict`` and ``update``.

    The hooks, through which a model specialises the IMM (the rail model,
    :mod:`kf_train.filters.rail_model`, gives all of them; every one is called as
    given, nothing else of the IMM is replaced):

    * ``transition``: ``(dt_s, state) -> Π`` (:class:`FixedTransition`,
      :class:`RateTransition` or a model's own). Π is checked at every prediction
      (once, if it is the same read-only matrix again) unless ``stochastic`` says
      it is row-stochastic by construction.
    * ``entry``: optional ``(j, x, P) -> (x, P)``, applied to each component that
      switches into mode j, component by component.
    * ``mixing``: optional ``(weights, means, covariances) -> (x0 (N, n), P0 (N, n, n))``:
      every mode's starting mixture at once, for ω_ij = ``weights[i, j]``, with the
      components as they enter each mode. It must give what ``entry`` and the
      mixture give (a vectorised form of it); without it, that is what runs.
    * ``matrices``: optional ``dt_s -> (F, Q, Fᵀ)``, the modes' stacked matrices
      (N, n, n) for the stacked path, for models that build them checked themselves;
      without it, the stack asks each mode and checks (:class:`LinearStack`).
    * ``adaptation``: optional :class:`~kf_train.filters.noise_adaptation.NoiseAdaptation`
      (stacked modes only): the measurement noise in use is the state's learned scale
      times the R given, and each update teaches the scale (the state's ``noise``).
      Without it the state's scale stays as it is (1: R as given).
    """

    def __init__(self, modes: Sequence, transition: Callable, mode_names=None,
                 entry: Optional[Callable] = None, *, mixing: Optional[Callable] = None,
                 matrices: Optional[Callable] = None, stochastic: bool = False,
                 adaptation: Optional[NoiseAdaptation] = None):
        """Keep the models and hooks; names default to mode0, mode1, …."""
        if len(modes) < 1:
            raise ValueError('an IMM needs at least one mode')
        self.modes = tuple(modes)
        self.transition, self.entry, self.mixing = transition, entry, mixing
        self.stochastic = bool(stochastic)
        names = tuple(mode_names) if mode_names is not None else tuple(
            f'mode{i}' for i in range(len(self.modes)))
        if len(names) != len(self.modes) or len(set(names)) != len(names):
            raise ValueError(f'mode_names must be {len(self.modes)} distinct names, got '
                             f'{names!r}')
        self.mode_names = names
        self._stack = LinearStack.of(self.modes)
        self.adaptation = adaptation if adaptation is not None and adaptation.enabled else None
        if self.adaptation is not None and self._stack is None:
            raise ValueError('measurement noise adaptation needs modes that are LinearModels '
                             'measuring a scalar')
        if matrices is None and self._stack is not None:
            matrices = self._stack.matrices
        self.matrices = matrices
        self._checked_matrix = None

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
        return imm_stack.combine(state.means, state.covariances, state.probabilities)

    def _transition_matrix(self, dt_s: float, state: IMMState) -> np.ndarray:
        """Return the checked Π of this prediction (a read-only Π is checked once)."""
        matrix = self.transition(dt_s, state)
        if self.stochastic or matrix is self._checked_matrix:
            return matrix
        checked = check_transition_matrix(matrix, self.mode_count)
        if _frozen(matrix):  # it cannot change: the next call may skip the check
            self._checked_matrix = matrix
        return checked

    def mix(self, state: IMMState, matrix: np.ndarray):
        """Return (c̄, mixed means, mixed covariances) for transition matrix Π."""
        return self._mix(state, check_transition_matrix(matrix, self.mode_count))

    def _mix(self, state: IMMState, matrix: np.ndarray):
        """Do :meth:`mix` for a checked Π."""
        mu = state.probabilities
        cbar = mu.dot(matrix)                                   # c̄_j = Σ_i Π_ij μ_i
        if 0.0 in cbar.tolist():  # an unreachable mode keeps its own estimate (c̄_j = 0)
            reachable = np.where(cbar > 0.0, cbar, 1.0)
            weights = matrix * mu[:, None] / reachable
            for j in np.flatnonzero(cbar == 0.0):
                weights[:, j] = 0.0
                weights[j, j] = 1.0
        else:
            weights = matrix * mu[:, None] / cbar               # ω_ij = Π_ij μ_i / c̄_j
        mixed_x, mixed_P = self._mixed(weights, state.means, state.covariances)
        return cbar, mixed_x, mixed_P

    def _mixed(self, weights: np.ndarray, means: np.ndarray, covs: np.ndarray):
        """Return every mode's starting mixture (x0_j, P0_j) for mixing weights ω_ij."""
        if self.mixing is not None:
            return self.mixing(weights, means, covs)
        return imm_stack.mix(weights, *self._entered(means, covs, weights))

    def _entered(self, means: np.ndarray, covs: np.ndarray, weights: np.ndarray):
        """
        Return the components as they enter each mode: (N, n), (N, n, n) without entry.

        With the entry hook, (N, N, n) and (N, N, n, n): [j, i] is component i entering
        mode j (itself for i = j, and where ω_ij = 0, which the mixture ignores).
        """
        if self.entry is None:
            return means, covs
        count = self.mode_count
        xs = np.repeat(means[None], count, axis=0)
        Ps = np.repeat(covs[None], count, axis=0)
        for j in range(count):
            for i in range(count):
                if i != j and weights[i, j] > 0.0:
                    xs[j, i], Ps[j, i] = self.entry(j, means[i], covs[i])
        return xs, Ps

    def predict(self, state: IMMState, dt_s: float, u=None) -> IMMState:
        """Return the state predicted over dt_s: mixing, then each mode's prediction."""
        dt_s = imm_stack.duration(dt_s)
        cbar, mixed_x, mixed_P = self._mix(state, self._transition_matrix(dt_s, state))
        means, covs = self._predict_modes(mixed_x, mixed_P, dt_s, u)
        total = sum(cbar.tolist())
        return IMMState(_read_only(means), _read_only(covs), _read_only(cbar / total),
                        state.noise)

    def _predict_modes(self, means: np.ndarray, covs: np.ndarray, dt_s: float, u=None):
        """Return each mode's own prediction of its (means[j], covs[j]) over dt_s."""
        if self._stack is not None and u is None:
            return imm_stack.predict(means, covs, *self.matrices(dt_s))
        predicted_x = np.empty_like(means)
        predicted_P = np.empty_like(covs)
        for j, mode in enumerate(self.modes):
            predicted_x[j], predicted_P[j] = mode.predict(means[j], covs[j], dt_s, u)
        return predicted_x, predicted_P

    def error_walk_rate_hz(self, state: IMMState) -> Optional[float]:
        """Return the learned rate of the measurement error's walk: None, it is white here."""
        return None

    def predict_ahead(self, state: IMMState, dt_s: float, u=None
                      ) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) dt_s ahead: one IMM prediction, moment-matched."""
        return self.estimate(self.predict(state, dt_s, u))

    def predict_update(self, state: IMMState, dt_s: float, z, R=None,
                       index: Optional[int] = None) -> Tuple[IMMState, UpdateResult]:
        """Return :meth:`update` (``index``: :meth:`update_component`) after :meth:`predict`."""
        predicted = self.predict(state, dt_s)
        if index is None:
            return self.update(predicted, z, R)
        return self.update_component(predicted, z, R, index)

    def update(self, state: IMMState, z, R=None) -> Tuple[IMMState, UpdateResult]:
        """
        Return the state corrected by z, and the innovation of the whole mixture.

        The returned UpdateResult is the moment-matched one: predicted measurement
        ẑ = Σ c̄_j ẑ_j, S = Σ c̄_j (S_j + (ẑ_j - ẑ)(ẑ_j - ẑ)ᵀ), NIS = yᵀ S⁻¹ y, and the
        gain P_xz S⁻¹, so that a χ² gate treats the IMM like one filter.
        """
        if self._stack is not None:
            return self._update_stacked(state, z, R)
        prior_mu = state.probabilities
        means = np.empty_like(state.means)
        covs = np.empty_like(state.covariances)
        results = []
        for j, mode in enumerate(self.modes):
            means[j], covs[j], result = mode.update(
                state.means[j], state.covariances[j], z, R)
            results.append(result)
        logs = np.array([log_likelihood(result) for result in results])
        posterior = imm_stack.posterior(prior_mu, logs)        # μ_j = c̄_j Λ_j / Σ
        new_state = IMMState(_read_only(means), _read_only(covs), _read_only(posterior),
                             state.noise)
        return new_state, self._mixture_innovation(state, results)

    def update_component(self, state: IMMState, z, R, index: int
                         ) -> Tuple[IMMState, UpdateResult]:
        """
        Return the state corrected by a direct measurement z of state ``index`` (H = e_index).

        A second sensor of the same modes (the rail model's Doppler speed: index 1): the
        modes' own measurement is not involved, R (1x1) is used as given, and the learned
        scale (the state's ``noise``, which belongs to the modes' own measurement) is
        neither applied nor taught. The IMM arithmetic is :meth:`update`'s, stacked;
        the modes must be LinearModels measuring a scalar.
        """
        stack = self._stack
        if stack is None:
            raise ValueError('a component update needs modes that are LinearModels '
                             'measuring a scalar')
        n = stack.dim_x
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < n:
            raise ValueError(f'index must be a state index in [0, {n - 1}], got {index!r}')
        H = np.zeros((self.mode_count, 1, n))
        H[:, 0, index] = 1.0
        return self._update_stacked(state, z, R, H, index, learn=False)

    def _update_stacked(self, state: IMMState, z, R, H: Optional[np.ndarray] = None,
                        selected: Optional[int] = None, learn: bool = True
                        ) -> Tuple[IMMState, UpdateResult]:
        """
        Do :meth:`update` on the stack: every mode a LinearModel measuring a scalar.

        ``H`` (N, 1, n) and ``selected`` replace the modes' own measurement (then R
        must be given); ``learn`` False neither applies nor teaches the learned scale.
        """
        stack = self._stack
        z = _measurement(z)
        if H is None:
            H, selected = stack.H, stack.selected
        elif R is None:
            raise ValueError('R must be given when H is not the modes own measurement')
        reported = stack.R if R is None else _noise_row(R)
        R = noise_in_use(reported, state.noise, learn)
        result = imm_stack.update(state.means, state.covariances, z, H, R,
                                  stack.identity, selected)
        posterior = imm_stack.posterior(state.probabilities, result.log_likelihoods)
        y, S, nis, gain = imm_stack.mixture_innovation(state.probabilities, state.means, result)
        return self.finish_update(state, result.means, result.covariances, posterior,
                                  (y, S, nis, gain), float(reported[0]), learn)

    def finish_update(self, prior: IMMState, means: np.ndarray, covariances: np.ndarray,
                      posterior: np.ndarray, innovation: tuple, reported_m2: float,
                      learn: bool) -> Tuple[IMMState, UpdateResult]:
        """
        Return the updated state and its UpdateResult from the stacked update's arrays.

        ``innovation``: the mixture's (y, S, NIS, K (n,)); ``reported_m2``: the variance
        given. The gate's NIS and the learned scale's lesson, for every path.
        """
        y, S, nis, gain = innovation
        noise = prior.noise
        gate_nis = None
        if learn and noise.scale < 1.0:
            # Weighted with the learned R, gated with the R given: a fix is an outlier
            # only if even the receiver's own accuracy cannot explain it.
            gate_nis = y * y / (S + (1.0 - noise.scale) * reported_m2)
        if self.adaptation is not None and learn:
            noise = self.adaptation.learn(noise, y, S, reported_m2)
        new_state = IMMState(_read_only(means), _read_only(covariances),
                             _read_only(posterior), noise)
        return new_state, UpdateResult(np.array([y]), np.array([[S]]), nis, gain[:, None],
                                       gate_nis)

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


class IMMFilter:
    """
    An IMM holding its state, with the interface of :class:`kf_train.filters.family.Filter`.

    The one holder of a running IMM state: the rail preset's offline series
    (:class:`kf_train.batch.RailSeriesFilter`) runs one from its first measurement on.

    ``predict``/``update`` replace the state only once the whole step succeeded;
    ``predict_ahead`` never changes it; ``snapshot()`` is the immutable state itself.
    """

    kind = 'imm'

    def __init__(self, imm: IMM, x0, P0, probabilities=None):
        """Start every mode at (x0, P0) with ``probabilities`` (uniform by default)."""
        self.imm = imm
        x0 = as_vector('x0', x0).copy()
        self._initial = (x0, as_covariance('P0', P0, x0.shape[0]), probabilities)
        self.reset()

    @property
    def dim_x(self) -> int:
        """Return the number of states n."""
        return self._state.means.shape[1]

    @property
    def mode_names(self) -> Tuple[str, ...]:
        """Return the mode names."""
        return self.imm.mode_names

    @property
    def mode_probabilities(self) -> np.ndarray:
        """Return a copy of the mode probabilities (after an update: the posterior)."""
        return self._state.probabilities.copy()

    @property
    def state(self) -> IMMState:
        """Return the whole (immutable) state."""
        return self._state

    def _estimate(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) of the state, computed once per state."""
        kept = getattr(self, '_estimated', None)
        if kept is None or kept[0] is not self._state:
            kept = self._estimated = (self._state,) + tuple(self.imm.estimate(self._state))
        return kept[1], kept[2]

    @property
    def mean(self) -> np.ndarray:
        """Return the combined mean, a new array."""
        return self._estimate()[0].copy()

    @property
    def covariance(self) -> np.ndarray:
        """Return the combined covariance, a new array."""
        return self._estimate()[1].copy()

    x, P = mean, covariance

    def reset(self, x0=None, P0=None, probabilities=None) -> None:
        """Start again from (x0, P0) (the initial ones by default)."""
        initial_x, initial_P, initial_mu = self._initial
        self._state = self.imm.initial_state(
            initial_x if x0 is None else x0, initial_P if P0 is None else P0,
            initial_mu if probabilities is None else probabilities)

    def predict(self, dt_s: float, u=None) -> None:
        """Propagate over dt_s."""
        self._state = self.imm.predict(self._state, dt_s, u)

    def update(self, z, R=None) -> UpdateResult:
        """Correct with z; return the mixture's innovation statistics."""
        self._state, result = self.imm.update(self._state, z, R)
        return result

    def predict_ahead(self, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) dt_s ahead; the filter is unchanged."""
        return self.imm.predict_ahead(self._state, dt_s, u)

    def snapshot(self) -> IMMState:
        """Return the state (immutable, so keeping it is enough)."""
        return self._state

    def restore(self, snapshot: IMMState) -> None:
        """Return to a snapshot (checked against this IMM's shape)."""
        if not isinstance(snapshot, IMMState) or snapshot.means.shape != self._state.means.shape:
            raise ValueError('snapshot must be an IMMState of this filter')
        self._state = snapshot

    def copy(self) -> 'IMMFilter':
        """Return an independent filter in the same state."""
        other = object.__new__(IMMFilter)
        other.imm, other._initial, other._state = self.imm, self._initial, self._state
        return other

    def diagnostics(self):
        """Return the mode probabilities by name."""
        return dict(zip(regime_columns(self.imm.mode_names), self._state.probabilities.tolist()))
