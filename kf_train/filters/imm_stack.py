"""
The IMM's arithmetic on all modes at once: stacked (N, n) means and (N, n, n) covariances.

:mod:`kf_train.filters.imm` runs a bank of N Kalman filters. When every mode is a plain
:class:`~kf_train.filters.models.LinearModel` measuring one scalar (the rail model, and
the linear regimes of filterpy's ``IMMEstimator``), the N filters are the same
equations on different numbers, so each equation is one batched numpy call over the
stack instead of N small ones; the per-call overhead of numpy, not the arithmetic, is
what a 6-state filter costs. The equations and their order are those of
:mod:`kf_train.filters.kalman` (``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``, the Joseph-form
update, symmetrisation after each step) and of :func:`kf_train.filters.imm.combine`
(mixture moments about the mixture mean), so the results are the per-mode ones to
rounding. Inputs here are internal arrays of checked shapes: nothing is re-validated
but the results' finiteness (an overflow raises ValueError, as kalman's steps do).
"""

import math
from typing import NamedTuple, Optional, Tuple

from kf_train.filters.models import LinearDynamicsModel, LinearModel
from kf_train.filters.validation import as_covariance, as_duration, as_matrix
import numpy as np

_LOG_2PI = math.log(2.0 * math.pi)
# How many dt values a LinearStack keeps stacked matrices for (a stream repeats a few).
_KEPT = 64


class StackUpdate(NamedTuple):
    """What the batched scalar update produced, per mode."""

    means: np.ndarray
    """Corrected means (N, n)."""
    covariances: np.ndarray
    """Corrected covariances (N, n, n)."""
    innovations: np.ndarray
    """y_j = z - H_j x_j (N,)."""
    variances: np.ndarray
    """s_j = H_j P_j H_jᵀ + R_j (N,)."""
    gains: np.ndarray
    """K_j = P_j H_jᵀ / s_j (N, n)."""
    log_likelihoods: np.ndarray
    """log N(y_j; 0, s_j) (N,)."""


def duration(dt_s) -> float:
    """Return a checked duration [s], as as_duration does; a finite float >= 0 passes as is."""
    if type(dt_s) is float and 0.0 <= dt_s < math.inf:
        return dt_s
    return as_duration('dt_s', dt_s)


def check_finite(means: np.ndarray, covariances: np.ndarray, step: str) -> None:
    """Raise ValueError if a step overflowed into a non-finite state."""
    # A NaN or ±inf makes the sum NaN or ±inf; a finite sum that overflows is re-checked.
    if not math.isfinite(float(means.sum()) + float(covariances.sum())):
        if not (np.isfinite(means).all() and np.isfinite(covariances).all()):
            raise ValueError(f'{step} produced a non-finite state; inputs are too large')


def symmetrised(P: np.ndarray) -> np.ndarray:
    """Return (P + Pᵀ)/2 of each matrix of a stack (exactly symmetric)."""
    return (P + P.swapaxes(-1, -2).copy()) * 0.5


def combine(means: np.ndarray, covariances: np.ndarray, probabilities: np.ndarray):
    """Return the moment-matched (x, P) of one Gaussian mixture (as imm.combine)."""
    x = probabilities.dot(means)                                     # x = Σ μ_j x_j
    d = means - x
    n = means.shape[1]
    P = probabilities.dot(covariances.reshape(-1, n * n)).reshape(n, n) + \
        (probabilities[:, None] * d).T.dot(d)                          # Σ μ_j (P_j + d dᵀ)
    return x, (P + P.T) * 0.5


def mix(weights: np.ndarray, means: np.ndarray, covariances: np.ndarray):
    """
    Return the N mixtures x0_j, P0_j of components weighted by column j of ``weights``.

    ``weights`` (N, N) holds ω_ij; ``means`` is (N, n) (the same components for every
    mode) or (N, N, n) with means[j, i] component i as it enters mode j (likewise
    ``covariances``, (N, n, n) or (N, N, n, n)). x0_j = Σ_i ω_ij x_i,
    P0_j = Σ_i ω_ij (P_i + d dᵀ), d = x_i - x0_j.
    """
    count = weights.shape[0]
    n = means.shape[-1]
    columns = weights.T                                              # [j, i] = ω_ij
    if means.ndim == 2:
        x0 = columns.dot(means)                                      # x0_j = Σ_i ω_ij x_i
        spread = columns.dot(covariances.reshape(count, n * n))      # Σ_i ω_ij P_i
        d = means[None, :, :] - x0[:, None, :]                       # d_ji = x_i - x0_j
    else:
        x0 = np.matmul(columns[:, None, :], means)[:, 0, :]
        spread = np.matmul(columns[:, None, :],
                           covariances.reshape(count, count, n * n))[:, 0, :]
        d = means - x0[:, None, :]
    P0 = spread.reshape(count, n, n) + np.matmul(
        (columns[:, :, None] * d).swapaxes(1, 2), d)                 # + Σ_i ω_ij d dᵀ
    return x0, symmetrised(P0)


def predict(means: np.ndarray, covariances: np.ndarray, F: np.ndarray, Q: np.ndarray):
    """Return each mode's prediction: x⁻ = F x, P⁻ = F P Fᵀ + Q (stacks F, Q (N, n, n))."""
    x = np.matmul(F, means[:, :, None])[:, :, 0]                     # x⁻ = F x
    P = np.matmul(np.matmul(F, covariances), F.swapaxes(1, 2)) + Q   # P⁻ = F P Fᵀ + Q
    P = symmetrised(P)
    check_finite(x, P, 'prediction')
    return x, P


def update(means: np.ndarray, covariances: np.ndarray, z: float, H: np.ndarray,
           R: np.ndarray, identity: np.ndarray) -> StackUpdate:
    """
    Return each mode corrected by the scalar z: H (N, 1, n), R (N,), Joseph form.

    S is 1x1, so K = P Hᵀ / s and NIS = y² / s in closed form, as kalman.update does.
    """
    HP = np.matmul(H, covariances)                                   # H P⁻ (N, 1, n)
    y = z - np.matmul(H, means[:, :, None])[:, 0, 0]                 # y = z - H x⁻
    s = np.matmul(HP, H.swapaxes(1, 2))[:, 0, 0] + R                 # s = H P⁻ Hᵀ + R
    if not s.all():
        raise ValueError(f'innovation covariance S = H P Hᵀ + R is singular: {s.tolist()}')
    K = HP[:, 0, :] / s[:, None]                                     # K = P⁻ Hᵀ / s
    x = means + K * y[:, None]                                       # x = x⁻ + K y
    I_KH = identity - K[:, :, None] * H                              # I - K H
    # Joseph form, P = (I - K H) P⁻ (I - K H)ᵀ + K R Kᵀ: stays symmetric and positive
    # semi-definite even when K is not exactly optimal.
    P = np.matmul(np.matmul(I_KH, covariances), I_KH.swapaxes(1, 2)) + \
        (K * R[:, None])[:, :, None] * K[:, None, :]
    P = symmetrised(P)
    check_finite(x, P, 'update')
    nis = y * y / s                                                  # NIS = y² / s
    if not np.isfinite(nis).all():
        raise ValueError(f'update produced an invalid NIS {nis.tolist()}; S = {s.tolist()}')
    log_likelihoods = -0.5 * (nis + np.log(s) + _LOG_2PI)           # log N(y; 0, s)
    return StackUpdate(x, P, y, s, K, log_likelihoods)


def posterior(prior: np.ndarray, log_likelihoods: np.ndarray) -> np.ndarray:
    """Return μ_j ∝ c̄_j Λ_j, normalised in the log domain (no underflow to 0/0)."""
    with np.errstate(divide='ignore'):
        weights = np.log(prior) + log_likelihoods                    # log(c̄_j Λ_j)
    weights = np.exp(weights - weights.max())
    return weights / weights.sum()                                   # μ_j = c̄_j Λ_j / Σ


def mixture_innovation(prior: np.ndarray, means: np.ndarray, result: StackUpdate):
    """
    Return (y, S, NIS, K) of the prior mixture's scalar innovation.

    ẑ = Σ c̄_j ẑ_j, S = Σ c̄_j (s_j + (ẑ_j - ẑ)²), P_xz = Σ c̄_j (K_j s_j + (x_j - x̄)(ẑ_j - ẑ))
    with ẑ_j - ẑ = -(y_j - y), K = P_xz / S, NIS = y² / S.
    """
    c = prior
    y = c.dot(result.innovations)                                    # y = z - Σ c̄_j ẑ_j
    d = result.innovations - y
    S = c.dot(result.variances) + c.dot(d * d)
    x_bar = c.dot(means)
    Pxz = c.dot(result.gains * result.variances[:, None] - (means - x_bar) * d[:, None])
    nis = y * (y / S)                                                # yᵀ S⁻¹ y
    return y, S, float(nis), Pxz / S


def frozen(array) -> bool:
    """Return whether ``array`` is a read-only ndarray owning its data (it cannot change)."""
    return type(array) is np.ndarray and not array.flags.writeable and array.base is None


class LinearStack:
    """
    The F(dt), Q(dt), H and R of N LinearModels measuring a scalar, stacked.

    F(dt) and Q(dt) are asked of the models at every call and checked as
    kalman.predict checks them; a stack built from read-only arrays that own their
    data (a cache's, such as the rail model's) is kept and reused while the models
    return those very arrays. H and R are read when the stack is built.
    """

    def __init__(self, modes):
        """Stack the measurement matrices and noises of ``modes`` (see :meth:`of`)."""
        self.modes = tuple(modes)
        n = self.modes[0].dim_x
        self.dim_x = n
        self.H = np.array([mode.H for mode in self.modes])          # (N, 1, n)
        self.R = np.array([mode.R[0, 0] for mode in self.modes])     # (N,)
        self.identity = np.eye(n)
        for array in (self.H, self.R, self.identity):
            array.flags.writeable = False
        self._kept = {}

    @classmethod
    def of(cls, modes) -> Optional['LinearStack']:
        """Return the stack of ``modes``, or None unless each is a plain scalar LinearModel."""
        for mode in modes:
            if not (isinstance(mode, LinearModel) and mode.B is None and mode.dim_z == 1
                    and type(mode).predict is LinearDynamicsModel.predict
                    and type(mode).update is LinearModel.update
                    and mode.dim_x == modes[0].dim_x):
                return None
        return cls(modes)

    def matrices(self, dt_s: float) -> Tuple[np.ndarray, np.ndarray]:
        """Return the checked, stacked (F(dt_s), Q(dt_s)), each (N, n, n)."""
        sources = [mode.F(dt_s) for mode in self.modes] + [mode.Q(dt_s) for mode in self.modes]
        kept = self._kept.get(dt_s)
        if kept is not None and all(a is b for a, b in zip(kept[2], sources)):
            return kept[0], kept[1]
        count, n = len(self.modes), self.dim_x
        F = np.array([as_matrix('F', value, n, n) for value in sources[:count]])
        Q = np.array([as_covariance('Q', value, n) for value in sources[count:]])
        if all(frozen(value) for value in sources):
            if len(self._kept) >= _KEPT:
                self._kept.pop(next(iter(self._kept)))
            self._kept[dt_s] = (F, Q, sources)
        return F, Q
