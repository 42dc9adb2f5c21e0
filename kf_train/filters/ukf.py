"""
Unscented Kalman filter: Merwe scaled sigma points, angle-aware, never crashing on P.

The unscented transform (Wan & van der Merwe) carries a mean x and covariance P
through a function by 2n + 1 sigma points

    χ_0 = x,   χ_i = x + √c·L_i,   χ_{n+i} = x − √c·L_i   (L Lᵀ = P, L_i its columns)
    λ = α²(n + κ) − n,   c = n + λ = α²(n + κ)
    Wm_0 = λ / c,   Wc_0 = λ / c + 1 − α² + β,   Wm_i = Wc_i = 1 / (2c)

and the weighted mean and covariance of the transformed points. Everything here is
computed in *deviation form*, relative to the transformed centre point
Y_0 = f(χ_0): with d_i = Y_i ⊖ Y_0 (i ≥ 1; angles wrapped) and δ the mean offset,

    mean = Y_0 ⊕ δ,      δ = Σ_{i≥1} Wm_i d_i  (angles: the circular mean, below)
    cov  = Σ_{i≥1} Wc_i d_i d_iᵀ − δ_l δ_lᵀ + ε εᵀ + (1 − α² + β) δ δᵀ

where δ_l = Σ_{i≥1} Wm_i d_i and ε = δ_l − δ (zero for non-angular components).
That is Σ_i Wc_i (Y_i ⊖ mean)(Y_i ⊖ mean)ᵀ exactly (the weights Wm sum to 1), but
without the terms Wm_0·Y_0 and Wc_0·(Y_0 − mean)² that cancel catastrophically
for small α (Wm_0 ≈ −10⁶ at MATLAB's default α = 1e-3): the UKF stays accurate
for any α > 0.

Angles (the bearing): the weighted circular mean atan2(Σ Wm sin θ, Σ Wm cos θ),
written relative to θ_0 so that the large weights cancel analytically,

    δ_θ = atan2(Σ_{i≥1} Wm_i sin d_i, 1 − Σ_{i≥1} 2 Wm_i sin²(d_i / 2)),

and every residual is wrapped to (−π, π].

Where the model is linear (the preset dynamics x⁻ = F x + B u, a linear H), the
transformed deviations are computed as F·(√c L_i) directly: the same numbers the
transform of χ_i gives in exact arithmetic, without the rounding of x + √c L_i.

The covariance is kept positive definite: before sigma points are drawn, and after
every predict and update, P is symmetrised and Cholesky-factorised; if that fails,
a jitter ε·s·I (s the largest |diagonal|, ε = 2.2e-16) is added and grown tenfold
until it succeeds, and if even a jitter of s fails, the eigenvalues are clipped.
No covariance that passed validation makes the filter raise (filterpy's UKF raises
LinAlgError instead: rlabbe/filterpy issues #62, #218).
"""

import math
from typing import Callable, NamedTuple, Optional, Sequence, Tuple

from kf_train.filters.contract import PredictThenUpdate
from kf_train.filters.ekf import wrap_angle
from kf_train.filters.kalman import UpdateResult
from kf_train.filters.validation import as_covariance, as_finite_array, as_vector
import numpy as np

# Sigma points at ±√(n)·σ (β = 2 is optimal for Gaussian priors). MATLAB trackingUKF
# defaults to α = 1e-3, whose points sit 0.002σ from the mean and see only the local
# slope: on the range-bearing seed that UKF is as overconfident as the EKF while
# α = 1 is consistent (docs/filters.md has the measurements).
DEFAULT_ALPHA = 1.0
DEFAULT_BETA = 2.0
DEFAULT_KAPPA = 0.0
_EPS = float(np.finfo(float).eps)
# Scale used for the jitter of an all-zero covariance: its square (1e-308) is still
# a normal double, so sigma points built from it do not underflow.
_FLOOR_SCALE = math.sqrt(float(np.finfo(float).tiny))


# ---------------------------------------------------------------------------
# Positive-definite square roots
# ---------------------------------------------------------------------------

class SquareRoot(NamedTuple):
    """A factor L of a (regularised) covariance: L Lᵀ = P + jitter·I."""

    L: np.ndarray
    """(n, n) factor; lower triangular unless the eigenvalue fallback was used."""
    P: np.ndarray
    """The matrix actually factorised: P symmetrised, plus the jitter."""
    jitter: float
    """What was added to the diagonal (0.0 when P factorised as it was)."""
    method: str
    """'cholesky', 'jitter' or 'eigen'."""


def robust_cholesky(P) -> SquareRoot:
    """
    Return a factor of P that always exists: Cholesky, else with growing jitter.

    P is symmetrised first. When the factorisation fails, ε·s·I is added (s the
    largest |diagonal|, or 1.5e-154 for an all-zero P) and multiplied by ten until it
    succeeds; beyond a jitter of s the eigenvalues are clipped to ε·s instead.
    """
    P = as_finite_array('P', P)
    if P.ndim != 2 or P.shape[0] != P.shape[1]:
        raise ValueError(f'P must be a square matrix, got shape {P.shape}')
    P = 0.5 * (P + P.T)
    try:
        return SquareRoot(np.linalg.cholesky(P), P, 0.0, 'cholesky')
    except np.linalg.LinAlgError:
        pass
    n = P.shape[0]
    scale = float(np.max(np.abs(np.diag(P)))) if n else 0.0
    scale = max(scale, _FLOOR_SCALE)
    jitter = _EPS * scale
    eye = np.eye(n)
    while jitter <= scale:
        regularised = P + jitter * eye
        try:
            return SquareRoot(np.linalg.cholesky(regularised), regularised, jitter, 'jitter')
        except np.linalg.LinAlgError:
            jitter *= 10.0
    # Far from positive definite (a large negative eigenvalue): clip the spectrum.
    try:
        w, V = np.linalg.eigh(P)
    except np.linalg.LinAlgError:  # pragma: no cover - eigh converges for finite input
        w, V = np.maximum(np.diag(P), 0.0), eye
    floor = _EPS * scale
    clipped = np.maximum(w, floor)
    L = V * np.sqrt(clipped)
    regularised = (V * clipped) @ V.T
    regularised = 0.5 * (regularised + regularised.T)
    return SquareRoot(L, regularised, float(np.max(clipped - w)), 'eigen')


def keep_positive_definite(P) -> Tuple[np.ndarray, float]:
    """Return (P symmetrised and, if needed, regularised to factorise; jitter added)."""
    root = robust_cholesky(P)
    return root.P, root.jitter


# ---------------------------------------------------------------------------
# Sigma points and the unscented transform
# ---------------------------------------------------------------------------

def _finite_number(name: str, value) -> float:
    """Return a finite scalar."""
    array = as_finite_array(name, value)
    if array.ndim != 0 or isinstance(value, bool):
        raise ValueError(f'{name} must be a number, got {value!r}')
    return float(array)


class MerweScaledSigmaPoints:
    """Van der Merwe's scaled sigma points for an n-dimensional state."""

    def __init__(self, n: int, alpha: float = DEFAULT_ALPHA, beta: float = DEFAULT_BETA,
                 kappa: float = DEFAULT_KAPPA):
        """Check the parameters: alpha > 0, any finite beta, n + kappa > 0."""
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f'n must be a positive integer, got {n!r}')
        alpha = _finite_number('alpha', alpha)
        beta = _finite_number('beta', beta)
        kappa = _finite_number('kappa', kappa)
        if alpha <= 0.0:
            raise ValueError(f'alpha must be > 0, got {alpha!r}')
        if n + kappa <= 0.0:
            raise ValueError(f'kappa must be > -n = {-n} (so that n + kappa > 0), '
                             f'got {kappa!r}')
        c = alpha * alpha * (n + kappa)            # c = n + λ = α²(n + κ)
        if not (math.isfinite(c) and c > 0.0 and math.isfinite(1.0 / c)):
            raise ValueError(f'alpha² (n + kappa) = {c!r} must be a positive, invertible '
                             'number')
        self.n, self.alpha, self.beta, self.kappa = int(n), alpha, beta, kappa
        self.c = c
        self.lam = c - n                           # λ = α²(n + κ) − n
        self.sqrt_c = math.sqrt(c)
        self.Wm = np.full(2 * n + 1, 0.5 / c)      # Wm_i = 1 / (2c)
        self.Wm[0] = self.lam / c                  # Wm_0 = λ / c
        self.Wc = self.Wm.copy()
        self.Wc[0] += 1.0 - alpha * alpha + beta   # Wc_0 = λ / c + 1 − α² + β
        self.w = 0.5 / c                           # every Wm_i = Wc_i, i ≥ 1

    @property
    def num_sigmas(self) -> int:
        """Return 2n + 1."""
        return 2 * self.n + 1

    def deviations(self, L: np.ndarray) -> np.ndarray:
        """Return the sigma-point offsets s_i (2n, n): +√c L_i, then −√c L_i."""
        S = self.sqrt_c * L.T                      # row i: √c L_i
        return np.concatenate([S, -S])

    def sigma_points(self, x, P) -> np.ndarray:
        """Return the 2n + 1 sigma points (rows) of (x, P), P factorised robustly."""
        x = as_vector('x', x, self.n)
        root = robust_cholesky(as_covariance('P', P, self.n))
        return np.vstack([x, x + self.deviations(root.L)])

    def __repr__(self) -> str:
        """Show the parameters."""
        return (f'MerweScaledSigmaPoints(n={self.n}, alpha={self.alpha!r}, '
                f'beta={self.beta!r}, kappa={self.kappa!r})')


class Transformed(NamedTuple):
    """The unscented transform of a set of sigma points."""

    mean: np.ndarray
    """Weighted mean (m,), circular for angular components (wrapped)."""
    covariance: np.ndarray
    """Weighted covariance (m, m) of the residuals, noise not included."""
    offset: np.ndarray
    """δ: mean ⊖ Y_0 (m,)."""


def unscented_moments(points: MerweScaledSigmaPoints, centre, d,
                      angular: Optional[Sequence[bool]] = None) -> Transformed:
    """
    Return the mean and covariance of transformed sigma points given as deviations.

    ``centre`` is Y_0 (m,), the transform of the centre point; ``d`` (2n, m) holds
    Y_i ⊖ Y_0 for i = 1..2n, angular components already wrapped.
    """
    centre = np.asarray(centre, dtype=float)
    d = np.asarray(d, dtype=float)
    w = points.w
    linear_offset = w * d.sum(axis=0)              # δ_l = Σ_{i≥1} Wm_i d_i
    offset = linear_offset.copy()
    mean = centre + offset                         # Y_0 ⊕ δ
    if angular is not None and any(angular):
        for j in np.flatnonzero(np.asarray(angular, dtype=bool)):
            # circular mean relative to θ_0: atan2(Σ Wm sin d, 1 − Σ 2 Wm sin²(d/2))
            sine = w * float(np.sum(np.sin(d[:, j])))
            cosine = 1.0 - 2.0 * w * float(np.sum(np.sin(0.5 * d[:, j]) ** 2))
            offset[j] = math.atan2(sine, cosine)
            mean[j] = float(wrap_angle(centre[j] + offset[j]))
    excess = linear_offset - offset                # ε = δ_l − δ
    # Σ_i Wc_i (Y_i ⊖ mean)(Y_i ⊖ mean)ᵀ in deviation form:
    # Σ_{i≥1} W d dᵀ − δ_l δ_lᵀ + ε εᵀ + (1 − α² + β) δ δᵀ
    cov = (w * (d.T @ d) - np.outer(linear_offset, linear_offset)
           + np.outer(excess, excess)
           + (1.0 - points.alpha ** 2 + points.beta) * np.outer(offset, offset))
    return Transformed(mean, 0.5 * (cov + cov.T), offset)


def _wrap_columns(d: np.ndarray, angular) -> np.ndarray:
    """Wrap the angular columns of d in place and return it."""
    if angular is not None:
        for j in np.flatnonzero(np.asarray(angular, dtype=bool)):
            d[:, j] = wrap_angle(d[:, j])
    return d


# ---------------------------------------------------------------------------
# Predict and update on (x, P)
# ---------------------------------------------------------------------------

def unscented_predict(x, P, points: MerweScaledSigmaPoints, Q, *,
                      fx: Optional[Callable] = None, F=None, offset=None
                      ) -> Tuple[np.ndarray, np.ndarray, float]:
    """
    Return (x⁻, P⁻, jitter) through the unscented transform, then + Q.

    Either ``fx`` (maps sigma points (k, n) to (k, n)) or a linear ``F`` (and an
    additive ``offset`` such as B u): for a linear map the deviations are F s_i,
    exact. ``jitter`` reports what keeping P (or P⁻) positive definite added.
    """
    x = as_vector('x', x, points.n)
    n = points.n
    P = as_covariance('P', P, n)
    Q = as_covariance('Q', Q, n)
    if (fx is None) == (F is None):
        raise ValueError('give either fx or F')
    root = robust_cholesky(P)
    s = points.deviations(root.L)                  # χ_i − x, i ≥ 1
    if fx is None:
        F = np.asarray(F, dtype=float)
        centre = F @ x                             # f(χ_0) = F x (+ B u)
        if offset is not None:
            centre = centre + offset
        d = s @ F.T                                # f(χ_i) − f(χ_0) = F s_i
    else:
        Y = np.asarray(fx(np.vstack([x, x + s])), dtype=float)
        if Y.shape != (2 * n + 1, n):
            raise ValueError(f'fx must return shape ({2 * n + 1}, {n}), got {Y.shape}')
        centre, d = Y[0], Y[1:] - Y[0]
    moments = unscented_moments(points, centre, d)
    P_prior, jitter = keep_positive_definite(moments.covariance + Q)  # P⁻ = UT + Q
    _check_finite(moments.mean, P_prior, 'prediction')
    return moments.mean, P_prior, max(root.jitter, jitter)


def unscented_update(x, P, z, points: MerweScaledSigmaPoints, R, *,
                     hx: Optional[Callable] = None, H=None,
                     angular: Optional[Sequence[bool]] = None
                     ) -> Tuple[np.ndarray, np.ndarray, UpdateResult, float]:
    """
    Return (x, P, UpdateResult, jitter) after measurement z.

    Either ``hx`` (maps sigma points (k, n) to predicted measurements (k, m)) or a
    linear ``H``; ``angular`` flags the measurement components that are angles:

        ẑ = mean of h(χ_i),  S = P_zz + R,  P_xz = Σ Wc_i (χ_i − x⁻)(h(χ_i) ⊖ ẑ)ᵀ,
        K = P_xz S⁻¹,  y = z ⊖ ẑ,  x = x⁻ + K y,  P = P⁻ − K S Kᵀ

    (with a linear H, P in Joseph form, as the KF: accurate even for a tiny R).
    """
    x = as_vector('x', x, points.n)
    n = points.n
    P = as_covariance('P', P, n)
    z = as_vector('z', z)
    m = z.shape[0]
    R = as_covariance('R', R, m)
    if (hx is None) == (H is None):
        raise ValueError('give either hx or H')
    root = robust_cholesky(P)
    s = points.deviations(root.L)                  # χ_i − x⁻, i ≥ 1
    if hx is None:
        H = np.asarray(H, dtype=float)
        centre = H @ x                             # h(χ_0)
        d = s @ H.T                                # h(χ_i) − h(χ_0) = H s_i
    else:
        Z = np.asarray(hx(np.vstack([x, x + s])), dtype=float)
        if Z.shape != (2 * n + 1, m):
            raise ValueError(f'hx must return shape ({2 * n + 1}, {m}), got {Z.shape}')
        centre = Z[0]
        d = _wrap_columns(Z[1:] - Z[0], angular)   # h(χ_i) ⊖ h(χ_0)
    moments = unscented_moments(points, centre, d, angular)
    S = moments.covariance + R                     # S = P_zz + R
    S = 0.5 * (S + S.T)
    # P_xz = Σ_{i≥1} Wc_i s_i (d_i − δ)ᵀ: the state points are symmetric about x⁻
    # (Σ Wm s = 0), so the centre term vanishes and δ drops out of the sum.
    Pxz = points.w * (s.T @ d)
    y = _wrap_columns((z - moments.mean)[None, :], angular)[0]  # y = z ⊖ ẑ
    try:
        K = np.linalg.solve(S, Pxz.T).T            # K = P_xz S⁻¹
        nis = float(y @ np.linalg.solve(S, y))     # NIS = yᵀ S⁻¹ y
    except np.linalg.LinAlgError:
        raise ValueError(f'innovation covariance S = P_zz + R is singular: {S.tolist()}'
                         ) from None
    x_post = x + K @ y                             # x = x⁻ + K y
    if hx is None:
        # A linear measurement: the transform is exact, and the Joseph form
        # (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ keeps P accurate even when R is tiny.
        I_KH = np.eye(n) - K @ H
        P_post = I_KH @ root.P @ I_KH.T + K @ R @ K.T
    else:
        P_post = root.P - K @ S @ K.T              # P = P⁻ − K S Kᵀ
    P_post, jitter = keep_positive_definite(P_post)
    _check_finite(x_post, P_post, 'update')
    if not (math.isfinite(nis) and nis >= 0.0):
        raise ValueError(f'update produced an invalid NIS {nis}; S = {S.tolist()}')
    return x_post, P_post, UpdateResult(y, S, nis, K), max(root.jitter, jitter)


def _check_finite(x: np.ndarray, P: np.ndarray, step: str) -> None:
    """Raise if a step overflowed."""
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        raise ValueError(f'{step} produced a non-finite state; inputs are too large')


# ---------------------------------------------------------------------------
# Measurement models as functions of many states at once
# ---------------------------------------------------------------------------

class BatchMeasurement(NamedTuple):
    """A measurement model evaluated on many states: what the UKF and PF need."""

    h: Optional[Callable]
    """Maps states (k, n) to measurements (k, m); None for a linear model (use H)."""
    H: Optional[np.ndarray]
    """The measurement matrix of a linear model, else None."""
    angular: Tuple[bool, ...]
    """Which measurement components are angles (residuals wrapped, circular mean)."""

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Return the predicted measurements (k, m) of states X (k, n)."""
        return X @ np.ascontiguousarray(self.H.T) if self.h is None else self.h(X)


def batch_measurement(model) -> BatchMeasurement:
    """
    Return the measurement of a LinearModel or ExtendedModel in batch form.

    A linear model gives its H; the range-bearing measurement is vectorised; any other
    measurement object (``h(x)``, ``names``, optional ``angular``) is evaluated row
    by row.
    """
    H = getattr(model, 'H', None)
    if H is not None:
        return BatchMeasurement(None, np.asarray(H, dtype=float),
                                (False,) * np.asarray(H).shape[0])
    measurement = model.measurement
    m = measurement.dim_z
    angular = tuple(bool(a) for a in getattr(measurement, 'angular', (False,) * m))
    if all(hasattr(measurement, key) for key in ('x_index', 'y_index', 'sensor_position_m')):
        xi, yi = measurement.x_index, measurement.y_index
        sx, sy = (float(v) for v in measurement.sensor_position_m)

        def range_bearing(X: np.ndarray) -> np.ndarray:
            dx, dy = X[:, xi] - sx, X[:, yi] - sy
            return np.column_stack([np.arctan2(dy, dx), np.hypot(dx, dy)])
        return BatchMeasurement(range_bearing, None, angular)

    def rows(X: np.ndarray) -> np.ndarray:
        return np.array([measurement.h(row) for row in X], dtype=float).reshape(-1, m)
    return BatchMeasurement(rows, None, angular)


# ---------------------------------------------------------------------------
# The preset adapter: the same interface as LinearModel and ExtendedModel
# ---------------------------------------------------------------------------

class UnscentedModel(PredictThenUpdate):
    """
    A preset's model run as a UKF: a :class:`~kf_train.filters.contract.StepModel`.

    Built from a LinearModel or ExtendedModel (:meth:`from_model`); the dynamics are
    the model's F(dt), Q(dt), B(dt) (linear, so the transform is exact there), the
    measurement goes through sigma points. ``regularisations`` counts the steps where
    P had to be regularised to stay positive definite.
    """

    def __init__(self, F, Q, measurement: BatchMeasurement, R, *, B=None,
                 state_names: Sequence[str], measurement_names: Sequence[str],
                 control_names: Sequence[str] = (), alpha: float = DEFAULT_ALPHA,
                 beta: float = DEFAULT_BETA, kappa: float = DEFAULT_KAPPA):
        """Store the model and build the sigma points for its state dimension."""
        self.F, self.Q, self.B = F, Q, B
        self.measurement = measurement
        self.state_names = tuple(state_names)
        self.measurement_names = tuple(measurement_names)
        self.control_names = tuple(control_names)
        self.R = as_covariance('R', R, len(self.measurement_names))
        if (B is None) != (not self.control_names):
            raise ValueError('B must be given exactly when control_names are')
        self.points = MerweScaledSigmaPoints(len(self.state_names), alpha, beta, kappa)
        self.regularisations = 0

    @classmethod
    def from_model(cls, model, *, alpha: float = DEFAULT_ALPHA, beta: float = DEFAULT_BETA,
                   kappa: float = DEFAULT_KAPPA) -> 'UnscentedModel':
        """Return the UKF of a LinearModel or ExtendedModel."""
        return cls(model.F, model.Q, batch_measurement(model), model.R, B=model.B,
                   state_names=model.state_names, measurement_names=model.measurement_names,
                   control_names=model.control_names, alpha=alpha, beta=beta, kappa=kappa)

    @property
    def dim_x(self) -> int:
        """Return the number of state components."""
        return len(self.state_names)

    @property
    def dim_z(self) -> int:
        """Return the number of measurement components."""
        return len(self.measurement_names)

    def predict(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return (x⁻, P⁻) predicted over dt_s with control u (required iff B is set)."""
        offset = None
        if self.B is None:
            if u is not None:
                raise ValueError('u given to a model without control input')
        else:
            if u is None:
                raise ValueError(f'u ({", ".join(self.control_names)}) is required')
            u = as_vector('u', u, len(self.control_names))
            offset = np.asarray(self.B(dt_s), dtype=float) @ u   # B u
        x, P, jitter = unscented_predict(x, P, self.points, self.Q(dt_s), F=self.F(dt_s),
                                         offset=offset)
        self.regularisations += jitter > 0.0
        return x, P

    def update(self, x, P, z, R=None) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
        """Return (x, P, UpdateResult) after measurement z; R defaults to the model's."""
        R = self.R if R is None else R
        z = as_vector('z', z, self.dim_z)
        x, P, result, jitter = unscented_update(
            x, P, z, self.points, R, hx=self.measurement.h, H=self.measurement.H,
            angular=self.measurement.angular)
        self.regularisations += jitter > 0.0
        return x, P, result

    def __repr__(self) -> str:
        """Show the sigma-point parameters."""
        return f'UnscentedModel({self.state_names}, {self.points!r})'
