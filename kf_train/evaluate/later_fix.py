"""
The 2-s prediction scored against the later fix: for real logs, which have no truth.

A prediction made at a fix's stamp t for t + horizon is compared with the fix at
t + horizon: the one within :data:`MATCH_TOLERANCE_S` of it, else the straight line
between the two fixes around it, when those are at most :data:`MAX_BRACKET_S` apart
(a wider gap leaves the prediction unscored: the train may have done anything in
it). :func:`errors` gives each scored prediction's error and whether it lies inside
its 2σ band, and :func:`score` their RMSE and coverage, for the predictions made from
a warm-up on (or those a mask chooses), the band being the prediction's variance
plus the later fix's R (the fix is no truth: its own noise is part of the error).
"""

from typing import NamedTuple, Optional, Tuple, Union

from kf_train.sim import RAIL_HORIZON_S, RAIL_WARMUP_S
import numpy as np

MAX_BRACKET_S = 1.0
"""The widest fix pair [s] a later fix is interpolated in."""
MATCH_TOLERANCE_S = 1e-3
"""A fix this close [s] to t + horizon is the later fix itself."""


class LaterFixScore(NamedTuple):
    """The predictions' RMSE [m] and 2σ coverage against the later fix, and their count."""

    rmse_m: float
    coverage: float
    count: int


def _bracket(t: np.ndarray, horizon_s: float) -> Tuple[np.ndarray, ...]:
    """Return (left, right, weight of right, exact, valid) (N,) of the fix at t + horizon."""
    goal = t + horizon_s
    right = np.searchsorted(t, goal - MATCH_TOLERANCE_S)
    valid = right < t.size
    right = np.minimum(right, t.size - 1)
    exact = valid & (np.abs(t[right] - goal) <= MATCH_TOLERANCE_S)
    left = np.maximum(right - 1, 0)
    span = t[right] - t[left]
    inside = valid & ~exact & (right > 0) & (span <= MAX_BRACKET_S) & (t[right] >= goal)
    weight = np.where(inside, (goal - t[left]) / np.where(span > 0, span, 1.0), 0.0)
    return left, right, weight, exact, exact | inside


def _at_goal(values: np.ndarray, left: np.ndarray, right: np.ndarray, weight: np.ndarray,
             exact: np.ndarray) -> np.ndarray:
    """Return the values at t + horizon: the matched fix's, else interpolated."""
    return np.where(exact, values[right], values[left] + weight * (values[right] - values[left]))


def later_fix(t: np.ndarray, z: np.ndarray, horizon_s: float = RAIL_HORIZON_S
              ) -> Tuple[np.ndarray, np.ndarray]:
    """Return (target, valid) (N,): the fix at t + horizon, interpolated where need be."""
    t, z = np.asarray(t, dtype=float), np.asarray(z, dtype=float)
    left, right, weight, exact, valid = _bracket(t, horizon_s)
    return _at_goal(z, left, right, weight, exact), valid


class LaterFixErrors(NamedTuple):
    """The scored predictions' errors against the later fix, and which were inside the band."""

    error_m: np.ndarray
    """(K,): prediction minus the later fix, of the scored predictions in order."""
    covered: np.ndarray
    """(K,) bool: the error within 2σ (the prediction's variance plus the later fix's R)."""
    scored: np.ndarray
    """(N,) bool: which predictions were scored (made as asked, a later fix to score them)."""

    def summary(self) -> LaterFixScore:
        """Return the RMSE, 2σ coverage and count (NaN figures when none is scored)."""
        count = int(self.error_m.size)
        if not count:
            return LaterFixScore(float('nan'), float('nan'), 0)
        return LaterFixScore(float(np.sqrt(np.mean(self.error_m ** 2))),
                             float(np.mean(self.covered)), count)


def errors(t: np.ndarray, z: np.ndarray, mean: np.ndarray, variance: np.ndarray,
           r_m2: Union[float, np.ndarray], made: Optional[np.ndarray] = None,
           horizon_s: float = RAIL_HORIZON_S) -> LaterFixErrors:
    """
    Return the errors of the predictions against the later fix, and their 2σ band's verdict.

    ``mean``, ``variance`` (N,): the prediction made at each fix for t + horizon;
    ``r_m2``: the fixes' variance (one, or (N,): the later fix's, interpolated as the
    fix is); ``made`` (N,) bool: which predictions to score (default: those made from
    RAIL_WARMUP_S after the first fix on).
    """
    t = np.asarray(t, dtype=float)
    bracket = _bracket(t, horizon_s)
    valid = bracket[-1]
    target = _at_goal(np.asarray(z, dtype=float), *bracket[:-1])
    r_later = _at_goal(np.broadcast_to(np.asarray(r_m2, dtype=float), t.shape), *bracket[:-1])
    if made is None:
        made = t >= t[0] + RAIL_WARMUP_S
    scored = valid & made
    error = np.asarray(mean, dtype=float)[scored] - target[scored]
    band = 2.0 * np.sqrt(np.maximum(np.asarray(variance, dtype=float)[scored], 0.0)
                         + r_later[scored])
    return LaterFixErrors(error, np.abs(error) <= band, scored)


def score(t: np.ndarray, z: np.ndarray, mean: np.ndarray, variance: np.ndarray,
          r_m2: Union[float, np.ndarray], made: Optional[np.ndarray] = None,
          horizon_s: float = RAIL_HORIZON_S) -> LaterFixScore:
    """Return the RMSE, 2σ coverage and count of the predictions against the later fix."""
    return errors(t, z, mean, variance, r_m2, made, horizon_s).summary()
