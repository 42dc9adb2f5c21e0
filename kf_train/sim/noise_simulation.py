"""
A train driven by white-noise acceleration: data with known q and R, for tuning.

The seed's train (:mod:`kf_train.sim.simulation`) moves at a constant velocity: its
process noise is zero, so it cannot show whether a noise estimator finds a q > 0.
Here the truth is the very model the filters assume with
``process_noise_density`` = q: over each step of dt,

    x_k = F(dt) x_{k−1} + w_k,   w_k ~ N(0, q·[[dt³/3, dt²/2], [dt²/2, dt]]),
    z_k = x_k[0] + v_k,          v_k ~ N(0, σ²),

which is exactly what the velocity of a train does under a random (white) force,
integrated over the step. The rows come as a :class:`~kf_train.sim.scenarios.Scenario`
(times, measurements, truth), ready for a preset with [position, velocity] states.
"""

from typing import Sequence

from kf_train.filters import as_finite_array, as_vector
from kf_train.sim.scenarios import Scenario
import numpy as np


def _positive(name: str, value, allow_zero: bool = True) -> float:
    """Return a finite scalar >= 0 (> 0 unless allow_zero), or raise naming it."""
    array = as_finite_array(name, value)
    if array.ndim != 0 or float(array) < 0.0 or (not allow_zero and float(array) == 0.0):
        raise ValueError(f'{name} must be a finite number {">=" if allow_zero else ">"} 0, '
                         f'got {value!r}')
    return float(array)


def white_noise_acceleration_scenario(q: float, noise_std_m: float, n_samples: int, *,
                                      dt_s: float = 0.1, seed: int = 0,
                                      initial_state: Sequence[float] = (0.0, 10.0),
                                      t0_s: float = 0.0) -> Scenario:
    """
    Return ``n_samples`` rows at t0_s + k·dt_s (k = 1..N) of a train under random force.

    ``q`` [m²/s³] is the white-noise acceleration density, ``noise_std_m`` the
    position measurement's σ [m]; the truth starts from ``initial_state`` [m, m/s]
    at ``t0_s``. Noise comes from ``numpy.random.default_rng(seed)``.
    """
    q = _positive('q', q)
    noise_std_m = _positive('noise_std_m', noise_std_m)
    dt_s = _positive('dt_s', dt_s, allow_zero=False)
    if not isinstance(n_samples, (int, np.integer)) or isinstance(n_samples, bool) \
            or n_samples < 1:
        raise ValueError(f'n_samples must be a positive integer, got {n_samples!r}')
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
    x0 = as_vector('initial_state', initial_state, 2)
    rng = np.random.default_rng(int(seed))
    # w_k = √q · L ε with L Lᵀ = [[dt³/3, dt²/2], [dt²/2, dt]] (Cholesky), ε ~ N(0, I)
    L = np.linalg.cholesky(np.array([[dt_s ** 3 / 3.0, dt_s ** 2 / 2.0],
                                     [dt_s ** 2 / 2.0, dt_s]]))
    w = np.sqrt(q) * (rng.standard_normal((n_samples, 2)) @ L.T)
    velocity = x0[1] + np.cumsum(w[:, 1])                       # v_k = v_{k−1} + w_k[1]
    previous_velocity = np.concatenate([[x0[1]], velocity[:-1]])
    position = x0[0] + np.cumsum(dt_s * previous_velocity + w[:, 0])  # p_k = p + dt·v + w[0]
    z = position + noise_std_m * rng.standard_normal(n_samples)
    t = float(t0_s) + np.arange(1, n_samples + 1) * dt_s
    return Scenario('white-noise-acceleration', float(t0_s), t, z[:, None], None,
                    np.column_stack([position, velocity]), x0.copy(),
                    ('position', 'velocity'), ('position',))
