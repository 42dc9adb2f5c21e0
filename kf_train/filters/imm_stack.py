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

from kf_train.filters.kalman import LOG_2PI
from kf_train.filters.models import LinearDynamicsModel, LinearModel
from kf_train.filters.validation import as_covariance, as_duration, as_matrix
import numpy as np

# How many dt values a LinearStack keeps stacked matrices for (a stream repeats a few).
_KEPT = 64
_ONES = {}
_IDENTITIES = {}


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
    # A NaN or ±inf makes a sum NaN or ±inf (a dot with ones: the cheapest sum); a
    # finite sum that overflows is re-checked entry by entry.
    total = means.reshape(-1).dot(_ones(means.size)) + \
        covariances.reshape(-1).dot(_ones(covariances.size))
    if not math.isfinite(total):
        if not (np.isfinite(means).all() and np.isfinite(covariances).all()):
            raise ValueError(f'{step} produced a non-finite state; inputs are too large')


def _ones(size: int) -> np.ndarray:
    """Return a read-only vector of ``size`` ones, built once per size."""
    ones = _ONES.get(size)
    if ones is None:
        ones = _ONES[size] = np.ones(size)
        ones.flags.writeable = False
    return ones


def _identities(count: int, n: int) -> np.ndarray:
    """Return a new (count, n, n) stack of identities (copied from one kept per shape)."""
    template = _IDENTITIES.get((count, n))
    if template is None:
        template = _IDENTITIES[count, n] = np.tile(np.eye(n), (count, 1, 1))
        template.flags.writeable = False
    return template.copy()


def symmetrised(P: np.ndarray) -> np.ndarray:
    """Return (P + Pᵀ)/2 of each matrix of a stack (exactly symmetric)."""
    # (Copying the transpose first is faster than adding the strided view.)
    P = P + P.swapaxes(-1, -2).copy()
    P *= 0.5
    return P


def combine(means: np.ndarray, covariances: np.ndarray, probabilities: np.ndarray):
    """Return the moment-matched (x, P) of one Gaussian mixture (as imm.combine)."""
    x = probabilities.dot(means)                                     # x = Σ μ_j x_j
    d = means - x
    n = means.shape[1]
    P = (probabilities[:, None] * d).T.dot(d)                        # Σ μ_j d dᵀ
    P += probabilities.dot(covariances.reshape(-1, n * n)).reshape(n, n)  # + Σ μ_j P_j
    P += P.T                                                         # symmetrised:
    P *= 0.5                                                         # (P + Pᵀ) / 2
    return x, P


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
        d = means - x0[:, None, :]                                   # d_ji = x_i - x0_j
    else:
        rows = columns[:, None, :]
        x0 = np.matmul(rows, means).reshape(count, n)
        spread = np.matmul(rows, covariances.reshape(count, count, n * n))
        d = means - x0[:, None, :]
    P0 = spread.reshape(count, n, n) + np.matmul(
        (columns[:, :, None] * d).swapaxes(1, 2), d)                 # + Σ_i ω_ij d dᵀ
    return x0, symmetrised(P0)


def predict(means: np.ndarray, covariances: np.ndarray, F: np.ndarray, Q: np.ndarray,
            F_transposed: np.ndarray, final: bool = True):
    """
    Return each mode's prediction: x⁻ = F x, P⁻ = F P Fᵀ + Q (stacks F, Q, Fᵀ (N, n, n)).

    ``final=False`` leaves the symmetrising and the finiteness check to the caller (a
    look-ahead that moment-matches the modes at once does both on the mixture).
    """
    x = np.matmul(F, means[:, :, None]).reshape(means.shape)        # x⁻ = F x
    P = np.matmul(np.matmul(F, covariances), F_transposed) + Q       # P⁻ = F P Fᵀ + Q
    if final:
        P = symmetrised(P)
        check_finite(x, P, 'prediction')
    return x, P


def update(means: np.ndarray, covariances: np.ndarray, z: float, H: np.ndarray,
           R: np.ndarray, identity: np.ndarray, selected: Optional[int] = None
           ) -> StackUpdate:
    """
    Return each mode corrected by the scalar z: H (N, 1, n), R (N,) or (1,), Joseph form.

    R is each mode's variance, or one for all modes (the row of a (1, 1) R, broadcast).

    S is 1x1, so K = P Hᵀ / s and NIS = y² / s in closed form, as kalman.update does.
    ``selected``: the index k when every H is the unit row e_k; then H P, H x and
    H P Hᵀ are P's row k, x_k and P_kk, which is what the products give exactly.
    """
    count = means.shape[0]
    if selected is None:
        HP = np.matmul(H, covariances)                               # H P⁻ (N, 1, n)
        y = z - np.matmul(H, means[:, :, None]).reshape(count)       # y = z - H x⁻
        s = np.matmul(HP, H.swapaxes(1, 2)).reshape(count) + R       # s = H P⁻ Hᵀ + R
    else:
        HP = covariances[:, selected, :]
        y = z - means[:, selected]
        s = covariances[:, selected, selected] + R
    s_list = s.tolist()
    if 0.0 in s_list:
        raise ValueError(f'innovation covariance S = H P Hᵀ + R is singular: {s_list}')
    K = HP.reshape(means.shape) / s[:, None]                         # K = P⁻ Hᵀ / s
    x = K * y[:, None]
    x += means                                                       # x = x⁻ + K y
    if selected is None:
        I_KH = identity - K[:, :, None] * H                          # I - K H
    else:
        I_KH = _identities(count, means.shape[1])                    # I - K e_kᵀ: the
        I_KH[:, :, selected] -= K                                    # same numbers
    # Joseph form, P = (I - K H) P⁻ (I - K H)ᵀ + K R Kᵀ: stays symmetric and positive
    # semi-definite even when K is not exactly optimal.
    P = np.matmul(np.matmul(I_KH, covariances), I_KH.swapaxes(1, 2))
    # K R Kᵀ as a stack of outer products (one product per entry, as the broadcast's)
    P += np.matmul((K * R[:, None])[:, :, None], K[:, None, :])
    P = symmetrised(P)
    check_finite(x, P, 'update')
    logs = []
    for y_j, s_j in zip(y.tolist(), s_list):
        nis = y_j * y_j / s_j                                        # NIS = y² / s
        if not math.isfinite(nis) or nis < 0.0:
            raise ValueError(f'update produced an invalid NIS {nis}; S = {s_list}')
        logs.append(-0.5 * (nis + math.log(s_j) + LOG_2PI))         # log N(y; 0, s)
    return StackUpdate(x, P, y, s, K, logs)


def posterior(prior, log_likelihoods) -> np.ndarray:
    """Return μ_j ∝ c̄_j Λ_j, normalised in the log domain (no underflow to 0/0)."""
    weights = [math.log(c) + log if c > 0.0 else -math.inf            # log(c̄_j Λ_j)
               for c, log in zip(prior.tolist(), log_likelihoods)]
    top = max(weights)
    weights = [math.exp(w - top) for w in weights]
    total = sum(weights)
    return np.array([w / total for w in weights])                    # μ_j = c̄_j Λ_j / Σ


def mixture_innovation(prior: np.ndarray, means: np.ndarray, result: StackUpdate):
    """
    Return (y, S, NIS, K) of the prior mixture's scalar innovation.

    ẑ = Σ c̄_j ẑ_j, S = Σ c̄_j (s_j + (ẑ_j - ẑ)²), P_xz = Σ c̄_j (K_j s_j + (x_j - x̄)(ẑ_j - ẑ))
    with ẑ_j - ẑ = -(y_j - y), K = P_xz / S, NIS = y² / S.
    """
    c = prior.tolist()
    y_modes, s_modes = result.innovations.tolist(), result.variances.tolist()
    y = 0.0
    for c_j, y_j in zip(c, y_modes):
        y += c_j * y_j                                               # y = z - Σ c̄_j ẑ_j
    d = [y_j - y for y_j in y_modes]
    S = 0.0
    for c_j, s_j, d_j in zip(c, s_modes, d):
        S += c_j * (s_j + d_j * d_j)                                 # Σ c̄_j (s_j + d_j²)
    x_bar = prior.dot(means)
    # P_xz = Σ c̄_j s_j K_j - Σ c̄_j d_j (x_j - x̄): two weighted sums of rows
    weights = np.array([[c_j * s_j for c_j, s_j in zip(c, s_modes)],
                        [c_j * d_j for c_j, d_j in zip(c, d)]])
    Pxz = weights[0].dot(result.gains) - weights[1].dot(means - x_bar)
    nis = y * (y / S)                                                # yᵀ S⁻¹ y
    return y, S, nis, Pxz / S


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
        # The index k when every H is the unit row e_k (a position measured directly).
        unit = np.flatnonzero(self.H[0, 0] == 1.0)
        self.selected = int(unit[0]) if unit.size == 1 and np.all(self.H == self.H[0]) and \
            np.count_nonzero(self.H[0, 0]) == 1 else None
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

    def matrices(self, dt_s: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the checked, stacked (F(dt_s), Q(dt_s), F(dt_s)ᵀ), each (N, n, n)."""
        sources = [mode.F(dt_s) for mode in self.modes] + [mode.Q(dt_s) for mode in self.modes]
        kept = self._kept.get(dt_s)
        if kept is not None and all(a is b for a, b in zip(kept[3], sources)):
            return kept[:3]
        count, n = len(self.modes), self.dim_x
        # Modes often share one matrix object (the rail model's moving regimes): it is
        # checked once. A new dt (a stream with jittered stamps) pays these checks.
        checked = {}

        def check(kind, value, checker):
            key = (kind, id(value))
            if key not in checked:
                checked[key] = checker(value)
            return checked[key]
        F = np.array([check('F', value, lambda v: as_matrix('F', v, n, n))
                      for value in sources[:count]])
        Q = np.array([check('Q', value, lambda v: as_covariance('Q', v, n))
                      for value in sources[count:]])
        F_transposed = F.swapaxes(1, 2).copy()
        if all(frozen(value) for value in sources):
            for array in (F, Q, F_transposed):
                array.flags.writeable = False
            if len(self._kept) >= _KEPT:
                self._kept.pop(next(iter(self._kept)))
            self._kept[dt_s] = (F, Q, F_transposed, sources)
        return F, Q, F_transposed
