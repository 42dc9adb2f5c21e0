"""
Regularised particle filter: the particle filter that tracks where the bootstrap collapses.

The bootstrap filter (:mod:`kf_train.filters.particle`) fails on the range-bearing seed
for three reasons, and this filter answers each (Musso, Oudjane & Le Gland 2001;
Oudjane & Musso 2000; Gilks & Berzuini 2001):

* **Initialisation from the first measurement.** A 12-m prior against a likelihood
  0.07 m wide leaves a handful of the prior's particles alive. After a reset the
  prior is Gaussian, N(m⁻, P⁻) (the predicted particles' moments), so the first
  update draws the particles where the measurement puts them and weights them by
  that prior, which makes the first posterior exact:

  - a linear measurement: the Kalman posterior of (m⁻, P⁻), drawn directly;
  - range and bearing: z_i ~ N(z, R) mapped to a position p_i = s + r_i (cos θ_i,
    sin θ_i); the other states (the velocity) from the prior's conditional
    N(m_v + P_vp P_pp⁻¹ (p_i − m_p), P_vv − P_vp P_pp⁻¹ P_pv); log-weight
    log N(p_i; m_p, P_pp) + log r_i (the proposal's density is N(h(p); z, R)·|∂h/∂p|,
    |∂h/∂p| = 1/r). The prior's own particles are kept instead when their
    likelihood weights have the larger effective sample size (a tight prior).

* **Progressive correction (tempering).** When weighting by the whole likelihood L
  would leave fewer than ``resample_threshold``·N effective particles, L is applied
  in stages L^λ₁, L^λ₂, … (Σλ = 1), each λ the largest that keeps that ESS
  (bisection in log λ), with a resample-and-move after each stage, so the cloud
  walks into the likelihood instead of collapsing onto the few particles that
  happen to be inside it.

* **Regularisation with a Metropolis-Hastings move** after every resampling: each
  particle proposes x' = x + h·D·ε, D Dᵀ = the particles' covariance, ε from the
  kernel, h the bandwidth that minimises the mean integrated squared error for a
  Gaussian density (the regularised PF), and keeps x' with probability
  min(1, L(x')^φ N(x'; m⁻, P⁻) / (L(x)^φ N(x; m⁻, P⁻))) (φ the likelihood power
  reached; N(m⁻, P⁻) the Gaussian fit of the prediction). The jitter re-diversifies
  the copies of a resampled particle in every state, positions included, where the
  model has no process noise; the acceptance step keeps the cloud's spread from
  growing by the kernel's (1 + h²) at every resampling.

Kernels: ``gaussian`` (default), h = (4 / (N (d + 2)))^(1/(d+4)); ``epanechnikov``
(on the unit ball), h = A·N^(−1/(d+4)), A = (8 c_d⁻¹ (d + 4) (2√π)^d)^(1/(d+4)),
c_d the unit ball's volume; d the rank of the particles' covariance. ``gordon`` is
Gordon et al.'s roughening (σ_j = K·E_j·N^(−1/d), E_j the particles' range in state
j) inside this filter, for comparison only: it ignores the covariance's orientation.

Everything else (prediction, log-weights, systematic resampling, the moments, the
exact ``predict_ahead``, snapshots, a rejected step leaving the filter as it was) is
the bootstrap filter's. The same seed gives the same numbers, bit for bit.
"""

import math
from typing import Dict, NamedTuple, Optional, Tuple

from kf_train.filters import kalman
from kf_train.filters.ekf import RangeBearing
from kf_train.filters.kalman import UpdateResult
from kf_train.filters.particle import (
    _ess, _innovation, _moments, _wrap, DEFAULT_RESAMPLE_THRESHOLD, log_normalise,
    ParticleFilter, psd_factor, systematic_resample)
from kf_train.filters.validation import as_covariance, as_vector
import numpy as np

KERNELS = ('gaussian', 'epanechnikov', 'gordon')
MAX_TEMPERING_STAGES = 50
"""Stages of one progressive correction at most (then the rest is applied at once)."""
# Smallest stage, relative to the likelihood power still to apply: bounds the
# bisection in log λ (8 halvings of the 1e-6..1 bracket pin λ to a ratio of 1.055).
MIN_STAGE_FRACTION = 1e-6
BISECTION_STEPS = 8
COUNTERS = ('measurement_initialisations', 'tempering_stages', 'moves_proposed',
            'moves_accepted')


def optimal_bandwidth(n_particles: int, dim: int, kernel: str) -> float:
    """
    Return the kernel bandwidth h that minimises the MISE for a Gaussian density.

    Gaussian kernel N(0, I): h = (4 / (N (d + 2)))^(1/(d+4)). Epanechnikov kernel on
    the unit ball: h = A N^(−1/(d+4)), A = (8 c_d⁻¹ (d + 4) (2√π)^d)^(1/(d+4)).
    """
    if kernel == 'epanechnikov':
        ball = math.pi ** (dim / 2.0) / math.gamma(dim / 2.0 + 1.0)   # c_d
        A = (8.0 / ball * (dim + 4) * (2.0 * math.sqrt(math.pi)) ** dim) ** (1.0 / (dim + 4))
        return A * n_particles ** (-1.0 / (dim + 4))
    return (4.0 / (n_particles * (dim + 2))) ** (1.0 / (dim + 4))


def kernel_draws(rng: np.random.Generator, n_particles: int, dim: int, kernel: str
                 ) -> np.ndarray:
    """Return (N, d) draws of the kernel: N(0, I), or Epanechnikov on the unit ball."""
    if kernel == 'epanechnikov':
        # Density ∝ 1 − |ε|²: uniform direction, |ε|² ~ Beta(d/2, 2).
        direction = rng.standard_normal((n_particles, dim))
        direction /= np.linalg.norm(direction, axis=1)[:, None]
        return direction * np.sqrt(rng.beta(dim / 2.0, 2.0, size=n_particles))[:, None]
    return rng.standard_normal((n_particles, dim))


def regularisation_jitter(rng: np.random.Generator, X: np.ndarray, kernel: str,
                          roughening: float = 0.2) -> Optional[np.ndarray]:
    """
    Return the jitter (N, n) of equally weighted particles X, or None if they coincide.

    ``gaussian``/``epanechnikov``: h·D·ε_i with D Dᵀ = Cov(X), h the optimal bandwidth
    for the rank d of Cov(X): the jitter's covariance is h²·Cov(X) (Gaussian kernel),
    the cloud's shape scaled. ``gordon``: N(0, σ_j²) per state, σ_j = K·E_j·N^(−1/n),
    E_j = max − min of state j (Gordon, Salmond & Smith 1993): axis-aligned, blind
    to correlations.
    """
    N, n = X.shape
    if kernel == 'gordon':
        spread = np.ptp(X, axis=0)                             # E_j
        if not np.any(spread):
            return None
        sigma = roughening * spread * N ** (-1.0 / n)          # K·E_j·N^(−1/n)
        return rng.standard_normal(X.shape) * sigma
    D = psd_factor('particle covariance', _moments(X, np.full(N, 1.0 / N))[1], n)
    if not D.shape[1]:
        return None
    h = optimal_bandwidth(N, D.shape[1], kernel)
    return h * kernel_draws(rng, N, D.shape[1], kernel) @ D.T   # h·D·ε


class GaussianLogDensity:
    """log N(x; m, P) up to a constant, through the pseudo-inverse for a singular P."""

    def __init__(self, mean: np.ndarray, cov: np.ndarray):
        """Factor P = V diag(w) Vᵀ, keeping the eigenvalues above rounding."""
        w, V = np.linalg.eigh(cov)
        keep = w > np.finfo(float).eps * max(float(np.max(np.abs(w))), 1e-300)
        self.mean = mean
        self.whiten = np.ascontiguousarray(V[:, keep] / np.sqrt(w[keep]))

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """Return −½ (x_i − m)ᵀ P⁺ (x_i − m) for the rows of X."""
        white = (X - self.mean) @ self.whiten
        return -0.5 * np.sum(white * white, axis=1)


def tempering_step(log_w: np.ndarray, log_likelihood: np.ndarray, remaining: float,
                   target_ess: float) -> float:
    """Return the largest λ in [MIN_STAGE_FRACTION·remaining, remaining] with ESS ≥ target."""
    def ess(power: float) -> float:
        a = log_w + power * log_likelihood
        a = np.exp(a - np.max(a))
        return float(np.sum(a)) ** 2 / float(np.sum(a * a))   # (Σ w)² / Σ w²
    low, high = remaining * MIN_STAGE_FRACTION, remaining
    if ess(low) < target_ess:
        return low
    for _ in range(BISECTION_STEPS):
        middle = math.sqrt(low * high)                         # bisection in log λ
        if ess(middle) >= target_ess:
            low = middle
        else:
            high = middle
    return low


def conditional_draws(rng: np.random.Generator, mean: np.ndarray, cov: np.ndarray,
                      known: Tuple[int, ...], values: np.ndarray
                      ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return states whose ``known`` components are ``values`` (N, k), the rest drawn.

    The others come from the Gaussian conditional of N(mean, cov); also returns
    log N(values_i; m_k, P_kk) up to a constant. Raises LinAlgError if P_kk is not
    positive definite.
    """
    n = mean.shape[0]
    other = [j for j in range(n) if j not in known]
    known = list(known)
    L = np.linalg.cholesky(cov[np.ix_(known, known)])          # P_kk = L Lᵀ
    offset = values - mean[known]
    white = np.linalg.solve(L, offset.T)                       # L⁻¹ (v − m_k)
    with np.errstate(over='ignore'):
        log_density = -0.5 * np.sum(white * white, axis=0)
    X = np.empty((values.shape[0], n))
    X[:, known] = values
    if other:
        gain = np.linalg.solve(L.T, np.linalg.solve(L, cov[np.ix_(known, other)])).T
        conditional = cov[np.ix_(other, other)] - gain @ cov[np.ix_(known, other)]
        G = psd_factor('conditional covariance', 0.5 * (conditional + conditional.T),
                       len(other))                             # P_oo − P_ok P_kk⁻¹ P_ko
        X[:, other] = mean[other] + offset @ gain.T            # m_o + P_ok P_kk⁻¹ (v − m_k)
        if G.shape[1]:
            X[:, other] += rng.standard_normal((values.shape[0], G.shape[1])) @ G.T
    return X, log_density


def range_bearing_positions(rng: np.random.Generator, z: np.ndarray, R: np.ndarray,
                            measurement: RangeBearing, n_particles: int
                            ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return positions (N, 2) drawn from z_i ~ N(z, R), and log |∂h/∂p|⁻¹ = log r_i.

    A draw with range r_i ≤ 0 (no position has it) gets −inf.
    """
    draws = z + rng.standard_normal((n_particles, 2)) @ np.linalg.cholesky(R).T
    bearing, distance = draws[:, 0], draws[:, 1]
    sx, sy = (float(v) for v in measurement.sensor_position_m)
    positions = np.column_stack([sx + distance * np.cos(bearing),
                                 sy + distance * np.sin(bearing)])
    with np.errstate(invalid='ignore', divide='ignore'):
        log_jacobian = np.where(distance > 0.0, np.log(np.abs(distance)), -np.inf)
    return positions, log_jacobian


class RegularisedSnapshot(NamedTuple):
    """The bootstrap snapshot's fields, whether the next update is a first, the counters."""

    particles: np.ndarray
    log_weights: np.ndarray
    rng_state: Dict
    resample_count: int
    awaiting_first_update: bool
    counters: Tuple[int, ...]


class RegularisedParticleFilter(ParticleFilter):
    """
    The regularised particle filter on a LinearModel or ExtendedModel (see module doc).

    Same interface as :class:`ParticleFilter`; ``diagnostics`` adds the counters.
    """

    def __init__(self, model, x0, P0, *, n_particles: int = 1000, seed: int = 0,
                 resample_threshold: float = DEFAULT_RESAMPLE_THRESHOLD,
                 kernel: str = 'gaussian', metropolis: bool = True, tempering: bool = True,
                 initialise_from_measurement: bool = True, roughening: float = 0.2):
        """Draw the initial particles from N(x0, P0); ``roughening`` is for 'gordon'."""
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")
        self.kernel = kernel
        self.metropolis = bool(metropolis)
        self.tempering = bool(tempering)
        self.initialise_from_measurement = bool(initialise_from_measurement)
        super().__init__(model, x0, P0, n_particles=n_particles, seed=seed,
                         resample_threshold=resample_threshold, roughening=roughening)

    # -- state ----------------------------------------------------------------

    def reset(self, x0, P0, seed: Optional[int] = None) -> None:
        """Restart from N(x0, P0); the next update is a first one again."""
        super().reset(x0, P0, seed)
        self._awaiting_first_update = True
        self._counters = dict.fromkeys(COUNTERS, 0)

    @property
    def counters(self) -> Dict[str, int]:
        """Return the counters since the last reset (see COUNTERS)."""
        return dict(self._counters)

    def snapshot(self) -> RegularisedSnapshot:
        """Return the bootstrap snapshot, the first-update flag and the counters."""
        return RegularisedSnapshot(*super().snapshot(), self._awaiting_first_update,
                                   tuple(self._counters[key] for key in COUNTERS))

    def restore(self, snapshot: RegularisedSnapshot) -> None:
        """Return to a snapshot taken from a filter of the same size."""
        if not isinstance(snapshot, RegularisedSnapshot):
            raise ValueError('snapshot must come from a RegularisedParticleFilter')
        super().restore(snapshot)
        self._awaiting_first_update = bool(snapshot.awaiting_first_update)
        self._counters = dict(zip(COUNTERS, snapshot.counters))

    # -- update ---------------------------------------------------------------

    def update(self, z, R=None) -> UpdateResult:
        """
        Correct the particles with z (first update from the measurement, then tempered).

        Returns the innovation statistics of the predicted particles, as the
        bootstrap filter does. A ValueError leaves particles, weights, generator and
        counters exactly as they were.
        """
        m = len(self.model.measurement_names)
        z = as_vector('z', z, m)
        R = as_covariance('R', self.model.R if R is None else R, m)
        try:
            inverse_factor = np.linalg.inv(np.linalg.cholesky(R)).T   # (L⁻¹)ᵀ, R = L Lᵀ
        except np.linalg.LinAlgError:
            raise ValueError(f'R must be positive definite for the likelihood, got '
                             f'{R.tolist()}') from None
        rng_state = self._rng.bit_generator.state
        counters = dict(self._counters)
        try:
            return self._update(z, R, inverse_factor)
        except ValueError:
            self._rng.bit_generator.state = rng_state
            self._counters = counters
            raise

    def _log_likelihood(self, X: np.ndarray, z: np.ndarray, inverse_factor: np.ndarray
                        ) -> Tuple[np.ndarray, np.ndarray]:
        """Return the residuals r_i = z ⊖ h(x_i) and log L_i = −½ r_iᵀ R⁻¹ r_i."""
        residual = _wrap(z - self.measurement.predict(X), self.measurement.angular)
        with np.errstate(over='ignore', invalid='ignore'):
            white = residual @ inverse_factor                  # (L⁻¹ r_i)ᵀ
            log_likelihood = -0.5 * np.sum(white * white, axis=1)
        return residual, np.where(np.isnan(log_likelihood), -np.inf, log_likelihood)

    def _update(self, z, R, inverse_factor) -> UpdateResult:
        """Do :meth:`update` on checked inputs; raise before changing anything."""
        X, log_w = self._particles, self._log_w
        residual, log_likelihood = self._log_likelihood(X, z, inverse_factor)
        with np.errstate(over='ignore', invalid='ignore'):
            result = _innovation(X, np.exp(log_w), residual, R)  # inf NIS for huge residuals
        prior_mean, prior_cov = self._estimate()
        predictive = GaussianLogDensity(prior_mean, prior_cov)
        threshold = self.resample_threshold * self.n_particles
        resamples = 0
        start = None
        if self._awaiting_first_update and self.initialise_from_measurement:
            start = self._from_measurement(z, R, prior_mean, prior_cov, log_w + log_likelihood)
        if start is not None:
            X, log_w = start
            log_likelihood = self._log_likelihood(X, z, inverse_factor)[1]
            self._counters['measurement_initialisations'] += 1
        else:
            log_normalise(log_w + log_likelihood)              # raises when none is finite
            X, log_w, log_likelihood, resamples = self._tempered(
                X, log_w, log_likelihood, z, inverse_factor, predictive, threshold)
        if _ess(log_w) < threshold:
            X, log_likelihood = self._resample(X, log_w, log_likelihood)
            X = self._move(X, log_likelihood, 1.0, z, inverse_factor, predictive)[0]
            log_w = np.full(self.n_particles, -math.log(self.n_particles))
            resamples += 1
        if not np.all(np.isfinite(X)):
            raise ValueError('update produced non-finite particles; inputs are too large')
        self._set(X, log_w)
        self.resample_count += resamples
        self._awaiting_first_update = False
        return result

    def _from_measurement(self, z, R, prior_mean, prior_cov, bootstrap_log_w
                          ) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """
        Return (particles, log-weights) drawn from the measurement, or None.

        None: the measurement has no inverse here (neither linear nor range-bearing),
        the prior is singular on the measured states, or the prior's particles
        weighted by the likelihood have the larger effective sample size.
        """
        N = self.n_particles
        H = self.measurement.H
        if H is not None:
            # Linear: the exact Kalman posterior of the Gaussian prior, drawn directly.
            x, P, _ = kalman.update(prior_mean, prior_cov, z, H, R)
            G = psd_factor('P', P, self.dim_x)
            X = np.broadcast_to(x, (N, self.dim_x)).copy()
            if G.shape[1]:
                X += self._rng.standard_normal((N, G.shape[1])) @ G.T
            return X, np.full(N, -math.log(N))
        measurement = getattr(self.model, 'measurement', None)
        if not isinstance(measurement, RangeBearing):
            return None
        positions, log_jacobian = range_bearing_positions(self._rng, z, R, measurement, N)
        known = (measurement.x_index, measurement.y_index)
        try:
            X, log_prior = conditional_draws(self._rng, prior_mean, prior_cov, known,
                                             positions)
        except np.linalg.LinAlgError:
            return None
        with np.errstate(invalid='ignore'):
            log_w = log_prior + log_jacobian                   # p⁻(p_i) / |∂h/∂p|
        log_w = np.where(np.isnan(log_w), -np.inf, log_w)
        if not np.any(np.isfinite(log_w)):
            return None
        log_w = log_normalise(log_w)[0]
        if (np.any(np.isfinite(bootstrap_log_w))
                and _ess(log_w) < _ess(log_normalise(bootstrap_log_w)[0])):
            return None
        return X, log_w

    def _tempered(self, X, log_w, log_likelihood, z, inverse_factor, predictive, threshold):
        """
        Apply the likelihood in stages; return (X, log_w, log L of X, resamplings).

        Each stage applies L^λ with the largest λ keeping ESS ≥ threshold, then
        resamples and moves (targeting L^φ·p⁻, φ the power applied so far).
        """
        remaining, applied, stages = 1.0, 0.0, 0
        while True:
            final = log_normalise(log_w + remaining * log_likelihood)[0]
            if not self.tempering or stages >= MAX_TEMPERING_STAGES or _ess(final) >= threshold:
                return X, final, log_likelihood, stages
            power = tempering_step(log_w, log_likelihood, remaining, threshold)
            log_w = log_normalise(log_w + power * log_likelihood)[0]
            remaining -= power
            applied += power
            stages += 1
            self._counters['tempering_stages'] += 1
            X, log_likelihood = self._resample(X, log_w, log_likelihood)
            log_w = np.full(self.n_particles, -math.log(self.n_particles))
            X, log_likelihood, moved = self._move(X, log_likelihood, applied, z,
                                                  inverse_factor, predictive)
            if not moved:
                # Every particle is a copy of one: no move can spread them.
                return X, log_normalise(log_w + remaining * log_likelihood)[0], \
                    log_likelihood, stages

    def _resample(self, X, log_w, log_likelihood) -> Tuple[np.ndarray, np.ndarray]:
        """Return the systematically resampled particles and their log-likelihoods."""
        index = systematic_resample(np.exp(log_w), float(self._rng.random()))
        return X[index], log_likelihood[index]

    def _move(self, X, log_likelihood, power, z, inverse_factor, predictive):
        """
        Return (X, log L, moved): each particle jittered, kept by Metropolis-Hastings.

        Target L(x)^power·N(x; m⁻, P⁻); the proposal x' = x + h D ε is symmetric, so
        α = min(1, exp(power (log L' − log L) + log p⁻(x') − log p⁻(x))).
        """
        jitter = regularisation_jitter(self._rng, X, self.kernel, self.roughening)
        if jitter is None:
            return X, log_likelihood, False
        proposed = X + jitter
        proposed_ll = self._log_likelihood(proposed, z, inverse_factor)[1]
        self._counters['moves_proposed'] += self.n_particles
        if not self.metropolis:
            self._counters['moves_accepted'] += self.n_particles
            return proposed, proposed_ll, True
        with np.errstate(invalid='ignore'):
            log_alpha = (power * (proposed_ll - log_likelihood)
                         + predictive(proposed) - predictive(X))
        accept = np.log(self._rng.random(self.n_particles)) < log_alpha   # NaN: rejected
        self._counters['moves_accepted'] += int(np.count_nonzero(accept))
        return (np.where(accept[:, None], proposed, X),
                np.where(accept, proposed_ll, log_likelihood), True)

    def __repr__(self) -> str:
        """Show the size, seed and variant."""
        return (f'RegularisedParticleFilter(n_particles={self.n_particles}, seed={self.seed}, '
                f'resample_threshold={self.resample_threshold}, kernel={self.kernel!r}, '
                f'metropolis={self.metropolis}, tempering={self.tempering}, '
                f'initialise_from_measurement={self.initialise_from_measurement})')
