"""
The rail IMM's mixing with its entry transformation, as gathers: a few numpy calls a step.

Mixing starts regime j from the moment-matched mixture of the components as they enter
it, x0_j = Σ_i ω_ij x_ji, P0_j = Σ_i ω_ij (P_ji + d dᵀ), d = x_ji - x0_j
(:meth:`kf_train.filters.rail_model.RailModel.entry`). A component entering another
regime changes one entry, the commanded acceleration ℓ: ℓ' = c_j x[k_j] + w_j,
w_j ~ N(0, W_j) (accelerate: ℓ = A + w, brake: ℓ = -B + w, cruise: ℓ = w, stand: ℓ = 0).
As x' = T_j x + w with T_j the identity but for ℓ's row c_j e_kᵀ, every entry of
x_ji = T_j x_i and of P_ji = T_j P_i T_jᵀ + W_j is one entry of x_i or P_i times c_j,
c_j² or 1 (plus W_j on ℓ's variance): a product with a single nonzero term, exact. So
all N² components come out of the stacked means and covariances by one gather (a fixed
index table) and one multiplication (a fixed table of those factors): the same numbers
:meth:`~kf_train.filters.rail_model.RailModel.entry` gives, component by component, in
two numpy calls instead of N² small ones. The tables depend only on the regimes, so
they are built once.
"""

from typing import Sequence, Tuple

import numpy as np


class EntryGather:
    """
    The index and factor tables of every component i entering every regime j.

    ``sources[j]``: the state ℓ is taken from on entering regime j (None: none, ℓ = w);
    ``factors[j]``: c_j; ``noises[j]``: W_j, ℓ's variance added; ``ell``: ℓ's index.
    A component staying in its own regime (i = j) is itself.
    """

    def __init__(self, sources: Sequence, factors: Sequence[float],
                 noises: Sequence[float], dim_x: int, ell: int):
        """Build the tables for N = len(sources) regimes of ``dim_x`` states."""
        count, n = len(sources), dim_x
        self.sources, self.factors = tuple(sources), tuple(float(c) for c in factors)
        self.noises, self.ell = tuple(float(w) for w in noises), ell
        # index of x_ji[a] in the flattened (N, n) means, and its factor
        index_x = np.empty((count, count, n), dtype=np.intp)
        factor_x = np.ones((count, count, n))
        for j in range(count):
            for i in range(count):
                index_x[j, i] = i * n + np.arange(n)
                if i != j:
                    source = sources[j]
                    index_x[j, i, ell] = i * n + (ell if source is None else source)
                    factor_x[j, i, ell] = 0.0 if source is None else factors[j]
        # index of P_ji[a, b] in the flattened (N, n, n) covariances, and its factor
        state = index_x - np.arange(count)[None, :, None] * n    # the state within x_i
        rows, columns = state[:, :, :, None], state[:, :, None, :]
        origin = (np.arange(count) * n * n)[None, :, None, None]
        self.index_P = (origin + rows * n + columns).reshape(count, count, n * n)
        self.factor_P = (factor_x[:, :, :, None] * factor_x[:, :, None, :]).reshape(
            count, count, n * n)
        self.noise_P = np.zeros((count, count, n * n))
        for j in range(count):
            for i in range(count):
                if i != j:
                    self.noise_P[j, i, ell * n + ell] = noises[j]
        self.index_x, self.factor_x = index_x, factor_x
        for array in (self.index_x, self.factor_x, self.index_P, self.factor_P, self.noise_P):
            array.flags.writeable = False

    def enter(self, j: int, x: np.ndarray, P: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return one component (x, P) as it enters regime j: x' = T_j x + w, the same rule.

        ℓ' = c_j x[k_j] + w (ℓ' = w without a source): ℓ's row and column become
        c_j times k_j's, its variance c_j² P[k_j, k_j] + W_j.
        """
        x, P = x.copy(), P.copy()
        ell, source, factor = self.ell, self.sources[j], self.factors[j]
        if source is None:
            x[ell] = 0.0
            P[ell, :] = 0.0
            P[:, ell] = 0.0
            P[ell, ell] = self.noises[j]
        else:
            x[ell] = factor * x[source]
            P[ell, :] = factor * P[source, :]
            P[:, ell] = factor * P[:, source]
            P[ell, ell] = factor * factor * P[source, source] + self.noises[j]
        return x, P

    def components(self, means: np.ndarray, covariances: np.ndarray
                   ) -> Tuple[np.ndarray, np.ndarray]:
        """Return x_ji (N, N, n) and P_ji (N, N, n²), [j, i] component i entering regime j."""
        xs = means.reshape(-1)[self.index_x]                          # x_i's entries ...
        xs *= self.factor_x                                           # ... ℓ' = c_j x[k_j]
        Ps = covariances.reshape(-1)[self.index_P]                    # T_j P_i T_jᵀ ...
        Ps *= self.factor_P
        Ps += self.noise_P                                            # ... + W_j
        return xs, Ps

    def mix(self, columns: np.ndarray, means: np.ndarray, covariances: np.ndarray
            ) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return every regime's starting mixture (x0 (N, n), P0 (N, n, n)).

        ``columns`` (N, N) holds [j, i] = ω_ij. P0 is left for the prediction to
        symmetrise (F P0 Fᵀ + Q is symmetrised anyway).
        """
        count, n = means.shape
        xs, Ps = self.components(means, covariances)
        weights = columns[:, None, :]
        x0 = np.matmul(weights, xs)                                   # x0_j = Σ_i ω_ij x_ji
        d = xs - x0                                                   # d_ji = x_ji - x0_j
        P0 = np.matmul(weights, Ps).reshape(count, n, n)              # Σ_i ω_ij P_ji
        P0 += np.matmul((columns[:, :, None] * d).swapaxes(1, 2), d)  # + Σ_i ω_ij d dᵀ
        return x0.reshape(count, n), P0
