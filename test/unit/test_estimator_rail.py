"""The streaming estimator running the rail preset (issue 11): the IMM behind (x, P)."""

import dataclasses
import math
import os

from kf_train.estimator import (
    EstimatorSettings, LIVE_PRESETS, preset_defaults, Rejected, resolve_preset, SEED_SWITCH,
    StreamEstimator)
from kf_train.filters import IMMFilter, make_rail_filter, MODE_NAMES, RailModelParameters
from kf_train.presets import RAIL_PRESET_PATH, RailPreset
from kf_train.ros.estimator_params import DEFAULTS as NODE_DEFAULTS
from kf_train.sim.rail import family_parameters, rail_scenario
import numpy as np
import pytest

NS = 1_000_000_000
RAIL = EstimatorSettings(preset='rail', history_s=1.0, gate_probability=0.999)


@pytest.fixture(scope='module')
def metro():
    """Return a 120-s metro run (departure, cruise, brake): stamps [ns], positions [m]."""
    params = dataclasses.replace(family_parameters('metro', 2), duration_s=120.0)
    scenario, run = rail_scenario(2, 'metro', parameters=params)
    stamps = [int(round(t * 10)) * (NS // 10) for t in scenario.t_s]
    return stamps, scenario.z[:, 0].tolist(), run


def _feed(estimator, stamps, zs):
    """Fuse every measurement; return the steps (a gated one, about 1 in 1000, skipped)."""
    steps = []
    for stamp, z in zip(stamps, zs):
        try:
            steps.append(estimator.process(stamp, z, 1.0))
        except Rejected as rejection:
            assert rejection.reason == 'outlier'
    return steps


def test_the_rail_preset_runs_live_with_its_own_defaults():
    assert LIVE_PRESETS[0] == 'rail'
    preset = resolve_preset('rail')
    assert isinstance(preset, RailPreset)
    assert (preset.dim_x, preset.dim_z, preset.dim_u) == (6, 1, 0)
    defaults = preset_defaults('rail')
    params = RailModelParameters()
    assert defaults['initial_state'] == (0.0, 0.0, 0.0, 0.0, params.accelerate_mps2,
                                         params.brake_mps2)
    assert defaults['initial_covariance'] == tuple(np.diag(params.initial_covariance(1.0)))
    assert (defaults['nominal_period_s'], defaults['horizon_s']) == (0.1, 2.0)
    # A preset file with model: rail_regimes is a rail preset too.
    assert isinstance(resolve_preset(RAIL_PRESET_PATH), RailPreset)
    estimator = StreamEstimator(RAIL)
    assert estimator.horizon_s == 2.0 and estimator.model.dim_x == 6


def test_it_is_the_rail_imm_step_for_step(metro):
    """First measurement, predictions, updates, the 2-s look-ahead: the IMMFilter's."""
    stamps, zs, _ = metro
    estimator = StreamEstimator(RAIL)
    filt = make_rail_filter(zs[0], variance_m2=1.0)
    step = estimator.process(stamps[0], zs[0], 1.0)
    assert step.update is None  # first_measurement: initialised, not updated
    # The same arithmetic on the same inputs: equal to the last bit.
    np.testing.assert_array_equal(step.x, filt.mean)
    np.testing.assert_array_equal(step.P, filt.covariance)
    for k in range(1, 300):
        step = estimator.process(stamps[k], zs[k], 1.0)
        filt.predict((stamps[k] - stamps[k - 1]) / NS)
        result = filt.update(zs[k])
        np.testing.assert_array_equal(step.x, filt.mean)
        np.testing.assert_array_equal(step.P, filt.covariance)
        assert step.update.nis == result.nis
        ahead, P_ahead = filt.predict_ahead(2.0)
        # The published prediction is the IMM's mixture 2 s ahead (RailModel.predict_ahead).
        assert step.prediction_stamp_ns == stamps[k] + 2 * NS
        np.testing.assert_array_equal(step.predicted_x, ahead)
        np.testing.assert_array_equal(step.predicted_P, P_ahead)
        names, mu = estimator.mode_probabilities()
        assert names == MODE_NAMES
        np.testing.assert_array_equal(mu, filt.mode_probabilities)


def test_mode_probabilities_sum_to_one_and_are_none_without_an_imm(metro):
    stamps, zs, _ = metro
    estimator = StreamEstimator(RAIL)
    assert estimator.mode_probabilities() is None  # nothing fused yet
    for step_stamp, z in zip(stamps[:400], zs[:400]):
        estimator.process(step_stamp, z, 1.0)
        names, mu = estimator.mode_probabilities()
        assert len(names) == 4 and np.all(mu >= 0.0)
        # Normalised by one division: the sum is 1 to a few ulps.
        assert mu.sum() == pytest.approx(1.0, abs=1e-12)
    mu[:] = 0.0  # a copy: the estimator's state is not touched
    assert estimator.mode_probabilities()[1].sum() == pytest.approx(1.0, abs=1e-12)
    train = StreamEstimator(EstimatorSettings(preset='train'))
    train.process(stamps[0], zs[0], 1.0)
    assert train.mode_probabilities() is None


def test_out_of_sequence_measurements_equal_in_order_fusion(metro):
    """Rewinding restores the whole IMM state behind a kept mean: replays repeat exactly."""
    stamps, zs, _ = metro
    order = list(range(200))
    for k in range(20, 190, 15):  # swap neighbours, and one three steps late
        order[k], order[k + 1] = order[k + 1], order[k]
    order[100], order[103] = order[103], order[100]
    in_order = StreamEstimator(RAIL)
    expected = _feed(in_order, stamps[:200], zs[:200])[-1]
    shuffled = StreamEstimator(RAIL)
    for k in order:
        step = shuffled.process(stamps[k], zs[k], 1.0)
    # 12 swapped pairs (one late each), and 103 first: 101, 102 and 100 come late.
    assert shuffled.stats().out_of_sequence == 15
    np.testing.assert_array_equal(step.x, expected.x)
    np.testing.assert_array_equal(step.P, expected.P)
    np.testing.assert_array_equal(step.predicted_x, expected.predicted_x)
    np.testing.assert_array_equal(shuffled.mode_probabilities()[1],
                                  in_order.mode_probabilities()[1])


def test_a_huge_outlier_is_gated_counted_and_changes_nothing(metro):
    stamps, zs, _ = metro
    estimator = StreamEstimator(RAIL)
    _feed(estimator, stamps[:100], zs[:100])
    x, P = estimator.state
    mu = estimator.mode_probabilities()[1]
    with pytest.raises(Rejected) as caught:
        estimator.process(stamps[100], zs[100] + 1e6, 1.0)
    assert caught.value.reason == 'outlier' and caught.value.update.nis > 1e10
    assert estimator.stats().rejections['outlier'] == 1
    np.testing.assert_array_equal(estimator.state[0], x)
    np.testing.assert_array_equal(estimator.state[1], P)
    np.testing.assert_array_equal(estimator.mode_probabilities()[1], mu)
    # The next good measurement is fused as if the outlier had never come.
    reference = StreamEstimator(RAIL)
    _feed(reference, stamps[:100], zs[:100])
    np.testing.assert_array_equal(estimator.process(stamps[101], zs[101], 1.0).x,
                                  reference.process(stamps[101], zs[101], 1.0).x)


def test_consecutive_outliers_reset_and_the_next_measurement_reinitialises(metro):
    stamps, zs, _ = metro
    estimator = StreamEstimator(dataclasses.replace(RAIL, max_consecutive_outliers=3,
                                                    lockout='reset'))
    _feed(estimator, stamps[:50], zs[:50])
    for k in range(50, 53):
        with pytest.raises(Rejected):
            estimator.process(stamps[k], 1e6, 1.0)
    assert estimator.stats().resets['outlier_lockout'] == 1
    assert not estimator.initialized and estimator.mode_probabilities() is None
    # Never gated: it starts the filter with the three rejected fixes it agrees with
    # (kf_train.estimator.reacquire), so four fixes at 1e6 m, standing.
    step = estimator.process(stamps[53], 1e6, 1.0)
    assert step.x[0] == pytest.approx(1e6, abs=1e-3) and step.reset is None
    assert estimator.stats().fused == 51 and estimator.stats().rejections['outlier'] == 3
    assert estimator.mode_probabilities()[1].sum() == pytest.approx(1.0)


def test_reset_set_state_and_reconfigure_keep_the_imm_consistent(metro):
    stamps, zs, _ = metro
    estimator = StreamEstimator(RAIL)
    _feed(estimator, stamps[:150], zs[:150])
    # A reconfiguration keeps the state, the IMM's included.
    mu = estimator.mode_probabilities()[1]
    estimator.reconfigure(dataclasses.replace(RAIL, gate_probability=0.9999))
    np.testing.assert_array_equal(estimator.mode_probabilities()[1], mu)
    reference = StreamEstimator(RAIL)
    _feed(reference, stamps[:151], zs[:151])
    np.testing.assert_array_equal(estimator.process(stamps[150], zs[150], 1.0).x,
                                  reference.state[0])
    # set_state: an (x, P) the IMM did not produce starts every regime there, evenly.
    x = np.array([500.0, 10.0, 0.0, 0.0, 0.8, 0.9])
    estimator.set_state(stamps[151], x, np.diag([1.0, 1.0, 0.1, 0.1, 0.1, 0.1]))
    np.testing.assert_array_equal(estimator.mode_probabilities()[1], [0.25] * 4)
    np.testing.assert_array_equal(estimator.state[0], x)
    step = estimator.process(stamps[152], 501.0, 1.0)
    assert 500.0 < step.x[0] < 501.5
    with pytest.raises(ValueError, match='x must'):
        estimator.set_state(stamps[160], [1.0, 2.0], np.eye(2))
    estimator.reset()
    assert estimator.mode_probabilities() is None and estimator.state is None
    assert estimator.process(stamps[170], zs[170], 1.0).x[0] == zs[170]


def test_prior_initialisation_runs_the_imm_from_the_preset_prior(metro):
    stamps, zs, _ = metro
    estimator = StreamEstimator(dataclasses.replace(RAIL, initialization='prior'))
    step = estimator.process(stamps[0], zs[0], 1.0)
    assert step.update is not None  # the prior was predicted and updated
    # The preset's prior, [0, 0, 0, 0, A, B], held one nominal period before the stamp.
    preset = resolve_preset('rail')
    filt = IMMFilter(preset.model(), preset.initial_state, preset.initial_covariance)
    filt.predict(preset.nominal_period_s)
    filt.update(zs[0])
    np.testing.assert_array_equal(step.x, filt.mean)
    np.testing.assert_array_equal(step.P, filt.covariance)


@pytest.mark.parametrize('kind', ['ukf', 'pf', 'bootstrap-pf'])
def test_filters_other_than_the_imm_are_refused_for_rail(kind):
    with pytest.raises(ValueError, match='filter must be kf .* rail'):
        StreamEstimator(dataclasses.replace(RAIL, filter=kind))
    StreamEstimator(dataclasses.replace(RAIL, filter='ekf'))  # the same IMM


def test_settings_that_do_not_suit_the_rail_model_are_refused(tmp_path):
    with pytest.raises(ValueError, match='process_noise_density must be 0'):
        StreamEstimator(dataclasses.replace(RAIL, process_noise_density=0.1))
    with pytest.raises(ValueError, match='initial_state'):
        StreamEstimator(dataclasses.replace(RAIL, initial_state=(0.0, 1.0)))
    # A rail preset file with a bad figure names the file and the key.
    bad = os.path.join(tmp_path, 'my_rail.yaml')
    with open(RAIL_PRESET_PATH, encoding='utf-8') as source, open(bad, 'w') as target:
        target.write(source.read().replace('stop_speed_mps: 0.3', 'stop_speed_mps: -1'))
    with pytest.raises(ValueError, match='stop_speed_mps'):
        StreamEstimator(dataclasses.replace(RAIL, preset=bad))


def test_a_train_braking_to_a_stop_is_never_predicted_to_reverse(metro):
    stamps, zs, run = metro
    estimator = StreamEstimator(RAIL)
    steps, stand = [], []
    for stamp, z in zip(stamps, zs):
        try:
            steps.append(estimator.process(stamp, z, 1.0))
        except Rejected:
            continue
        stand.append(estimator.mode_probabilities()[1][0])
    for step in steps:
        # The mixture of per-regime paths held at their stop: never behind the estimate
        # (positions ~1e3 m, rounding ~1e-13 m).
        assert step.predicted_x[0] >= step.x[0] - 1e-9
        assert step.predicted_x[1] >= -1e-12
    # At a station it stands: from 8 s after the arrival (the filter needs a few
    # seconds to be sure) to 2 s before the departure. Noise bursts that look like a
    # departure make it doubt now and then (test_rail_model.test_stopped_means_stopped),
    # so the typical values are checked, not the worst.
    arrive, depart = run.stops[1]
    standing = [k for k, step in enumerate(steps)
                if arrive + 8.0 <= step.stamp_ns / NS <= depart - 2.0]
    assert len(standing) > 50, 'the run must hold a stop'
    assert np.median([abs(steps[k].x[1]) for k in standing]) < 0.05
    assert np.median([stand[k] for k in standing]) > 0.9


# -- the hostile-input contract with the new defaults (rail, gate 0.9999) -----------------

EPOCH_NS = 1_700_000_000 * NS
PERIOD_NS = NS // 10
HOSTILE = {
    # name: (reason, changes to a valid next measurement)
    'wrong frame': ('wrong_frame', {'frame_id': 'map'}),
    'NaN position': ('non_finite', {'position': math.nan}),
    '+Inf position': ('non_finite', {'position': math.inf}),
    'NaN variance': ('non_finite', {'variance': math.nan}),
    'Inf variance': ('non_finite', {'variance': math.inf}),
    'zero variance': ('bad_variance', {'variance': 0.0}),
    'negative variance': ('bad_variance', {'variance': -1.0}),
    'zero stamp': ('zero_stamp', {'stamp': 0}),
    'future stamp': ('future_stamp', {'stamp_offset': int(1.5 * NS)}),
    'duplicate of the newest': ('duplicate_stamp', {'stamp_offset': -PERIOD_NS}),
    'duplicate in the history': ('duplicate_stamp', {'stamp_offset': -4 * PERIOD_NS}),
    'stale': ('stale_stamp', {'stamp_offset': -12 * PERIOD_NS}),
    'a 10⁶ m outlier': ('outlier', {'position_offset': 1e6}),
    'a 10 m outlier': ('outlier', {'position_offset': 10.0}),
    'a 10⁶ m outlier, tiny variance': ('outlier', {'position_offset': 1e6, 'variance': 1e-12}),
    'overflowing position': ('numerical', {'position': 1e300}),
}


def _state_bytes(estimator):
    """Return the whole filter state as bytes (the IMM's probabilities included)."""
    x, P = estimator.state
    mu = estimator.mode_probabilities()[1]
    history = tuple((e.stamp_ns, e.x.tobytes(), e.P.tobytes(), e.kind)
                    for e in estimator._history)
    return x.tobytes(), P.tobytes(), mu.tobytes(), estimator.last_stamp_ns, history


@pytest.mark.parametrize('name', HOSTILE)
def test_hostile_inputs_are_rejected_counted_and_change_nothing_with_the_defaults(name, metro):
    """The node's defaults (rail, gate 0.9999, history 1 s) keep the input contract."""
    reason, change = HOSTILE[name]
    stamps, zs, _ = metro
    stamps = [EPOCH_NS + s for s in stamps[:31]]
    settings = dataclasses.replace(NODE_DEFAULTS, expected_frame_id='odom')
    assert (settings.preset, settings.gate_probability, settings.history_s) == (
        'rail', 0.9999, 1.0)

    def fed():
        estimator = StreamEstimator(settings)
        for stamp, z in zip(stamps[:30], zs[:30]):
            estimator.process(stamp, z, 1.0, frame_id='odom')
        return estimator
    estimator, twin = fed(), fed()
    before = _state_bytes(estimator)
    stamp = change.get('stamp', stamps[30] + change.get('stamp_offset', 0))
    position = change.get('position', zs[30] + change.get('position_offset', 0.0))
    with pytest.raises(Rejected) as raised:
        estimator.process(stamp, position, change.get('variance', 1.0),
                          frame_id=change.get('frame_id', 'odom'), now_ns=stamps[29])
    assert raised.value.reason == reason and raised.value.reset is None
    rejections = estimator.stats().rejections
    assert rejections[reason] == 1 and sum(rejections.values()) == 1
    assert sum(estimator.stats().resets.values()) == 0
    assert _state_bytes(estimator) == before
    # It keeps running exactly as if the bad input had never come.
    step = estimator.process(stamps[30], zs[30], 1.0, frame_id='odom', now_ns=stamps[29])
    np.testing.assert_array_equal(step.x, twin.process(stamps[30], zs[30], 1.0).x)
    assert np.all(np.isfinite(step.x)) and np.all(np.isfinite(step.predicted_P))


def test_default_settings_are_the_rail_preset_with_the_gate_and_the_seed_is_a_switch_away():
    core = EstimatorSettings()
    assert (core.preset, core.initialization, core.gate_probability) == (
        'rail', 'first_measurement', 0.9999)
    assert StreamEstimator().gate_threshold == pytest.approx(15.1367, abs=1e-4)
    seed = EstimatorSettings(**SEED_SWITCH)
    assert (seed.preset, seed.initialization, seed.gate_probability) == ('train', 'prior', 1.0)
    assert StreamEstimator(seed).gate_threshold == math.inf


def test_predict_to_is_the_published_prediction_and_changes_nothing(metro):
    stamps, zs, _ = metro
    estimator = StreamEstimator(RAIL)
    with pytest.raises(ValueError, match='no state yet'):
        estimator.predict_to(stamps[0])
    step = _feed(estimator, stamps[:200], zs[:200])[-1]
    before = _state_bytes(estimator)
    x, P = estimator.predict_to(step.prediction_stamp_ns)
    np.testing.assert_array_equal(x, step.predicted_x)
    np.testing.assert_array_equal(P, step.predicted_P)
    x[0] = -1.0  # a copy
    assert _state_bytes(estimator) == before
    with pytest.raises(ValueError, match='before the newest'):
        estimator.predict_to(stamps[150])
    # The train's KF too (its x⁻ = F x over the horizon).
    train = StreamEstimator(EstimatorSettings(**SEED_SWITCH))
    step = _feed(train, stamps[:20], zs[:20])[-1]
    np.testing.assert_array_equal(train.predict_to(step.prediction_stamp_ns)[0],
                                  step.predicted_x)


def test_variance_in_use_is_the_variance_given_times_the_learned_scale():
    estimator = StreamEstimator(EstimatorSettings(preset='rail'))
    assert estimator.variance_in_use(3.0) == 3.0            # nothing learned yet
    rng = np.random.default_rng(5)
    for k in range(200):       # a standing train, fixes scattered by 0.1 m, 3 m² given
        estimator.process(10 ** 9 + k * 10 ** 8, 0.1 * float(rng.standard_normal()), 3.0)
    scale = estimator.noise_scale()
    assert scale < 0.1                                       # learned: R given overstates
    assert estimator.variance_in_use(3.0) == 3.0 * scale
    overridden = StreamEstimator(EstimatorSettings(preset='rail', measurement_variance=2.0))
    overridden.process(10 ** 9, 0.0, 3.0)
    assert overridden.variance_in_use(3.0) == 2.0 * overridden.noise_scale()
    train = StreamEstimator(EstimatorSettings(preset='train'))
    train.process(10 ** 9, 0.0, 3.0)
    assert train.noise_scale() is None and train.variance_in_use(3.0) == 3.0
