"""
filterpy's CV KF, CA KF and IMM(CV+CA), run for a whole grid of tunings at once.

A hindsight grid search runs the same filter hundreds of times on one run; in
filterpy that takes many minutes a run. These are the same filters written for a
batch of G tunings at once (arrays (G, n) and (G, n, n)), step for step as
filterpy's ``KalmanFilter`` and ``IMMEstimator`` compute them: predict
x = F x, P = F P Fᵀ + Q; update y = z - H x, S = H P Hᵀ + R, K = P Hᵀ S⁻¹,
x += K y, P = (I - K H) P (I - K H)ᵀ + K R Kᵀ; the IMM's mixing, likelihood
exp(logpdf) floored at the smallest float, and μ = c̄ Λ / Σ. ``rail_eval.py`` runs
the real filterpy filter at the tuning the grid picks and reports how far the two
tracks differ (they agree to rounding), so the figures it prints are filterpy's.
"""

import sys

from filterpy.common import Q_continuous_white_noise
import numpy as np

_TINY = sys.float_info.min


def transition(dim: int, dt: float, hold_acceleration: bool = True) -> np.ndarray:
    """Return F(dt): CV (dim 2) or CA (dim 3); CA without hold: a = 0 (a CV in 3 states)."""
    F = np.eye(dim)
    F[0, 1] = dt
    if dim == 3:
        F[0, 2], F[1, 2] = dt * dt / 2.0, dt
        if not hold_acceleration:
            F[:, 2] = 0.0
    return F


def cv_in_ca_noise(dt: float, q: float) -> np.ndarray:
    """Return the 3x3 Q of a CV filter in [p, v, a]: white acceleration q, a = 0."""
    Q = np.zeros((3, 3))
    Q[:2, :2] = Q_continuous_white_noise(2, dt, q)
    return Q


def _update(x, P, z, R):
    """Batched filterpy update with H = [1, 0, ...]; return (x, P, y, S)."""
    y = z - x[..., 0]                                       # y = z - H x
    S = P[..., 0, 0] + R                                    # S = H P Hᵀ + R
    K = P[..., :, 0] / S[..., None]                         # K = P Hᵀ S⁻¹
    x = x + K * y[..., None]                                # x += K y
    n = x.shape[-1]
    I_KH = np.broadcast_to(np.eye(n), P.shape).copy()
    I_KH[..., :, 0] -= K                                    # I - K H
    P = np.einsum('...ab,...bc,...dc->...ad', I_KH, P, I_KH) + \
        R * np.einsum('...a,...b->...ab', K, K)            # Joseph form
    return x, P, y, S


def batch_kf(z, qs, dim: int, dt: float, initial_variances, horizon_s: float):
    """
    Return (mean, variance) of the horizon_s predictions (G, N) of a CV/CA KF per q.

    Sample 0 initialises x = [z0, 0(, 0)], P = diag(initial_variances); every later
    sample is one predict over the nominal dt and an update, as FilterpyKF does.
    """
    qs = np.asarray(qs, dtype=float)
    G, N = qs.size, len(z)
    F, F2 = transition(dim, dt), transition(dim, horizon_s)
    Q = qs[:, None, None] * Q_continuous_white_noise(dim, dt, 1.0)
    Q2 = qs[:, None, None] * Q_continuous_white_noise(dim, horizon_s, 1.0)
    x = np.zeros((G, dim))
    x[:, 0] = z[0]
    P = np.broadcast_to(np.diag(initial_variances[:dim]), (G, dim, dim)).copy()
    mean, variance = np.empty((G, N)), np.empty((G, N))
    for k in range(N):
        if k:
            x = x @ F.T                                       # x = F x
            P = F @ P @ F.T + Q                               # P = F P Fᵀ + Q
            x, P, _, _ = _update(x, P, z[k], 1.0)
        mean[:, k] = x @ F2[0]
        variance[:, k] = np.einsum('a,gab,b->g', F2[0], P, F2[0]) + Q2[:, 0, 0]
    return mean, variance


def batch_imm(z, configs, dt: float, initial_variances, horizon_s: float):
    """
    Return (mean, variance) (G, N) of filterpy's IMM(CV+CA) per (q_cv, q_ca, switch).

    Filter 0 is the CV one (a held at 0), filter 1 the CA one; μ0 = [0.5, 0.5],
    M = [[1 - s, s], [s, 1 - s]]. The prediction ahead is the μ-weighted mixture of
    each filter's own prediction, as FilterpyIMM.predict_ahead.
    """
    configs = np.asarray(configs, dtype=float)
    G, N = configs.shape[0], len(z)
    q_cv, q_ca, switch = configs.T
    F = np.stack([transition(3, dt, False), transition(3, dt)])            # (2, 3, 3)
    F2 = np.stack([transition(3, horizon_s, False), transition(3, horizon_s)])
    Q = np.stack([q_cv[:, None, None] * cv_in_ca_noise(dt, 1.0),
                  q_ca[:, None, None] * Q_continuous_white_noise(3, dt, 1.0)], axis=1)
    Q2 = np.stack([q_cv[:, None, None] * cv_in_ca_noise(horizon_s, 1.0),
                   q_ca[:, None, None] * Q_continuous_white_noise(3, horizon_s, 1.0)], axis=1)
    M = np.empty((G, 2, 2))
    M[:, 0, 0] = M[:, 1, 1] = 1.0 - switch
    M[:, 0, 1] = M[:, 1, 0] = switch
    x = np.zeros((G, 2, 3))
    x[:, :, 0] = z[0]
    P = np.broadcast_to(np.diag(initial_variances), (G, 2, 3, 3)).copy()
    mu = np.full((G, 2), 0.5)
    cbar = np.einsum('gi,gij->gj', mu, M)
    mean, variance = np.empty((G, N)), np.empty((G, N))
    for k in range(N):
        if k:
            omega = M * mu[:, :, None] / cbar[:, None, :]          # ω_ij = M_ij μ_i / c̄_j
            xs = np.einsum('gij,gia->gja', omega, x)               # mixed means
            d = x[:, :, None, :] - xs[:, None, :, :]               # x_i - xs_j
            Ps = np.einsum('gij,giab->gjab', omega, P) + \
                np.einsum('gij,gija,gijb->gjab', omega, d, d)
            x = np.einsum('jab,gjb->gja', F, xs)
            P = np.einsum('jab,gjbc,jdc->gjad', F, Ps, F) + Q
            x, P, y, S = _update(x, P, z[k], 1.0)
            likelihood = np.exp(-0.5 * (y * y / S + np.log(2.0 * np.pi * S)))
            likelihood = np.where(likelihood == 0.0, _TINY, likelihood)
            mu = cbar * likelihood
            mu /= mu.sum(axis=1, keepdims=True)
            cbar = np.einsum('gi,gij->gj', mu, M)
        means = np.einsum('ja,gja->gj', F2[:, 0, :], x)
        vars_ = np.einsum('ja,gjab,jb->gj', F2[:, 0, :], P, F2[:, 0, :]) + Q2[:, :, 0, 0]
        mean[:, k] = np.sum(mu * means, axis=1)
        variance[:, k] = np.sum(mu * (vars_ + (means - mean[:, k, None]) ** 2), axis=1)
    return mean, variance
