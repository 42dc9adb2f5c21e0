"""A receiver's held position (the last fix repeated exactly) fused as a standstill."""

from kf_train.batch import rail_log_likelihoods, RailNoise, Segment
from kf_train.estimator import EstimatorSettings, Rejected, StreamEstimator
from kf_train.estimator.live_presets import resolve_preset
from kf_train.presets.rail import RAIL_PRESET_PATH
from kf_train.sim.rail import rail_scenario
import numpy as np
import pytest
import yaml

NS = 1_000_000_000


def _preset(tmp_path, **overrides) -> str:
    """Return the path of a copy of rail.yaml with parameter overrides."""
    with open(RAIL_PRESET_PATH) as stream:
        data = yaml.safe_load(stream)
    data['parameters'].update(overrides)
    path = tmp_path / 'rail.yaml'
    path.write_text(yaml.safe_dump(data))
    return str(path)


def _held_run(seed: int, rows: int, hold_probability: float = 0.8):
    """
    Return (stamps ns, z, variances, true speed) of a metro run whose receiver holds.

    Errors: a slow walk (σ_u 0.1 m/s, as a receiver's) plus 5 cm white, variance 4 m²
    given; while the train stands each fix repeats the last one with hold_probability.
    """
    scenario, _ = rail_scenario(seed=seed, family='metro')
    rng = np.random.default_rng(seed)
    dt = np.diff(scenario.t_s[:rows], prepend=scenario.t_s[0])
    slow = np.cumsum(0.1 * np.sqrt(dt) * rng.standard_normal(rows) * np.sqrt(dt))
    z = scenario.truth[:rows, 0] + slow + 0.05 * rng.standard_normal(rows)
    speed = scenario.truth[:rows, 1]
    for k in range(1, rows):
        if speed[k] < 0.05 and rng.random() < hold_probability:
            z[k] = z[k - 1]
    stamps = np.round(scenario.t_s[:rows] * NS).astype(np.int64) + NS
    return stamps, z, np.full(rows, 4.0), speed


def _replay(estimator: StreamEstimator, stamps, z, variances):
    """Return P(stand) after each fix (NaN where rejected)."""
    stand = np.full(z.size, np.nan)
    for k in range(z.size):
        try:
            estimator.process(int(stamps[k]), float(z[k]), float(variances[k]))
            stand[k] = estimator.mode_probabilities()[1][0]
        except Rejected:
            pass
    return stand


@pytest.fixture(scope='module')
def held():
    """Return a 3000-fix (300-s) metro run with held positions at its stops."""
    return _held_run(3, 3000)


def test_held_fixes_are_fused_as_a_standstill(held):
    """Holds count as fused, standstill holds, and the velocity is never negative."""
    stamps, z, variances, speed = held
    estimator = StreamEstimator(EstimatorSettings())
    stand = _replay(estimator, stamps, z, variances)
    stats = estimator.stats()
    repeats = int(np.sum(z[1:] == z[:-1]))
    assert repeats > 300
    # Nearly every repeat is a hold (the first of a stop may come before the track stops).
    assert stats.holds >= 0.9 * repeats
    assert stats.rejections['repeated'] == 0
    standing = speed < 0.05
    standing[:100] = False                      # the start: the track is still joining
    assert np.nanmedian(stand[standing]) > 0.95


def _epochs(rows: int, order: str):
    """Return the messages of ``rows`` epochs as (row, 'fix' or 'speed'), in ``order``."""
    first = [(0, 'fix'), (0, 'speed')]          # a speed never starts the filter
    if order == 'fix first':
        return first + [(k, message) for k in range(1, rows) for message in ('fix', 'speed')]
    if order == 'speed first':
        return first + [(k, message) for k in range(1, rows) for message in ('speed', 'fix')]
    late = [event for k in range(1, rows - 1) for event in ((k + 1, 'speed'), (k, 'fix'))]
    return first + [(1, 'speed')] + late + [(rows - 1, 'fix')]  # behind the next speed


def _fed(held, rows: int, order: str) -> StreamEstimator:
    """Return an estimator (history_s 1, as the node's) fed fixes and Doppler speeds."""
    stamps, z, variances, speed = held
    doppler = speed + 0.05 * np.random.default_rng(3).standard_normal(speed.size)
    estimator = StreamEstimator(EstimatorSettings(history_s=1.0))
    for k, message in _epochs(rows, order):
        try:
            if message == 'fix':
                estimator.process(int(stamps[k]), float(z[k]), float(variances[k]))
            else:
                estimator.process_velocity(int(stamps[k]), float(doppler[k]), 0.05 ** 2)
        except Rejected:
            pass
    return estimator


@pytest.mark.parametrize('order', ['speed first', 'late behind the next speed'])
def test_a_hold_is_a_hold_whichever_message_of_its_epoch_comes_first(held, order):
    """
    A Doppler published before its fix: the same holds, repeats and states as after it.

    The node keeps a history (history_s 1), where a fix after its epoch's speed (or the
    next epoch's) is fused before those speeds again, with an in-order fix's rules (the
    hold, the repeated epoch), as the newest position it is.
    """
    rows = 1500
    assert sorted(_epochs(rows, order)) == sorted(_epochs(rows, 'fix first'))
    straight, swapped = _fed(held, rows, 'fix first'), _fed(held, rows, order)
    first, second = straight.stats(), swapped.stats()
    assert first.holds > 100 and second.holds == first.holds
    assert second.rejections == first.rejections and second.fused == first.fused
    assert second.out_of_sequence == first.fused - 1    # every fix but the first (holds too)
    # The same equations in the same order: the speed's update after a dt of 0 is
    # fused in order by predict_update and replayed as an update, rounding apart.
    (x1, P1), (x2, P2) = straight.state, swapped.state
    np.testing.assert_allclose(x2, x1, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(P2, P1, rtol=1e-9, atol=1e-12)


def test_a_held_stamp_has_had_its_position(held):
    """A late copy of a held fix is a duplicate; a late speed of that stamp goes after it."""
    stamps, z, variances, speed = held
    k = next(k for k in range(400, z.size) if z[k] == z[k - 1] == z[k - 2])
    estimator = StreamEstimator(EstimatorSettings(history_s=1.0))
    _replay(estimator, stamps[:k + 3], z[:k + 3], variances[:k + 3])
    assert estimator.stats().holds >= 2
    with pytest.raises(Rejected) as raised:
        estimator.process(int(stamps[k]), float(z[k]), float(variances[k]))
    assert raised.value.reason == 'duplicate_stamp'
    step = estimator.process_velocity(int(stamps[k]), 0.0, 0.05 ** 2)
    assert step.replayed == 2 and estimator.stats().velocities['out_of_sequence'] == 1


def test_a_hold_is_a_speed_of_zero_with_the_hold_variance(held):
    """A hold's state is a speed of 0 ± 0.3 m/s fused at its stamp; its step has no update."""
    stamps, z, variances, _ = held
    k = next(k for k in range(200, z.size) if z[k] == z[k - 1])
    estimator, twin = (StreamEstimator(EstimatorSettings()) for _ in range(2))
    _replay(estimator, stamps[:k], z[:k], variances[:k])
    _replay(twin, stamps[:k], z[:k], variances[:k])
    step = estimator.process(int(stamps[k]), float(z[k]), float(variances[k]))
    assert estimator.stats().holds == twin.stats().holds + 1
    assert step.update is None          # no position innovation (nor NIS) to publish
    speed = twin.process_velocity(int(stamps[k]), 0.0, 0.3 ** 2)
    np.testing.assert_array_equal(step.x, speed.x)
    np.testing.assert_array_equal(step.P, speed.P)
    np.testing.assert_array_equal(step.predicted_x, speed.predicted_x)
    assert estimator.stats().fused == twin.stats().fused + 1


@pytest.mark.parametrize('override', [{'hold_speed_std_mps': 0.0},
                                      {'hold_max_variance_m2': 3.9}])
def test_without_a_hold_the_repeats_at_stops_are_positions(tmp_path, held, override):
    """No hold with a hold speed of 0, or a variance given above hold_max_variance_m2."""
    stamps, z, variances, _ = held
    estimator = StreamEstimator(EstimatorSettings(preset=_preset(tmp_path, **override)))
    _replay(estimator, stamps, z, variances)
    assert estimator.stats().holds == 0
    assert estimator.stats().fused >= 0.99 * z.size


def test_a_repeat_while_moving_is_still_a_repeated_epoch():
    """An exact repeat 0.1 s after a fix at ~15 m/s is rejected, never taken as a hold."""
    stamps, z, variances, speed = _held_run(4, 1500, hold_probability=0.0)
    moving = [k for k in range(600, 1500, 97) if speed[k] > 10.0]
    z[moving] = z[[k - 1 for k in moving]]
    estimator = StreamEstimator(EstimatorSettings())
    _replay(estimator, stamps, z, variances)
    assert estimator.stats().holds == 0
    assert estimator.stats().rejections['repeated'] == len(moving) > 3


def test_a_rewind_replays_a_hold_as_a_speed(held):
    """Two fixes before a hold swapped: the replay gives the in-order state."""
    stamps, z, variances, _ = held
    k = next(k for k in range(400, z.size) if z[k] == z[k - 1] == z[k - 2])
    order = list(range(k + 3))
    order[k - 4], order[k - 3] = order[k - 3], order[k - 4]
    straight = StreamEstimator(EstimatorSettings(history_s=1.0))
    swapped = StreamEstimator(EstimatorSettings(history_s=1.0))
    _replay(straight, stamps[:k + 3], z[:k + 3], variances[:k + 3])
    _replay(swapped, stamps[order], z[order], variances[order])
    assert swapped.stats().out_of_sequence == 1
    assert swapped.stats().holds == straight.stats().holds >= 2
    (x1, P1), (x2, P2) = straight.state, swapped.state
    # The same equations in the same order after the swap's rewind: rounding only.
    np.testing.assert_allclose(x2, x1, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(P2, P1, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize('engine', ['numpy', 'numba'])
def test_the_likelihood_takes_holds_as_the_node_does(engine, held):
    """The tuner's likelihood fuses the same holds as speeds of 0, the same numbers."""
    if engine == 'numba':
        pytest.importorskip('numba')
    stamps, z, variances, _ = held
    estimator = StreamEstimator(EstimatorSettings())
    gated, ys = [], []
    for k in range(z.size):
        try:
            step = estimator.process(int(stamps[k]), float(z[k]), float(variances[k]))
            gated.append(False)
            ys.append(np.nan if step.update is None else float(step.update.innovation[0]))
        except Rejected as rejection:
            gated.append(True)
            ys.append(float(rejection.update.innovation[0]))
    assert estimator.stats().holds > 300
    base = resolve_preset('rail').parameters
    result = rail_log_likelihoods(
        base, [Segment(stamps / 1e9, z[:, None])], [RailNoise()], innovations=True,
        variances=[variances], adaptation=base.adaptation(),
        gate_threshold=estimator.gate_threshold, engine=engine)
    np.testing.assert_array_equal(result.gated[0], gated[1:])
    # The holds: NaN in both (no position innovation); the node's y elsewhere.
    assert np.isnan(result.innovation[0]).sum() == estimator.stats().holds
    # The node's own equations on the same floats but for dt (ns there): within ~1e-12
    # (test_rail_likelihood_node); 1e-8 for a margin.
    np.testing.assert_allclose(result.innovation[0], ys[1:], rtol=0.0, atol=1e-8)
