"""Tests of kf_train.filters.ekf: the range-bearing measurement, the wrap, and the EKF."""

import math

from filterpy.kalman import ExtendedKalmanFilter as FilterpyEKF
from kf_train.batch import run_series, SeriesError
from kf_train.filters import (
    ekf_update, ExtendedKalmanFilter, FunctionMeasurement, RangeBearing, wrap_angle)
from kf_train.presets import load_preset
from kf_train.sim import range_bearing_scenario
import numpy as np
import pytest


def test_wrap_angle_range_and_identity():
    """Angles in (−π, π] pass bit for bit; others land in (−π, π] on the same circle."""
    inside = np.array([0.0, 1e-300, -1e-300, 1.0, -1.0, math.pi, -math.pi + 1e-15, 3.0])
    np.testing.assert_array_equal(wrap_angle(inside), inside)
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(3 * math.pi) == pytest.approx(math.pi, abs=1e-15)
    rng = np.random.default_rng(0)
    a = rng.uniform(-1e3, 1e3, 10000)
    w = wrap_angle(a)
    assert np.all((w > -math.pi) & (w <= math.pi))
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)


def test_range_bearing_measurement_in_every_quadrant():
    """The bearing is atan2(y, x) (all quadrants), the range √(x² + y²), from the sensor."""
    m = RangeBearing()
    for x, y in [(3.0, 4.0), (-3.0, 4.0), (-3.0, -4.0), (3.0, -4.0), (-1.0, 0.0)]:
        z = m.h([x, 0.0, y, 0.0])
        assert z[0] == math.atan2(y, x)
        assert z[1] == 5.0 or z[1] == 1.0
    offset = RangeBearing(sensor_position_m=(1.0, 2.0))
    np.testing.assert_allclose(offset.h([4.0, 9.0, 6.0, 9.0]), [math.atan2(4, 3), 5.0])


def test_jacobian_matches_finite_differences():
    """The analytic Jacobian equals central differences, and is zero for velocities."""
    m = RangeBearing(sensor_position_m=(0.5, -1.0))
    rng = np.random.default_rng(1)
    for _ in range(20):
        x = rng.uniform(-50, 50, 4)
        H = m.jacobian(x)
        numeric = np.empty((2, 4))
        for j in range(4):
            step = np.zeros(4)
            step[j] = 1e-6 * max(1.0, abs(x[j]))
            diff = m.residual(m.h(x + step), m.h(x - step))  # wrapped across ±π
            numeric[:, j] = diff / (2 * step[j])
        np.testing.assert_allclose(H, numeric, rtol=1e-6, atol=1e-9)
        assert np.all(H[:, [1, 3]] == 0.0)


def test_range_jacobian_is_guarded_near_the_sensor():
    """Within min_range_m of the sensor the Jacobian raises a clear ValueError."""
    m = RangeBearing(min_range_m=1e-3)
    m.h([0.0, 0.0, 0.0, 0.0])  # the measurement itself is defined
    with pytest.raises(ValueError, match='undefined at the sensor.*min_range_m = 0.001'):
        m.jacobian([1e-4, 0.0, -2e-4, 0.0])
    m.jacobian([1e-3, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match='min_range_m must be > 0'):
        RangeBearing(min_range_m=0.0)
    with pytest.raises(ValueError, match='x_index and y_index must differ'):
        RangeBearing(x_index=1, y_index=1)


def test_bearing_residual_is_wrapped():
    """A target just across the ±π cut gives a small residual, not ≈ 2π."""
    m = RangeBearing()
    y = m.residual([math.pi - 0.01, 10.0], [-math.pi + 0.01, 10.0])
    assert y[0] == pytest.approx(-0.02, abs=1e-12)
    x = np.array([-10.0, 0.0, -0.05, 0.0])   # bearing ≈ −π + 0.005
    P = np.diag([1.0, 1.0, 1.0, 1.0])
    z = np.array([math.pi - 0.005, 10.0])    # just across the cut
    x_new, _, result = ekf_update(x, P, z, m, np.diag([1e-4, 1.0]))
    assert abs(result.innovation[0]) < 0.02
    assert np.linalg.norm(x_new - x) < 0.2  # no 2π jump dragging the state around


def _filterpy_run(x0, P0, F, Q, R, zs, measurement):
    """Run filterpy's ExtendedKalmanFilter with the same measurement and wrap."""
    ekf = FilterpyEKF(dim_x=4, dim_z=2)
    ekf.x = x0.reshape(-1, 1).copy()
    ekf.P = P0.copy()
    ekf.F, ekf.Q, ekf.R = F, Q, R

    def residual(a, b):
        return measurement.residual(a.ravel(), b.ravel()).reshape(-1, 1)

    xs, Ps = [], []
    for z in zs:
        ekf.predict()
        ekf.update(z.reshape(-1, 1), lambda x: measurement.jacobian(x.ravel()),
                   lambda x: measurement.h(x.ravel()).reshape(-1, 1), residual=residual)
        xs.append(ekf.x[:, 0].copy())
        Ps.append(ekf.P.copy())
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_range_bearing_preset_matches_filterpy_ekf(seed):
    """The range-bearing preset equals filterpy's ExtendedKalmanFilter to 1e-9."""
    preset = load_preset('range-bearing')
    s = range_bearing_scenario(seed)
    dt = preset.nominal_period_s
    xs, Ps = _filterpy_run(preset.initial_state, preset.initial_covariance,
                           preset.dynamics.F(dt), preset.dynamics.Q(dt), preset.model.R,
                           s.z, preset.model.measurement)
    result = run_series(preset, s.t_s, s.z)
    np.testing.assert_allclose(result.x, xs, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(result.P, Ps, rtol=0.0, atol=1e-9 * np.max(np.abs(Ps)))


def test_ekf_across_the_branch_cut_matches_filterpy():
    """A target crossing the negative x-axis: both wrap, both agree, the track holds."""
    m = RangeBearing()
    dt = 0.5
    F = np.eye(4) + dt * np.diag([1.0, 0.0, 1.0], k=1)
    Q = np.diag([0.0, 1e-3, 0.0, 1e-3])
    R = np.diag([1e-4, 0.01])
    rng = np.random.default_rng(3)
    truth = np.array([-40.0, 0.0, 5.0, -1.0])  # moves from y = 5 to y = −5 at x = −40
    zs, states = [], []
    for _ in range(20):
        truth = F @ truth
        states.append(truth)
        zs.append(m.h(truth) + np.sqrt(np.diag(R)) * rng.standard_normal(2))
    zs = np.array(zs)
    assert np.any(zs[:, 0] > 3.0) and np.any(zs[:, 0] < -3.0)  # both sides of ±π
    x0, P0 = np.array([-40.0, 0.0, 5.0, -1.0]), np.diag([1.0, 0.1, 1.0, 0.1])
    xs, Ps = _filterpy_run(x0, P0, F, Q, R, zs, m)
    ekf = ExtendedKalmanFilter(x0, P0)
    ours = []
    for z in zs:
        ekf.predict(F, Q)
        ekf.update(z, m, R)
        ours.append(ekf.x)
    np.testing.assert_allclose(np.array(ours), xs, rtol=0.0, atol=1e-9)
    errors = np.linalg.norm((np.array(ours) - np.array(states))[:, [0, 2]], axis=1)
    assert np.max(errors) < 1.0


def test_rejected_update_leaves_the_filter_unchanged():
    """An update at the sensor raises and the EKF keeps its state."""
    ekf = ExtendedKalmanFilter([0.0, 0.0, 0.0, 0.0], np.eye(4))
    before = ekf.x, ekf.P
    with pytest.raises(ValueError, match='undefined at the sensor'):
        ekf.update([0.0, 1.0], RangeBearing(), np.eye(2))
    with pytest.raises(ValueError, match='z must have length 2'):
        ekf.update([0.0], RangeBearing(), np.eye(2))
    np.testing.assert_array_equal(ekf.x, before[0])
    np.testing.assert_array_equal(ekf.P, before[1])


def test_series_error_names_the_row():
    """A filter whose prediction reaches the sensor fails at that row, by index."""
    preset = load_preset('range-bearing')
    t = np.array([0.2, 0.4])
    z = np.array([[0.9, 57.0], [0.9, 57.0]])
    assert run_series(preset, t, z).x.shape == (2, 4)
    with pytest.raises(SeriesError) as error:
        run_series(preset, t, z, x0=[0.0, 0.0, 0.0, 0.0])
    assert error.value.row == 0
    assert 'undefined at the sensor' in error.value.reason


def test_function_measurement_is_a_linear_ekf():
    """With h(x) = H x the EKF update equals the linear Kalman update."""
    from kf_train.filters.kalman import update
    H = np.array([[1.0, 0.5]])
    m = FunctionMeasurement(lambda x: H @ x, lambda x: H, ['position'])
    x, P, R = np.array([1.0, 2.0]), np.array([[2.0, 0.3], [0.3, 1.0]]), np.array([[0.5]])
    a = ekf_update(x, P, [3.0], m, R)
    b = update(x, P, [3.0], H, R)
    np.testing.assert_allclose(a[0], b[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(a[1], b[1], rtol=0, atol=1e-15)
    assert a[2].nis == pytest.approx(b[2].nis, rel=1e-14)
