"""
The receiver's slow error as a random walk of the measured position, its rate learned online.

A GNSS receiver filters its own output, so its error is slow, not white: a fix repeats
most of the last one's error (on real u-blox logs the error moves by ~0.29 m over 2 s
while the white part is under 0.1 m, docs/real-logs.md). A filter that averages such
fixes as if their errors were independent holds a standing train where its first fixes
put it while the error moves on, and reads one step of the error at a stop as a
departure. So the rail model lets the measured position walk: after a fused fix
weighed with R = s r (the R in use), every regime's position variance grows by

    P_pp += c · s r · dt,

c [1/s] the walk's rate. Scaled by the R in use, the walk is the error's own size
whatever the receiver. But how much of the error is slow differs between receivers: on
white errors any walk costs accuracy (c = 2 took the simulated white runs' 2-s RMSE
from 0.76 to 1.18 m), on a receiver's filtered error it is the largest gain measured
(0.83-1.61 m to 0.60-1.05 m). So c is learned, from the one thing that tells: the
innovations of an optimal filter are white, a filter that under-models a slow error
leaves them positively correlated from fix to fix, one that over-models it negatively.
With ν_k = y_k / √S_k (clipped at ±3),

    log c ← log c + η ν_k ν_{k-1},

a stochastic-gradient step on E[ν_k ν_{k-1}] = 0, c within [rate_min_hz, rate_max_hz].
The walk after a fix uses c as learned before it (``walk_after``): the fix's own lesson
applies from the next one, so a step's prediction ahead is known before its update.

The learned figures are three numbers of the filter's state (the walk fields of
:class:`~kf_train.filters.noise_adaptation.NoiseScale`), so rewinding the state rewinds
them and a replay repeats them bit for bit; only fused position fixes teach them.
"""

from dataclasses import dataclass
from functools import cached_property
import math
from typing import Tuple

from kf_train.filters.noise_adaptation import NoiseScale
import numpy as np

NU_CLIP = 3.0
"""A lesson's normalised innovation is taken as at most this (3σ): outliers teach little."""


@dataclass(frozen=True)
class ErrorWalk:
    """How the walk's rate is learned; see the module docstring."""

    rate_hz: float = 0.01
    """c at the start [1/s]; 0 turns the walk off (the error is white)."""
    learning_rate: float = 0.02
    """η: the step of log c per unit product of successive normalised innovations."""
    rate_min_hz: float = 1e-3
    """Lower bound of c [1/s]."""
    rate_max_hz: float = 3.0
    """Upper bound of c [1/s]."""

    def __post_init__(self):
        """Check the figures: finite, >= 0, 0 < rate_min_hz <= rate_hz <= rate_max_hz."""
        for name in ('rate_hz', 'learning_rate', 'rate_min_hz', 'rate_max_hz'):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    not math.isfinite(value) or value < 0.0:
                raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
        if self.enabled and not 0.0 < self.rate_min_hz <= self.rate_hz <= self.rate_max_hz:
            raise ValueError(f'0 < rate_min_hz <= rate_hz <= rate_max_hz must hold, got '
                             f'{self.rate_min_hz}, {self.rate_hz} and {self.rate_max_hz}')

    @property
    def enabled(self) -> bool:
        """Return whether the position walks at all (rate_hz > 0)."""
        return self.rate_hz > 0.0

    @cached_property
    def bounds(self) -> Tuple[float, float]:
        """Return the bounds of the learned log(c / rate_hz), the state's ``walk_gain``."""
        return (math.log(self.rate_min_hz / self.rate_hz),
                math.log(self.rate_max_hz / self.rate_hz))

    def rate(self, noise: NoiseScale) -> float:
        """Return c, the walk's rate as learned so far [1/s]."""
        return self.rate_hz * math.exp(noise.walk_gain)

    def walk_after(self, noise: NoiseScale, in_use_m2: float) -> float:
        """Return the walk after a fix weighed with R = ``in_use_m2``: c · s r [m²/s]."""
        return self.rate(noise) * in_use_m2 if self.enabled else 0.0

    def learn(self, noise: NoiseScale, innovation_m: float, innovation_variance_m2: float,
              in_use_m2: float) -> NoiseScale:
        """
        Return ``noise`` after a fused position fix: the walk from it, and c's lesson.

        ``innovation_m`` y and ``innovation_variance_m2`` S are the update's, made with
        R = ``in_use_m2``.
        """
        if not self.enabled:
            return noise
        nu = min(max(innovation_m / math.sqrt(innovation_variance_m2), -NU_CLIP), NU_CLIP)
        low, high = self.bounds
        gain = min(max(noise.walk_gain + self.learning_rate * nu * noise.last_nu, low), high)
        # A new tuple, not _replace: this runs at every fix (1.7 against 0.5 µs).
        return NoiseScale(noise.scale, noise.information, noise.count,
                          self.walk_after(noise, in_use_m2), gain, nu)


def position_walked(covariances: np.ndarray, dt_s, walk_m2_per_s) -> np.ndarray:
    """
    Return ``covariances`` (..., n, n) with the walk over dt_s on the position: P_pp += w dt.

    ``dt_s`` and ``walk_m2_per_s`` floats, or arrays broadcasting against
    ``covariances[..., 0, 0]`` (the tuner's settings, each its own); ``covariances``
    itself when nothing walks.
    """
    step = np.multiply(walk_m2_per_s, dt_s)
    if not np.any(step):
        return covariances
    result = np.array(covariances, dtype=float)
    result[..., 0, 0] += step                                       # P_pp += c s r dt
    return result
