"""
Linear Kalman filter: predict, Joseph-form update, and side-effect-free look-ahead.

Notation follows the usual textbook (and filterpy): state ``x`` (n,), covariance
``P`` (n, n), transition ``F``, process noise ``Q``, control matrix ``B`` with input
``u``, measurement ``z`` (m,), measurement matrix ``H`` (m, n), measurement noise ``R``.

The module-level functions are pure; :class:`KalmanFilter` holds a state and
applies them, replacing its state only once a step has fully succeeded, so that a
rejected call leaves the filter exactly as it was.
"""

from typing import NamedTuple, Optional, Tuple

from kf_train.core.validation import as_covariance, as_matrix, as_vector
import numpy as np


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


def _control(B, u, dim_x: int) -> Optional[np.ndarray]:
    """Return B·u checked for shape, or None when there is no control input."""
    if B is None and u is None:
        return None
    if B is None or u is None:
        raise ValueError('B and u must be given together')
    u_vec = as_vector('u', u)
    B_mat = as_matrix('B', B, dim_x, u_vec.shape[0])
    return B_mat @ u_vec


def predict(x, P, F, Q, B=None, u=None) -> Tuple[np.ndarray, np.ndarray]:
    """Return the predicted mean and covariance; the inputs are not modified."""
    x = as_vector('x', x)
    n = x.shape[0]
    P = as_covariance('P', P, n)
    F = as_matrix('F', F, n, n)
    Q = as_covariance('Q', Q, n)
    control = _control(B, u, n)
    x_prior = F @ x                        # x⁻ = F x
    if control is not None:
        x_prior = x_prior + control        # x⁻ += B u
    P_prior = F @ P @ F.T + Q              # P⁻ = F P Fᵀ + Q
    P_prior = 0.5 * (P_prior + P_prior.T)  # keep it symmetric to the last bit
    _check_result(x_prior, P_prior, 'prediction')
    return x_prior, P_prior


def update(x, P, z, H, R) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Return the corrected mean and covariance and the innovation statistics."""
    x = as_vector('x', x)
    n = x.shape[0]
    P = as_covariance('P', P, n)
    z = as_vector('z', z)
    m = z.shape[0]
    H = as_matrix('H', H, m, n)
    R = as_covariance('R', R, m)

    y = z - H @ x                          # y = z - H x⁻
    S = H @ P @ H.T + R                    # S = H P⁻ Hᵀ + R
    S = 0.5 * (S + S.T)
    try:
        # K = P⁻ Hᵀ S⁻¹, solved rather than inverted; P and S are symmetric.
        K = np.linalg.solve(S, H @ P).T
        nis = float(y @ np.linalg.solve(S, y))  # NIS = yᵀ S⁻¹ y
    except np.linalg.LinAlgError:
        raise ValueError(
            f'innovation covariance S = H P Hᵀ + R is singular: {S.tolist()}') from None
    x_post = x + K @ y                     # x = x⁻ + K y
    I_KH = np.eye(n) - K @ H
    # Joseph form, P = (I - K H) P⁻ (I - K H)ᵀ + K R Kᵀ: stays symmetric and
    # positive semi-definite even when K is not exactly optimal.
    P_post = I_KH @ P @ I_KH.T + K @ R @ K.T
    P_post = 0.5 * (P_post + P_post.T)
    _check_result(x_post, P_post, 'update')
    if not np.isfinite(nis) or nis < 0.0:
        raise ValueError(f'update produced an invalid NIS {nis}; S = {S.tolist()}')
    return x_post, P_post, UpdateResult(y, S, nis, K)


def _check_result(x: np.ndarray, P: np.ndarray, step: str) -> None:
    """Raise if a step overflowed into a non-finite state."""
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
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
        self._x, self._P = predict(self._x, self._P, F, Q, B, u)

    def predict_ahead(self, F, Q, B=None, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the predicted (x, P) without changing the filter."""
        return predict(self._x, self._P, F, Q, B, u)

    def update(self, z, H, R) -> UpdateResult:
        """Correct the state with measurement z; return the innovation statistics."""
        self._x, self._P, result = update(self._x, self._P, z, H, R)
        return result

    def copy(self) -> 'KalmanFilter':
        """Return an independent filter with the same state."""
        return KalmanFilter(self._x, self._P)
