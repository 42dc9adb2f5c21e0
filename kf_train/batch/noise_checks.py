"""
Is a noise setting right for the data? Innovation consistency and prediction error.

When the filter's model is right its innovations y_k are independent with the
covariances S_k it computes (Bar-Shalom, Li & Kirubarajan 2001, §5.4):

* the NIS y_kᵀ S_k⁻¹ y_k is χ²(m) at every row, so the sum over K rows is χ²(K·m)
  and the mean NIS has the two-sided bounds of :func:`kf_train.filters.chi2_mean_bounds`;
  a mean above them says the filter's noise is too small, below them too large;
* the whitened innovations are white: their lag-1 autocorrelation is ≈ N(0, 1/K)
  (a q too small leaves the model's errors in the innovations, correlated in time).

Where the truth is known, :func:`prediction_errors` measures what a user sees: the
error of the prediction ``horizon_s`` ahead (2 s for the train), against the truth at
t + horizon_s (interpolated linearly between truth rows; rows whose t + horizon_s is
past the segment's last truth are left out).
"""

import math
from typing import Dict, NamedTuple, Optional, Tuple

from kf_train.batch.noise_likelihood import Innovations, NoiseSetting, TuningProblem
from kf_train.filters import chi2_mean_bounds, chi2_quantile
import numpy as np


class ConsistencyReport(NamedTuple):
    """The innovations of one setting against their χ² and whiteness bounds."""

    count: int
    """Innovations K."""
    dof: int
    """Measurement dimension m: each NIS is χ²(m)."""
    mean_nis: float
    low: float
    high: float
    """Two-sided bounds of the mean NIS at the report's confidence."""
    lag1: float
    """Lag-1 autocorrelation of the whitened innovations (mean over components)."""
    lag1_bound: float
    """|lag1| beyond this rejects whiteness at the same confidence (z/√(K·m))."""

    @property
    def verdict(self) -> str:
        """Return 'consistent', 'noise too small' (NIS too large) or 'noise too large'."""
        if self.mean_nis > self.high:
            return 'noise too small'
        if self.mean_nis < self.low:
            return 'noise too large'
        return 'consistent'

    @property
    def consistent(self) -> bool:
        """Return whether the mean NIS lies inside its bounds."""
        return self.verdict == 'consistent'

    @property
    def white(self) -> bool:
        """Return whether the lag-1 autocorrelation lies inside its bound."""
        return abs(self.lag1) <= self.lag1_bound


def whitened(innovations: Innovations) -> np.ndarray:
    """Return L_k⁻¹ y_k with L_k L_kᵀ = S_k: unit-variance, independent under the model."""
    y, S = innovations.y, innovations.S
    if y.shape[1] == 1:
        return y / np.sqrt(S[:, 0, :])
    L = np.linalg.cholesky(S)
    return np.linalg.solve(L, y[:, :, None])[..., 0]


def nis_consistency(innovations: Innovations, confidence: float = 0.99) -> ConsistencyReport:
    """Return the mean NIS and lag-1 whiteness of ``innovations`` with their bounds."""
    K, m = innovations.y.shape
    if K < 2:
        raise ValueError(f'need at least 2 innovations for a consistency check, got {K}')
    low, high = chi2_mean_bounds(K, m, confidence)
    e = whitened(innovations)
    # ρ₁ = Σ e_k e_{k+1} / Σ e_k² per component (about 0, sd 1/√K under the model)
    lag1 = float(np.mean(np.sum(e[1:] * e[:-1], axis=0) / np.sum(e * e, axis=0)))
    z = math.sqrt(chi2_quantile(confidence, 1))
    # Averaging m independent components divides the variance by m.
    return ConsistencyReport(K, m, float(np.mean(innovations.nis())), low, high, lag1,
                             z / math.sqrt(K * m))


class PredictionReport(NamedTuple):
    """Errors of the prediction horizon_s ahead against the truth."""

    horizon_s: float
    count: int
    """Predictions compared."""
    rmse: Dict[str, float]
    """Root-mean-square error per state with truth."""


def errors_against_truth(t_s: np.ndarray, truth: np.ndarray, target_s: np.ndarray,
                         predicted: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return (predicted − truth, the rows compared): truth interpolated at ``target_s``.

    Only targets inside the span of the known (finite) truth are compared.
    """
    known = np.isfinite(truth)
    t_known = t_s[known]
    if t_known.size < 1:
        return np.empty(0), np.zeros(target_s.shape, dtype=bool)
    inside = (target_s >= t_known[0]) & (target_s <= t_known[-1])
    return predicted[inside] - np.interp(target_s[inside], t_known, truth[known]), inside


def prediction_errors(problem: TuningProblem, setting: NoiseSetting,
                      horizon_s: float) -> Optional[PredictionReport]:
    """
    Return the RMSE of the predictions ``horizon_s`` ahead, or None without truth.

    Every filtered row's prediction (the node's ``prediction`` topic) is compared with
    the truth at t + horizon_s, interpolated between truth rows of its segment.
    """
    if not horizon_s > 0.0 or not math.isfinite(horizon_s):
        raise ValueError(f'horizon_s must be a finite number > 0, got {horizon_s!r}')
    names = problem.preset.state_names
    squares, counts = np.zeros(len(names)), np.zeros(len(names), dtype=np.int64)
    for segment, run in zip(problem.segments, problem.run(setting, horizon_s)):
        if segment.truth is None or run is None:
            continue
        result, first = run
        target = segment.t_s[first:] + horizon_s
        for i in range(len(names)):
            error, _ = errors_against_truth(segment.t_s, segment.truth[:, i], target,
                                            result.predicted_x[:, i])
            squares[i] += float(np.sum(error * error))
            counts[i] += int(error.size)
    if not np.any(counts):
        return None
    rmse = {name: math.sqrt(squares[i] / counts[i]) for i, name in enumerate(names)
            if counts[i]}
    return PredictionReport(float(horizon_s), int(counts.max()), rmse)
