"""The rail likelihood the node runs: per-fix variances, the learned scale on R, the χ² gate."""

import math

from kf_train.batch import rail_log_likelihoods, RailNoise, Segment
from kf_train.estimator import EstimatorSettings, Rejected, StreamEstimator
from kf_train.estimator.live_presets import resolve_preset
from kf_train.filters import LOG_2PI, RailModelParameters
from kf_train.sim.rail import rail_scenario
import numpy as np
import pytest

GATE = 15.136705226623606      # χ²(1) at 0.9999: the node's default gate (checked below)
HOLD_VARIANCE = 0.3 ** 2       # a held position's speed of 0: hold_speed_std_mps²


def _run(seed: int, rows: int, outliers=(), true_scale: float = 0.5, jitter_s: float = 0.0,
         gaps=(), decades: float = 3.0):
    """
    Return (stamps ns, segment, variances) of a metro run: variances over 3 decades.

    Each fix's error is N(0, true_scale · r_k) (so the node learns s ≈ true_scale), plus
    +60 m at the rows in ``outliers``; stamps jittered by ±``jitter_s``, each row of
    ``gaps`` delayed (with all after it) by 3 s.
    """
    scenario, _ = rail_scenario(seed=seed, family='metro')
    rng = np.random.default_rng(seed)
    t = scenario.t_s[:rows] + rng.uniform(-jitter_s, jitter_s, rows)
    for row in gaps:
        t[row:] += 3.0
    stamps = np.round(t * 1e9).astype(np.int64)
    variances = 10.0 ** rng.uniform(-1.0, decades - 1.0, rows)         # 0.1 to 100 m²
    z = scenario.truth[:rows, 0] + np.sqrt(true_scale * variances) * rng.standard_normal(rows)
    z[list(outliers)] += 60.0
    return stamps, Segment(stamps / 1e9, z[:, None]), variances


def _node(stamps, segment, variances, reasons=None):
    """
    Return the node's per-fix (gated, y, S, scale after) and its ℓ, from its own states.

    ``reasons``, a list, receives each rejection's reason.
    """
    estimator = StreamEstimator(EstimatorSettings())
    assert estimator.gate_threshold == pytest.approx(GATE, rel=1e-12)
    imm = estimator.model.imm
    gated, ys, Ss, scales, total = [], [], [], [], 0.0
    for k, (stamp, z, r) in enumerate(zip(stamps.tolist(), segment.z[:, 0].tolist(),
                                          variances.tolist())):
        if k:
            fusion = estimator._fusion         # the IMM state behind the newest (x, P)
            prior = estimator.model.state_of(fusion.x, fusion.P)
            predicted = imm.predict(prior, (stamp - fusion.last_stamp_ns) / 1e9)
            s_now = prior.noise.scale
            R = r * s_now
            y = z - predicted.means[:, 0]
            s = predicted.covariances[:, 0, 0] + R
            with np.errstate(divide='ignore'):
                logs = np.log(predicted.probabilities) - 0.5 * (y * y / s + np.log(s) + LOG_2PI)
            top = logs.max()
            term = top + math.log(np.exp(logs - top).sum())
            # A held position is fused as a speed of 0 (Fusion._fuse_hold): its term.
            y = -predicted.means[:, 1]
            s = predicted.covariances[:, 1, 1] + HOLD_VARIANCE
            with np.errstate(divide='ignore'):
                logs = np.log(predicted.probabilities) - 0.5 * (y * y / s + np.log(s) + LOG_2PI)
            top = logs.max()
            hold_term = top + math.log(np.exp(logs - top).sum())
        holds = estimator.stats().holds
        try:
            step = estimator.process(stamp, z, r)
            result, rejected = step.update, False
            if estimator.stats().holds > holds:
                term = hold_term
        except Rejected as rejection:
            assert rejection.reason in ('outlier', 'repeated')
            if reasons is not None:
                reasons.append(rejection.reason)
            result, rejected = rejection.update, True
        if k == 0:
            continue
        if result is None:                     # a hold: no position innovation
            y = S = math.nan
        else:
            y, S = float(result.innovation[0]), float(result.innovation_covariance[0, 0])
        if rejected:                           # the density at the gate's edge
            gate_S = S + (1.0 - s_now) * r if s_now < 1.0 else S
            term = -0.5 * (GATE + math.log(gate_S) + LOG_2PI)
        total += term
        gated.append(rejected)
        ys.append(y)
        Ss.append(S)
        scales.append(estimator.noise_scale())
    return np.array(gated), np.array(ys), np.array(Ss), np.array(scales), total


@pytest.fixture(scope='module')
def node_run():
    """Return a 1200-fix run with isolated 60-m outliers, and what the node made of it."""
    stamps, segment, variances = _run(11, 1200, outliers=range(150, 1200, 97))
    return segment, variances, _node(stamps, segment, variances)


def test_the_likelihood_is_the_nodes_with_variances_learned_scale_and_gate(node_run):
    """The numpy reference gates, learns and scores exactly as the StreamEstimator does."""
    segment, variances, (gated, ys, Ss, scales, node_ll) = node_run
    base = resolve_preset('rail').parameters
    result = rail_log_likelihoods(base, [segment], [RailNoise()], innovations=True,
                                  variances=[variances], adaptation=base.adaptation(),
                                  gate_threshold=GATE, engine='numpy')
    # The run gates its 11 outliers and some noise beyond 4σ: the gate matters here.
    assert gated.sum() >= 11
    np.testing.assert_array_equal(result.gated[0], gated)
    assert result.gated_count[0] == gated.sum()
    # Same equations on the same floats but for dt (float seconds here, integer ns there:
    # ~1e-17 s apart) and summation orders: each state entry is within a few ulps, the
    # filter forgets older rounding, so y (~1 m, z ~ 1e3 m) agrees to ~1e-12 m, S and the
    # scale (a ratio of averages of y²) to ~1e-12 relative; 1e-8 leaves a margin of 1e4.
    np.testing.assert_allclose(result.innovation[0], ys, rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(result.variance[0], Ss, rtol=1e-8)
    np.testing.assert_allclose(result.scale[0], scales, rtol=1e-8)
    # ℓ (~ -2e3): a sum of 1199 terms each within ~1e-12: 1e-9 relative.
    assert result.log_likelihood[0] == pytest.approx(node_ll, rel=1e-9)
    assert scales[-1] == pytest.approx(0.5, rel=0.5)   # it learned the true scale's order


@pytest.mark.parametrize('engine', ['numpy', 'numba'])
def test_a_repeated_epoch_is_judged_on_the_r_in_use_as_the_node_judges_it(engine):
    """Exact repeats of the last fix while moving: the node's 'repeated', gated here."""
    if engine == 'numba':
        pytest.importorskip('numba')
    # Errors of 3-10 cm for 0.1-1 m² given: the learned R is ~1 % of it, and a repeat
    # 0.1 s after its fix (1-2 m behind a moving train) passes the gate on the R given.
    stamps, segment, variances = _run(16, 1200, true_scale=0.01, decades=1.0)
    z = segment.z.copy()
    rows = list(range(200, 1200, 53))
    z[rows, 0] = z[[row - 1 for row in rows], 0]
    segment = Segment(segment.t_s, z)
    reasons = []
    gated, ys, Ss, scales, node_ll = _node(stamps, segment, variances, reasons)
    assert reasons.count('repeated') >= 10        # the moving ones (some are at stops)
    base = resolve_preset('rail').parameters
    result = rail_log_likelihoods(base, [segment], [RailNoise()], innovations=True,
                                  variances=[variances], adaptation=base.adaptation(),
                                  gate_threshold=GATE, engine=engine)
    np.testing.assert_array_equal(result.gated[0], gated)
    # As in the test above: the same equations, within ~1e-12; 1e-8 for a margin.
    np.testing.assert_allclose(result.innovation[0], ys, rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(result.scale[0], scales, rtol=1e-8)
    assert result.log_likelihood[0] == pytest.approx(node_ll, rel=1e-9)


@pytest.mark.parametrize('engine', ['numpy', 'numba'])
def test_a_repeat_after_an_outage_is_judged_on_the_speed_as_the_node_judges_it(engine):
    """30-s outages while moving, each ended by the last fix again: rejected, gated here."""
    if engine == 'numba':
        pytest.importorskip('numba')
    stamps, segment, variances = _run(16, 2600, true_scale=0.01, decades=1.0)
    keep = np.ones(2600, dtype=bool)
    repeats = []
    for last in (700, 2000):                      # at 18 and 12 m/s (10 Hz rows)
        keep[last + 1:last + 301] = False          # 30 s without a fix
        repeats.append(last + 301)
    z = segment.z.copy()
    for row in repeats:
        z[row, 0] = z[row - 301, 0]                # the last fix before the outage again
    stamps, variances = stamps[keep], variances[keep]
    segment = Segment(segment.t_s[keep], z[keep])
    reasons = []
    gated, ys, Ss, scales, node_ll = _node(stamps, segment, variances, reasons)
    assert reasons.count('repeated') >= 2
    base = resolve_preset('rail').parameters
    result = rail_log_likelihoods(base, [segment], [RailNoise()], innovations=True,
                                  variances=[variances], adaptation=base.adaptation(),
                                  gate_threshold=GATE, engine=engine)
    np.testing.assert_array_equal(result.gated[0], gated)
    # Each repeat passes the gate on its prediction (the speed rule gates it).
    after = np.nonzero(np.diff(segment.t_s) > 20.0)[0]
    assert after.size == 2 and np.all(gated[after])
    assert np.all(ys[after] ** 2 / Ss[after] < GATE)
    # As in the tests above: the same equations, within ~1e-12; 1e-8 for a margin.
    np.testing.assert_allclose(result.innovation[0], ys, rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(result.scale[0], scales, rtol=1e-8)
    assert result.log_likelihood[0] == pytest.approx(node_ll, rel=1e-9)


def test_the_defaults_keep_the_fixed_r_likelihood():
    """Without variances, adaptation and gate: R fixed, nothing gated, the scale stays 1."""
    _, segment, _ = _run(12, 300)
    base = RailModelParameters()
    plain = rail_log_likelihoods(base, [segment], [RailNoise(), RailNoise(1e-3)],
                                 innovations=True, engine='numpy')
    assert plain.gated_count.tolist() == [0, 0]
    assert np.all(plain.scale == 1.0)
    # R of the setting overrides the variances, as the node's measurement_variance does.
    overridden = rail_log_likelihoods(base, [segment], [RailNoise(None, None, None, 1.0)],
                                      variances=[np.full(300, 50.0)], engine='numpy')
    assert overridden.log_likelihood[0] == plain.log_likelihood[0]


def test_a_gated_fix_scores_the_edge_and_does_not_move_the_state():
    """One 1-km outlier: gated; the state, the next innovations and ℓ's other terms hold."""
    _, segment, variances = _run(13, 200)
    base = RailModelParameters()
    kwargs = {'innovations': True, 'variances': [variances],
              'adaptation': base.adaptation(), 'gate_threshold': GATE, 'engine': 'numpy'}
    clean = rail_log_likelihoods(base, [segment], [RailNoise()], **kwargs)
    z = segment.z.copy()
    z[100] += 1000.0
    hit = rail_log_likelihoods(base, [Segment(segment.t_s, z)], [RailNoise()], **kwargs)
    assert hit.gated[0].tolist() == [k == 99 for k in range(199)]
    assert clean.gated_count[0] == 0
    edge = -0.5 * (GATE + math.log(hit.variance[0, 99] * 1.0) + LOG_2PI)
    scale_before = hit.scale[0, 98]
    if scale_before < 1.0:
        edge = -0.5 * (GATE + math.log(hit.variance[0, 99] + (1.0 - scale_before)
                                       * variances[100]) + LOG_2PI)
    before = clean.innovation[0, :99]
    np.testing.assert_array_equal(hit.innovation[0, :99], before)
    assert hit.scale[0, 99] == scale_before                # a gated fix teaches nothing
    # The fix after it is predicted over two periods: its term differs; the rest of ℓ
    # up to the outlier is the clean run's.
    assert np.isfinite(hit.log_likelihood[0])
    assert hit.log_likelihood[0] != clean.log_likelihood[0]
    assert edge < -0.5 * GATE


def _numba_case():
    """Return (segment, variances, settings): jitter, a 3-s gap, outliers, 12 in a row."""
    outliers = list(range(100, 900, 61)) + list(range(500, 512))   # 12 gated: 1.3 s > 1.5 τ
    _, segment, variances = _run(14, 1000, outliers=outliers, jitter_s=0.004, gaps=(300,))
    settings = [RailNoise(), RailNoise(1e-3, 1e-5, None, None), RailNoise(1e-2, 1e-3, 1e-5, 0.8),
                RailNoise(3e-5, 1e-6, 1e-7, None)]
    return segment, variances, settings


def test_the_compiled_likelihood_is_the_numpy_reference():
    """The compiled engine against numpy: ℓ, gated fixes, y, S, the scale path per setting."""
    pytest.importorskip('numba')
    segment, variances, settings = _numba_case()
    base = RailModelParameters()
    results = [rail_log_likelihoods(base, [segment, segment], settings, innovations=True,
                                    variances=[variances, variances[::-1].copy()],
                                    adaptation=base.adaptation(), gate_threshold=GATE,
                                    engine=engine) for engine in ('numpy', 'numba')]
    reference, compiled = results
    assert np.all(reference.gated_count >= 12)             # the run of 12 is gated
    np.testing.assert_array_equal(compiled.gated, reference.gated)
    np.testing.assert_array_equal(compiled.gated_count, reference.gated_count)
    # The same equations in other orders (loops against numpy's reductions; Q as the
    # unit tables' weighted sum either way): each term of ℓ (|ℓ| ~ 4e3 over 2000 fixes)
    # within ~1e-13 relative, y within ~1e-12 m; 1e-9 relative (and 1e-8 m for y,
    # which crosses 0) leaves a margin of 1e3 or more.
    np.testing.assert_allclose(compiled.log_likelihood, reference.log_likelihood, rtol=1e-9)
    np.testing.assert_allclose(compiled.innovation, reference.innovation, rtol=0, atol=1e-8)
    np.testing.assert_allclose(compiled.variance, reference.variance, rtol=1e-9)
    np.testing.assert_allclose(compiled.scale, reference.scale, rtol=1e-9)


def test_the_compiled_likelihood_without_node_features_is_the_numpy_one():
    """The defaults (R fixed, no gate, no learning) agree too; 'auto' takes numba."""
    pytest.importorskip('numba')
    # Errors of σ = 1 m, as R = 1 says: a model that fits (with 60-m fixes fused, or
    # errors 10x R, near-degenerate regime probabilities amplify rounding from step to
    # step, and no fixed tolerance holds over 1000 steps).
    _, segment, _ = _run(14, 1000, true_scale=1.0, jitter_s=0.004, gaps=(300,), decades=0.0)
    settings = _numba_case()[2]
    base = RailModelParameters(noise_window=0)
    reference, compiled = (rail_log_likelihoods(base, [segment], settings, engine=engine)
                           for engine in ('numpy', 'auto'))
    np.testing.assert_allclose(compiled.log_likelihood, reference.log_likelihood, rtol=1e-9)
    assert compiled.gated_count.tolist() == [0] * len(settings)


def test_bad_inputs_are_refused():
    """An unknown engine, a variance <= 0, variances not one per segment: ValueError."""
    _, segment, variances = _run(15, 50)
    base = RailModelParameters()
    with pytest.raises(ValueError, match='engine'):
        rail_log_likelihoods(base, [segment], [RailNoise()], engine='fortran')
    bad = variances.copy()
    bad[3] = 0.0
    with pytest.raises(ValueError, match='variances'):
        rail_log_likelihoods(base, [segment], [RailNoise()], variances=[bad], engine='numpy')
    with pytest.raises(ValueError, match='one array per segment'):
        rail_log_likelihoods(base, [segment], [RailNoise()], variances=[], engine='numpy')
    with pytest.raises(ValueError, match='gate_threshold'):
        rail_log_likelihoods(base, [segment], [RailNoise()], gate_threshold=0.0)
