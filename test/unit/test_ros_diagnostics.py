"""The estimator node's /diagnostics status, built without ROS (kf_train.ros.diagnostics)."""

import dataclasses
import math

from kf_train.estimator import (
    CONTROL_REJECTION_REASONS, NS_PER_S, REJECTION_REASONS, RESET_REASONS, StreamEstimator)
from kf_train.filters import chi2_mean_bounds
from kf_train.ros.diagnostics import (
    Activity, condition_number, CONSISTENCY_CONFIDENCE, filter_status, nis_bounds, NodeCounts)
from kf_train.ros.estimator_params import DEFAULTS
import numpy as np
import pytest

COUNTS = NodeCounts(received=7, fused=5, rejected=2, set_state_refused=1,
                    controls_received=0, controls_rejected=0)
# The node's defaults on the train's KF without a gate, as before issue 11 made the rail
# preset the default (its regime probabilities: the node's own tests).
TRAIN_NODE = dataclasses.replace(DEFAULTS, preset='train', gate_probability=1.0)
ACTIVE = Activity(input_rate_hz=10.0, fused_rate_hz=9.5, age_s=0.05, ever_fused=True)


def _estimator(updates=5, **settings):
    """Return an estimator of TRAIN_NODE after ``updates`` measurements at 10 Hz."""
    estimator = StreamEstimator(dataclasses.replace(TRAIN_NODE, **settings))
    for k in range(1, updates + 1):
        estimator.process(k * NS_PER_S // 10, 1.0 * k, 1.0)
    return estimator


def test_status_values_in_order():
    """Every value, in the order the node has always published them, formatted as then."""
    estimator = _estimator()
    status = filter_status(estimator, COUNTS, ACTIVE, 1.0, [1.0, 0.5])
    keys = [key for key, _ in status.values]
    assert keys == (
        ['preset', 'filter', 'initialized', 'input_rate_hz', 'fused_rate_hz',
         'last_measurement_age_s', 'received', 'fused', 'fused_out_of_sequence', 'rejected']
        + [f'rejected.{reason}' for reason in REJECTION_REASONS] + ['resets']
        + [f'resets.{reason}' for reason in RESET_REASONS]
        + ['reacquisitions', 'set_state_refused', 'gate_probability', 'gate_threshold',
           'nis_window_count', 'nis_window_mean', 'nis_lower_99', 'nis_upper_99',
           'covariance_condition'])
    values = dict(status.values)
    lower, upper = chi2_mean_bounds(2, 1, CONSISTENCY_CONFIDENCE)
    assert values['preset'] == 'train' and values['filter'] == 'kf'
    assert values['initialized'] == 'true'
    assert (values['input_rate_hz'], values['fused_rate_hz']) == ('10.000', '9.500')
    assert values['last_measurement_age_s'] == '0.050'
    assert (values['received'], values['fused'], values['rejected']) == ('7', '5', '2')
    assert values['nis_window_mean'] == '0.75'
    assert (values['nis_lower_99'], values['nis_upper_99']) == (f'{lower:.6g}', f'{upper:.6g}')
    assert values['gate_probability'] == '1' and values['gate_threshold'] == 'inf'
    assert (status.level, status.message, status.timeout_warning) == ('OK', 'ok', None)


def test_waiting_and_timed_out():
    """Before any measurement: waiting; past timeout_s without a fused one: WARN, once worded."""
    estimator = StreamEstimator(TRAIN_NODE)
    waiting = filter_status(estimator, NodeCounts(0, 0, 0, 0, 0, 0),
                            Activity(0.0, 0.0, 0.5, False), 1.0, [])
    assert (waiting.level, waiting.message) == ('OK', 'waiting for measurements')
    values = dict(waiting.values)
    assert values['last_measurement_age_s'] == 'never' and values['nis_window_count'] == '0'
    assert 'covariance_condition' not in values and 'nis_window_mean' not in values
    late = filter_status(estimator, NodeCounts(0, 0, 0, 0, 0, 0),
                         Activity(0.0, 0.0, 2.04, False), 1.0, [])
    assert late.level == 'WARN'
    assert late.message == late.timeout_warning == (
        'no measurement fused yet for 2.0 s (timeout_s 1)')
    stopped = filter_status(_estimator(), COUNTS, ACTIVE._replace(age_s=3.0), 2.5, [])
    assert stopped.timeout_warning == 'no measurement fused for 3.0 s (timeout_s 2.5)'


@pytest.mark.parametrize('nis, words', [
    ([50.0] * 20, 'inconsistent: noise parameters too small (mean NIS 50 > '),
    ([1e-4] * 20, 'inconsistent: noise parameters too large (mean NIS 0.0001 < '),
])
def test_inconsistent_noise_warns(nis, words):
    """A mean NIS outside its 99% bounds is a WARN naming the direction."""
    status = filter_status(_estimator(), COUNTS, ACTIVE, 1.0, nis)
    assert status.level == 'WARN' and status.message.startswith(words)
    assert status.message.endswith('over 20 updates)')


def test_ill_conditioned_covariance_warns_and_warnings_join():
    """A covariance condition above 1e12 warns; several warnings join with '; '."""
    estimator = _estimator()
    estimator.set_state(10 * NS_PER_S, [0.0, 1.0], [[1.0, 0.0], [0.0, 1e-14]])
    status = filter_status(estimator, COUNTS, ACTIVE._replace(age_s=5.0), 1.0, [50.0] * 5)
    assert dict(status.values)['covariance_condition'] == '1e+14'
    parts = status.message.split('; ')
    assert [part.split(' ')[0] for part in parts] == ['no', 'inconsistent:', 'ill-conditioned']


def test_control_presets_show_their_control_counts():
    """A preset with a control adds the node's and the estimator's control counts."""
    estimator = StreamEstimator(dataclasses.replace(TRAIN_NODE, preset='car'))
    estimator.add_control(NS_PER_S, [1.0])
    counts = COUNTS._replace(controls_received=3, controls_rejected=1)
    values = dict(filter_status(estimator, counts, ACTIVE, 1.0, []).values)
    assert values['controls_received'] == '3' and values['controls_rejected'] == '1'
    assert {key for key in values if key.startswith('controls.')} == {
        f'controls.{key}' for key in estimator.stats().controls}
    assert {key for key in values if key.startswith('controls_rejected.')} == {
        f'controls_rejected.{reason}' for reason in CONTROL_REJECTION_REASONS}


def test_filter_specific_values():
    """UKF: its regularisations; particle filter: ESS and resamplings once initialised."""
    ukf = dict(filter_status(_estimator(filter='ukf'), COUNTS, ACTIVE, 1.0, []).values)
    assert ukf['filter'] == 'ukf' and ukf['ukf_regularisations'] == '0'
    for kind in ('pf', 'bootstrap-pf'):
        pf = _estimator(filter=kind, pf_particles=200, process_noise_density=0.1)
        values = dict(filter_status(pf, COUNTS, ACTIVE, 1.0, []).values)
        assert float(values['pf_ess']) <= 200 and int(values['pf_resample_count']) >= 0
        fresh = StreamEstimator(dataclasses.replace(TRAIN_NODE, filter=kind))
        assert 'pf_ess' not in dict(filter_status(fresh, COUNTS, ACTIVE, 1.0, []).values)


def test_nis_bounds_are_the_chi2_bounds():
    """The cached bounds are chi2_mean_bounds at 99%."""
    assert nis_bounds(30, 2) == chi2_mean_bounds(30, 2, 0.99)


def test_condition_number_is_numpys_bit_for_bit():
    """condition_number(P) = np.linalg.cond(P), also singular, 1x1, 6x6 and non-finite."""
    rng = np.random.default_rng(4)
    matrices = [np.zeros((2, 2)), np.diag([1.0, 0.0]), np.array([[2.5]]),
                np.array([[np.inf, 0.0], [0.0, 1.0]])]
    for n in (1, 2, 2, 2, 6):
        for _ in range(200):
            A = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-6, 6)
            matrices.append(A @ A.T)
    for P in matrices:
        expected = float(np.linalg.cond(P))
        got = condition_number(P)
        assert got == expected or (math.isnan(got) and math.isnan(expected)), P
