"""
The 2-state step and the white-noise Q(dt) have one home each; their copies equal it.

kf_train.filters.closed_form is the written-out predict and correct; the hot loops
(FastTrainFilter.step/run) transcribe it inline, and the estimator's closed-form adapter
calls it. models.white_noise_terms is the white-noise Q(dt); the presets' continuous
noise uses its integrals. All are held here bit for bit: the same operations in the
same order give the same doubles. The bank (the generic n-state arithmetic, vectorised
across objects) is held to it to rounding.
"""

from kf_train.batch import run_bank
from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.filters import (
    closed_form, FastTrainFilter, NS_PER_S, white_noise_terms, WhiteNoiseAcceleration)
from kf_train.presets import preset_from_mapping
import numpy as np

Q_DENSITY = 0.3
# The train's constant-velocity KF without a gate: the defaults before issue 11 (the
# defaults are now the rail preset with the gate on; test_estimator_rail.py).
TRAIN = {'preset': 'train', 'gate_probability': 1.0}


def _cases(seed: int, n: int):
    """Yield n random (state, z, dt, R): states with a valid covariance, awkward scales."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        p00, p11 = 10.0 ** rng.uniform(-6, 4, 2)
        p01 = rng.uniform(-0.99, 0.99) * np.sqrt(p00 * p11)
        state = (float(rng.normal(0, 1e3)), float(rng.normal(0, 30)), float(p00), float(p01),
                 float(p11))
        yield state, float(rng.normal(0, 1e3)), float(rng.exponential(0.2)), float(
            10.0 ** rng.uniform(-4, 3))


def _reference(state, z, dt, R):
    """Return closed_form's posterior and statistics for one predict over dt and update."""
    q00, q01, q11 = white_noise_terms(Q_DENSITY, dt)
    prior = closed_form.predict(*state, dt, q00, q01, q11)
    return closed_form.correct(*prior, z, R)


def test_fast_step_and_run_are_closed_form_bit_for_bit():
    """FastTrainFilter.step and .run (inline transcriptions) equal closed_form exactly."""
    noise = WhiteNoiseAcceleration(Q_DENSITY)
    for state, z, dt, R in _cases(1, 300):
        posterior, update = _reference(state, z, dt, R)
        x, P = np.array(state[:2]), np.array([[state[2], state[3]], [state[3], state[4]]])
        fast = FastTrainFilter(x, P, noise)
        assert fast.step(z, dt, R) == update.nis
        assert fast.state == posterior and fast.last_update() == update
        run = FastTrainFilter(x, P, noise).run([z], [dt], [R])
        assert (run.x[0, 0], run.x[0, 1], run.P[0, 0, 0], run.P[0, 0, 1], run.P[0, 1, 1]) == (
            posterior)


def test_the_bank_is_closed_form_to_rounding():
    """Every object of a bank of trains (the generic Joseph form) equals closed_form to 1e-12."""
    cases = list(_cases(2, 500))
    state = (3.0, 5.0, 4.0, 0.5, 1.0)
    preset = preset_from_mapping({
        'name': 'white-noise', 'states': ['position', 'velocity'],
        'measurements': ['position'], 'motion': 'constant_velocity',
        'process_noise': {'continuous': [[0.0, 0.0], [0.0, Q_DENSITY]]},
        'R': [[0.25]], 'initial_state': state[:2],
        'initial_covariance': [[state[2], state[3]], [state[3], state[4]]],
        'nominal_period_s': 0.1})
    # One row per object, each at its own time (whole nanoseconds: the bank's dt).
    t = (np.rint(np.array([c[2] for c in cases]) * NS_PER_S) + 1.0) / NS_PER_S
    z = np.array([[c[1]] for c in cases])
    result = run_bank(preset, t, z, None, np.arange(len(cases)))
    for i, dt in enumerate(t.tolist()):
        posterior, update = _reference(state, float(z[i, 0]), dt, 0.25)
        ours = (result.x[i, 0], result.x[i, 1], result.P[i, 0, 0], result.P[i, 0, 1],
                result.P[i, 1, 1])
        # Rounding only: the Joseph form and numpy's dt³ against the reduced form.
        np.testing.assert_allclose(ours, posterior, rtol=1e-12, atol=1e-12)


def test_the_estimators_closed_form_is_closed_form_bit_for_bit():
    """The train estimator's fast model is closed_form: same state after each step."""
    settings = EstimatorSettings(**TRAIN, process_noise_density=Q_DENSITY,
                                 initial_state=(0.0, 5.0))
    estimator = StreamEstimator(settings)
    rng = np.random.default_rng(3)
    state, stamp_ns, previous_ns = None, 0, 0
    for k in range(200):
        stamp_ns += int(rng.integers(1, 400_000_000))
        z = 10.0 * stamp_ns / 1e9 + float(rng.normal())
        step = estimator.process(stamp_ns, z, 0.5)
        if state is not None:
            dt = (stamp_ns - previous_ns) / 1e9
            posterior, update = _reference(state, z, dt, 0.5)
            assert (float(step.x[0]), float(step.x[1]), float(step.P[0, 0]),
                    float(step.P[0, 1]), float(step.P[1, 1])) == posterior
            assert step.update.nis == update.nis
        state = (float(step.x[0]), float(step.x[1]), float(step.P[0, 0]), float(step.P[0, 1]),
                 float(step.P[1, 1]))
        previous_ns = stamp_ns


def test_white_noise_q_has_one_home():
    """Q(dt) of models and of the presets' continuous noise agree."""
    rng = np.random.default_rng(4)
    dts = np.concatenate([[0.0, 0.1, 0.2, 1.0, 2.5], rng.exponential(0.5, 200)])
    preset = preset_from_mapping({
        'name': 'white-noise', 'states': ['position', 'velocity'],
        'measurements': ['position'], 'motion': 'constant_velocity',
        'process_noise': {'continuous': [[0.0, 0.0], [0.0, Q_DENSITY]]},
        'R': [[1.0]], 'initial_state': [0.0, 0.0], 'initial_covariance': [1.0, 1.0],
        'nominal_period_s': 0.1})
    batch = preset.dynamics.Q_batch(dts)
    for k, dt in enumerate(dts.tolist()):
        q00, q01, q11 = white_noise_terms(Q_DENSITY, dt)
        Q = WhiteNoiseAcceleration(Q_DENSITY)(dt)
        assert (Q[0, 0], Q[0, 1], Q[1, 0], Q[1, 1]) == (q00, q01, q01, q11)
        # The presets' general form ∫ F(s) Qc F(s)ᵀ ds with Qc = diag(0, q) has the same
        # operations, its zero terms adding exactly, but raises arrays to powers with
        # numpy, whose pow kernel may differ from CPython's (glibc, < 0.52 ulp): SIMD
        # kernels are accurate to about 1 ulp. dt³/3 and dt²/2 then round once more in
        # the division and once in the product with q: at most ~3.5 ulp apart in
        # total, so 8 eps relative leaves a margin. dt itself is exact in both.
        tolerance = 8 * np.finfo(float).eps
        np.testing.assert_allclose([batch[k, 0, 0], batch[k, 0, 1], batch[k, 1, 0]],
                                   [q00, q01, q01], rtol=tolerance, atol=0.0)
        assert batch[k, 1, 1] == q11
