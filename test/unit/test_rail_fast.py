"""
The compiled rail IMM (kf_train.filters.rail_fast) against its numpy reference (issue 23).

The reference (:class:`RailModel`) is the readable spec; :class:`FastRailModel` does the
same equations as compiled loops, so the two agree to rounding, not to the bit: a sum
of N·n = 24 products in another order, or a fused multiply-add, moves a result by a few
ulps of the largest term. The bound below is norm-wise (each array's difference over
its largest entry): the step's error is ~n·N·eps = 24 · 1.1e-16 ≈ 3e-15 of the norm,
grown by the Joseph form's and the mixing's cancellations by at most the covariances'
condition (≤ ~1e4 here: P_pp ≈ 1 m² against P_AA ≈ 1e-3) and over a run damped by
the filter's own stability: 1e-9 leaves a margin of ~1e2 over the worst measured
(1.5e-10 after 500 steps), and sits far above the rounding floor (1e-16), so it
checks the equations, not the order of the sums.
"""

import dataclasses

from kf_train.estimator import EstimatorSettings, Rejected, StreamEstimator
from kf_train.filters import (
    FastRailModel, IMM, jit_enabled, JIT_VARIABLE, make_rail_filter, rail_model, RailModel,
    RailModelParameters)
from kf_train.sim.rail import family_parameters, rail_scenario
import numpy as np
import pytest

pytest.importorskip('numba')

NS = 1_000_000_000
RTOL = 1e-9
RAIL = EstimatorSettings(preset='rail', history_s=2.0, gate_probability=0.999)


def assert_close(actual, desired, what='', floor=0.0):
    """Assert a norm-wise difference below RTOL × max(|desired|, floor) (exact where both 0)."""
    actual, desired = np.asarray(actual, dtype=float), np.asarray(desired, dtype=float)
    assert actual.shape == desired.shape, what
    scale = max(np.max(np.abs(desired)) if desired.size else 0.0, floor)
    assert np.max(np.abs(actual - desired), initial=0.0) <= RTOL * scale, what


def assert_states_close(actual, desired):
    """Assert two IMMStates equal to RTOL, their learned noise scales too."""
    assert_close(actual.means, desired.means, 'means')
    assert_close(actual.covariances, desired.covariances, 'covariances')
    assert_close(actual.probabilities, desired.probabilities, 'probabilities')
    assert actual.noise.count == desired.noise.count
    assert_close(actual.noise, desired.noise, 'noise')          # the scale and the walk
    for array in actual[:3]:
        assert not array.flags.writeable


def assert_results_close(actual, desired, z):
    """Assert two UpdateResults equal to RTOL, the gate's NIS too; z the measurement."""
    # y = z - ẑ: its rounding is ẑ's, relative to |z| (a y near 0 is a cancellation),
    # and y²/S carries it as 2 |y| δy / S.
    assert_close(actual.innovation, desired.innovation, 'innovation', abs(z))
    y, S = float(desired.innovation[0]), float(desired.innovation_covariance[0, 0])
    for name in ('innovation_covariance', 'gain'):
        assert_close(getattr(actual, name), getattr(desired, name), name)
    assert_close(actual.nis, desired.nis, 'nis', 2.0 * abs(y) * abs(z) / S)
    assert (actual.gate_nis is None) == (desired.gate_nis is None)
    if desired.gate_nis is not None:
        assert_close(actual.gate_nis, desired.gate_nis, 'gate_nis', 2.0 * abs(y) * abs(z) / S)


@pytest.fixture(scope='module')
def models():
    """Return (reference, compiled) rail models of the default parameters."""
    return RailModel(), FastRailModel()


def _random_states(reference, seed, count):
    """Yield states of a reference run: random regimes, speeds, dts, fixes, speeds."""
    rng = np.random.default_rng(seed)
    state = reference.first_estimate(100.0, 4.0)
    position, speed = 100.0, 0.0
    for k in range(count):
        dt = float(rng.choice([0.1, 0.1 + rng.uniform(-0.002, 0.002), rng.uniform(0.0, 3.0)]))
        speed = max(0.0, speed + rng.normal(0.0, 1.0) * dt + (2.0 if k % 40 < 10 else -0.5))
        position += speed * dt
        state = reference.predict(state, dt)
        yield state, dt, float(position + rng.normal(0.0, 1.5)), rng
        state = reference.update(state, position + rng.normal(0.0, 1.5), [[2.25]])[0]
        if k % 5 == 0:
            state = reference.update_velocity(state, speed + rng.normal(0.0, 0.2), 0.04)[0]


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_every_step_is_the_reference_s(models, seed):
    """Predict, update, speed update, both at once, estimate, 2-s look-ahead: same states."""
    reference, fast = models
    for state, dt, z, rng in _random_states(reference, seed, 150):
        assert_states_close(fast.predict(state, dt), reference.predict(state, dt))
        R = [[float(rng.uniform(0.01, 25.0))]]
        for given in (R, None):
            ours, result = fast.update(state, z, given)
            theirs, their_result = reference.update(state, z, given)
            assert_states_close(ours, theirs)
            assert_results_close(result, their_result, z)
        speed = float(state.means[1, 1] + rng.normal(0.0, 0.5))
        ours, result = fast.update_velocity(state, speed, 0.04)
        theirs, their_result = reference.update_velocity(state, speed, 0.04)
        assert_states_close(ours, theirs)
        assert_results_close(result, their_result, speed)
        for index, value, noise in ((None, z, R), (None, z, None), (1, speed, [[0.04]])):
            ours, result = fast.predict_update(state, dt, value, noise, index)
            theirs, their_result = reference.predict_update(state, dt, value, noise, index)
            assert_states_close(ours, theirs)
            assert_results_close(result, their_result, value)
        for ours, theirs in zip(fast.estimate(state), reference.estimate(state)):
            assert_close(ours, theirs)
        for horizon_s in (2.0, dt):
            for ours, theirs in zip(fast.predict_ahead(state, horizon_s),
                                    reference.predict_ahead(state, horizon_s)):
                assert_close(ours, theirs)


def test_a_step_hands_out_its_estimate_and_prediction_once(models):
    """predict_update's own estimate and look-ahead: once each, equal to the bit to a new call."""
    reference = models[0]
    fast = FastRailModel()
    for state, dt, z, _ in _random_states(reference, 4, 40):
        for horizon_s in (2.0, 0.5):
            fast.predict_ahead(state, horizon_s)           # the horizon a step predicts to
            updated = fast.predict_update(state, dt, z)[0]
            kept = fast.estimate(updated), fast.predict_ahead(updated, horizon_s)
            again = fast.estimate(updated), fast.predict_ahead(updated, horizon_s)
            # The same kernels on the same arrays: equal to the bit (the tolerance is 0).
            for ours, theirs in zip(kept, again):
                for mine, new in zip(ours, theirs):
                    assert mine is not new and np.array_equal(mine, new)
            for ours, theirs in zip(again, (reference.estimate(updated),
                                            reference.predict_ahead(updated, horizon_s))):
                for mine, expected in zip(ours, theirs):
                    assert_close(mine, expected)
            other = fast.predict_update(state, dt, z + 3.0)[0]
            # Another state, or another horizon, is computed afresh.
            assert np.array_equal(fast.predict_ahead(updated, horizon_s)[1], again[1][1])
            assert np.array_equal(fast.predict_ahead(other, 1.0)[1],
                                  FastRailModel().predict_ahead(other, 1.0)[1])


def test_learned_noise_and_gate_nis_follow_the_reference(models):
    """A scale learned below 1 (gate_nis set) and at its bounds, step for step."""
    reference, fast = models
    for scale in (1e-3, 0.3, 1.0, 100.0):
        for state, dt, z, rng in _random_states(reference, 7, 20):
            state = state._replace(noise=state.noise._replace(
                scale=scale, information=20.0, count=50))
            ours, result = fast.update(state, z, [[2.0]])
            theirs, their_result = reference.update(state, z, [[2.0]])
            assert_states_close(ours, theirs)
            assert_results_close(result, their_result, z)
            assert (result.gate_nis is not None) == (scale < 1.0)


def test_a_whole_run_stays_with_the_reference(models):
    """300 steps from each model's own state: the differences do not grow."""
    reference, fast = models
    ours = theirs = reference.first_estimate(0.0, 1.0)
    rng = np.random.default_rng(5)
    for k in range(300):
        dt = 0.1 + float(rng.uniform(-0.002, 0.002))
        z = 0.02 * k * k + float(rng.normal())
        ours = fast.update(fast.predict(ours, dt), z, [[1.0]])[0]
        theirs = reference.update(reference.predict(theirs, dt), z, [[1.0]])[0]
        assert_states_close(ours, theirs)


def test_unreachable_regimes_and_zero_dt(models):
    """A zero dt (Π = I) from a sure regime: c̄_j = 0 for the others, which keep their own."""
    reference, fast = models
    state = reference.first_estimate(5.0, 1.0)
    sure = state._replace(probabilities=np.array([0.0, 1.0, 0.0, 0.0]))
    for dt in (0.0, 0.1):
        assert_states_close(fast.predict(sure, dt), reference.predict(sure, dt))


@pytest.mark.filterwarnings('ignore::RuntimeWarning')  # the overflow, on purpose
def test_errors_are_the_reference_s(models):
    """Bad inputs raise ValueError on both paths; an overflow too."""
    reference, fast = models
    state = reference.first_estimate(5.0, 1.0)
    for model in models:
        with pytest.raises(ValueError):
            model.predict(state, -1.0)
        with pytest.raises(ValueError):
            model.update(state, float('nan'))
        with pytest.raises(ValueError):
            model.update_component(state, 1.0, None, 1)
        with pytest.raises(ValueError):
            model.update_component(state, 1.0, [[1.0]], 6)
        with pytest.raises(ValueError):
            model.update(state._replace(covariances=np.zeros((4, 6, 6))), 1.0, [[0.0]])
        huge = state._replace(means=state.means * 1e306)
        with pytest.raises(ValueError):
            model.predict(huge, 1e3)
        with pytest.raises(ValueError):
            model.predict_update(huge, 1e3, 1.0)
        with pytest.raises(ValueError):
            model.predict_ahead(state, 1.0, u=[1.0])


def test_the_compiled_model_overrides_no_private_part_of_the_imm():
    """Only public IMM methods are compiled: the hooks and the flow are the reference's."""
    for name in vars(IMM):
        if name.startswith('_') and not name.startswith('__'):
            assert getattr(FastRailModel, name) is getattr(IMM, name), name
    for name in vars(RailModel):
        if name.startswith('_') and not name.startswith('__'):
            assert getattr(FastRailModel, name) is getattr(RailModel, name), name


def test_the_switch(monkeypatch):
    """Opt-in: compiled with KF_TRAIN_JIT=1 where numba is; the estimator's fast_path too."""
    monkeypatch.delenv(JIT_VARIABLE, raising=False)
    assert not jit_enabled() and type(rail_model()) is RailModel
    assert type(StreamEstimator(RAIL).model.imm) is RailModel
    monkeypatch.setenv(JIT_VARIABLE, '1')
    assert jit_enabled() and type(rail_model()) is FastRailModel
    FastRailModel().warm_up()  # make jit-cache's: every kernel once
    assert type(make_rail_filter(0.0).imm) is FastRailModel
    assert type(StreamEstimator(RAIL).model.imm) is FastRailModel
    assert type(rail_model(jit=False)) is RailModel
    monkeypatch.setenv(JIT_VARIABLE, '0')
    assert not jit_enabled() and type(rail_model()) is RailModel
    monkeypatch.setenv(JIT_VARIABLE, '1')
    monkeypatch.setattr(StreamEstimator, 'fast_path', False)
    assert type(StreamEstimator(RAIL).model.imm) is RailModel


def _stream(fast_path, monkeypatch, events):
    """Return every output of an estimator fed ``events`` (fast_path: compiled or not)."""
    monkeypatch.setattr(StreamEstimator, 'fast_path', fast_path)
    monkeypatch.setenv(JIT_VARIABLE, '1' if fast_path else '0')
    estimator = StreamEstimator(RAIL)
    outputs = []
    for kind, stamp, value, variance in events:
        try:
            if kind == 'position':
                step = estimator.process(stamp, value, variance)
            else:
                step = estimator.process_velocity(stamp, value, variance)
        except Rejected as rejection:
            outputs.append(rejection.reason)
            continue
        outputs.append(step)
    return outputs


def test_the_stream_with_rewinds_speeds_and_gaps_is_the_reference_s(monkeypatch):
    """Jittered stamps, gaps, late (out-of-sequence) fixes and speeds, through the estimator."""
    params = dataclasses.replace(family_parameters('metro', 4), duration_s=90.0)
    scenario, run = rail_scenario(4, 'metro', parameters=params)
    rng = np.random.default_rng(11)
    stamps = (scenario.t_s + rng.uniform(-0.002, 0.002, scenario.t_s.size)) * NS
    events = []
    for k, (stamp, z) in enumerate(zip(stamps.astype(np.int64).tolist(),
                                       scenario.z[:, 0].tolist())):
        if 200 <= k < 230:
            continue                                   # a 3-s gap
        events.append(('position', stamp, z, 1.0))
        if k % 3 == 0:
            speed = float(run.state_at(np.array([stamp / NS])).velocity_mps[0]
                          + rng.normal(0.0, 0.1))
            events.append(('speed', stamp + NS // 50, speed, 0.01))
    for k in range(20, len(events) - 5, 37):            # late by a few steps: a rewind
        events[k], events[k + 3] = events[k + 3], events[k]
    ours = _stream(True, monkeypatch, events)
    theirs = _stream(False, monkeypatch, events)
    assert len(ours) == len(theirs)
    for mine, reference in zip(ours, theirs):
        if isinstance(reference, str):
            assert mine == reference
            continue
        assert_close(mine.x, reference.x)
        assert_close(mine.P, reference.P)
        assert_close(mine.predicted_x, reference.predicted_x)
        assert_close(mine.predicted_P, reference.predicted_P)


def test_parameters_reach_the_kernels():
    """Other rates, stop speed and entry noises: still the reference's numbers."""
    params = RailModelParameters(stop_rate_hz=3.0, stop_speed_mps=1.5, plateau_std_mps2=0.3,
                                 cruise_std_mps2=0.2, departure_rate_hz=0.2, stand_noise=0.01)
    reference, fast = RailModel(params), FastRailModel(params)
    for state, dt, z, _ in _random_states(reference, 3, 60):
        assert_states_close(fast.predict(state, dt), reference.predict(state, dt))
        assert_states_close(fast.update(state, z)[0], reference.update(state, z)[0])


def test_the_compiled_dynamics_are_rail_dynamics_own(models):
    """F(dt), Q(dt) compiled (up to 1.5 τ: the series), the quadrature's beyond."""
    reference, fast = models
    tau_s = reference.parameters.response_time_s
    rng = np.random.default_rng(2)
    for dt in [0.0, 1e-6, 0.05 * tau_s, 0.0999 * tau_s, 0.1 * tau_s, 1.5 * tau_s,
               1.5001 * tau_s, 5.0] + rng.uniform(0.0, 2.0 * tau_s, 40).tolist():
        F, Q = fast.dynamics(dt)
        assert not F.flags.writeable and not Q.flags.writeable
        F_ref, Q_ref, _ = reference.matrices(dt)
        for j in range(4):
            assert_close(F[j], F_ref[j], f'F at {dt}')
            assert_close(Q[j], Q_ref[j], f'Q at {dt}')
