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
from typing import Dict, Optional, Tuple

from kf_train.batch.noise_likelihood import is_constant_velocity, LOG_2PI, measured_states
from kf_train.filters import white_noise_integrals
from kf_train.presets import Preset
import numpy as np


def batched(preset: Preset) -> bool:
    """Return whether :class:`WindowLikelihood` runs ``preset`` (else: one q at a time)."""
    return (preset.linear and is_constant_velocity(preset) and preset.dim_z == 1
            and measured_states(preset) == (0,))


class GainCache:
    """
    The covariance pass of earlier windows, per q, for windows that share it.

    The covariances, innovation variances s_k and gains of the filter do not depend on
    the measured values, only on the times, R, the starting variances and q. A node
    sampled at a fixed rate sees the same times in every window, and its grids repeat
    (the coarse grid whole, the fine grids mostly), so :class:`WindowLikelihood` takes
    s_k and the gains of a q computed for an earlier window instead of recomputing
    them: the same numbers from the same operations, so ℓ is bit for bit the same.
    Each batch is kept as computed; a q points into its batch. At most
    :data:`MAX_CACHED_Q` q are kept (then all are forgotten): memory stays bounded.
    """

    def __init__(self):
        """Start empty."""
        self.key: Optional[tuple] = None
        self.columns: Dict[float, Tuple[np.ndarray, np.ndarray, int]] = {}
        self.sums: Dict[bytes, np.ndarray] = {}

    def use(self, key: tuple) -> None:
        """Keep what was computed for windows of ``key`` only (forget it if another)."""
        if key != self.key or len(self.columns) > MAX_CACHED_Q or len(
                self.sums) > MAX_CACHED_GRIDS:
            self.key, self.columns, self.sums = key, {}, {}


MAX_CACHED_Q = 2048
"""q values whose covariance pass a :class:`GainCache` keeps (~7 kB each for 300 rows)."""
MAX_CACHED_GRIDS = 256
"""Grids whose Σ log s_k a :class:`GainCache` keeps (a grid seen again reuses it)."""


class WindowLikelihood:
    """ℓ(q) of one window for many q at once (see the module docstring)."""

    def __init__(self, preset: Preset, t_s: np.ndarray, z: np.ndarray,
                 u: Optional[np.ndarray], variance_m2: float, first_velocity_std_mps: float,
                 cache: Optional[GainCache] = None):
        """
        Take the window: times (N,) [s], positions (N,), controls (N, p) or None, R.

        ``cache`` (optional) holds the covariance pass of earlier windows of the same
        times, R and first velocity variance, reused for the q it has (bit for bit).
        """
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
        self._cache = cache
        if cache is not None:
            cache.use((np.concatenate((dt,) + self._Q + self._W).tobytes(), self._r,
                       self._p11))

    def log_likelihoods(self, q: np.ndarray) -> np.ndarray:
        """Return ℓ(q) for every q of ``q`` (G,): −½ Σ_k (log 2π + log s_k + y_k² / s_k)."""
        q = np.asarray(q, dtype=float)
        S, K = self._gains(q)
        Y = self._innovations(K)
        cache = self._cache
        key = q.tobytes()
        log_sum = None if cache is None else cache.sums.get(key)
        if log_sum is None:
            log_sum = np.log(S).sum(axis=0)
            if cache is not None:
                cache.sums[key] = log_sum
        total = log_sum + (Y * Y / S).sum(axis=0)
        return -0.5 * (self.rows * LOG_2PI + total)

    def _gains(self, q: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Return s_k (rows, G) and the gains K_k (rows, 2, G): cached or computed."""
        cache = self._cache
        if cache is None:
            return self._covariance_pass(q)
        columns = cache.columns
        values = q.tolist()
        found = [columns.get(v) for v in values]
        # Each q once (the fine grids of grid_search may share points).
        missing = list(dict.fromkeys(v for v, hit in zip(values, found) if hit is None))
        if missing:
            S, K = self._covariance_pass(np.array(missing))
            for i, v in enumerate(missing):
                columns[v] = (S, K, i)
            found = [columns[v] for v in values]
        first = found[0]
        if all(hit[0] is first[0] for hit in found) and [
                hit[2] for hit in found] == list(range(first[2], first[2] + len(found))):
            span = slice(first[2], first[2] + len(found))   # one batch, in order
            return (np.ascontiguousarray(first[0][:, span]),
                    np.ascontiguousarray(first[1][:, :, span]))
        S = np.empty((self.rows, q.size))
        K = np.empty((self.rows, 2, q.size))
        batches: Dict[int, list] = {}
        for j, hit in enumerate(found):
            batches.setdefault(id(hit[0]), []).append((j, hit))
        for group in batches.values():
            at = [j for j, _ in group]
            index = [hit[2] for _, hit in group]
            S[:, at] = group[0][1][0][:, index]
            K[:, :, at] = group[0][1][1][:, :, index]
        return S, K

    def _covariance_pass(self, q: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Return s_k (rows, G) and the gains K_k (rows, 2, G) of the filter for q (G,)."""
        count, r = q.shape[0], self._r
        # Every row's noise for every q at once: Q_k + q W_k (rows, G).
        noise = [base[:, None] + weight[:, None] * q for base, weight in zip(self._Q, self._W)]
        n00, n01, n11 = noise
        p00, p01, p11 = np.full(count, r), np.zeros(count), np.full(count, self._p11)
        S = np.empty((self.rows, count))
        K = np.empty((self.rows, 2, count))
        for k, dt in enumerate(self._dt):
            a = p01 + dt * p11                               # P⁻ = F P Fᵀ + Q + q W
            m00 = p00 + dt * (p01 + a) + n00[k]
            m01 = a + n01[k]
            m11 = p11 + n11[k]
            s = np.add(m00, r, out=S[k])                     # s = H P⁻ Hᵀ + R
            gain = K[k]
            np.divide(m00, s, out=gain[0])                   # K = P⁻ Hᵀ / s
            k1 = np.divide(m01, s, out=gain[1])
            keep = r / s                                     # 1 - k0
            # Joseph form for this optimal K, H = [1, 0] (closed_form.correct):
            p00, p01, p11 = keep * m00, keep * m01, m11 - k1 * m01
        return S, K

    def _innovations(self, K: np.ndarray) -> np.ndarray:
        """Return the innovations y_k (rows, G) of the window's data under the gains K."""
        count = K.shape[2]
        state = np.empty((2, count))
        x0, x1 = state
        x0.fill(self._x0[0])
        x1.fill(self._x0[1])
        Y = np.empty((self.rows, count))
        b = self._b
        for k, dt in enumerate(self._dt):
            x0 += dt * x1                                    # x⁻ = F x (+ B u)
            if b is not None:
                x0 += b[0][k]
                x1 += b[1][k]
            y = np.subtract(self._z[k], x0, out=Y[k])        # y = z - H x⁻
            state += K[k] * y                                # x = x⁻ + K y
        return Y


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
