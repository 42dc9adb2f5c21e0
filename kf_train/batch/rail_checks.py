"""
Is a rail noise setting right for the data? The node's own filter, run row by row.

:func:`rail_check` runs the rail preset with a setting through
:class:`~kf_train.batch.RailSeriesFilter` (the replay's filter, equal bit for bit to the
streaming estimator without a gate, started by each segment's first measurement) and
returns what ``kf-train tune --preset rail`` prints before and after tuning:

* the mixture innovations y_k and their variances S_k (the moment-matched ones the
  node publishes on ``innovation``), for the mean-NIS and whiteness checks of
  :func:`kf_train.batch.nis_consistency`. An IMM's predicted measurement is a mixture,
  not a Gaussian, but E[y²] = S still holds when the model is right, so the mean NIS
  has expectation 1 and its χ² bounds are the check's yardstick (docs/rail.md: 0.98
  on the Monte-Carlo runs of the tests);
* where the truth is known, the error of the prediction ``horizon_s`` ahead (the
  node's ``prediction``: :meth:`RailModel.predict_ahead`) against the truth at
  t + horizon_s, interpolated between truth rows, and the share of those errors
  within ±2σ of the predicted position.
"""

import math
from typing import NamedTuple, Optional, Sequence

from kf_train.batch.noise_checks import errors_against_truth
from kf_train.batch.noise_likelihood import Innovations, Segment
from kf_train.batch.rail_series import RailSeriesFilter
from kf_train.presets import RailPreset
import numpy as np


class RailPrediction(NamedTuple):
    """Errors of the prediction horizon_s ahead against the truth."""

    horizon_s: float
    count: int
    rmse: dict
    """Root-mean-square error per state with truth (position, velocity)."""
    coverage: float
    """Share of position errors within ±2σ of the predicted position."""


class RailCheck(NamedTuple):
    """One setting's innovations and, with truth, its prediction errors."""

    innovations: Innovations
    prediction: Optional[RailPrediction]


def _run(preset: RailPreset, segment: Segment, variance_m2: float, horizon_s: float):
    """Return (y, S, predicted x (N, 6), predicted position variance (N,)) of a segment."""
    rows = segment.t_s.shape[0]
    f = RailSeriesFilter(preset)
    R = np.array([[variance_m2]])
    ys, Ss = np.zeros(max(rows - 1, 0)), np.zeros(max(rows - 1, 0))
    ahead_x, ahead_var = np.zeros((rows, preset.dim_x)), np.zeros(rows)
    for k in range(rows):
        if k:
            f.predict(float(segment.t_s[k] - segment.t_s[k - 1]))
        result = f.update(segment.z[k], R)
        if result is not None:
            ys[k - 1] = float(result.innovation[0])
            Ss[k - 1] = float(result.innovation_covariance[0, 0])
        if horizon_s > 0.0:
            x, P = f.predict_ahead(horizon_s)
            ahead_x[k], ahead_var[k] = x, P[0, 0]
    return ys, Ss, ahead_x, ahead_var


def rail_check(preset: RailPreset, segments: Sequence[Segment], variance_m2: float,
               horizon_s: float = 0.0) -> RailCheck:
    """Return the innovations and (with truth and ``horizon_s`` > 0) the prediction errors."""
    names = preset.state_names[:2]                       # position, velocity
    ys, Ss = [], []
    squares, counts = np.zeros(2), np.zeros(2, dtype=np.int64)
    covered = compared = 0
    for segment in segments:
        want = horizon_s > 0.0 and segment.truth is not None
        y, S, ahead_x, ahead_var = _run(preset, segment, variance_m2, horizon_s if want else 0.0)
        ys.append(y)
        Ss.append(S)
        if not want:
            continue
        target = segment.t_s + horizon_s
        for i in range(2):
            error, inside = errors_against_truth(segment.t_s, segment.truth[:, i], target,
                                                 ahead_x[:, i])
            squares[i] += float(np.sum(error * error))
            counts[i] += int(error.size)
            if i == 0:
                # |e| <= 2σ of the predicted position
                covered += int(np.count_nonzero(error * error <= 4.0 * ahead_var[inside]))
                compared += int(error.size)
    y, S = np.concatenate(ys), np.concatenate(Ss)
    innovations = Innovations(y[:, None], S[:, None, None])
    prediction = None
    if compared:
        rmse = {name: math.sqrt(squares[i] / counts[i]) for i, name in enumerate(names)
                if counts[i]}
        prediction = RailPrediction(float(horizon_s), compared, rmse, covered / compared)
    return RailCheck(innovations, prediction)
