"""No regime's mean acceleration beyond a train's (rail_model.bound_acceleration)."""

from kf_train.filters import (
    bound_acceleration, FastRailModel, IMM, numba_available, RailModel, RailModelParameters)
from kf_train.filters.rail_model import ACCELERATION, ACCELERATION_LIMIT_MPS2
import numpy as np
import pytest


def _covariance(seed: int) -> np.ndarray:
    """Return a random well-conditioned 6 x 6 covariance."""
    A = np.random.default_rng(seed).normal(size=(6, 6))
    return A @ A.T + np.eye(6)


def test_the_bound_is_the_conditional_mean_at_the_limit():
    P = _covariance(4)
    x = np.random.default_rng(5).normal(size=6)
    for a, limit in ((9.0, ACCELERATION_LIMIT_MPS2), (-7.5, -ACCELERATION_LIMIT_MPS2)):
        x[ACCELERATION] = a
        bounded = bound_acceleration(x, P)
        # E[x | a = limit] = x + P[:, a] (limit - a) / P_aa
        expected = x + P[:, ACCELERATION] * (limit - a) / P[ACCELERATION, ACCELERATION]
        np.testing.assert_allclose(bounded, expected, rtol=1e-12, atol=1e-15)
        assert bounded[ACCELERATION] == limit
    x[ACCELERATION] = 2.9
    assert bound_acceleration(x, P) is x
    # Stacked (settings × regimes) equals one regime at a time.
    xs = np.random.default_rng(6).normal(scale=5.0, size=(3, 4, 6))
    stacked = bound_acceleration(xs, np.broadcast_to(P, (3, 4, 6, 6)))
    for k in range(3):
        for j in range(4):
            np.testing.assert_array_equal(stacked[k, j], bound_acceleration(xs[k, j], P))


def _after_a_jump(model):
    """Return (state before, the fix): a cruising train, 3 s unfused, a fix 60 m ahead."""
    state = model.first_estimate(0.0, 1.0)
    for k in range(1, 101):
        state = model.update(model.predict(state, 0.4), 20.0 * 0.4 * k, [[1.0]])[0]
    return model.predict(state, 3.2), 20.0 * 0.4 * 108 + 60.0


def test_a_jump_read_as_motion_is_bounded():
    # A receiver's along-track jump after seconds without a fix (the case of a real
    # log): without the bound the regimes nearest the fix take a > 4 m/s² here, and
    # took 14 m/s² on that log.
    model = RailModel(RailModelParameters(noise_window=0))
    state, z = _after_a_jump(model)
    unbounded, _ = IMM.update(model, state, z, [[1.0]])     # the update before the holds
    assert np.max(np.abs(unbounded.means[:, ACCELERATION])) > ACCELERATION_LIMIT_MPS2 + 1.0
    updated, _ = model.update(state, z, [[1.0]])
    assert np.all(np.abs(updated.means[:, ACCELERATION]) <= ACCELERATION_LIMIT_MPS2)
    assert np.any(np.abs(updated.means[:, ACCELERATION]) == ACCELERATION_LIMIT_MPS2)
    # Position and velocity moved with it: the bounded mean is no longer at the fix.
    beyond = np.abs(unbounded.means[:, ACCELERATION]) > ACCELERATION_LIMIT_MPS2
    assert np.all(updated.means[beyond, 1] < unbounded.means[beyond, 1])


@pytest.mark.skipif(not numba_available(), reason='numba is not installed')
def test_the_compiled_bound_is_the_reference_s():
    parameters = RailModelParameters(noise_window=0)
    reference, fast = RailModel(parameters), FastRailModel(parameters)
    state, z = _after_a_jump(reference)
    ours, theirs = fast.update(state, z, [[1.0]])[0], reference.update(state, z, [[1.0]])[0]
    at_limit = np.abs(theirs.means[:, ACCELERATION]) == ACCELERATION_LIMIT_MPS2
    assert at_limit.any()
    np.testing.assert_array_equal(ours.means[at_limit, ACCELERATION],
                                  theirs.means[at_limit, ACCELERATION])
    scale = np.max(np.abs(theirs.means))
    assert np.max(np.abs(ours.means - theirs.means)) <= 1e-9 * scale
    ours = fast.predict_update(reference.predict(state, 0.0), 0.0, z, [[1.0]])[0]
    assert np.max(np.abs(ours.means - theirs.means)) <= 1e-9 * scale
