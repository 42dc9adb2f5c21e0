"""The stacked IMM (kf_train.filters.imm_stack) against the original mode-by-mode algorithm."""

import dataclasses
import math

from imm_reference import ReferenceRailModel
from kf_train.filters.imm import IMM, IMMFilter
from kf_train.filters.rail_model import (
    hold_velocity, make_rail_filter, RailModel, RailModelParameters)
from kf_train.sim.rail import family_parameters, rail_scenario
import numpy as np
import pytest

HORIZON_S = 2.0
# The reference has no learned noise scale and no error walk (test/imm_reference.py).
FIXED_R = RailModelParameters(noise_window=0, error_walk_rate_hz=0.0)
UNIT_ROUNDOFF = 2.0 ** -53
# Roundings along the longest chain of one predict + update + 2-s prediction, per
# component (inner products and sums count as Higham's γ_m = m·u): the transition row
# (exp and a 4-term sum: 5), the mixing weights Π μ / c̄ (c̄ a 4-term sum: 6), the mixed
# mean and covariance (4-term sums of ω x and of ω (P + d dᵀ): 4 + 6), symmetrising (1),
# F P Fᵀ + Q (two 6-term inner products and the add: 13), symmetrising (1), the update
# (s, K, x + K y: 4; I - K H and the Joseph products (I - KH) P (I - KH)ᵀ + K R Kᵀ:
# 1 + 12 + 3; symmetrising: 1), the log-domain probabilities (log, exp, a 4-term sum: 6)
# and the outputs' mixture moments (4 + 6): c = 73. Each implementation is within c·u of
# exact arithmetic, so the two are within 2c·u of each other after one step. (The
# stacked mixing gathers the entering components exactly and leaves P0 unsymmetrised,
# F P0 Fᵀ + Q being symmetrised anyway: one rounding fewer, so c bounds it still.)
PER_STEP = 2 * 73 * UNIT_ROUNDOFF
# Sensitivity of the compared outputs to a position error, per metre. The dominant
# error is positional: the innovation y = z - x cancels two numbers of size X (the
# positions, up to ~1e4 m), so a relative rounding ε becomes an absolute ε·X in y, in
# the corrections K y and in the spreads d = x_j - x between regimes. Means take it
# with gain 1. A probability μ_j = c̄_j Λ_j / Σ moves by μ_j (δL_j - Σ μ_k δL_k) with
# δL_k = y_k δx / s_k, at most 2 max_k μ_k |y_k| / s_k per metre (7.7 /m at most on
# these runs: a regime with a large innovation has a small probability). A covariance
# moves through Σ μ_j d_j d_jᵀ by 2 μ_j |d_j| per metre (0.8 m at most here).
# SENSITIVITY = 20 bounds all three with a margin.
SENSITIVITY = 20.0


def _tolerance(steps: int, positions_m: float, covariance: float = 0.0) -> float:
    """
    Return the largest difference allowed after k = ``steps`` steps.

    ``positions_m`` is X, the largest position so far; ``covariance`` the largest
    covariance entry so far (a covariance carries its own rounding, relative to it).

    Errors are assumed to add up step after step without damping: the filter does damp
    them in the observed directions, but the capabilities A, B (q = 1e-6) and a
    regime that lost all probability (its mean is a long running average) are nearly
    neutral, so k·PER_STEP is the bound after k steps, times X·SENSITIVITY (plus the
    covariances' own magnitude).
    A discrete choice that could flip on a rounding (the 1600-step bracket of a stop in
    the no-reversal prediction, when a grid velocity lies within 1e-13 m/s of 0) would
    exceed this; at grid spacing 1.25 ms and |a| ~ 1 m/s² that has a chance of ~1e-10
    per prediction, and none occurs in these runs.
    """
    return steps * PER_STEP * (positions_m * SENSITIVITY + covariance)


@pytest.fixture(scope='module')
def runs():
    """Return (family, seed, t, z) of a metro and a regional run, 240 s each."""
    cases = []
    for family, seed in (('metro', 12), ('regional', 11)):
        params = dataclasses.replace(family_parameters(family, seed), duration_s=240.0)
        scenario, _ = rail_scenario(seed, family, parameters=params)
        cases.append((family, seed, scenario.t_s, scenario.z[:, 0]))
    return cases


def _differences(new, old, z_m, dts=None):
    """Yield (step, {name: |new - old|}, tolerance) along a run of both models."""
    sn, so = new.first_estimate(z_m[0]), old.first_estimate(z_m[0])
    scale, spread = abs(z_m[0]), float(np.max(so.covariances))
    for k in range(1, z_m.size):
        dt = 0.1 if dts is None else float(dts[k])
        sn, so = new.predict(sn, dt), old.predict(so, dt)
        sn, rn = new.update(sn, float(z_m[k]))
        so, ro = old.update(so, float(z_m[k]))
        xn, Pn = new.estimate(sn)
        xo, Po = old.estimate(so)
        an, An = new.predict_ahead(sn, HORIZON_S)
        ao, Ao = old.predict_ahead(so, HORIZON_S)
        mu = so.probabilities
        scale = max(scale, abs(float(z_m[k])), float(np.max(np.abs(so.means))),
                    abs(float(ao[0])))
        spread = max(spread, float(np.max(so.covariances)), float(np.max(Ao)))
        # A regime with probability 1e-200 cannot move anything: weigh per-mode
        # estimates by their probability (the mixture moments do the same).
        yield k, {
            'mode means': np.max(mu[:, None] * np.abs(sn.means - so.means)),
            'mode covariances': np.max(mu[:, None, None] *
                                       np.abs(sn.covariances - so.covariances)),
            'probabilities': np.max(np.abs(sn.probabilities - so.probabilities)),
            'mean': np.max(np.abs(xn - xo)), 'covariance': np.max(np.abs(Pn - Po)),
            '2-s mean': np.max(np.abs(an - ao)), '2-s covariance': np.max(np.abs(An - Ao)),
            'NIS': abs(rn.nis - ro.nis), 'S': abs(rn.innovation_covariance[0, 0] -
                                                  ro.innovation_covariance[0, 0]),
            'gain': np.max(np.abs(rn.gain - ro.gain)),
        }, _tolerance(k, scale, spread)


def test_the_rail_imm_equals_the_original_algorithm(runs):
    largest = {}
    for family, seed, _, z in runs:
        for k, differences, tolerance in _differences(RailModel(FIXED_R), ReferenceRailModel(), z):
            for name, value in differences.items():
                assert value <= tolerance, (family, seed, k, name, value, tolerance)
                largest[name] = max(largest.get(name, 0.0), value / tolerance)
    # The runs went through every regime, so every path of the stack was exercised.
    assert len(largest) == 10


def test_jittered_stamps_equal_the_original_algorithm(runs):
    # A new dt at every step (a sensor's stamp jitter, ±5 ms): the rail model's own F(dt),
    # Q(dt) (power series) and Π(dt) (floats) against the reference's (quadrature, the
    # stack's checked path). Q differs by ~1e-15 of ‖Q‖, far inside the rounding bound.
    dts = 0.1 + np.random.default_rng(3).uniform(-0.005, 0.005, size=2400)
    for family, seed, _, z in runs:
        for k, differences, tolerance in _differences(RailModel(FIXED_R), ReferenceRailModel(), z,
                                                      dts):
            for name, value in differences.items():
                assert value <= tolerance, (family, seed, k, name, value, tolerance)


def test_the_generic_paths_equal_the_rail_models_own(runs):
    # The same regimes through the generic IMM: its own transition check, the entry hook
    # component by component, and (wrapped) each mode's own predict and update.
    rail = RailModel(FIXED_R)

    class Wrapped:
        """A mode the stack does not recognise: the IMM calls its predict and update."""

        def __init__(self, mode):
            self.mode = mode

        def predict(self, x, P, dt_s, u=None):
            return self.mode.predict(x, P, dt_s, u)

        def update(self, x, P, z, R=None):
            return self.mode.update(x, P, z, R)

    stacked_generic = IMM(rail.modes, rail.transition, rail.mode_names, rail.entry)
    mode_by_mode = IMM([Wrapped(mode) for mode in rail.modes], rail.transition,
                       rail.mode_names, rail.entry)
    assert stacked_generic._stack is not None and mode_by_mode._stack is None
    _, _, _, z = runs[0]
    states = [rail.first_estimate(z[0])] * 3
    models = (rail, stacked_generic, mode_by_mode)
    scale = abs(z[0])
    for k in range(1, 600):
        states = [m.predict(s, 0.1) for m, s in zip(models, states)]
        steps = [m.update(s, float(z[k])) for m, s in zip(models, states)]
        # The rail model's own update adds the no-reversal projection (its one rule).
        states = [steps[0][0]] + [state._replace(means=hold_velocity(state.means,
                                                                     state.covariances))
                                  for state, _ in steps[1:]]
        scale = max(scale, float(np.max(np.abs(states[0].means))))
        tolerance = _tolerance(k, scale)
        for state, (_, result) in zip(states[1:], steps[1:]):
            np.testing.assert_allclose(state.means, states[0].means, rtol=0, atol=tolerance)
            np.testing.assert_allclose(state.covariances, states[0].covariances, rtol=0,
                                       atol=tolerance)
            np.testing.assert_allclose(state.probabilities, states[0].probabilities, rtol=0,
                                       atol=tolerance)
            assert result.nis == pytest.approx(steps[0][1].nis, abs=tolerance)


def test_an_unreachable_mode_keeps_its_estimate():
    # c̄_stand = 0 (no probability, -> stand impossible at a sure speed): the stand
    # regime keeps its own estimate, and its probability stays exactly 0.
    model = RailModel()
    state = model.first_estimate(0.0)
    state = state._replace(probabilities=np.array([0.0, 0.5, 0.5, 0.0]))
    means = np.array(state.means)
    means[:, 1] = 20.0
    covariances = np.array(state.covariances)
    covariances[:, 1, :] = covariances[:, :, 1] = 0.0   # surely at 20 m/s: no slow regime
    state = state._replace(means=means, covariances=covariances)
    predicted = model.predict(state, 0.1)
    assert predicted.probabilities[0] == 0.0
    assert np.all(np.isfinite(predicted.means)) and np.all(np.isfinite(predicted.covariances))
    assert math.isclose(predicted.probabilities.sum(), 1.0)


def test_overflow_and_bad_inputs_raise_and_leave_the_filter_alone():
    filt = make_rail_filter(0.0)
    filt.predict(0.1)
    filt.update(0.1)
    kept = filt.snapshot()
    for bad in (1e300, float('nan'), -1.0, 'x'):
        with pytest.raises(ValueError):
            filt.predict(bad)
        assert filt.snapshot() is kept
    for bad_z, bad_R in ((np.array([1.0, 2.0]), None), (1.0, np.array([[-1.0]])),
                         (1.0, np.array([[float('nan')]])), (float('inf'), None)):
        with pytest.raises(ValueError):
            filt.update(bad_z, bad_R)
        assert filt.snapshot() is kept
    with pytest.raises(ValueError):
        filt.predict_ahead(float('inf'))
    assert isinstance(filt, IMMFilter)
