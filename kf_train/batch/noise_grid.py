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

A run is two passes: the covariance pass (P, s_k and the gains, which do not depend on
the measured values) and the data pass (the means and innovations). A
:class:`GainCache` keeps the covariance passes of the q computed for earlier windows
of the same time steps, which a fixed-rate stream's windows share: a later window
runs the data pass alone for those q, and ℓ is bit for bit what it was without.
"""

import math
from typing import Dict, Optional, Tuple

from kf_train.filters import LOG_2PI, white_noise_integrals
from kf_train.presets import is_constant_velocity, measured_states, Preset
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
    s_k and the gains of the q computed for an earlier window (and Σ log s_k of a grid
    seen before) instead of recomputing them: the same numbers from the same
    operations, so ℓ is bit for bit the same. The store holds at most
    :data:`MAX_CACHED_VALUES` rows times q; when full, it is emptied.
    """

    def __init__(self):
        """Start empty."""
        self.key: Optional[tuple] = None
        self.capacity = 0
        """q the store holds, for the rows of the current key."""
        self._forget()

    def _forget(self) -> None:
        """Drop everything kept."""
        self.columns: Dict[float, int] = {}
        """q -> its column in the store."""
        self.log_sums: Dict[bytes, np.ndarray] = {}
        """A grid's bytes -> its Σ_k log s_k."""
        self._s: Optional[np.ndarray] = None
        self._k: Optional[np.ndarray] = None

    def use(self, key: tuple, rows: int) -> None:
        """Keep what was computed for windows of ``key`` only (forget it if another)."""
        if key != self.key:
            self.key = key
            self.capacity = max(MAX_CACHED_VALUES // max(rows, 1), 1)
            self._forget()
        if len(self.log_sums) > MAX_CACHED_GRIDS:
            self.log_sums = {}

    def missing(self, q: list) -> list:
        """Return the q (each once) to compute and :meth:`add`; empty the store if full."""
        columns = self.columns
        missing = list(dict.fromkeys(v for v in q if v not in columns))
        if len(columns) + len(missing) > self.capacity:
            self.columns = {}
            missing = list(dict.fromkeys(q))
        return missing

    def add(self, q: list, S: np.ndarray, K: np.ndarray) -> None:
        """Keep s_k (rows, G) and the gains (rows, 2, G) of the q (G values, new ones)."""
        if self._s is None:     # allocated once; its pages are touched as it fills
            self._s = np.empty((S.shape[0], self.capacity))
            self._k = np.empty((S.shape[0], 2, self.capacity))
        used, count = len(self.columns), len(q)
        self._s[:, used:used + count] = S
        self._k[:, :, used:used + count] = K
        self.columns.update(zip(q, range(used, used + count)))

    def take(self, q: list) -> Tuple[np.ndarray, np.ndarray]:
        """Return s_k (rows, G) and the gains (rows, 2, G) of q all kept."""
        columns = np.array([self.columns[v] for v in q])
        starts = np.flatnonzero(np.diff(columns) != 1) + 1
        if starts.size >= MAX_RUNS:          # scattered: gathered column by column
            return np.take(self._s, columns, axis=1), np.take(self._k, columns, axis=2)
        # A few runs of adjacent columns (grids computed together): copied as blocks.
        runs = [(int(columns[a]), int(columns[a]) + b - a) for a, b in zip(
            [0, *starts.tolist()], [*starts.tolist(), columns.size])]
        return (np.concatenate([self._s[:, a:b] for a, b in runs], axis=1),
                np.concatenate([self._k[:, :, a:b] for a, b in runs], axis=2))


MAX_CACHED_VALUES = 2 ** 20
"""Rows times q whose covariance pass a :class:`GainCache` keeps (24 bytes each: 24 MB;
a 10⁵-measurement replay of the train preset visits ~1500 q of its 300-row windows,
11 MB)."""
MAX_RUNS = 8
"""Up to this many runs of adjacent columns, :meth:`GainCache.take` copies blocks."""
MAX_CACHED_GRIDS = 1024
"""Grids whose Σ log s_k a :class:`GainCache` keeps (then forgets)."""


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
                       self._p11), self.rows)

    def log_likelihoods(self, q: np.ndarray) -> np.ndarray:
        """Return ℓ(q) for every q of ``q`` (G,): −½ Σ_k (log 2π + log s_k + y_k² / s_k)."""
        q = np.asarray(q, dtype=float)
        S, K = self._gains(q)
        Y = self._innovations(K)
        cache = self._cache
        log_sum = None if cache is None else cache.log_sums.get(q.tobytes())
        if log_sum is None:
            log_sum = np.log(S).sum(axis=0)
            if cache is not None:
                cache.log_sums[q.tobytes()] = log_sum
        total = log_sum + (Y * Y / S).sum(axis=0)
        return -0.5 * (self.rows * LOG_2PI + total)

    def _gains(self, q: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Return s_k (rows, G) and the gains K_k (rows, 2, G), reusing the q kept."""
        cache = self._cache
        if cache is None or q.size > cache.capacity:
            return self._covariance_pass(q)
        values = q.tolist()
        # Each q once (the fine grids of grid_search may share points).
        missing = cache.missing(values)
        if missing:
            cache.add(missing, *self._covariance_pass(np.array(missing)))
        return cache.take(values)

    def _covariance_pass(self, q: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Return s_k (rows, G) and the gains K_k (rows, 2, G) of the filter for q (G,)."""
        count, r = q.shape[0], self._r
        # Every row's noise for every q at once: Q_k + q W_k (rows, G).
        noise = [base[:, None] + weight[:, None] * q for base, weight in zip(self._Q, self._W)]
        n00, n01, n11 = noise
        p00, p01, p11 = np.full(count, r), np.zeros(count), np.full(count, self._p11)
        S = np.empty((self.rows, count))
        K = np.empty((self.rows, 2, count))
        # Scratch arrays written in place (no allocation per step); the operations and
        # their order are those of the formulas in the comments, so are the numbers.
        a, m00, m01, m11, keep = (np.empty(count) for _ in range(5))
        add, subtract, multiply, divide = np.add, np.subtract, np.multiply, np.divide
        for dt, s, gain, n00_k, n01_k, n11_k in zip(self._dt, S, K, n00, n01, n11):
            # P⁻ = F P Fᵀ + Q + q W: with a = p01 + dt p11, m00 = p00 + dt (p01 + a)
            # + n00, m01 = a + n01, m11 = p11 + n11.
            add(p01, multiply(p11, dt, a), a)
            add(p00, multiply(add(p01, a, m00), dt, m00), m00)
            add(m00, n00_k, m00)
            add(a, n01_k, m01)
            add(p11, n11_k, m11)
            add(m00, r, s)                                   # s = H P⁻ Hᵀ + R
            divide(m00, s, gain[0])                          # K = P⁻ Hᵀ / s
            k1 = divide(m01, s, gain[1])
            divide(r, s, keep)                               # 1 - k0
            # Joseph form for this optimal K, H = [1, 0] (closed_form.correct):
            # p00, p01, p11 = keep m00, keep m01, m11 - k1 m01.
            multiply(keep, m00, p00)
            multiply(keep, m01, p01)
            subtract(m11, multiply(k1, m01, p11), p11)
        return S, K

    def _innovations(self, K: np.ndarray) -> np.ndarray:
        """Return the innovations y_k (rows, G) of the window's data under the gains K."""
        count = K.shape[2]
        state = np.empty((2, count))
        x0, x1 = state
        x0.fill(self._x0[0])
        x1.fill(self._x0[1])
        Y = np.empty((self.rows, count))
        step, both = np.empty(count), np.empty((2, count))   # scratch: no allocations
        add, multiply, subtract = np.add, np.multiply, np.subtract
        b = self._b
        for k, (dt, z, y, gain) in enumerate(zip(self._dt, self._z, Y, K)):
            add(x0, multiply(x1, dt, step), x0)              # x⁻ = F x (+ B u)
            if b is not None:
                x0 += b[0][k]
                x1 += b[1][k]
            subtract(z, x0, y)                               # y = z - H x⁻
            add(state, multiply(gain, y, both), state)       # x = x⁻ + K y
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
