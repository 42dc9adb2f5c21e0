"""
Seed 000's non-Kalman velocity baselines and the straight-line extrapolation.

The seed keeps its buffers with the prior at index 0 (t = 0) and sample k at index k:
the raw velocity is ``[0, diff([0, z1, …, zN]) / dt]`` (the first position taken as
0) and its running average is MATLAB's ``filter(ones(1, 5) / 5, 1, v)``, a causal
moving average that treats the values before the start as zero.
"""

from kf_train.filters import as_duration, as_vector
import numpy as np


def raw_difference_velocity(measured_position_m, dt_s: float,
                            first_position_m: float = 0.0) -> np.ndarray:
    """Return [0, (z1 - x0)/dt, (z2 - z1)/dt, …]: N + 1 values for N measurements."""
    z = as_vector('measured_position_m', measured_position_m)
    dt_s = as_duration('dt_s', dt_s)
    if dt_s == 0.0:
        raise ValueError('dt_s must be > 0')
    buffer = np.concatenate(([first_position_m], z))
    return np.concatenate(([0.0], np.diff(buffer) / dt_s))


def running_average(values, window: int = 5) -> np.ndarray:
    """Return MATLAB's filter(ones(1, w)/w, 1, values): zeros before the start."""
    v = as_vector('values', values)
    if not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f'window must be a positive integer, got {window!r}')
    if v.shape[0] == 0:
        return v  # 'valid' below would give |(w - 1) - w| + 1 = 2 values, not 0
    padded = np.concatenate((np.zeros(window - 1), v))
    sums = np.convolve(padded, np.ones(window), mode='valid')
    return sums / window


def extrapolate(position_m, velocity_mps, ahead_s):
    """Return position + velocity · ahead_s, elementwise."""
    return (np.asarray(position_m, dtype=float)
            + np.asarray(ahead_s, dtype=float) * np.asarray(velocity_mps, dtype=float))
