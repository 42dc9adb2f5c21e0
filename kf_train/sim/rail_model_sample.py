"""
Measurements drawn from the rail IMM's own model: data whose noises are known exactly.

The rail scenario (:mod:`kf_train.sim.rail`) drives a train as trains are driven:
its plateaus are constant and its ramps S-curves, so it has no "true" acceleration or
command noise of the IMM's kind. To check that ``kf-train tune`` finds noises the
data do carry (and that its intervals cover them), :func:`sample_rail_model` draws a
run from the model itself, with the rules the filter assumes:

* the regime switches at the model's rates; a regime of :data:`STOPPING` (accelerate,
  cruise, brake) switches to stand at stop_rate_hz times
  :func:`~kf_train.filters.stop_probability` of the true velocity (σ = 0: 1 below
  stop_speed_mps, else 0), the filter's own stop rule;
* a switch applies :meth:`RailModel.entry`'s transformation, and the state moves by the
  regime's F(dt) plus N(0, Q(dt));
* **a train does not reverse**: a step that would end with a velocity below 0 ends
  with the train stopped instead (v = 0, a no longer negative, p not behind where it
  was; the filter projects its estimates onto v >= 0,
  :func:`~kf_train.filters.hold_velocity`).
  Without this, a cruise's command noise can run a slow train backwards for minutes
  (seed 7 of the coverage benchmark: -9 m/s, 29 % of the run), data no rail filter
  is built for, and its fit lands far from the truth;
* the position is measured with σ = noise_std_m.
"""

import math

from kf_train.filters import RailModel, RailModelParameters, stop_probability, STOPPING
import numpy as np

_STAND = 0
_VELOCITY = 1
_ACCELERATION = 2


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
        if regime in STOPPING:                  # → stand only when slow (the filter's rule)
            r[_STAND] = params.stop_rate_hz * stop_probability(
                float(x[_VELOCITY]), 0.0, params.stop_speed_mps)
        if r.sum() > 0.0 and rng.random() < -math.expm1(-r.sum() * dt_s):
            regime = int(rng.choice(4, p=r / r.sum()))
            mean, cov = model.entry(regime, x, np.zeros((6, 6)))
            x = rng.multivariate_normal(mean, cov, method='eigh') if cov.any() else mean
        mode = model.modes[regime]
        Q = mode.Q(dt_s)
        before_m = x[0]
        x = mode.F(dt_s) @ x + (rng.multivariate_normal(np.zeros(6), Q, method='eigh')
                                if Q.any() else 0.0)
        if x[_VELOCITY] < 0.0:                  # no reversal: the train stops and holds
            x[0], x[_VELOCITY], x[_ACCELERATION] = max(x[0], before_m), 0.0, \
                max(x[_ACCELERATION], 0.0)
        z[k] = x[0] + rng.normal(0.0, params.noise_std_m)
    return np.arange(1, rows + 1) * dt_s, z
