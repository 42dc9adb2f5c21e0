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

A group is consistent when a straight line p(t) = a + b t fits its positions within
their variances: the weighted residuals' χ² (N - 2 degrees of freedom) is within the
gate's own quantile (``gate_probability``). Over the few seconds of a group a
train's motion is a line to well within a metre; a burst of 200-m jumps is not.
"""

from typing import Sequence

from kf_train.filters import chi2_quantile
import numpy as np


def consistent_group(stamps_ns: Sequence[int], positions_m: Sequence[float],
                     variances_m2: Sequence[float], probability: float) -> bool:
    """Return whether a line fits the fixes within their variances (see the module docs)."""
    count = len(stamps_ns)
    if count < 3:
        return True  # a line fits two points exactly: nothing to tell them apart
    t = (np.asarray(stamps_ns, dtype=np.int64) - int(stamps_ns[0])) * 1e-9
    z = np.asarray(positions_m, dtype=float)
    variance = np.asarray(variances_m2, dtype=float)
    if not (np.all(np.isfinite(z)) and np.all(variance > 0.0) and np.all(np.isfinite(variance))):
        return False
    w = 1.0 / variance
    design = np.stack([np.ones(count), t - np.average(t, weights=w)], axis=1)
    root = np.sqrt(w)
    coefficients = np.linalg.lstsq(design * root[:, None], z * root, rcond=None)[0]
    residual = z - design.dot(coefficients)
    chi2 = float(np.sum(w * residual * residual))          # Σ r² / σ²
    return chi2 <= chi2_quantile(min(probability, 1.0 - 1e-12), count - 2)
