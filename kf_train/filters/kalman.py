"""
Linear Kalman filter: predict, Joseph-form update, and side-effect-free look-ahead.

Notation follows the usual textbook (and filterpy): state ``x`` (n,), covariance
``P`` (n, n), transition ``F``, process noise ``Q``, control matrix ``B`` with input
``u``, measurement ``z`` (m,), measurement matrix ``H`` (m, n), measurement noise ``R``.

The module-level functions are pure; :class:`KalmanFilter` holds a state and
applies them, replacing its state only once a step has fully succeeded, so that a
rejected call leaves the filter exactly as it was.
"""

import math
from typing import NamedTuple, Optional, Tuple

from kf_train.filters.validation import as_covariance, as_matrix, as_vector
import numpy as np

# Hot-path checks (see _vector, _matrix, _covariance): an input that already is a
# finite float64 array of the right shape is used as it is, without the copy and the
# numpy reductions of the general validators, which cost more than the filter step
# itself for small states. Anything else, or anything these quick checks cannot
# vouch for, goes through kf_train.filters.validation, which accepts or rejects it with
# the usual message; so the quick checks change the speed, never the outcome.
_F64 = np.dtype(np.float64)
# Up to this many entries, checking Python floats beats numpy's per-call overhead.
_SMALL = 64
_IDENTITIES = {}
_INF = float('inf')

LOG_2PI = math.log(2.0 * math.pi)
"""log 2π, of the Gaussian log-likelihood of an innovation: −½ (NIS + log det S + m·LOG_2PI)."""


class UpdateResult(NamedTuple):
    """What a measurement update produced besides the new state."""

    innovation: np.ndarray
    """y = z - H x⁻, shape (m,)."""
    innovation_covariance: np.ndarray
    """S = H P⁻ Hᵀ + R, shape (m, m)."""
    nis: float
    """Normalised innovation squared yᵀ S⁻¹ y: χ²(m) when the model is right."""
    gain: np.ndarray
    """Kalman gain K = P⁻ Hᵀ S⁻¹, shape (n, m)."""
    gate_nis: Optional[float] = None
    """The NIS an outlier gate should test, when it is not ``nis``: a filter that learned
    a measurement noise below the one given gates with the given one (None: ``nis``)."""


def _control(B, u, dim_x: int) -> Optional[np.ndarray]:
    """Return B·u checked for shape, or None when there is no control input."""
    if B is None and u is None:
        return None
    if B is None or u is None:
        raise ValueError('B and u must be given together')
    u_vec = _vector('u', u)
    B_mat = _matrix('B', B, dim_x, u_vec.shape[0])
    return B_mat.dot(u_vec)


def _all_finite(array: np.ndarray) -> bool:
    """Return whether every entry of a float64 array is finite."""
    if array.size <= _SMALL:
        # A NaN or ±inf makes the sum NaN or ±inf, and 0·(NaN or ±inf) is NaN. A sum
        # of finite entries that overflows is re-checked entry by entry below.
        entries = array.tolist() if array.ndim == 1 else array.ravel().tolist()
        if 0.0 * sum(entries) == 0.0:
            return True
    return bool(np.isfinite(array).all())


def _vector(name: str, value, dim: Optional[int] = None) -> np.ndarray:
    """Return ``value`` as validation.as_vector would, without copying a valid array."""
    array = value
    if type(value) is float:  # a scalar measurement, as as_vector takes it
        array = np.array((value,))
    elif type(value) is not np.ndarray or value.dtype is not _F64:
        try:
            array = np.array(value, dtype=float)
        except (TypeError, ValueError):
            return as_vector(name, value, dim)
    if (array.ndim == 1 and (dim is None or array.shape[0] == dim)
            and _all_finite(array)):
        return array
    return as_vector(name, value, dim)


def _matrix(name: str, value, rows: int, cols: int) -> np.ndarray:
    """Return ``value`` as validation.as_matrix would, without copying a valid array."""
    if (type(value) is np.ndarray and value.dtype is _F64
            and value.shape == (rows, cols) and _all_finite(value)):
        return value
    return as_matrix(name, value, rows, cols)


def _covariance(name: str, value, dim: int) -> np.ndarray:
    """
    Return ``value`` as validation.as_covariance would; 1x1 and 2x2 checked in closed form.

    Accepted here without eigvalsh: a float64 [[a]] with 0 <= a < inf, or an exactly
    symmetric [[a, b], [b, d]] with a, d >= 0 and 0 <= a·d - b² < inf. That is
    positive semi-definite up to a few ulps (far inside COVARIANCE_RTOL), and any
    NaN or ±inf entry fails one of the comparisons. Everything else, including valid
    matrices on the edge of the tolerance, is left to as_covariance.
    """
    if (dim <= 2 and type(value) is np.ndarray and value.dtype is _F64
            and value.shape == (dim, dim)):
        if dim == 1:
            if 0.0 <= value[0, 0] < _INF:
                return value
        else:
            a, b, c, d = value.ravel().tolist()
            if b == c and a >= 0.0 and d >= 0.0 and 0.0 <= a * d - b * b < _INF:
                return value
    return as_covariance(name, value, dim)


def predict(x, P, F, Q, B=None, u=None) -> Tuple[np.ndarray, np.ndarray]:
    """Return the predicted mean and covariance; the inputs are not modified."""
    x = _vector('x', x)
    return _predict(x, _covariance('P', P, x.shape[0]), F, Q, B, u)


def _predict(x: np.ndarray, P: np.ndarray, F, Q, B, u) -> Tuple[np.ndarray, np.ndarray]:
    """Do :func:`predict` for an ``x`` and ``P`` that are already validated."""
    n = x.shape[0]
    F = _matrix('F', F, n, n)
    Q = _covariance('Q', Q, n)
    control = _control(B, u, n)
    # (Out-of-place arithmetic: on arrays this small numpy's in-place operators are
    # the slower ones.)
    x_prior = F.dot(x)                     # x⁻ = F x
    if control is not None:
        x_prior = x_prior + control        # x⁻ += B u
    P_prior = F.dot(P).dot(F.T) + Q        # P⁻ = F P Fᵀ + Q
    # Keep it symmetric to the last bit; (copying the transpose first is faster).
    P_prior = (P_prior + P_prior.T.copy()) * 0.5
    _check_result(x_prior, P_prior, 'prediction')
    return x_prior, P_prior


def update(x, P, z, H, R) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Return the corrected mean and covariance and the innovation statistics."""
    x = _vector('x', x)
    return _update(x, _covariance('P', P, x.shape[0]), z, H, R)


def _update(x: np.ndarray, P: np.ndarray, z, H, R
            ) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Do :func:`update` for an ``x`` and ``P`` that are already validated."""
    n = x.shape[0]
    z = _vector('z', z)
    m = z.shape[0]
    H = _matrix('H', H, m, n)
    R = _covariance('R', R, m)

    y = z - H.dot(x)                       # y = z - H x⁻
    HP = H.dot(P)
    S = HP.dot(H.T) + R                    # S = H P⁻ Hᵀ + R
    if m == 1:
        # Scalar S (symmetric as it is): K = P⁻ Hᵀ / s and NIS = y² / s, no
        # factorisation needed.
        s = float(S[0, 0])
        if s == 0.0:
            _raise_singular(S)
        K = HP.T / s
        y0 = float(y[0])
        nis = y0 * y0 / s                  # NIS = yᵀ S⁻¹ y (float ** would raise on overflow)
    else:
        S = (S + S.T) * 0.5
        try:
            # K = P⁻ Hᵀ S⁻¹, solved rather than inverted; P and S are symmetric.
            K = np.linalg.solve(S, HP).T
            nis = float(y.dot(np.linalg.solve(S, y)))  # NIS = yᵀ S⁻¹ y
        except np.linalg.LinAlgError:
            _raise_singular(S)
    x_post = x + K.dot(y)                  # x = x⁻ + K y
    I_KH = _identity(n) - K.dot(H)
    # Joseph form, P = (I - K H) P⁻ (I - K H)ᵀ + K R Kᵀ: stays symmetric and
    # positive semi-definite even when K is not exactly optimal.
    P_post = I_KH.dot(P).dot(I_KH.T) + K.dot(R).dot(K.T)
    P_post = (P_post + P_post.T.copy()) * 0.5
    _check_result(x_post, P_post, 'update')
    if not math.isfinite(nis) or nis < 0.0:
        raise ValueError(f'update produced an invalid NIS {nis}; S = {S.tolist()}')
    return x_post, P_post, UpdateResult(y, S, nis, K)


def _identity(n: int) -> np.ndarray:
    """Return a read-only n x n identity matrix, built once per n."""
    eye = _IDENTITIES.get(n)
    if eye is None:
        eye = np.eye(n)
        eye.flags.writeable = False
        _IDENTITIES[n] = eye
    return eye


def _raise_singular(S: np.ndarray) -> None:
    """Raise the error for a singular innovation covariance."""
    raise ValueError(
        f'innovation covariance S = H P Hᵀ + R is singular: {S.tolist()}') from None


def _check_result(x: np.ndarray, P: np.ndarray, step: str) -> None:
    """Raise if a step overflowed into a non-finite state."""
    if x.size + P.size <= _SMALL and 0.0 * (sum(x.tolist()) + sum(P.ravel().tolist())) == 0.0:
        return  # the quick test of _all_finite, for both at once
    if not (_all_finite(x) and _all_finite(P)):
        raise ValueError(f'{step} produced a non-finite state; inputs are too large')


class KalmanFilter:
    """
    A linear Kalman filter holding a state (x, P).

    ``predict`` and ``update`` validate every input and replace the state only when
    the whole step succeeded. ``predict_ahead`` returns a prediction and leaves the
    filter untouched.
    """

    def __init__(self, x0, P0):
        """Start from mean ``x0`` (n,) and covariance ``P0`` (n, n)."""
        x0 = as_vector('x0', x0)
        self._x = x0
        self._P = as_covariance('P0', P0, x0.shape[0])

    @property
    def dim_x(self) -> int:
        """Return the number of state variables n."""
        return self._x.shape[0]

    @property
    def x(self) -> np.ndarray:
        """Return a copy of the state mean."""
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        """Return a copy of the state covariance."""
        return self._P.copy()

    def set_state(self, x, P) -> None:
        """Replace the state with a validated (x, P) of the same dimension."""
        x = as_vector('x', x, self.dim_x)
        P = as_covariance('P', P, self.dim_x)
        self._x, self._P = x, P

    def predict(self, F, Q, B=None, u=None) -> None:
        """Propagate the state through F (and B·u) and add process noise Q."""
        # The filter's own x and P were validated when they were set or computed.
        self._x, self._P = _predict(self._x, self._P, F, Q, B, u)

    def predict_ahead(self, F, Q, B=None, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the predicted (x, P) without changing the filter."""
        return _predict(self._x, self._P, F, Q, B, u)

    def update(self, z, H, R) -> UpdateResult:
        """Correct the state with measurement z; return the innovation statistics."""
        self._x, self._P, result = _update(self._x, self._P, z, H, R)
        return result

    def copy(self) -> 'KalmanFilter':
        """Return an independent filter with the same state."""
        return KalmanFilter(self._x, self._P)
