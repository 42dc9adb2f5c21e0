"""
Motion models for a 1-D constant-velocity state [position m, velocity m/s].

Two ways to give the process noise, both producing Q(dt) for any dt >= 0:

* :class:`WhiteNoiseAcceleration` — a continuous white-noise acceleration of
  spectral density ``q`` [m²/s³]. Integrated exactly over dt:
  ``Q(dt) = q · [[dt³/3, dt²/2], [dt²/2, dt]]``.
* :class:`PerStepNoise` — a fixed matrix added once per nominal step, as the
  seed tutorials write it (``P = F P Fᵀ + Q``). For dt equal to the nominal period
  this is exactly that matrix. A dt spanning several periods accumulates it as that
  many steps would (each step's noise carried forward through the rest of the
  interval), and a fraction of a period adds that fraction, so that a 2-s prediction
  is as uncertain as 20 seed steps and dt = 0 adds nothing.
"""

import math
from typing import Tuple, Union

from kf_train.filters import kalman
from kf_train.filters.contract import PredictThenUpdate
from kf_train.filters.validation import as_covariance, as_duration, as_matrix
import numpy as np


def constant_velocity_F(dt: float) -> np.ndarray:
    """Return the transition matrix F(dt) = [[1, dt], [0, 1]]."""
    dt = as_duration('dt', dt)
    return np.array([[1.0, dt], [0.0, 1.0]])


def _finite_noise(Q: np.ndarray, dt: float) -> np.ndarray:
    """Return Q, or raise ValueError naming dt when Q overflowed."""
    if not np.all(np.isfinite(Q)):
        raise ValueError(f'dt = {dt} s is too large: the process noise overflows')
    return Q


def white_noise_integrals(dt):
    """
    Return (dt³/3, dt²/2, dt), the integrals of s², s and 1 over [0, dt].

    They weigh a continuous white noise carried through F(s) = I + s·A (A² = 0):
    ∫₀^dt F(s) Qc F(s)ᵀ ds = dt·Qc + dt²/2·(A Qc + Qc Aᵀ) + dt³/3·A Qc Aᵀ. For the
    train's A and Qc = diag(0, q) that is Q(dt) = q·[[dt³/3, dt²/2], [dt²/2, dt]].
    ``dt`` is a float or an array (then elementwise, with the same operations).
    """
    return dt ** 3 / 3.0, dt ** 2 / 2.0, dt


def white_noise_terms(q: float, dt: float) -> Tuple[float, float, float]:
    """
    Return (Q00, Q01, Q11) of Q(dt) = q·[[dt³/3, dt²/2], [dt²/2, dt]]: THE white-noise Q(dt).

    Every path that needs a white-noise acceleration's Q(dt) gets it here (the presets'
    vectorised form from :func:`white_noise_integrals`).
    A float dt so large that dt³ overflows raises OverflowError (float powers do).
    """
    third, half, one = white_noise_integrals(dt)
    return q * third, q * half, q * one


class WhiteNoiseAcceleration:
    """Process noise from a white-noise acceleration of density q [m²/s³]."""

    def __init__(self, q: float):
        """Store the density q >= 0."""
        self.q = as_duration('q', q)

    def __call__(self, dt: float) -> np.ndarray:
        """Return Q(dt) = q · [[dt³/3, dt²/2], [dt²/2, dt]]."""
        dt = as_duration('dt', dt)
        try:
            q00, q01, q11 = white_noise_terms(self.q, dt)
        except OverflowError:  # Python float powers raise where numpy would give inf
            Q = np.full((2, 2), np.inf)
        else:
            Q = np.array([[q00, q01], [q01, q11]])
        with np.errstate(invalid='ignore'):
            return _finite_noise(Q, dt)

    def __repr__(self) -> str:
        """Show the density."""
        return f'WhiteNoiseAcceleration(q={self.q!r})'


def per_step_noise_terms(a: float, c: float, b: float, period_s: float,
                         dt: float) -> Tuple[float, float, float]:
    """
    Return (Q00, Q01, Q11) of a per-step matrix [[a, c], [c, b]] accumulated over dt.

    Full steps i = 1..n end at i·T; their noise is carried through the rest,
    s = dt - i·T = r + j·T (j = n - i = 0..n-1), by F(s). The remainder r ends at dt
    (s = 0) with weight r/T. With Q_step = [[a, c], [c, b]]:
      F(s) Q_step F(s)ᵀ = [[a + 2cs + bs², c + bs], [c + bs, b]],
    so Q(dt) needs only the weighted sums S0 = Σw, S1 = Σws, S2 = Σws². Written in r
    and j, every term is >= 0 (no cancellation), and dt = T (n = 1, r = 0) gives
    S1 = S2 = 0 exactly, hence Q(T) == Q_step bit for bit. Plain floats, so the
    closed-form fast path (kf_train.filters.fast) shares it.
    """
    T = period_s
    n = math.floor(dt / T)
    r = dt - n * T
    if r < 0.0:  # rounding when dt is a whole number of periods
        n, r = n - 1, r + T
    s0 = n + r / T
    s1 = n * r + T * n * (n - 1) / 2.0
    # r * r, not r ** 2: a product is correctly rounded on every machine, libm's pow is
    # not (glibc misrounds ~1 square in 1000, differently with and without FMA), and
    # the vectorised form (presets) squares with numpy, which is exact too.
    s2 = n * (r * r) + r * T * n * (n - 1) + T ** 2 * (n - 1) * n * (2 * n - 1) / 6.0
    return a * s0 + 2.0 * c * s1 + b * s2, c * s0 + b * s1, b * s0


def per_step_periods(dt, period_s: float) -> Tuple[np.ndarray, np.ndarray]:
    """Return (n, r) for an array dt = n·T + r: whole periods T and the remainder 0 <= r <= T."""
    dt = np.asarray(dt, dtype=float)
    T = float(period_s)
    n = np.floor(dt / T)
    r = dt - n * T
    low = r < 0.0  # rounding when dt is a whole number of periods
    return np.where(low, n - 1.0, n), np.where(low, r + T, r)


def per_step_weights(dt, period_s: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return the sums S0 = Σw, S1 = Σw·s, S2 = Σw·s² of per-step noise for an array dt.

    :func:`per_step_noise_terms` for arrays, with the same operations: a dt of n whole
    periods T plus a remainder r collects the noise of n full steps, the step ending at
    i·T carried to dt over s = dt - i·T = r + j·T (j = 0..n-1, weight 1), and a
    fraction r/T of a step at s = 0. Written in r and j every term is >= 0 (no
    cancellation), and dt = T gives (1, 0, 0) exactly.
    """
    T = float(period_s)
    n, r = per_step_periods(dt, T)
    s0 = n + r / T                                              # Σ w
    s1 = n * r + T * n * (n - 1.0) / 2.0                        # Σ w·s
    s2 = (n * r ** 2 + r * T * n * (n - 1.0)
          + T ** 2 * (n - 1.0) * n * (2.0 * n - 1.0) / 6.0)     # Σ w·s²
    return s0, s1, s2


class PerStepNoise:
    """A fixed process-noise matrix Q_step added once per nominal period [s]."""

    def __init__(self, Q_step, period_s: float):
        """Store a symmetric PSD 2x2 ``Q_step`` and the period it belongs to."""
        self.Q_step = as_covariance('Q_step', Q_step, 2)
        self.period_s = as_duration('period_s', period_s)
        if self.period_s == 0.0:
            raise ValueError('period_s must be > 0')

    def __call__(self, dt: float) -> np.ndarray:
        """Return the noise accumulated over dt by steps of period_s."""
        dt = as_duration('dt', dt)
        a, c, b = self.Q_step[0, 0], self.Q_step[0, 1], self.Q_step[1, 1]
        with np.errstate(over='ignore', invalid='ignore'):
            q00, q01, q11 = per_step_noise_terms(a, c, b, self.period_s, dt)
            Q = np.array([[q00, q01], [q01, q11]])
        return _finite_noise(0.5 * (Q + Q.T), dt)

    def __repr__(self) -> str:
        """Show the matrix and period."""
        return f'PerStepNoise(Q_step={self.Q_step.tolist()!r}, period_s={self.period_s!r})'


ProcessNoise = Union[WhiteNoiseAcceleration, PerStepNoise]


class ConstantVelocityModel:
    """1-D constant velocity: x(t + dt) = x(t) + v·dt, v(t + dt) = v(t), plus noise."""

    dim_x = 2

    def __init__(self, noise: ProcessNoise):
        """Use ``noise`` (a callable dt -> Q) for the process noise."""
        self.noise = noise

    def F(self, dt: float) -> np.ndarray:
        """Return the transition matrix for dt."""
        return constant_velocity_F(dt)

    def Q(self, dt: float) -> np.ndarray:
        """Return the process noise for dt."""
        return self.noise(dt)

    def __repr__(self) -> str:
        """Show the noise model."""
        return f'ConstantVelocityModel({self.noise!r})'


# H for a position-only measurement of [position, velocity].
POSITION_H = np.array([[1.0, 0.0]])


class LinearDynamicsModel(PredictThenUpdate):
    """
    Linear dynamics F(dt), Q(dt), B(dt) with named components; subclasses add the update.

    The base of :class:`LinearModel` (linear measurement) and of
    :class:`kf_train.filters.ekf.ExtendedModel` (nonlinear measurement): both predict the same
    way and differ only in how a measurement corrects the state. With the update, a
    :class:`~kf_train.filters.contract.StepModel` (predict_update: predict then update).
    """

    def __init__(self, F, Q, R, *, B, state_names, measurement_names, control_names):
        """Store the dynamics and names; R is checked against the measurement dimension."""
        self.F, self.Q, self.B = F, Q, B
        self.state_names = tuple(state_names)
        self.measurement_names = tuple(measurement_names)
        self.control_names = tuple(control_names)
        self.R = as_covariance('R', R, len(self.measurement_names))
        if (B is None) != (not self.control_names):
            raise ValueError('B must be given exactly when control_names are')

    @property
    def dim_x(self) -> int:
        """Return the number of state components."""
        return len(self.state_names)

    @property
    def dim_z(self) -> int:
        """Return the number of measurement components."""
        return len(self.measurement_names)

    def predict(self, x, P, dt_s: float, u=None):
        """Return (x, P) predicted over dt_s with control u (required iff B is set)."""
        if self.B is None:
            if u is not None:
                raise ValueError('u given to a model without control input')
            return kalman.predict(x, P, self.F(dt_s), self.Q(dt_s))
        if u is None:
            raise ValueError(f'u ({", ".join(self.control_names)}) is required')
        return kalman.predict(x, P, self.F(dt_s), self.Q(dt_s), self.B(dt_s), u)


class LinearModel(LinearDynamicsModel):
    """
    A linear-Gaussian model: what a filter needs to predict and update.

    ``F``, ``Q`` and ``B`` are callables of dt [s] (``B`` may be None for no control);
    ``H`` and the default measurement noise ``R`` are fixed matrices. Names label the
    state, measurement and control components (used by replay output columns).
    """

    def __init__(self, F, Q, H, R, *, B=None, state_names=('position', 'velocity'),
                 measurement_names=('position',), control_names=()):
        """Store the model; H and R are checked against the names' dimensions."""
        super().__init__(F, Q, R, B=B, state_names=state_names,
                         measurement_names=measurement_names, control_names=control_names)
        self.H = as_matrix('H', H, self.dim_z, self.dim_x)

    def update(self, x, P, z, R=None):
        """Return (x, P, UpdateResult) after measurement z; R defaults to the model's."""
        return kalman.update(x, P, z, self.H, self.R if R is None else R)


def constant_velocity_model(noise: 'ProcessNoise', R=1.0) -> LinearModel:
    """Return the 1-D constant-velocity model measuring position with variance R."""
    return LinearModel(constant_velocity_F, noise, POSITION_H, [[float(R)]])
