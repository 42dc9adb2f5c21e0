"""
Extended Kalman filter: a nonlinear measurement h(x) with its analytic Jacobian.

The dynamics stay linear (``F``, ``Q``, ``B`` as in :mod:`kf_train.filters.kalman`); the
update linearises the measurement at the predicted state:

    y = z ⊖ h(x⁻)        (⊖: subtraction, angles wrapped to (−π, π])
    H = ∂h/∂x at x⁻
    S = H P⁻ Hᵀ + R,  K = P⁻ Hᵀ S⁻¹,  x = x⁻ + K y,
    P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph form)

:class:`RangeBearing` is the measurement of seed 003's example 3 (MATLAB
trackingEKF): bearing ``atan2(y, x)`` [rad] and range ``√(x² + y²)`` [m] from a
sensor. The seed writes ``atan(y/x)``, which equals atan2 wherever x > 0 (the whole
seed scenario); atan2 keeps the bearing right in every quadrant.
"""

import math
from typing import Callable, Optional, Sequence, Tuple

from kf_train.filters import kalman
from kf_train.filters.kalman import UpdateResult
from kf_train.filters.models import LinearDynamicsModel
from kf_train.filters.validation import as_covariance, as_matrix, as_vector
import numpy as np

TWO_PI = 2.0 * math.pi


def wrap_angle(angle_rad):
    """Return ``angle_rad`` wrapped to (−π, π]; values already inside are unchanged."""
    angle = np.asarray(angle_rad, dtype=float)
    # a − 2π·⌈(a − π) / 2π⌉: 0 turns for a in (−π, π], so those pass bit for bit.
    turns = np.ceil((angle - math.pi) / TWO_PI)
    return np.where(turns == 0.0, angle, angle - TWO_PI * turns)


class RangeBearing:
    """Bearing and range of a target at state components (x, y) from a fixed sensor."""

    names = ('bearing', 'range')
    angular = (True, False)
    """Which components are angles (their residuals are wrapped)."""

    def __init__(self, dim_x: int = 4, x_index: int = 0, y_index: int = 2,
                 sensor_position_m: Sequence[float] = (0.0, 0.0), min_range_m: float = 1e-6):
        """Measure state components x_index, y_index of a dim_x state from the sensor."""
        if not (isinstance(dim_x, int) and dim_x >= 2):
            raise ValueError(f'dim_x must be an integer >= 2, got {dim_x!r}')
        for name, index in (('x_index', x_index), ('y_index', y_index)):
            if not (isinstance(index, int) and 0 <= index < dim_x):
                raise ValueError(f'{name} must be an integer in [0, {dim_x}), got {index!r}')
        if x_index == y_index:
            raise ValueError('x_index and y_index must differ')
        self.dim_x, self.x_index, self.y_index = dim_x, x_index, y_index
        self.sensor_position_m = as_vector('sensor_position_m', sensor_position_m, 2)
        min_range_m = float(as_vector('min_range_m', min_range_m, 1)[0])
        if min_range_m <= 0.0:
            raise ValueError(f'min_range_m must be > 0, got {min_range_m}')
        self.min_range_m = min_range_m

    @property
    def dim_z(self) -> int:
        """Return the number of measurement components (2)."""
        return 2

    def _offset(self, x) -> Tuple[float, float]:
        """Return the target's position relative to the sensor."""
        x = as_vector('x', x, self.dim_x)
        return (float(x[self.x_index] - self.sensor_position_m[0]),
                float(x[self.y_index] - self.sensor_position_m[1]))

    def h(self, x) -> np.ndarray:
        """Return [bearing atan2(dy, dx), range √(dx² + dy²)] for state x."""
        dx, dy = self._offset(x)
        return np.array([math.atan2(dy, dx), math.hypot(dx, dy)])

    def jacobian(self, x) -> np.ndarray:
        """Return ∂h/∂x (2, dim_x); raise ValueError when x is within min_range_m."""
        dx, dy = self._offset(x)
        r2 = dx * dx + dy * dy
        r = math.sqrt(r2)
        if not r >= self.min_range_m:
            raise ValueError(
                f'range-bearing Jacobian is undefined at the sensor: the predicted target '
                f'is {r:.3g} m from it (< min_range_m = {self.min_range_m:g} m)')
        H = np.zeros((2, self.dim_x))
        H[0, self.x_index] = -dy / r2   # ∂bearing/∂x = −dy / r²
        H[0, self.y_index] = dx / r2    # ∂bearing/∂y = dx / r²
        H[1, self.x_index] = dx / r     # ∂range/∂x = dx / r
        H[1, self.y_index] = dy / r     # ∂range/∂y = dy / r
        return H

    def residual(self, z, z_predicted) -> np.ndarray:
        """Return z − h with the bearing difference wrapped to (−π, π]."""
        y = as_vector('z', z, 2) - as_vector('z_predicted', z_predicted, 2)
        y[0] = float(wrap_angle(y[0]))
        return y

    def __repr__(self) -> str:
        """Show the configuration."""
        return (f'RangeBearing(dim_x={self.dim_x}, x_index={self.x_index}, '
                f'y_index={self.y_index}, sensor_position_m={self.sensor_position_m.tolist()}, '
                f'min_range_m={self.min_range_m!r})')


class FunctionMeasurement:
    """A measurement given by functions: h(x), its Jacobian, and an optional residual."""

    def __init__(self, h: Callable, jacobian: Callable, names: Sequence[str],
                 residual: Optional[Callable] = None):
        """Store the functions; ``residual(z, h)`` defaults to z − h."""
        self._h, self._jacobian, self._residual = h, jacobian, residual
        self.names = tuple(names)

    @property
    def dim_z(self) -> int:
        """Return the number of measurement components."""
        return len(self.names)

    def h(self, x) -> np.ndarray:
        """Return the predicted measurement for state x."""
        return as_vector('h(x)', self._h(x), self.dim_z)

    def jacobian(self, x) -> np.ndarray:
        """Return ∂h/∂x."""
        x = as_vector('x', x)
        return as_matrix('jacobian(x)', self._jacobian(x), self.dim_z, x.shape[0])

    def residual(self, z, z_predicted) -> np.ndarray:
        """Return the residual z ⊖ h."""
        z = as_vector('z', z, self.dim_z)
        if self._residual is None:
            return z - as_vector('z_predicted', z_predicted, self.dim_z)
        return as_vector('residual', self._residual(z, z_predicted), self.dim_z)


def ekf_update(x, P, z, measurement, R) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Return the corrected (x, P) and the innovation statistics; inputs are unchanged."""
    x = as_vector('x', x)
    n = x.shape[0]
    P = as_covariance('P', P, n)
    m = measurement.dim_z
    z = as_vector('z', z, m)
    R = as_covariance('R', R, m)
    z_predicted = measurement.h(x)           # h(x⁻)
    H = measurement.jacobian(x)              # H = ∂h/∂x at x⁻
    y = measurement.residual(z, z_predicted)  # y = z ⊖ h(x⁻)
    return _linearised_update(x, P, y, H, R)


def _linearised_update(x, P, y, H, R) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Apply the Kalman update for residual y and measurement Jacobian H."""
    n = x.shape[0]
    S = H @ P @ H.T + R                      # S = H P⁻ Hᵀ + R
    S = 0.5 * (S + S.T)
    try:
        K = np.linalg.solve(S, H @ P).T      # K = P⁻ Hᵀ S⁻¹
        nis = float(y @ np.linalg.solve(S, y))  # NIS = yᵀ S⁻¹ y
    except np.linalg.LinAlgError:
        raise ValueError(
            f'innovation covariance S = H P Hᵀ + R is singular: {S.tolist()}') from None
    x_post = x + K @ y                       # x = x⁻ + K y
    I_KH = np.eye(n) - K @ H
    P_post = I_KH @ P @ I_KH.T + K @ R @ K.T  # Joseph form
    P_post = 0.5 * (P_post + P_post.T)
    if not (np.all(np.isfinite(x_post)) and np.all(np.isfinite(P_post))
            and math.isfinite(nis) and nis >= 0.0):
        raise ValueError('update produced a non-finite state; inputs are too large')
    return x_post, P_post, UpdateResult(y, S, nis, K)


class ExtendedModel(LinearDynamicsModel):
    """
    Linear dynamics with a nonlinear measurement: the EKF counterpart of LinearModel.

    Same interface as :class:`kf_train.filters.models.LinearModel`: ``predict(x, P, dt_s,
    u=None)`` and ``update(x, P, z, R=None)``, and the state, measurement and control
    names.
    """

    def __init__(self, F, Q, measurement, R, *, B=None, state_names=('x', 'vx', 'y', 'vy'),
                 control_names=()):
        """Store the model; R is checked against the measurement's dimension."""
        super().__init__(F, Q, R, B=B, state_names=state_names,
                         measurement_names=measurement.names, control_names=control_names)
        self.measurement = measurement

    def update(self, x, P, z, R=None):
        """Return (x, P, UpdateResult) after measurement z; R defaults to the model's."""
        return ekf_update(x, P, z, self.measurement, self.R if R is None else R)


class ExtendedKalmanFilter:
    """An EKF holding (x, P); a rejected step leaves the state unchanged."""

    def __init__(self, x0, P0):
        """Start from mean ``x0`` (n,) and covariance ``P0`` (n, n)."""
        x0 = as_vector('x0', x0)
        self._x = x0
        self._P = as_covariance('P0', P0, x0.shape[0])

    @property
    def x(self) -> np.ndarray:
        """Return a copy of the state mean."""
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        """Return a copy of the state covariance."""
        return self._P.copy()

    def predict(self, F, Q, B=None, u=None) -> None:
        """Propagate the state through the linear dynamics."""
        self._x, self._P = kalman.predict(self._x, self._P, F, Q, B, u)

    def update(self, z, measurement, R) -> UpdateResult:
        """Correct the state with measurement z of the given measurement model."""
        self._x, self._P, result = ekf_update(self._x, self._P, z, measurement, R)
        return result
