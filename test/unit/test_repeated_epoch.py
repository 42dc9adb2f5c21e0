"""A receiver's repeated epoch: the last fused position again while the track moves."""

import dataclasses
import math

from kf_train.estimator import EstimatorSettings, Rejected, StreamEstimator
from kf_train.estimator import receiver_rules
from kf_train.filters import moved_past, numba_available
import numpy as np
import pytest

NS = 1_000_000_000
GIVEN_M2 = 3.0          # the variance each fix carries; the learned R is far lower
GATE = 15.136705226623606      # χ²(1) at 0.9999: the default gate
OUTAGE_NS = 30 * NS
JITS = [False] + ([True] if numba_available() else [])


def _stamp(k: int) -> int:
    return NS + k * NS // 5                                    # 5 Hz


def _cruise(estimator: StreamEstimator, count: int, speed_mps: float = 20.0) -> list:
    """Feed a train cruising at speed_mps, fixes scattered by 2 cm; return the fixes."""
    rng = np.random.default_rng(3)
    fixes = [speed_mps * 0.2 * k + 0.02 * float(rng.standard_normal()) for k in range(count)]
    for k, z in enumerate(fixes):
        estimator.process(_stamp(k), z, GIVEN_M2)
    return fixes


@pytest.mark.parametrize('jit', JITS)
def test_a_repeat_while_cruising_is_rejected_and_changes_nothing(jit):
    estimator = StreamEstimator(EstimatorSettings(), jit=jit)
    fixes = _cruise(estimator, 300)
    assert estimator.noise_scale() < 1e-2        # R learned far below the 3 m² given
    x, P = estimator.predict_to(_stamp(301))
    with pytest.raises(Rejected) as raised:
        estimator.process(_stamp(300), fixes[-1], GIVEN_M2)     # 4 m behind: a repeat
    assert raised.value.reason == 'repeated'
    assert 'repeated epoch' in str(raised.value)
    assert estimator.stats().rejections['repeated'] == 1
    assert estimator.stats().rejections['outlier'] == 0
    x_after, P_after = estimator.predict_to(_stamp(301))
    np.testing.assert_array_equal(x_after, x)                 # the state as before
    np.testing.assert_array_equal(P_after, P)
    step = estimator.process(_stamp(301), 20.0 * 0.2 * 301, GIVEN_M2)   # on it goes
    assert step.x[1] == pytest.approx(20.0, abs=0.1)


@pytest.mark.parametrize('jit', JITS)
def test_the_same_repeat_passes_the_gate_without_the_rule(jit):
    # What the rule is for: on the R given (the gate's), a 4-m step back is no outlier.
    estimator = StreamEstimator(EstimatorSettings(), jit=jit)
    fixes = _cruise(estimator, 300)
    step = estimator.process(_stamp(300), fixes[-1] + 1e-9, GIVEN_M2)   # not exact
    assert step.x[1] < 19.0                                  # weighed as braking


@pytest.mark.parametrize('jit', JITS)
def test_a_standing_trains_held_position_is_fused(jit):
    estimator = StreamEstimator(EstimatorSettings(), jit=jit)
    rng = np.random.default_rng(4)
    held = 100.0
    for k in range(300):     # standing: the receiver holds its position 4 fixes in 5
        if k % 5 == 0:
            held = 100.0 + 0.02 * float(rng.standard_normal())
        estimator.process(_stamp(k), held, GIVEN_M2)
    assert estimator.stats().rejections['repeated'] == 0
    assert estimator.mode_probabilities()[1][0] > 0.9


@pytest.mark.parametrize('jit', JITS)
def test_a_receiver_that_keeps_repeating_reacquires_the_track_standing_there(jit):
    settings = EstimatorSettings(max_consecutive_outliers=5)
    estimator = StreamEstimator(settings, jit=jit)
    fixes = _cruise(estimator, 300)
    for k in range(300, 304):
        with pytest.raises(Rejected) as raised:
            estimator.process(_stamp(k), fixes[-1], GIVEN_M2)
        assert raised.value.reason == 'repeated'
    step = estimator.process(_stamp(304), fixes[-1], GIVEN_M2)   # the fifth: re-acquired
    assert estimator.stats().reacquisitions == 1
    assert step.x[0] == pytest.approx(fixes[-1], abs=0.5)
    assert abs(step.x[1]) < 2.0


def test_presets_with_r_as_given_never_judge_a_repeat():
    estimator = StreamEstimator(EstimatorSettings(preset='train'))
    for k in range(50):
        estimator.process(_stamp(k), 4.0 * k, 1.0)
    estimator.process(_stamp(50), 4.0 * 49, 1.0)             # a repeat: the gate's call
    assert estimator.stats().rejections['repeated'] == 0


def test_no_gate_no_repeat_rule():
    # gate_probability 1: nothing is judged, a repeat included (it is part of the gate).
    rail = StreamEstimator(dataclasses.replace(EstimatorSettings(), gate_probability=1.0))
    fixes = _cruise(rail, 300)
    rail.process(_stamp(300), fixes[-1], GIVEN_M2)
    assert rail.stats().rejections['repeated'] == 0


@pytest.mark.parametrize('jit', JITS)
def test_a_repeat_after_an_outage_is_rejected_though_it_passes_the_gate(jit):
    # After 30 s without fixes the regimes spread over hundreds of metres (braking to a
    # halt is among them), so the last fix again passes the gate even on the R in use;
    # a train that was doing 20 m/s cannot be there.
    estimator = StreamEstimator(EstimatorSettings(), jit=jit)
    fixes = _cruise(estimator, 300)
    after = _stamp(299) + OUTAGE_NS
    with pytest.raises(Rejected) as raised:
        estimator.process(after, fixes[-1], GIVEN_M2)
    assert raised.value.reason == 'repeated'
    assert raised.value.update.nis < GATE                   # the prediction's gate passes
    assert 'cannot have stopped there' in str(raised.value)
    step = estimator.process(after + NS // 5, 20.0 * (0.2 * 300 + 30.0), GIVEN_M2)
    assert step.x[1] == pytest.approx(20.0, abs=0.5)          # on it goes, no re-acquiring
    assert estimator.stats().reacquisitions == 0


def test_without_the_speed_rule_that_repeat_stops_the_train(monkeypatch):
    monkeypatch.setattr(receiver_rules, 'moved_past', lambda *args: False)
    estimator = StreamEstimator(EstimatorSettings())
    fixes = _cruise(estimator, 300)
    step = estimator.process(_stamp(299) + OUTAGE_NS, fixes[-1], GIVEN_M2)
    assert step.x[1] < 1.0                  # fused: "braked to a halt" 600 m back


@pytest.mark.parametrize('jit', JITS)
def test_a_standing_trains_position_held_through_an_outage_is_fused(jit):
    estimator = StreamEstimator(EstimatorSettings(), jit=jit)
    rng = np.random.default_rng(5)
    for k in range(300):
        z = 100.0 + 0.02 * float(rng.standard_normal())
        estimator.process(_stamp(k), z, GIVEN_M2)
    estimator.process(_stamp(299) + OUTAGE_NS, z, GIVEN_M2)    # the same fix, 30 s on
    assert estimator.stats().rejections['repeated'] == 0


def test_moved_past_is_the_least_travel_braking_at_the_limit():
    # v⁻ = 2 m/s (a known speed), 0.2 s: it cannot stop, d = (2 - ½·3·0.2)·0.2 = 0.34 m.
    d = 0.34
    assert moved_past(2.0, 0.0, 0.2, d * d / GATE * (1.0 - 1e-9), GATE)
    assert not moved_past(2.0, 0.0, 0.2, d * d / GATE * (1.0 + 1e-9), GATE)
    # 30 s at 18 m/s, σ_v 0.1: v⁻ = 18 - √γ·0.1, it stops within dt after v⁻²/(2·3).
    lower = 18.0 - math.sqrt(GATE * 0.01)
    d = lower * lower / 6.0
    assert d == pytest.approx(51.6, abs=0.1)
    assert moved_past(18.0, 0.01, 30.0, d * d / GATE * (1.0 - 1e-9), GATE)
    assert not moved_past(18.0, 0.01, 30.0, d * d / GATE * (1.0 + 1e-9), GATE)
    # A speed whose lower bound is 0 or below may have stopped anywhere: never.
    assert not moved_past(0.3, 0.01, 30.0, 1e-12, GATE)
    assert not moved_past(0.0, 0.0, 30.0, 0.0, GATE)
