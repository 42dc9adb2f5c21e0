"""
The measurement noise learned online: a scale on the reported variance, by recursive likelihood.

A GNSS receiver reports an accuracy (hAcc), and the variance a message carries is
built from it; but that figure describes the receiver's slow error, not what one fix
adds to the next: on real train logs the filter's NIS averages 0.05-0.08 when the
reported variance is used as R (docs/rail.md), and during a cold start a receiver
reports hAcc of hundreds of metres for fixes a few metres off. So R is not trusted as
given: the filter uses R = s·r, r the variance given to the update, and learns the
scale s from its own innovations.

For a scalar measurement the innovation y is N(0, S), S = h + s·r, h = H P Hᵀ the
prediction's share. Its log-likelihood's derivative in log s (the score) and the
Fisher information are

    u = ½ a (y²/S - 1),    i = ½ a²,    a = s·r / S (R's share of S),

and s follows them by recursive Fisher scoring in log s (Ljung and Söderström 1983):

    J ← (1 - 1/window) J + i,    log s ← log s + u / J.

When the innovations are far smaller than S, log s falls by up to 1/(a·window) a fix
once J is full, and faster at the start (J = the prior's information); an average of
y² − h (covariance matching, Mehra 1972, this module's rule until 2026-11-28) falls by
e per window only once the large lessons of a cold start or of the prior have been
forgotten: it kept the node's R at hAcc²/4 through a simulated cold start whose fixes
were a few metres off for an hAcc of hundreds (the 2-s prediction 70 m behind), and
took 400 fixes to reach its floor on a clean real log (docs/real-logs.md). Each fix's
lesson is weighed by its own information, so a fix whose S is mostly the prediction's
(the first fixes, after a gap) teaches little, and the size of r does not matter: a
cold start's hAcc of a kilometre says nothing about s until its fixes show it.

Robust to the gross fixes the gate lets through: a lesson's NIS is taken as at most
``CLIP_NIS`` (3σ; divided by E[min(χ²₁, CLIP_NIS)] so that the right s stays the
fixed point), and one step moves log s by at most ``STEP_MAX``. The prior is s = 1
(R as reported) with the information of ``prior`` fixes whose S is all R. s stays
within [scale_min, scale_max], so no run of lucky or unlucky innovations can make the
filter ignore its measurements or believe one fix exactly.

Only fused measurements teach s (a gated-out fix never reaches the update that
adapts), and the whole adaptation is three numbers of the filter's state
(:class:`NoiseScale`), so rewinding to an old state rewinds it too, and a replay
repeats it bit for bit.
"""

from dataclasses import dataclass
import math
from typing import NamedTuple, TypeVar

from kf_train.filters.chi2 import chi2_cdf, chi2_sf
import numpy as np

Variance = TypeVar('Variance', np.ndarray, float)
"""A variance given to an update: R's row (1,) or a float [m²]."""


class NoiseScale(NamedTuple):
    """The learned measurement noise: the scale in use, what taught it, the error's walk."""

    scale: float = 1.0
    """s: the measurement noise in use is s times the variance given (1: as given)."""
    information: float = 0.0
    """J: the forgetting sum of the fixes' Fisher information about log s (0: none yet)."""
    count: int = 0
    """How many measurements have taught it (up to the window: then it stays there)."""
    walk_m2_per_s: float = 0.0
    """
    The rail model's error walk since the last fused fix, c · s r [m²/s] (0: none;
    :mod:`~kf_train.filters.error_walk`).
    """
    walk_gain: float = 0.0
    """log(c / c₀): the walk's rate c as learned, against the rate it starts at."""
    last_nu: float = 0.0
    """The last fused fix's normalised innovation y/√S, clipped (0: none yet)."""


FIXED = NoiseScale()
"""The state of a filter that does not adapt: R as given."""
CLIP_NIS = 9.0
"""A lesson's NIS is taken as at most this: one gross fix raises s by a bounded step."""
CLIPPED_NIS_MEAN = chi2_cdf(CLIP_NIS, 3) + CLIP_NIS * chi2_sf(CLIP_NIS, 1)
"""E[min(X, CLIP_NIS)], X ~ χ²₁ (= P(χ²₃ <= c) + c P(χ²₁ > c)): 0.9950."""
STEP_MAX = 0.2
"""The largest step of log s for one fix (s changes by at most 22 % a fix)."""


@dataclass(frozen=True)
class NoiseAdaptation:
    """How the scale is learned; see the module docstring."""

    window: int = 100
    """The averages' memory [measurements]; 0 turns the adaptation off."""
    prior: int = 1
    """
    Weight of the prior s = 1, as a number of measurements.

    One: the first fixes decide. A receiver's reported accuracy overstates what a fix
    adds to the next by ~20× (hAcc 2 m for a white part under 0.1 m on real u-blox
    logs, docs/real-logs.md), and through a cold start by more, so R as reported is a
    weak guess. A prior of 10 fixes held s at 0.024 after 20 s of a simulated cold
    start whose fixes called for 10⁻³, and the 2-s prediction 28 m behind a departing
    train (benchmarks/receiver_eval.py, metro 1: 2.23 m against 1.46 m with 1).
    """
    scale_min: float = 1e-5
    """
    Lower bound of s.

    Low enough for a smooth receiver: tp-lib's clean Belgian logs (R given as 3 m²)
    scatter by about 1 cm about a smooth path, s ~ 10⁻⁵, and a floor of 10⁻³ held their
    2-s prediction at 1.1-1.7× a hindsight-tuned CA, 0.9-1.2× with 10⁻⁵
    (docs/real-logs.md, "A floor of 10⁻⁵ on the learned scale").
    """
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
        S = innovation_variance_m2
        share = state.scale * reported_m2 / S                     # a = s r / S
        nis = min(innovation_m * innovation_m / S, CLIP_NIS)
        score = 0.5 * share * (nis / CLIPPED_NIS_MEAN - 1.0)      # u = ½ a (y²/S - 1)
        # The prior, s = 1, as the information of ``prior`` fixes whose S is all R.
        information = state.information if state.count else 0.5 * self.prior
        information = information * (1.0 - 1.0 / self.window) + 0.5 * share * share
        step = min(max(score / information, -STEP_MAX), STEP_MAX)  # log s += u / J
        scale = min(max(state.scale * math.exp(step), self.scale_min), self.scale_max)
        return state._replace(scale=scale, information=information,
                              count=min(state.count + 1, self.window))
