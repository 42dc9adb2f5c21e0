"""
Rauch-Tung-Striebel smoother: the best estimate at every row given all the rows.

Input is a forward filter's output: for each row k the corrected ``x[k]``, ``P[k]``
and the prediction into row k from row k − 1, ``x_prior[k]``, ``P_prior[k]``, made
with ``F[k]`` (control input and process noise are already inside the prediction, so
the smoother needs neither). Backwards from the last row, which the filter already
smoothed:

    G_k  = P_k F_{k+1}ᵀ (P⁻_{k+1})⁻¹
    xs_k = x_k + G_k (xs_{k+1} − x⁻_{k+1})
    Ps_k = P_k + G_k (Ps_{k+1} − P⁻_{k+1}) G_kᵀ

Both recursions are affine in the smoothed quantity, so for small states they run
vectorised (:func:`kf_train.batch.affine.affine_recursion`, on vec(Ps) for the
covariance); larger states run row by row.
"""

from typing import NamedTuple

from kf_train.batch.affine import affine_recursion
from kf_train.batch.series import SeriesResult
from kf_train.filters import as_finite_array
import numpy as np

# vec(Ps) has n² entries; the vectorised covariance pass costs O(n⁶) per row.
VECTORISED_MAX_STATES = 2


class SmootherResult(NamedTuple):
    """Smoothed estimates for every row, and the smoother gains."""

    x: np.ndarray
    """Smoothed means (N, n)."""
    P: np.ndarray
    """Smoothed covariances (N, n, n)."""
    gain: np.ndarray
    """G_k (N − 1, n, n) for k = 0..N−2 (the last row has none)."""


def _stack(name: str, value, shape) -> np.ndarray:
    """Return ``value`` as a finite array of the given shape."""
    array = as_finite_array(name, value)
    if array.shape != shape:
        raise ValueError(f'{name} must have shape {shape}, got {array.shape}')
    return array


def rts_smooth(x, P, x_prior, P_prior, F) -> SmootherResult:
    """Return the RTS-smoothed means and covariances of a filtered series."""
    x = as_finite_array('x', x)
    if x.ndim != 2:
        raise ValueError(f'x must have shape (N, n), got {x.shape}')
    N, n = x.shape
    P = _stack('P', P, (N, n, n))
    x_prior = _stack('x_prior', x_prior, (N, n))
    P_prior = _stack('P_prior', P_prior, (N, n, n))
    F = _stack('F', F, (N, n, n))
    if N <= 1:
        return SmootherResult(x.copy(), P.copy(), np.empty((0, n, n)))

    # G_kᵀ = (P⁻_{k+1})⁻¹ F_{k+1} P_k, P⁻ and P symmetric; solved, not inverted.
    try:
        G = np.swapaxes(np.linalg.solve(P_prior[1:], F[1:] @ P[:-1]), -1, -2)
    except np.linalg.LinAlgError:
        bad = next(k for k in range(1, N) if np.linalg.matrix_rank(P_prior[k]) < n)
        raise ValueError(f'P_prior[{bad}] is singular: the smoother needs an invertible '
                         f'predicted covariance, got {P_prior[bad].tolist()}') from None
    if not np.all(np.isfinite(G)):
        raise ValueError('smoother gain is not finite: P_prior is (nearly) singular')

    # xs_k = G_k xs_{k+1} + (x_k − G_k x⁻_{k+1}), run backwards from xs_{N−1} = x_{N−1}
    c = x[:-1] - (G @ x_prior[1:, :, None])[..., 0]
    xs = np.empty_like(x)
    xs[-1] = x[-1]
    # Ps_k = G_k Ps_{k+1} G_kᵀ + (P_k − G_k P⁻_{k+1} G_kᵀ)
    D = P[:-1] - G @ P_prior[1:] @ np.swapaxes(G, -1, -2)
    Ps = np.empty_like(P)
    Ps[-1] = P[-1]
    if n <= VECTORISED_MAX_STATES:
        xs[:-1] = affine_recursion(G[::-1], c[::-1], x[-1])[::-1]
        # Row-major vec(G X Gᵀ) = (G ⊗ G) vec(X)
        GG = np.einsum('kij,kab->kiajb', G, G).reshape(N - 1, n * n, n * n)
        vec = affine_recursion(GG[::-1], D[::-1].reshape(N - 1, n * n),
                               P[-1].reshape(n * n))[::-1]
        Ps[:-1] = vec.reshape(N - 1, n, n)
    else:
        for k in range(N - 2, -1, -1):
            xs[k] = G[k] @ xs[k + 1] + c[k]
            Ps[k] = G[k] @ Ps[k + 1] @ G[k].T + D[k]
    Ps = 0.5 * (Ps + np.swapaxes(Ps, -1, -2))
    return SmootherResult(xs, Ps, G)


def smooth_series(result: SeriesResult) -> SmootherResult:
    """Return the RTS smoothing of a :class:`~kf_train.batch.series.SeriesResult`."""
    return rts_smooth(result.x, result.P, result.x_prior, result.P_prior, result.F)
