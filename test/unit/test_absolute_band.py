"""The band about the truth: P plus the receiver's unseen slow error (covariance_reference)."""

from kf_train.estimator import EstimatorSettings, SEED_SWITCH, StreamEstimator
from kf_train.presets.rail import RAIL_PRESET_PATH
from kf_train.ros.estimator_params import load_estimator_config
from kf_train.ros.param_spec import ParameterError
from kf_train.ros.session import EstimatorSession, Measurement
import numpy as np
import pytest
import yaml

NS = 1_000_000_000


def _fixes(estimator: StreamEstimator, count: int, variance_m2=4.0, first=0):
    """Fuse ``count`` fixes of a train at 10 m/s, 0.2 s apart; return the last step."""
    rng = np.random.default_rng(first)
    step = None
    for k in range(first, first + count):
        variance = variance_m2(k) if callable(variance_m2) else variance_m2
        step = estimator.process((k + 1) * NS // 5, 2.0 * k + 0.05 * rng.standard_normal(),
                                 variance)
    return step


def test_b_is_the_scale_times_the_newest_variance_given():
    """B = absolute_error_scale (6) × the newest fused fix's variance; 0 before one."""
    estimator = StreamEstimator(EstimatorSettings())
    assert estimator.receiver_error_variance_m2() == 0.0
    _fixes(estimator, 20, variance_m2=lambda k: 1.0 + k)
    assert estimator.receiver_error_variance_m2() == pytest.approx(6.0 * 20.0, rel=1e-15)
    estimator.reset()
    assert estimator.receiver_error_variance_m2() == 0.0


def test_absolute_adds_b_to_both_position_variances_only():
    """absolute(step): P_pp and the prediction's P_pp grow by B; all else is the step's."""
    estimator = StreamEstimator(EstimatorSettings())
    step = _fixes(estimator, 30)
    B = estimator.receiver_error_variance_m2()
    assert B == 24.0
    band = estimator.absolute(step)
    for name in ('P', 'predicted_P'):
        expected = getattr(step, name).copy()
        expected[0, 0] += B
        np.testing.assert_array_equal(getattr(band, name), expected)
    np.testing.assert_array_equal(band.x, step.x)
    np.testing.assert_array_equal(band.predicted_x, step.predicted_x)
    assert band.stamp_ns == step.stamp_ns and band.update is step.update
    # The filter itself is untouched.
    np.testing.assert_array_equal(estimator.state[1], step.P)


def test_a_white_noise_preset_has_no_b(tmp_path):
    """The seed's train preset and a rail preset with scale 0: the band is P itself."""
    seed = StreamEstimator(EstimatorSettings(**SEED_SWITCH))
    step = _fixes(seed, 10)
    assert seed.receiver_error_variance_m2() == 0.0 and seed.absolute(step) is step
    with open(RAIL_PRESET_PATH) as stream:
        data = yaml.safe_load(stream)
    data['parameters']['absolute_error_scale'] = 0.0
    path = tmp_path / 'rail.yaml'
    path.write_text(yaml.safe_dump(data))
    rail = StreamEstimator(EstimatorSettings(preset=str(path)))
    step = _fixes(rail, 10)
    assert rail.receiver_error_variance_m2() == 0.0 and rail.absolute(step) is step


def test_the_session_publishes_the_band_the_parameter_asks_for():
    """covariance_reference absolute: the node's steps carry P + B; receiver: P."""
    sessions = {reference: EstimatorSession(load_estimator_config(
        [], [f'covariance_reference:={reference}']), lambda: 0.0)
        for reference in ('receiver', 'absolute')}
    published = {}
    for reference, session in sessions.items():
        for k in range(30):
            outputs = session.on_measurement(
                Measurement((k + 1) * NS // 5, 'odom', 2.0 * k, 4.0), (k + 1) * NS // 5)
        published[reference] = outputs.step
    receiver, absolute = published['receiver'], published['absolute']
    B = sessions['absolute'].estimator.receiver_error_variance_m2()
    assert B == 24.0
    assert absolute.P[0, 0] == receiver.P[0, 0] + B
    assert absolute.predicted_P[0, 0] == receiver.predicted_P[0, 0] + B
    np.testing.assert_array_equal(absolute.P[1:, 1:], receiver.P[1:, 1:])
    # The state behind both is the same: only what is published differs.
    np.testing.assert_array_equal(sessions['absolute'].estimator.state[1],
                                  sessions['receiver'].estimator.state[1])


def test_an_unknown_reference_is_refused():
    """Only receiver and absolute: anything else is the node's parameter error."""
    with pytest.raises(ParameterError, match='covariance_reference'):
        load_estimator_config([], ['covariance_reference:=truth'])
