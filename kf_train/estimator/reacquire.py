"""
Re-acquisition after a lock-out: from a consistent group of fixes, never from one fix.

``max_consecutive_outliers`` gate rejections in a row mean the track and the data
disagree. Either the track is wrong (a manoeuvre the model missed, a long gap, a
restarted sensor), and the rejected fixes then agree with each other; or the fixes
are wrong (a burst of multipath jumps, a receiver artefact), and they scatter. Only
the first is a reason to start again: the rejected fixes are then one group, and the
filter restarts from all of them (:meth:`kf_train.estimator.fusion.Fusion.measure`),
so no single gross fix can seed the new track. Scattered fixes are rejected and the
track coasts on.

By default (``lockout`` reacquire) the track is kept: a real run is one track from
start to end, through gaps, cold starts and receiver artefacts. The track is widened
by the jump between it and the group's line (:func:`jump_covariance`) and the group
fused into it, so the regimes, the learned noise scale and the capabilities survive.
``lockout`` reset forgets the track and starts again from the group.

A group is consistent when a straight line p(t) = a + b t fits its positions within
their variances: the weighted residuals' χ² (N - 2 degrees of freedom) is within the
gate's own quantile (``gate_probability``). Over the few seconds of a group a
train's motion is a line to well within a metre; a burst of 200-m jumps is not.
"""

from typing import NamedTuple, Optional, Sequence

from kf_train.filters import chi2_quantile
import numpy as np


class LineFit(NamedTuple):
    """A weighted straight line p(t) = position_m + velocity_mps (t - the last stamp)."""

    position_m: float
    """The line at the group's last stamp."""
    velocity_mps: float
    covariance: np.ndarray
    """Of (position_m, velocity_mps), from the fixes' variances (2, 2)."""
    chi2: float
    """Σ r² / σ² of the residuals (N - 2 degrees of freedom)."""


def fit_line(stamps_ns: Sequence[int], positions_m: Sequence[float],
             variances_m2: Sequence[float]) -> LineFit:
    """Return the weighted least-squares line through >= 2 fixes (finite, variances > 0)."""
    t = (np.asarray(stamps_ns, dtype=np.int64) - int(stamps_ns[-1])) * 1e-9
    z = np.asarray(positions_m, dtype=float)
    w = 1.0 / np.asarray(variances_m2, dtype=float)
    design = np.stack([np.ones(t.size), t], axis=1)
    root = np.sqrt(w)
    coefficients = np.linalg.lstsq(design * root[:, None], z * root, rcond=None)[0]
    residual = z - design.dot(coefficients)
    # cov = (Aᵀ W A)⁻¹: the fit's own uncertainty at the last stamp.
    covariance = np.linalg.inv(design.T.dot(design * w[:, None]))
    return LineFit(float(coefficients[0]), float(coefficients[1]), covariance,
                   float(np.sum(w * residual * residual)))


def consistent_group(stamps_ns: Sequence[int], positions_m: Sequence[float],
                     variances_m2: Sequence[float], probability: float) -> bool:
    """Return whether a line fits the fixes within their variances (see the module docs)."""
    count = len(stamps_ns)
    if count < 3:
        return True  # a line fits two points exactly: nothing to tell them apart
    z = np.asarray(positions_m, dtype=float)
    variance = np.asarray(variances_m2, dtype=float)
    if not (np.all(np.isfinite(z)) and np.all(variance > 0.0) and np.all(np.isfinite(variance))):
        return False
    chi2 = fit_line(stamps_ns, z, variance).chi2
    return chi2 <= chi2_quantile(min(probability, 1.0 - 1e-12), count - 2)


def jump_covariance(state_names: Sequence[str], predicted_x: np.ndarray,
                    line: LineFit) -> Optional[np.ndarray]:
    """
    Return the covariance of the jump between a track and a group's line, or None.

    The track predicted to the group's last stamp misses the line by Δp in position
    and Δv in velocity. The jump is taken as zero-mean with variances Δp² plus the
    line's own variance (and likewise Δv²): large enough that the group decides where
    the train is and how fast it goes, no larger than the disagreement, so the rest
    of the track (acceleration, capabilities, regimes, learned noise) is kept. None
    when the model has no ``position`` state (nothing to widen).
    """
    names = list(state_names)
    if 'position' not in names:
        return None
    jump = np.zeros((len(names), len(names)))
    p = names.index('position')
    jump[p, p] = (line.position_m - predicted_x[p]) ** 2 + line.covariance[0, 0]
    if 'velocity' in names:
        v = names.index('velocity')
        jump[v, v] = (line.velocity_mps - predicted_x[v]) ** 2 + line.covariance[1, 1]
    return jump
