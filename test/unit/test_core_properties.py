"""Property test: the filter keeps a valid covariance over long runs of random inputs."""

from hypothesis import given, settings, strategies as st
from kf_train.filters import constant_velocity_F, KalmanFilter, POSITION_H, WhiteNoiseAcceleration
import numpy as np
import pytest

STEPS_PER_EXAMPLE = 1000
EXAMPLES = 100  # 10⁵ predict/update steps in total


@pytest.mark.slow
@settings(max_examples=EXAMPLES, deadline=None, derandomize=True)
@given(
    dt_max=st.one_of(st.just(0.0), st.floats(0.0, 10.0)),
    jitter=st.booleans(),
    q=st.one_of(st.just(0.0), st.floats(0.0, 1e3)),
    log10_R=st.floats(-12.0, 12.0),
    log10_P0=st.floats(-6.0, 6.0),
    x0=st.tuples(st.floats(-1e3, 1e3), st.floats(-100.0, 100.0)),
    consistent=st.booleans(),
    seed=st.integers(0, 2 ** 32 - 1),
)
def test_covariance_stays_symmetric_psd(dt_max, jitter, q, log10_R, log10_P0, x0,
                                        consistent, seed):
    """
    P stays symmetric PSD and x finite for random CV models, noises and measurements.

    dt is dt_max or, with jitter, uniform in [0, dt_max] each step; R is log-uniform over
    [1e-12, 1e12]. The measurements are either drawn from the model itself or arbitrary
    values in ±1e4 m (a badly wrong model).
    """
    rng = np.random.default_rng(seed)
    R = 10.0 ** log10_R
    noise = WhiteNoiseAcceleration(q)
    kf = KalmanFilter(x0, 10.0 ** log10_P0 * np.eye(2))
    truth = np.array(x0, dtype=float)
    for _ in range(STEPS_PER_EXAMPLE):
        dt = dt_max * rng.uniform() if jitter else dt_max
        F, Q = constant_velocity_F(dt), noise(dt)
        if consistent:
            # Exact white-noise-acceleration increment: L Lᵀ = Q(dt).
            root = np.sqrt(q * dt)
            L = root * np.array([[dt / np.sqrt(3.0), 0.0], [np.sqrt(3.0) / 2.0, 0.5]])
            truth = F @ truth + L @ rng.standard_normal(2)
            z = truth[0] + np.sqrt(R) * rng.standard_normal()
        else:
            z = rng.uniform(-1e4, 1e4)
        kf.predict(F, Q)
        kf.update([z], POSITION_H, [[R]])
        x, P = kf.x, kf.P
        assert np.all(np.isfinite(x)), x
        assert np.all(np.isfinite(P)), P
        assert np.array_equal(P, P.T), P
        scale = np.max(np.abs(P))
        assert np.min(np.linalg.eigvalsh(P)) >= -1e-9 * scale, P
        assert P[0, 0] >= 0.0 and P[1, 1] >= 0.0, P
