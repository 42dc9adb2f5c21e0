"""The regime values of the estimator's /diagnostics status (kf_train.ros.diagnostics)."""

from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.ros.diagnostics import (
    Activity, filter_status, NodeCounts, regime_names, regime_values)
from kf_train.sim import rail_scenario
import numpy as np
import pytest

NS = 1_000_000_000


def _status_values(estimator):
    """Return the status values of ``estimator`` as a dict."""
    status = filter_status(estimator, NodeCounts(0, 0, 0, 0, 0, 0),
                           Activity(10.0, 10.0, 0.1, True), 5.0, [])
    return dict(status.values)


def test_rail_status_shows_the_likeliest_regime_and_every_probability():
    """Before a measurement: unknown; then each regime's probability and the likeliest."""
    estimator = StreamEstimator(EstimatorSettings(preset='rail'))
    names = ('stand', 'accelerate', 'cruise', 'brake')
    assert regime_names(estimator) == names
    assert regime_values(estimator) == [('regime', 'unknown')]
    scenario, _ = rail_scenario(4, 'metro')
    for t_s, z_m in zip(scenario.t_s[:300], scenario.z[:300, 0]):
        estimator.process(round(t_s * NS), float(z_m), 1.0)
    _, probabilities = estimator.mode_probabilities()
    values = _status_values(estimator)
    assert values['regime'] == names[int(np.argmax(probabilities))]
    shown = [float(values[f'regime.{name}']) for name in names]
    # Four decimals: each within 5e-5 of the probability, the sum within 4 × 5e-5 of 1.
    assert np.all(np.abs(np.array(shown) - probabilities) <= 5e-5)
    assert abs(sum(shown) - 1.0) <= 2e-4
    # What the model learned about the receiver, to 4 significant digits.
    assert float(values['measurement_noise_scale']) == \
        pytest.approx(estimator.noise_scale(), rel=5e-4)
    assert float(values['measurement_error_walk_rate_hz']) == \
        pytest.approx(estimator.error_walk_rate_hz(), rel=5e-4)


def test_a_model_without_regimes_adds_no_values():
    """The train's KF: no regime key at all."""
    estimator = StreamEstimator(EstimatorSettings(preset='train'))
    estimator.process(NS, 1.0, 1.0)
    assert regime_names(estimator) == () and regime_values(estimator) == []
    values = _status_values(estimator)
    assert not [key for key in values if key.startswith(('regime', 'measurement_'))]
