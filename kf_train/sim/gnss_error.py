"""
The slow GNSS position error of :mod:`kf_train.sim.gnss_receiver`: exact in any time step.

The error is e = x + w: w white (σ_w), x a mean-reverting integral of an
Ornstein-Uhlenbeck velocity u,

    du = -u / T_u dt + σ_u √(2 / T_u) dW,    dx = (u - x / T_x) dt,

a linear SDE d[x, u] = A [x, u] dt + B dW. Its transition over dt is
Φ(dt) = exp(A dt) and its covariance Q(dt) = ∫₀^dt Φ B Bᵀ Φᵀ ds, both in closed
form (:func:`transition_covariance`; equal to P∞ - Φ P∞ Φᵀ, P∞ the stationary
covariance, A P∞ + P∞ Aᵀ + B Bᵀ = 0). Both are exact for every dt, so jittered or dropped
stamps need no Euler step. The structure function of e is

    D(τ)² = E[(e(t+τ) - e(t))²] = 2 (P∞_xx - [Φ(τ) P∞]_xx) + 2 σ_w²     (τ > 0),

:func:`model_structure_function`. :func:`structure_function` measures D(τ) on any
error series (a simulated one, or a log's along-track position minus the integral of
its Doppler speed), to compare with the table in docs/rail.md.
"""

import math
from typing import Tuple

import numpy as np


def transition(dt_s: float, velocity_time_s: float,
               revert_time_s: float) -> np.ndarray:
    """Return Φ(dt) = exp(A dt) of the state [x, u] (x: position error, u: its velocity)."""
    a, b = 1.0 / revert_time_s, 1.0 / velocity_time_s
    fx, fu = math.exp(-a * dt_s), math.exp(-b * dt_s)
    if abs(b - a) > 1e-12 * max(a, b):
        fxu = (fx - fu) / (b - a)
    else:  # T_x = T_u: the limit dt·e^{-dt/T}
        fxu = dt_s * fx
    return np.array([[fx, fxu], [0.0, fu]])


def stationary_covariance(velocity_std_mps: float, velocity_time_s: float,
                          revert_time_s: float) -> np.ndarray:
    """Return P∞ of [x, u]: P_uu = σ_u², P_xu = σ_u²/(1/T_x + 1/T_u), P_xx = T_x P_xu."""
    uu = velocity_std_mps ** 2
    xu = uu / (1.0 / revert_time_s + 1.0 / velocity_time_s)
    return np.array([[revert_time_s * xu, xu], [xu, uu]])


def transition_covariance(dt_s: float, velocity_std_mps: float, velocity_time_s: float,
                          revert_time_s: float) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return (Φ(dt), Q(dt)), Q = ∫₀^dt Φ(s) B Bᵀ Φ(s)ᵀ ds: the exact discrete-time step.

    Q is integrated in closed form (expm1, no cancellation against P∞ at short steps);
    with T_x within 0.1 % of T_u it is P∞ - Φ P∞ Φᵀ, equal in exact arithmetic.
    """
    phi = transition(dt_s, velocity_time_s, revert_time_s)
    a, b = 1.0 / revert_time_s, 1.0 / velocity_time_s
    if abs(b - a) <= 1e-3 * max(a, b):
        p = stationary_covariance(velocity_std_mps, velocity_time_s, revert_time_s)
        q = p - phi @ p @ phi.T
        return phi, 0.5 * (q + q.T)

    def decayed(rate: float) -> float:
        """Return ∫₀^dt e^{-rate s} ds."""
        return -math.expm1(-rate * dt_s) / rate
    c2 = 2.0 * velocity_std_mps ** 2 / velocity_time_s   # B Bᵀ = diag(0, c²)
    uu = decayed(2.0 * b)
    xu = (decayed(a + b) - uu) / (b - a)
    xx = (decayed(2.0 * a) - 2.0 * decayed(a + b) + uu) / (b - a) ** 2
    return phi, c2 * np.array([[xx, xu], [xu, uu]])


def ou_step(dt_s: float, time_s: float) -> Tuple[float, float]:
    """Return (decay, innovation std) of a unit-variance OU process over dt: exact."""
    decay = math.exp(-dt_s / time_s)
    return decay, math.sqrt(max(1.0 - decay * decay, 0.0))


def model_structure_function(tau_s, velocity_std_mps: float, velocity_time_s: float,
                             revert_time_s: float, white_std_m: float) -> np.ndarray:
    """Return the model's D(τ) [m] at lags tau_s > 0 (closed form, see the module doc)."""
    tau = np.atleast_1d(np.asarray(tau_s, dtype=float))
    p = stationary_covariance(velocity_std_mps, velocity_time_s, revert_time_s)
    a, b = 1.0 / revert_time_s, 1.0 / velocity_time_s
    fx, fu = np.exp(-a * tau), np.exp(-b * tau)
    fxu = (fx - fu) / (b - a) if abs(b - a) > 1e-12 * max(a, b) else tau * fx
    covariance = fx * p[0, 0] + fxu * p[0, 1]
    return np.sqrt(2.0 * (p[0, 0] - covariance) + 2.0 * white_std_m ** 2)


def structure_function(t_s, error_m, tau_s, tolerance_s: float = 1e-3) -> np.ndarray:
    """
    Return D(τ) = RMS of e(t+τ) - e(t) over every pair of samples τ apart [m].

    ``t_s`` increasing sample times, ``error_m`` the error at them (NaN: no fix, left
    out); a pair counts when the later stamp is within ``tolerance_s`` of t + τ. NaN
    where no pair exists. Use one continuous stretch, or the error with any constant
    offset between stretches removed: D only sees differences.
    """
    t = np.asarray(t_s, dtype=float)
    e = np.asarray(error_m, dtype=float)
    keep = np.isfinite(e) & np.isfinite(t)
    t, e = t[keep], e[keep]
    result = []
    for tau in np.atleast_1d(np.asarray(tau_s, dtype=float)):
        later = np.clip(np.searchsorted(t, t + tau - tolerance_s), 0, max(t.size - 1, 0))
        pair = np.abs(t[later] - (t + tau)) <= tolerance_s if t.size else keep[:0]
        diff = e[later[pair]] - e[pair]
        result.append(math.sqrt(float(np.mean(diff ** 2))) if diff.size else math.nan)
    return np.array(result)
