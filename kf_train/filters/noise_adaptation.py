"""
The measurement noise learned online: a scale on the reported variance, by covariance matching.

A GNSS receiver reports an accuracy (hAcc), and the variance a message carries is
built from it; but that figure describes the receiver's slow error, not what one fix
adds to the next: on real train logs the filter's NIS averages 0.05-0.08 when the
reported variance is used as R (docs/rail.md). So R is not trusted as given: the
filter uses R = s·r, r the variance given to the update, and learns the scale s from
its own innovations (covariance matching, Mehra 1972; Myers and Tapley 1976).

For a scalar measurement the innovation y has variance S = h + s·r, h = H P Hᵀ the
prediction's share. So y² - h estimates s·r, and over a window

    s = Σ w_k (y_k² - h_k) / Σ w_k r_k,

the pooled ratio: a fix that reports a larger variance carries its share of it, so a
cold start with hAcc of a kilometre scales as much as it reports. Both sums are
exponentially weighted averages over ``window`` measurements; until that many have
been fused, each new one weighs 1/(count + prior) so the start adapts in tens of
fixes, not hundreds. The prior is s = 1 (R as reported) with the weight of ``prior``
measurements. s stays within [scale_min, scale_max], so no run of lucky or unlucky
innovations can make the filter ignore its measurements or believe one fix exactly.

Only fused measurements teach s (a gated-out fix never reaches the update that
adapts), and the whole adaptation is three floats of the filter's state
(:class:`NoiseScale`), so rewinding to an old state rewinds it too, and a replay
repeats it bit for bit.
"""

from dataclasses import dataclass
import math
from typing import NamedTuple, TypeVar

import numpy as np

Variance = TypeVar('Variance', np.ndarray, float)
"""A variance given to an update: R's row (1,) or a float [m²]."""


class NoiseScale(NamedTuple):
    """The adaptation's state: the scale in use and the two weighted averages behind it."""

    scale: float = 1.0
    """s: the measurement noise in use is s times the variance given (1: as given)."""
    excess_m2: float = 0.0
    """The weighted average of y² - h, the innovations' share not explained by P [m²]."""
    reported_m2: float = 0.0
    """The weighted average of the variances given, r [m²] (0: nothing fused yet)."""
    count: int = 0
    """How many measurements have taught it (up to the window: then it stays there)."""


FIXED = NoiseScale()
"""The state of a filter that does not adapt: R as given."""


@dataclass(frozen=True)
class NoiseAdaptation:
    """How the scale is learned; see the module docstring."""

    window: int = 100
    """The averages' memory [measurements]; 0 turns the adaptation off."""
    prior: int = 20
    """Weight of the prior s = 1, as a number of measurements."""
    scale_min: float = 1e-3
    """Lower bound of s."""
    scale_max: float = 100.0
    """Upper bound of s."""

    def __post_init__(self):
        """Check the figures: counts >= 0 (prior >= 1), 0 < scale_min <= 1 <= scale_max."""
        for name in ('window', 'prior'):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f'{name} must be an integer >= 0, got {value!r}')
        if self.prior < 1:
            raise ValueError(f'prior must be >= 1, got {self.prior}')
        for name in ('scale_min', 'scale_max'):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    not math.isfinite(value) or value <= 0.0:
                raise ValueError(f'{name} must be a finite number > 0, got {value!r}')
        if not self.scale_min <= 1.0 <= self.scale_max:
            raise ValueError(f'scale_min <= 1 <= scale_max must hold, got '
                             f'{self.scale_min} and {self.scale_max}')

    @property
    def enabled(self) -> bool:
        """Return whether the scale is learned at all (window > 0)."""
        return self.window > 0

    def learn(self, state: NoiseScale, innovation_m: float, innovation_variance_m2: float,
              reported_m2: float) -> NoiseScale:
        """
        Return the state after one fused measurement.

        ``innovation_m`` y and ``innovation_variance_m2`` S are the update's (S made
        with R = state.scale · ``reported_m2``); ``reported_m2`` is r, the variance given.
        """
        if not self.enabled or not reported_m2 > 0.0:
            return state
        h = innovation_variance_m2 - state.scale * reported_m2    # H P Hᵀ
        excess = innovation_m * innovation_m - h                  # y² - h: estimates s r
        if state.count == 0:
            # The prior, s = 1, as ``prior`` measurements of this variance.
            mean_excess, mean_reported, weight = reported_m2, reported_m2, self.prior
        else:
            mean_excess, mean_reported = state.excess_m2, state.reported_m2
            weight = min(state.count + self.prior, self.window)
        w = 1.0 / (weight + 1.0)
        mean_excess += w * (excess - mean_excess)                 # Σ w (y² - h) / Σ w
        mean_reported += w * (reported_m2 - mean_reported)        # Σ w r / Σ w
        scale = min(max(mean_excess / mean_reported, self.scale_min), self.scale_max)
        return NoiseScale(scale, mean_excess, mean_reported, min(state.count + 1, self.window))
