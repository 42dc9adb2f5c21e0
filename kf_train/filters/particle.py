"""
Bootstrap particle filter: linear-Gaussian dynamics, any measurement, log-weights.

N particles x_i with normalised log-weights ℓ_i (Σ exp ℓ_i = 1) represent the
state's distribution (Gordon, Salmond & Smith 1993, the "bootstrap" filter):

* predict: every particle moves through the model, x_i ← F x_i + B u + w_i with
  w_i ~ N(0, Q(dt)) drawn from the filter's own seeded ``numpy.random.Generator``;
  the weights stay.
* update: ℓ_i ← ℓ_i − ½ r_iᵀ R⁻¹ r_i with r_i = z ⊖ h(x_i) (a bearing residual
  wrapped to (−π, π]), then normalised by log-sum-exp,
  ℓ_i ← ℓ_i − (m + log Σ exp(ℓ_j − m)), m = max ℓ_j. The weights live in the log
  domain, so a measurement that makes every likelihood underflow (R tiny, a
  surprising z) still leaves the most likely particles with usable weights.
* resample: when the effective sample size ESS = 1 / Σ w_i² drops below
  ``resample_threshold``·N, systematic resampling (one uniform draw u₀, positions
  (u₀ + k) / N on the weights' cumulative sum) copies particle i ⌊N w_i⌋ or ⌈N w_i⌉
  times; the weights become equal.
* roughening (optional, ``roughening`` K > 0; Gordon, Salmond & Smith 1993): after
  resampling, every state component j gets a jitter N(0, σ_j²) with
  σ_j = K·E_j·N^(−1/n), E_j the particles' range in that component. The duplicated
  particles then differ again, at the price of a slightly widened distribution;
  K = 0 (the default) is the plain bootstrap filter.

The estimate is the particles' weighted mean Σ w_i x_i and covariance
Σ w_i (x_i − x̄)(x_i − x̄)ᵀ. Every step replaces the filter's state only once it has
fully succeeded, so a rejected measurement leaves particles, weights and the
generator exactly as they were; :meth:`ParticleFilter.snapshot` and
:meth:`ParticleFilter.restore` capture all three, so that a replay from a snapshot
repeats the same random draws, bit for bit.
"""

import math
from typing import Dict, NamedTuple, Optional, Tuple

from kf_train.filters.kalman import UpdateResult
from kf_train.filters.ukf import batch_measurement, BatchMeasurement
from kf_train.filters.validation import as_covariance, as_finite_array, as_vector
import numpy as np

DEFAULT_RESAMPLE_THRESHOLD = 0.5
MAX_PARTICLES = 100_000_000


def check_seed(seed) -> int:
    """Return a non-negative integer seed, or raise ValueError."""
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
    return int(seed)


def check_particles(n_particles) -> int:
    """Return a particle count in [1, 1e8], or raise ValueError."""
    if (not isinstance(n_particles, (int, np.integer)) or isinstance(n_particles, bool)
            or not 1 <= n_particles <= MAX_PARTICLES):
        raise ValueError(f'n_particles must be an integer in [1, {MAX_PARTICLES}], '
                         f'got {n_particles!r}')
    return int(n_particles)


def psd_factor(name: str, M, dim: int) -> np.ndarray:
    """Return G (dim, r) with G Gᵀ = M for a PSD M, r = its numerical rank (may be 0)."""
    M = as_covariance(name, M, dim)
    if not np.any(M):
        return np.zeros((dim, 0))
    if dim == 1 or np.count_nonzero(M - np.diag(np.diag(M))) == 0:
        d = np.maximum(np.diag(M), 0.0)
        keep = np.flatnonzero(d > 0.0)
        G = np.zeros((dim, keep.size))
        G[keep, np.arange(keep.size)] = np.sqrt(d[keep])  # zero rows stay exactly zero
        return G
    w, V = np.linalg.eigh(M)
    keep = w > np.finfo(float).eps * float(np.max(np.abs(w)))
    return V[:, keep] * np.sqrt(w[keep])


def systematic_resample(weights: np.ndarray, u0: float) -> np.ndarray:
    """Return the indices chosen by systematic resampling with offset u0 in [0, 1)."""
    N = weights.shape[0]
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0                       # guard against rounding below 1
    positions = (u0 + np.arange(N)) / N        # one draw, N evenly spaced positions
    return np.minimum(np.searchsorted(cumulative, positions, side='right'), N - 1)


def log_normalise(log_w: np.ndarray) -> Tuple[np.ndarray, float]:
    """Return (log-weights normalised by log-sum-exp, the log of their old total)."""
    top = float(np.max(log_w))
    if not math.isfinite(top):
        raise ValueError('every particle has zero likelihood for this measurement '
                         '(even in the log domain)')
    total = top + math.log(float(np.sum(np.exp(log_w - top))))  # log Σ exp ℓ
    return log_w - total, total


class Snapshot(NamedTuple):
    """Everything a particle filter's future depends on (immutable copies)."""

    particles: np.ndarray
    log_weights: np.ndarray
    rng_state: Dict
    resample_count: int


class ParticleFilter:
    """
    A bootstrap particle filter on a LinearModel or ExtendedModel.

    ``model`` supplies F(dt), Q(dt), optional B(dt), R and the measurement. The
    particles start as N draws from N(x0, P0) (P0 may be singular).
    """

    def __init__(self, model, x0, P0, *, n_particles: int = 1000, seed: int = 0,
                 resample_threshold: float = DEFAULT_RESAMPLE_THRESHOLD, roughening: float = 0.0):
        """Draw the initial particles from N(x0, P0) with a generator seeded by ``seed``."""
        self.model = model
        self.n_particles = check_particles(n_particles)
        self.seed = check_seed(seed)
        threshold = as_finite_array('resample_threshold', resample_threshold)
        if threshold.ndim != 0 or not 0.0 <= float(threshold) <= 1.0:
            raise ValueError(f'resample_threshold must be in [0, 1], got {resample_threshold!r}')
        self.resample_threshold = float(threshold)
        roughening = as_finite_array('roughening', roughening)
        if roughening.ndim != 0 or float(roughening) < 0.0:
            raise ValueError(f'roughening must be a number >= 0, got {roughening!r}')
        self.roughening = float(roughening)
        self.dim_x = len(model.state_names)
        self.measurement: BatchMeasurement = batch_measurement(model)
        self._noise_factors: Dict[float, np.ndarray] = {}
        self.reset(x0, P0)

    # -- state ----------------------------------------------------------------

    def reset(self, x0, P0, seed: Optional[int] = None) -> None:
        """Restart from N(x0, P0) with a fresh generator (``seed``, else the filter's)."""
        x0 = as_vector('x0', x0, self.dim_x)
        G = psd_factor('P0', P0, self.dim_x)
        if seed is not None:
            self.seed = check_seed(seed)
        rng = np.random.default_rng(self.seed)
        N = self.n_particles
        particles = np.broadcast_to(x0, (N, self.dim_x)).copy()
        if G.shape[1]:
            particles += rng.standard_normal((N, G.shape[1])) @ G.T  # x0 + G ξ
        self._rng = rng
        self._set(particles, np.full(N, -math.log(N)))
        self.resample_count = 0

    def _set(self, particles: np.ndarray, log_w: np.ndarray) -> None:
        """Replace the particles and log-weights; forget the cached moments."""
        self._particles, self._log_w = particles, log_w
        self._moments = None

    def _estimate(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return the weighted mean and covariance, computed once per state."""
        if self._moments is None:
            self._moments = _moments(self._particles, np.exp(self._log_w))
        return self._moments

    @property
    def particles(self) -> np.ndarray:
        """Return a copy of the particle states, shape (N, n)."""
        return self._particles.copy()

    @property
    def weights(self) -> np.ndarray:
        """Return the normalised weights, shape (N,)."""
        return np.exp(self._log_w)

    @property
    def log_weights(self) -> np.ndarray:
        """Return a copy of the normalised log-weights (N,)."""
        return self._log_w.copy()

    @property
    def ess(self) -> float:
        """Return the effective sample size 1 / Σ w_i²."""
        return _ess(self._log_w)

    @property
    def mean(self) -> np.ndarray:
        """Return the weighted mean Σ w_i x_i."""
        return self._estimate()[0].copy()

    @property
    def covariance(self) -> np.ndarray:
        """Return the weighted covariance Σ w_i (x_i − x̄)(x_i − x̄)ᵀ."""
        return self._estimate()[1].copy()

    def snapshot(self) -> Snapshot:
        """Return a copy of the state: particles, log-weights, generator state, counter."""
        particles, log_w = self._particles.copy(), self._log_w.copy()
        particles.flags.writeable = False
        log_w.flags.writeable = False
        return Snapshot(particles, log_w, _copy_state(self._rng.bit_generator.state),
                        self.resample_count)

    def restore(self, snapshot: Snapshot) -> None:
        """Return to a snapshot taken from a filter of the same size."""
        if snapshot.particles.shape != (self.n_particles, self.dim_x):
            raise ValueError(f'snapshot has {snapshot.particles.shape} particles, this filter '
                             f'{(self.n_particles, self.dim_x)}')
        rng = np.random.default_rng()
        rng.bit_generator.state = _copy_state(snapshot.rng_state)
        self._rng = rng
        self._set(np.array(snapshot.particles), np.array(snapshot.log_weights))
        self.resample_count = int(snapshot.resample_count)

    # -- steps ----------------------------------------------------------------

    def _noise_factor(self, dt_s: float) -> np.ndarray:
        """Return G with G Gᵀ = Q(dt), cached per dt."""
        G = self._noise_factors.get(dt_s)
        if G is None:
            G = psd_factor('Q', self.model.Q(dt_s), self.dim_x)
            if len(self._noise_factors) > 64:
                self._noise_factors.clear()
            self._noise_factors[dt_s] = G
        return G

    def _control(self, dt_s: float, u) -> Optional[np.ndarray]:
        """Return B(dt) u, or None without control input."""
        if self.model.B is None:
            if u is not None:
                raise ValueError('u given to a model without control input')
            return None
        if u is None:
            raise ValueError(f'u ({", ".join(self.model.control_names)}) is required')
        u = as_vector('u', u, len(self.model.control_names))
        return np.asarray(self.model.B(dt_s), dtype=float) @ u

    def predict(self, dt_s: float, u=None) -> None:
        """Move every particle: x_i ← F x_i + B u + w_i, w_i ~ N(0, Q(dt))."""
        F = np.asarray(self.model.F(dt_s), dtype=float)
        control = self._control(dt_s, u)
        G = self._noise_factor(float(dt_s))
        # (A C-contiguous Fᵀ keeps the product on BLAS: 20x faster for 1e5 particles.)
        particles = self._particles @ np.ascontiguousarray(F.T)  # F x_i
        if control is not None:
            particles += control                   # + B u
        if G.shape[1]:
            state = self._rng.bit_generator.state
            noise = self._rng.standard_normal((self.n_particles, G.shape[1]))
            particles += noise @ np.ascontiguousarray(G.T)  # + w_i, w_i ~ N(0, Q)
        if not np.all(np.isfinite(particles)):
            if G.shape[1]:
                self._rng.bit_generator.state = state  # leave the generator as it was
            raise ValueError('prediction produced non-finite particles; inputs are too large')
        self._set(particles, self._log_w)

    def predict_ahead(self, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return the mean and covariance predicted over dt_s, leaving the filter as it is.

        The dynamics are linear, so these are exact without drawing noise:
        F x̄ + B u and F P Fᵀ + Q.
        """
        F = np.asarray(self.model.F(dt_s), dtype=float)
        control = self._control(dt_s, u)
        x, P = self._estimate()
        x = F @ x
        if control is not None:
            x = x + control
        P = F @ P @ F.T + np.asarray(self.model.Q(dt_s), dtype=float)
        return x, 0.5 * (P + P.T)

    def update(self, z, R=None) -> UpdateResult:
        """
        Weight the particles by the likelihood of z; resample when ESS < threshold·N.

        Returns the innovation statistics of the predicted measurement distribution
        (before reweighting): y = z ⊖ ẑ, S = Σ w_i (h(x_i) ⊖ ẑ)(h(x_i) ⊖ ẑ)ᵀ + R,
        NIS = yᵀ S⁻¹ y, and as gain the linear-regression gain P_xz S⁻¹ (a
        diagnostic: the filter does not use it).
        """
        m = len(self.model.measurement_names)
        z = as_vector('z', z, m)
        R = as_covariance('R', self.model.R if R is None else R, m)
        try:
            L = np.linalg.cholesky(R)
        except np.linalg.LinAlgError:
            raise ValueError(f'R must be positive definite for the likelihood, got '
                             f'{R.tolist()}') from None
        angular = self.measurement.angular
        Zp = self.measurement.predict(self._particles)       # h(x_i) (N, m)
        residual = _wrap(z - Zp, angular)                     # r_i = z ⊖ h(x_i)
        # (An overflow means a likelihood of exactly zero: a log-weight of −inf.)
        with np.errstate(over='ignore', invalid='ignore'):
            white = residual @ np.ascontiguousarray(np.linalg.inv(L).T)  # (L⁻¹ r_i)ᵀ
            log_likelihood = -0.5 * np.sum(white * white, axis=1)  # −½ r_iᵀ R⁻¹ r_i
            log_w = self._log_w + log_likelihood
        log_w = np.where(np.isnan(log_w), -np.inf, log_w)
        log_w, _ = log_normalise(log_w)                       # raises when none is finite

        weights = np.exp(self._log_w)                         # the prior's weights
        result = _innovation(self._particles, weights, residual, R)
        particles = self._particles
        resampled = _ess(log_w) < self.resample_threshold * self.n_particles
        if resampled:
            # (The only random draw of an update, made once everything else succeeded.)
            index = systematic_resample(np.exp(log_w), float(self._rng.random()))
            particles = particles[index]
            if self.roughening > 0.0:
                spread = np.ptp(particles, axis=0) * (self.roughening * self.n_particles ** (
                    -1.0 / self.dim_x))
                particles = particles + self._rng.standard_normal(particles.shape) * spread
            log_w = np.full(self.n_particles, -math.log(self.n_particles))
        self._set(particles, log_w)
        self.resample_count += resampled
        return result

    def __repr__(self) -> str:
        """Show the size and seed."""
        return (f'ParticleFilter(n_particles={self.n_particles}, seed={self.seed}, '
                f'resample_threshold={self.resample_threshold})')


def _copy_state(state: Dict) -> Dict:
    """Return a deep copy of a bit generator's state dictionary."""
    return {key: (_copy_state(value) if isinstance(value, dict) else value)
            for key, value in state.items()}


def _ess(log_w: np.ndarray) -> float:
    """Return 1 / Σ w² for normalised log-weights."""
    return 1.0 / float(np.sum(np.exp(2.0 * log_w)))


def _wrap(d: np.ndarray, angular) -> np.ndarray:
    """Wrap the angular columns of d (k, m) to (−π, π] in place; return d."""
    for j, is_angle in enumerate(angular):
        if is_angle:
            d[:, j] = d[:, j] - 2.0 * math.pi * np.ceil((d[:, j] - math.pi) / (2.0 * math.pi))
    return d


def _moments(X: np.ndarray, w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Return the weighted mean and covariance of the rows of X."""
    mean = w @ X                                   # x̄ = Σ w_i x_i
    D = X - mean
    Dw = D * w[:, None]
    cov = Dw.T @ D                                 # Σ w_i (x_i − x̄)(x_i − x̄)ᵀ
    return mean, 0.5 * (cov + cov.T)


def _innovation(X: np.ndarray, w: np.ndarray, residual: np.ndarray, R: np.ndarray
                ) -> UpdateResult:
    """
    Return the innovation statistics from the residuals r_i = z ⊖ h(x_i), weights w.

    y = Σ w_i r_i is z ⊖ ẑ with ẑ the weighted mean of h(x_i) taken in the tangent
    space at z (for a bearing, equal to the circular mean to second order in the
    spread, and free of its sin/cos per particle); S = Σ w_i (r_i − y)(r_i − y)ᵀ + R.
    """
    y = w @ residual                               # y = Σ w r = z ⊖ ẑ
    dZ = residual - y                              # −(h(x_i) ⊖ ẑ)
    dZw = dZ * w[:, None]
    S = dZw.T @ dZ + R                             # S = Σ w dZ dZᵀ + R
    S = 0.5 * (S + S.T)
    Pxz = -(dZw.T @ (X - w @ X)).T                 # P_xz = Σ w (x − x̄)(h ⊖ ẑ)ᵀ
    try:
        K = np.linalg.solve(S, Pxz.T).T            # K = P_xz S⁻¹
        nis = float(y @ np.linalg.solve(S, y))     # NIS = yᵀ S⁻¹ y
    except np.linalg.LinAlgError:  # pragma: no cover - S ⪰ R, and R is positive definite
        K, nis = np.full(Pxz.shape, np.nan), math.inf
    return UpdateResult(y, S, nis, K)
