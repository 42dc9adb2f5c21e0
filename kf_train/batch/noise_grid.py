"""
The window likelihood of many process noises q at once: the suggested q from two grids.

:class:`~kf_train.batch.noise_suggestion.RunningNoiseEstimate` maximises ℓ(q), the exact
log-likelihood of a window of measurements (:mod:`kf_train.batch.noise_likelihood`),
over log q. Evaluated one q at a time that is 25-40 filter runs over the window, each
mostly numpy's per-call overhead on a few hundred rows. Here the filter runs once for a
whole vector of q values: every numpy call of a step advances all of them, so a grid of
a few hundred values costs about what two or three single runs cost.

:class:`WindowLikelihood` is that batched filter for the presets whose q the node can
suggest and whose measurement is the position alone (train, car, car-exact,
cv-position): states [position, velocity], F = [[1, dt], [0, 1]], H = [1, 0], the
preset's own Q(dt) and B(dt) u plus q·[[dt³/3, dt²/2], [dt²/2, dt]], started as the node
starts (``first_measurement``: the first row sets the position with variance R, the
velocity comes from the preset's initial state with σ = first_velocity_std_mps). The
update is the Joseph form for this optimal gain, reduced entry by entry as
:func:`kf_train.filters.closed_form.correct` does. Its ℓ equals the one-q likelihood to
rounding (tested).
"""

import math
from typing import Optional

from kf_train.batch.noise_likelihood import is_constant_velocity, LOG_2PI, measured_states
from kf_train.filters import white_noise_integrals
from kf_train.presets import Preset
import numpy as np


def batched(preset: Preset) -> bool:
    """Return whether :class:`WindowLikelihood` runs ``preset`` (else: one q at a time)."""
    return (preset.linear and is_constant_velocity(preset) and preset.dim_z == 1
            and measured_states(preset) == (0,))


class WindowLikelihood:
    """ℓ(q) of one window for many q at once (see the module docstring)."""

    def __init__(self, preset: Preset, t_s: np.ndarray, z: np.ndarray,
                 u: Optional[np.ndarray], variance_m2: float, first_velocity_std_mps: float):
        """Take the window: times (N,) [s], positions (N,), controls (N, p) or None, R."""
        dt = np.diff(t_s)
        Q = preset.dynamics.Q_batch(dt)                      # the preset's own Q(dt)
        third, half, one = white_noise_integrals(dt)         # q·W(dt), W's entries
        self._Q = (Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 1])
        self._W = (third, half, one)
        self._dt = dt.tolist()
        self._z = z[1:].tolist()
        B = preset.dynamics.B_batch(dt)
        self._b = None if B is None else np.matmul(B, u[1:, :, None])[:, :, 0].T.tolist()
        self._r = float(variance_m2)
        self._x0 = (float(z[0]), float(preset.initial_state[1]))
        self._p11 = float(first_velocity_std_mps) ** 2
        self.rows = len(self._dt)
        """Innovations ℓ sums (the rows after the first)."""

    def log_likelihoods(self, q: np.ndarray) -> np.ndarray:
        """Return ℓ(q) for every q of ``q`` (G,): −½ Σ_k (log 2π + log s_k + y_k² / s_k)."""
        q = np.asarray(q, dtype=float)
        count, r = q.shape[0], self._r
        # Every row's noise for every q at once: Q_k + q W_k (rows, G).
        noise = [base[:, None] + weight[:, None] * q for base, weight in zip(self._Q, self._W)]
        n00, n01, n11 = noise
        x0, x1 = np.full(count, self._x0[0]), np.full(count, self._x0[1])
        p00, p01, p11 = np.full(count, r), np.zeros(count), np.full(count, self._p11)
        S = np.empty((self.rows, count))
        Y = np.empty((self.rows, count))
        b = self._b
        for k, dt in enumerate(self._dt):
            x0 += dt * x1                                    # x⁻ = F x (+ B u)
            if b is not None:
                x0 += b[0][k]
                x1 += b[1][k]
            a = p01 + dt * p11                               # P⁻ = F P Fᵀ + Q + q W
            m00 = p00 + dt * (p01 + a) + n00[k]
            m01 = a + n01[k]
            m11 = p11 + n11[k]
            s = np.add(m00, r, out=S[k])                     # s = H P⁻ Hᵀ + R
            y = np.subtract(self._z[k], x0, out=Y[k])        # y = z - H x⁻
            k0, k1, keep = m00 / s, m01 / s, r / s           # K = P⁻ Hᵀ / s; 1 - k0
            x0 += k0 * y                                     # x = x⁻ + K y
            x1 += k1 * y
            # Joseph form for this optimal K, H = [1, 0] (closed_form.correct):
            p00, p01, p11 = keep * m00, keep * m01, m11 - k1 * m01
        total = np.log(S).sum(axis=0) + (Y * Y / S).sum(axis=0)
        return -0.5 * (self.rows * LOG_2PI + total)


def smallest_finite(values: np.ndarray) -> int:
    """Return the index of the smallest finite value (the first of equals)."""
    return int(np.argmin(np.where(np.isfinite(values), values, math.inf)))


FINE = 1e-2
"""Spacing of the fine grids in log q: the one-q search's tolerance (golden section and
bisection to 1e-2), so the answers agree to about that."""
COARSE = math.log(10.0) / 4.0
"""Spacing of the first grid over the whole range: a quarter decade."""


def _fine(a: float, b: float) -> np.ndarray:
    """Return a grid from a to b (a <= b) with spacing at most FINE."""
    return np.linspace(a, b, max(int(math.ceil((b - a) / FINE)), 2) + 1)


def grid_search(nll, low: float, high: float, threshold: float, z: float):
    """
    Return (q, low_q, high_q) of the window, or None where the grids cannot decide.

    ``nll(v)`` is −ℓ at log q for a vector v (:meth:`WindowLikelihood.log_likelihoods`
    negated). The search is that of the one-q path (:mod:`~kf_train.batch.noise_suggestion`)
    on grids instead of one q at a time:

    1. a quarter-decade grid over [low, high] (both ends on it);
    2. one batch of two fine grids (spacing FINE): the two coarse steps around the
       coarse minimum (where the golden section searches), and the two coarse steps up
       to where −ℓ first rises ``threshold`` above the coarse minimum (where the
       likelihood-ratio bound is);
    3. v̂ is the fine minimum (within FINE/2 of the true one, the golden section's
       within 1e-2); q = 0 is not rejected when −ℓ(low) − −ℓ(v̂) <= threshold, and then
       the upper bound is where −ℓ − −ℓ(v̂) crosses ``threshold`` (linear between the
       two fine points around it), else the Wald interval v̂ ± z σ with σ⁻² the
       central difference of −ℓ over the fine points beside v̂ (spacing h <= FINE, as
       the one-q path's h = 1e-2).

    None when the crossing is not within the fine grid (−ℓ(v̂) is then more than the
    coarse minimum minus its dip between coarse points) or v̂ is at a fine grid's end:
    the caller then searches one q at a time.
    """
    coarse = np.linspace(low, high, max(int(math.ceil((high - low) / COARSE)), 2) + 1)
    values = nll(coarse)
    best = smallest_finite(values)
    last = coarse.size - 1
    around = _fine(coarse[max(best - 1, 0)], coarse[min(best + 1, last)])
    rises = np.flatnonzero(values[best:] - values[best] > threshold)
    upper = None
    if rises.size:
        c = best + int(rises[0])
        upper = _fine(coarse[max(c - 2, best)], coarse[c])
    fine = nll(around if upper is None else np.concatenate((around, upper)))
    inner = fine[:around.size]
    j = smallest_finite(inner)
    v_hat, f_hat = float(around[j]), float(inner[j])
    drop_at_zero = float(values[0]) - f_hat
    if drop_at_zero <= threshold:                     # q = 0 not rejected: [0, LR bound]
        q = 0.0 if drop_at_zero <= 1e-3 else math.exp(v_hat)
        if float(values[-1]) - f_hat <= threshold:
            return q, 0.0, math.inf
        if upper is None:
            return None
        excess = fine[around.size:] - f_hat - threshold
        above = np.flatnonzero((excess > 0.0) & (upper > v_hat))
        if above.size == 0 or above[0] == 0 or not excess[above[0] - 1] <= 0.0:
            return None
        i = int(above[0])
        v0, v1, e0, e1 = upper[i - 1], upper[i], excess[i - 1], excess[i]
        return q, 0.0, math.exp(float(v0 + (v1 - v0) * (-e0) / (e1 - e0)))
    if j == 0 or j == inner.size - 1:
        return None
    h = float(around[1] - around[0])              # curvature of −ℓ in log q
    curvature = (float(inner[j + 1]) - 2.0 * f_hat + float(inner[j - 1])) / h ** 2
    sigma = 1.0 / math.sqrt(curvature) if curvature > 0.0 else math.inf
    return math.exp(v_hat), math.exp(v_hat - z * sigma), math.exp(v_hat + z * sigma)
