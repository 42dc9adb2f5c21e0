"""Re-acquisition after a lock-out: only a consistent group of fixes restarts the track."""

import dataclasses

from kf_train.estimator import EstimatorSettings, Rejected, StreamEstimator
from kf_train.estimator.reacquire import consistent_group
import numpy as np
import pytest

NS = 1_000_000_000
RAIL = EstimatorSettings(max_consecutive_outliers=5)
RESET = dataclasses.replace(RAIL, lockout='reset')


def _stamps(count: int, start: int = 0):
    return [NS + (start + k) * NS // 10 for k in range(count)]


def test_a_line_within_the_noise_is_consistent_and_scatter_is_not():
    stamps = _stamps(6)
    assert consistent_group(stamps, [0.0, 1.0, 2.1, 2.9, 4.0, 5.0], [1.0] * 6, 0.9999)
    assert not consistent_group(stamps, [0.0, 200.0, -150.0, 10.0, 190.0, 0.0], [1.0] * 6,
                                0.9999)
    assert consistent_group(stamps[:2], [0.0, 1e6], [1.0, 1.0], 0.9999)  # two: always
    assert not consistent_group(stamps[:3], [0.0, float('nan'), 1.0], [1.0] * 3, 0.9999)


def _cruising(estimator: StreamEstimator, count: int) -> None:
    """Feed a train cruising at 10 m/s, fixes exact to 0.1 m."""
    for k, stamp in enumerate(_stamps(count)):
        estimator.process(stamp, 1.0 * k + 0.1 * ((-1) ** k), 1.0)


def test_scattered_gross_fixes_never_restart_the_track():
    estimator = StreamEstimator(RAIL)
    _cruising(estimator, 200)
    jumps = [300.0, -250.0, 180.0, -320.0, 260.0, -190.0, 310.0, -280.0, 240.0, -300.0]
    for k, (stamp, jump) in enumerate(zip(_stamps(10, 200), jumps)):
        with pytest.raises(Rejected) as raised:
            estimator.process(stamp, 1.0 * (200 + k) + jump, 1.0)
        assert raised.value.reset is None
    assert estimator.stats().resets['outlier_lockout'] == 0
    # The track coasted through them and takes the next good fix.
    step = estimator.process(_stamps(1, 210)[0], 210.0, 1.0)
    assert step.x[0] == pytest.approx(210.0, abs=1.0)


def test_a_consistent_group_restarts_the_track_from_all_of_its_fixes():
    estimator = StreamEstimator(RESET)
    _cruising(estimator, 200)
    # The train is really 500 m further on (a missed jump of the map, a restarted
    # receiver): five fixes in a row agree with each other, and restart the track.
    moved = [500.0 + 1.0 * k for k in range(200, 206)]
    for k in range(5):
        with pytest.raises(Rejected) as raised:
            estimator.process(_stamps(1, 200 + k)[0], moved[k], 1.0)
    assert raised.value.reset == 'outlier_lockout'
    step = estimator.process(_stamps(1, 205)[0], moved[5], 1.0)
    # Six fixes, not one: the velocity is the group's 10 m/s already.
    assert step.x[0] == pytest.approx(moved[5], abs=1.0)
    assert step.x[1] == pytest.approx(10.0, abs=2.0)


def test_the_group_restart_is_what_in_order_fusion_of_the_group_gives():
    settings = dataclasses.replace(RESET, history_s=0.0)
    estimator = StreamEstimator(settings)
    _cruising(estimator, 100)
    moved = [900.0 + 1.0 * k for k in range(100, 106)]
    for k in range(5):
        with pytest.raises(Rejected):
            estimator.process(_stamps(1, 100 + k)[0], moved[k], 1.0)
    step = estimator.process(_stamps(1, 105)[0], moved[5], 1.0)
    fresh = StreamEstimator(dataclasses.replace(settings, gate_probability=1.0,
                                                initialization='first_measurement'))
    for k in range(6):
        expected = fresh.process(_stamps(1, 100 + k)[0], moved[k], 1.0)
    assert (step.x == expected.x).all() and (step.P == expected.P).all()


def test_a_consistent_group_reacquires_the_track_and_keeps_what_it_learned():
    """The default lock-out keeps the track: widened by the jump, the group fused into it."""
    estimator = StreamEstimator(RAIL)
    _cruising(estimator, 200)
    scale = estimator.noise_scale()
    moved = [500.0 + 1.0 * k for k in range(200, 206)]
    for k in range(4):
        with pytest.raises(Rejected) as raised:
            estimator.process(_stamps(1, 200 + k)[0], moved[k], 1.0)
        assert raised.value.reset is None
    step = estimator.process(_stamps(1, 204)[0], moved[4], 1.0)    # the fifth: fused
    stats = estimator.stats()
    assert stats.reacquisitions == 1 and sum(stats.resets.values()) == 0
    assert stats.rejections['outlier'] == 4 and stats.fused == 201
    # On the group's line: 500 m further, still 10 m/s (the track's and the group's).
    assert step.x[0] == pytest.approx(moved[4], abs=1.0)
    assert step.x[1] == pytest.approx(10.0, abs=1.0)
    assert np.all(np.isfinite(step.P)) and np.all(np.linalg.eigvalsh(step.P) > -1e-9)
    # Kept, not restarted: the regime probabilities are a distribution and the noise
    # scale learned before is the one that went on learning (not reset to 1).
    probabilities = estimator.mode_probabilities()[1]
    assert probabilities.sum() == pytest.approx(1.0) and probabilities[2] > 0.5   # cruise
    assert scale < 0.5 and estimator.noise_scale() < 1.0
    step = estimator.process(_stamps(1, 205)[0], moved[5], 1.0)      # gated, accepted
    assert step.update is not None and step.update.nis < 15.1


@pytest.mark.parametrize('speed_first', [False, True])
def test_a_speed_input_keeps_the_reacquisition(speed_first):
    """
    With a Doppler fused at every epoch (either message first), a group still re-acquires.

    The speeds fused while the group is rejected move the track past the group's first
    fixes; those shape the line, and the track is not reset. The node keeps a history
    (history_s 1), where a fix after its epoch's speed is fused before it.
    """
    estimator = StreamEstimator(dataclasses.replace(RAIL, history_s=1.0))

    def epoch(k: int, position_m: float):
        stamp = _stamps(1, k)[0]
        if speed_first and k:
            estimator.process_velocity(stamp, 10.0, 0.01)
        step = estimator.process(stamp, position_m, 1.0)
        if not speed_first:
            estimator.process_velocity(stamp, 10.0, 0.01)
        return step
    for k in range(200):
        epoch(k, 1.0 * k + 0.1 * ((-1) ** k))
    moved = [500.0 + 1.0 * k for k in range(200, 206)]
    for k in range(4):
        with pytest.raises(Rejected) as raised:
            epoch(200 + k, moved[k])
        assert raised.value.reason == 'outlier' and raised.value.reset is None
        if not speed_first:             # the rejected fix's speed, fused on the track
            estimator.process_velocity(_stamps(1, 200 + k)[0], 10.0, 0.01)
    step = epoch(204, moved[4])
    stats = estimator.stats()
    assert stats.reacquisitions == 1 and sum(stats.resets.values()) == 0
    assert step.x[0] == pytest.approx(moved[4], abs=1.0)
    assert step.x[1] == pytest.approx(10.0, abs=0.5)
    step = epoch(205, moved[5])                                     # gated, accepted
    assert step.update is not None and step.update.nis < 15.1


def test_reacquisition_is_the_widened_track_fused_with_the_group():
    """The re-acquired state is StepModel.widen by the jump, then the group in order."""
    from kf_train.estimator.reacquire import fit_line, jump_covariance
    settings = dataclasses.replace(RAIL, history_s=0.0)
    estimator = StreamEstimator(settings)
    _cruising(estimator, 100)
    # The fused arrays themselves: the IMM's regime states are kept under them.
    x0, P0 = estimator._fusion.x, estimator._fusion.P
    model = estimator.model
    moved = [900.0 + 1.0 * k for k in range(100, 105)]
    stamps = _stamps(5, 100)
    for k in range(4):
        with pytest.raises(Rejected):
            estimator.process(stamps[k], moved[k], 1.0)
    step = estimator.process(stamps[4], moved[4], 1.0)
    anchor = _stamps(1, 99)[0]
    line = fit_line(stamps, moved, [1.0] * 5)
    predicted, _ = model.predict_ahead(x0, P0, (stamps[-1] - anchor) / NS)
    x, P = model.widen(x0, P0, jump_covariance(model.state_names, predicted, line))
    for stamp, z in zip(stamps, moved):
        x, P, _ = model.predict_update(x, P, (stamp - anchor) / NS, np.array([z]),
                                       np.array([[1.0]]))
        anchor = stamp
    np.testing.assert_allclose(step.x, x, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(step.P, P, rtol=1e-9, atol=1e-9)


def test_the_jump_covers_the_disagreement_and_nothing_else():
    from kf_train.estimator.reacquire import fit_line, jump_covariance
    line = fit_line(_stamps(3), [10.0, 11.0, 12.0], [1.0] * 3)
    assert line.position_m == pytest.approx(12.0) and line.velocity_mps == pytest.approx(10.0)
    assert line.chi2 == pytest.approx(0.0, abs=1e-18)
    jump = jump_covariance(('position', 'velocity', 'acceleration'),
                           np.array([2.0, 4.0, 1.0]), line)
    assert jump[0, 0] == pytest.approx(100.0 + line.covariance[0, 0])
    assert jump[1, 1] == pytest.approx(36.0 + line.covariance[1, 1])
    assert np.count_nonzero(jump) == 2
    assert jump_covariance(('x', 'y'), np.zeros(2), line) is None
