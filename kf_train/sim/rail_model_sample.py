"""
Measurements drawn from the rail IMM's own model: data whose noises are known exactly.

The rail scenario (:mod:`kf_train.sim.rail`) drives a train as trains are driven:
its plateaus are constant and its ramps S-curves, so it has no "true" acceleration or
command noise of the IMM's kind. To check that ``kf-train tune`` finds noises the
data do carry (and that its intervals cover them), :func:`sample_rail_model` draws a
run from the model itself: the regime switches at the model's rates (brake → stand only
below stop_speed), a switch applies :meth:`RailModel.entry`'s transformation, the state
moves by the regime's F(dt) plus N(0, Q(dt)), and the position is measured with
σ = noise_std_m.
"""

import math

from kf_train.filters import RailModel, RailModelParameters
import numpy as np


def sample_rail_model(params: RailModelParameters, rows: int, seed: int,
                      dt_s: float = 0.1) -> tuple:
    """Return (t_s (rows,), z (rows,)): a seeded run of the rail IMM's own model."""
    rng = np.random.default_rng(seed)
    model = RailModel(params)
    rates = params.rates()
    x = np.array([0.0, 0.0, 0.0, 0.0, params.accelerate_mps2, params.brake_mps2])
    regime, z = 0, np.empty(rows)
    for k in range(rows):
        r = rates[regime].copy()
        if regime == 3:                         # brake → stand only when slow
            r[0] = params.stop_rate_hz * float(x[1] <= params.stop_speed_mps)
        if r.sum() > 0.0 and rng.random() < -math.expm1(-r.sum() * dt_s):
            regime = int(rng.choice(4, p=r / r.sum()))
            mean, cov = model.entry(regime, x, np.zeros((6, 6)))
            x = rng.multivariate_normal(mean, cov, method='eigh') if cov.any() else mean
        mode = model.modes[regime]
        Q = mode.Q(dt_s)
        x = mode.F(dt_s) @ x + (rng.multivariate_normal(np.zeros(6), Q, method='eigh')
                                if Q.any() else 0.0)
        z[k] = x[0] + rng.normal(0.0, params.noise_std_m)
    return np.arange(1, rows + 1) * dt_s, z
