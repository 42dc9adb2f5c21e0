"""``kf-train tune``'s validation: the hold-out, the node's score, the refusal, the verdicts."""

import math

from kf_train.batch import Innovations, nis_consistency, Segment
from kf_train.cli import main as kf_train_main
from kf_train.cli.tune import main as tune_main
from kf_train.estimator import Rejected, StreamEstimator
from kf_train.evaluate import later_fix, later_fix_errors, later_fix_score, MAX_BRACKET_S
from kf_train.filters import FastRailModel, JIT_VARIABLE, numba_available, RailModel
from kf_train.presets import load_rail_preset, rail_preset_from_mapping
from kf_train.sim.rail import rail_scenario
from kf_train.tune import rail as tune_rail_module, validation as validation_module
from kf_train.tune.validation import (
    Comparison, GAIN_SIGMAS, held_out_gain, inconsistent_reason, MIN_SPLIT_S, model_verdict,
    NIS_FACTOR, node_settings, rail_preset_yaml, score_setting, SettingScore, split_holdout,
    worse_reason)
import numpy as np
import pytest
import yaml

# -- the hold-out ------------------------------------------------------------------------


def _ramp(duration_s: float, step_s: float = 0.5) -> Segment:
    """Return a segment of rows every step_s over duration_s, z = t."""
    t = np.arange(0.0, duration_s + step_s / 2, step_s) + 100.0
    return Segment(t, t[:, None].copy(), None, None)


def test_split_holdout_cuts_each_segment_at_three_quarters_of_its_span():
    long, short = _ramp(400.0), _ramp(MIN_SPLIT_S / 2)
    holdout = split_holdout([long, short], 0.25)
    cut = 100.0 + 300.0
    assert holdout.windows[0] == (cut, math.inf)
    assert holdout.training[0].t_s[-1] < cut <= long.t_s[holdout.training[0].t_s.size]
    assert holdout.training[0].z.shape == (holdout.training[0].t_s.size, 1)
    assert holdout.windows[1] is None and holdout.training[1] is short
    assert holdout.kept_whole == 1
    off = split_holdout([long, short], 0.0)
    assert off.windows == [None, None] and off.kept_whole == 0
    assert off.training[0] is long
    with pytest.raises(ValueError):
        split_holdout([long], 1.0)


# -- the later fix -----------------------------------------------------------------------

def test_later_fix_takes_the_fix_at_t_plus_2_s_or_interpolates_within_a_bracket():
    t = np.array([0.0, 0.5, 2.0005, 2.4, 3.1, 4.5])
    z = np.array([0.0, 5.0, 20.0, 24.0, 31.0, 45.0])
    target, valid = later_fix(t, z)
    assert valid[0] and target[0] == 20.0                # within 1 ms: the fix itself
    assert valid[1] and target[1] == pytest.approx(24.0 + (2.5 - 2.4) / 0.7 * 7.0)
    assert 3.1 - 2.4 <= MAX_BRACKET_S
    assert not valid[2]               # 4.0005 lies between 3.1 and 4.5: 1.4 s, too wide
    assert not valid[3:].any()        # past the last fix
    score = later_fix_score(t, z, np.array([21.0, 24.1, 0, 0, 0, 0]), np.full(6, 0.25),
                            1.0, made=np.ones(6, dtype=bool))
    assert score.count == 2
    assert score.rmse_m == pytest.approx(math.sqrt((1.0 + (24.1 - target[1]) ** 2) / 2))
    assert score.coverage == 1.0      # |error| <= 2 sqrt(0.25 + 1)
    # The errors behind the score: the scored rows, in order, and their band's verdict.
    mean = np.array([21.0, 28.0, 0, 0, 0, 0])
    found = later_fix_errors(t, z, mean, np.full(6, 0.25), 1.0, made=np.ones(6, dtype=bool))
    assert found.scored.tolist() == [True, True, False, False, False, False]
    np.testing.assert_array_equal(found.error_m, mean[:2] - target[:2])
    assert found.covered.tolist() == [True, False]       # 28 - 24.14 > 2 sqrt(1.25)
    assert found.summary() == later_fix_score(t, z, mean, np.full(6, 0.25), 1.0,
                                              made=np.ones(6, dtype=bool))
    assert later_fix_errors(t, z, mean, np.full(6, 0.25), 1.0,
                            made=np.zeros(6, dtype=bool)).summary().count == 0


# -- the node's score --------------------------------------------------------------------

def test_score_setting_is_the_node_estimator_run_by_hand():
    scenario, _ = rail_scenario(seed=3, family='metro')
    rows = 600                                            # 60 s at 10 Hz
    z = scenario.z[:rows].copy()
    z[450, 0] += 1000.0                                   # one outlier for the gate
    segment = Segment(scenario.t_s[:rows], z, None, scenario.truth[:rows])
    window = (40.0 + float(segment.t_s[0]), math.inf)
    found = score_setting('rail', [segment], [window])
    # By hand: the node's defaults, stamps from 1 s, R = the preset's 1 m², the IMM
    # compiled where numba is (as the scoring runs it).
    estimator = StreamEstimator(node_settings('rail'), jit=numba_available())
    t = segment.t_s
    stamps = 10 ** 9 + np.round((t - t[0]) * 1e9).astype(np.int64)
    mean, variance, nis, gated = np.zeros(rows), np.zeros(rows), [], 0
    r_in_use = np.ones(rows)        # the later fix's share of the band: R learned
    for k in range(rows):
        try:
            step = estimator.process(int(stamps[k]), float(z[k, 0]), 1.0)
            mean[k], variance[k] = step.predicted_x[0], step.predicted_P[0, 0]
            if step.update is not None and t[k] >= window[0]:
                nis.append(step.update.nis)
        except Rejected as rejection:
            gated += rejection.reason == 'outlier' and t[k] >= window[0]
            x, P = estimator.predict_to(int(stamps[k]) + 2 * 10 ** 9)
            mean[k], variance[k] = x[0], P[0, 0]
        r_in_use[k] = estimator.noise_scale()
    made = (t >= window[0]) & (t + 2.0 <= t[-1] + 1e-9)
    ahead = np.searchsorted(t, t[made] + 2.0 - 1e-6)
    error = mean[made] - z[ahead, 0]
    truth_error = mean[made] - scenario.truth[:rows][ahead, 0]
    assert gated == 1 and found.gated == 1
    assert found.count == int(made.sum())
    assert found.rmse_m == pytest.approx(math.sqrt(np.mean(error ** 2)), rel=1e-12)
    assert found.coverage == pytest.approx(
        np.mean(np.abs(error) <= 2.0 * np.sqrt(variance[made] + r_in_use[ahead])), rel=1e-12)
    assert not np.all(r_in_use == 1.0)     # the scale was learned: the band is not R given
    assert found.truth_rmse_m == pytest.approx(math.sqrt(np.mean(truth_error ** 2)),
                                               rel=1e-12)
    assert found.mean_nis == pytest.approx(np.mean(nis), rel=1e-12)
    assert found.resets == found.reacquisitions == 0
    # The same preset given as an object (written to a file the node reads) scores alike.
    again = score_setting(load_rail_preset(), [segment], [window])
    assert _figures(again) == _figures(found)
    np.testing.assert_array_equal(again.errors_m, found.errors_m)
    np.testing.assert_array_equal(again.blocks, found.blocks)
    # The errors kept for the gain's test are those the RMSE is of, blocked by 10 s.
    np.testing.assert_allclose(found.errors_m, error, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(found.blocks, np.floor((t[made] - t[made][0]) / 10.0))


def _figures(score):
    """Return a SettingScore without its per-prediction arrays (comparable with ==)."""
    return score._replace(errors_m=None, blocks=None)


def _metro_minute():
    """Return 60 s of a simulated metro run at 10 Hz and its window after 40 s."""
    scenario, _ = rail_scenario(seed=3, family='metro')
    segment = Segment(scenario.t_s[:600], scenario.z[:600].copy(), None,
                      scenario.truth[:600])
    return segment, (40.0 + float(segment.t_s[0]), math.inf)


@pytest.fixture()
def models_run(monkeypatch):
    """Return the list of the rail IMM classes the scoring's estimators run (no opt-in)."""
    monkeypatch.delenv(JIT_VARIABLE, raising=False)
    seen = []

    class Recording(StreamEstimator):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            seen.append(type(self.model.imm))
    monkeypatch.setattr(validation_module, 'StreamEstimator', Recording)
    return seen


def test_the_scoring_runs_the_compiled_rail_model_where_numba_is(models_run):
    pytest.importorskip('numba')
    segment, window = _metro_minute()
    compiled = score_setting('rail', [segment], [window])
    reference = score_setting('rail', [segment], [window], jit=False)
    assert models_run == [FastRailModel, RailModel]
    # The compiled model is the reference's to a norm-wise relative 1e-9 per step
    # (test_rail_fast.py) on states of positions below ~1 km here: the predictions
    # agree within ~1e-6 m, the RMSEs (~1 m) as closely; 1e-5 leaves a margin of 10.
    assert _figures(compiled)._replace(rmse_m=0.0, coverage=0.0, truth_rmse_m=0.0,
                                       mean_nis=0.0) == \
        _figures(reference)._replace(rmse_m=0.0, coverage=0.0, truth_rmse_m=0.0, mean_nis=0.0)
    np.testing.assert_allclose(compiled.errors_m, reference.errors_m, rtol=0, atol=1e-5)
    assert compiled.rmse_m == pytest.approx(reference.rmse_m, abs=1e-5)
    assert compiled.truth_rmse_m == pytest.approx(reference.truth_rmse_m, abs=1e-5)
    assert compiled.coverage == pytest.approx(reference.coverage, abs=1.0 / compiled.count)
    assert compiled.mean_nis == pytest.approx(reference.mean_nis, rel=1e-5)


def test_the_scoring_falls_back_to_numpy_without_numba(models_run, monkeypatch):
    monkeypatch.setattr(validation_module, 'numba_available', lambda: False)
    segment, window = _metro_minute()
    score_setting('rail', [segment], [window])
    assert models_run == [RailModel]


def test_rail_preset_yaml_loads_back_to_the_same_preset():
    preset = load_rail_preset()
    again = rail_preset_from_mapping(yaml.safe_load(rail_preset_yaml(preset)))
    assert again._replace(source=preset.source) == preset


# -- the refusal -------------------------------------------------------------------------

@pytest.fixture(scope='module')
def short_run(tmp_path_factory):
    """Simulate a 160-s rail run as a CSV; return its directory."""
    directory = tmp_path_factory.mktemp('holdout')
    assert kf_train_main(['simulate', '--scenario', 'rail', '--duration', '160', '--seed', '4',
                          '-p', 'rail_gnss_model:=white', '--output',
                          str(directory / 'run.csv')]) == 0
    return directory


@pytest.fixture()
def bad_fit(monkeypatch):
    """Make the fit return a setting with absurd noises (q_a = q_ℓ = 1 m²/s⁵)."""
    real = tune_rail_module.fit_rail_noise

    def fit(*args, **kwargs):
        found = real(*args, **kwargs)
        return found._replace(setting=found.setting._replace(
            acceleration_noise=1.0, command_noise=1.0))
    monkeypatch.setattr(tune_rail_module, 'fit_rail_noise', fit)


def test_a_tuned_setting_worse_on_the_held_out_part_is_not_written(short_run, bad_fit,
                                                                   capsys):
    output = short_run / 'refused.yaml'
    assert tune_main([str(short_run / 'run.csv'), '-o', str(output)]) == 0
    out = capsys.readouterr().out
    assert 'held-out (last 25 %)' in out
    assert 'kept the start: on held-out (last 25 %) the tuned setting predicts worse' in out
    assert not output.exists() and not (short_run / 'refused-rail.yaml').exists()
    forced = short_run / 'forced.yaml'
    assert tune_main([str(short_run / 'run.csv'), '-o', str(forced), '--force',
                      '--validate', str(short_run / 'run.csv')]) == 0
    out = capsys.readouterr().out
    assert '--force: written although' in out
    assert 'run.csv (after 10 s), ' in out       # the whole run, scored after its warm-up
    assert forced.exists() and (short_run / 'forced-rail.yaml').exists()


def test_the_hold_out_options_apply_to_the_rail_preset_only(short_run, capsys):
    for option in (['--holdout', '0.1'], ['--force'], ['--validate', 'x.csv']):
        with pytest.raises(SystemExit):
            tune_main([str(short_run / 'run.csv'), '--preset', 'train', '-o',
                       str(short_run / 'x.yaml')] + option)
        assert 'applies to the rail preset only' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        tune_main([str(short_run / 'run.csv'), '-o', str(short_run / 'x.yaml'),
                   '--holdout', '1'])


# -- the verdicts ------------------------------------------------------------------------

def _report(e: np.ndarray, scale: float = 1.0):
    """Return nis_consistency of innovations e·scale with S = 1."""
    y = scale * e[:, None]
    return nis_consistency(Innovations(y, np.ones((e.size, 1, 1))), 0.99)


def test_the_verdict_is_silent_on_white_innovations_and_names_correlation():
    rng = np.random.default_rng(20)
    white = rng.standard_normal(20000)
    assert model_verdict(_report(white)) == []
    phi = 0.55
    ar1 = np.empty_like(white)
    ar1[0] = white[0]
    for k in range(1, white.size):      # unit variance: sqrt(1 − φ²) on the new draw
        ar1[k] = phi * ar1[k - 1] + math.sqrt(1.0 - phi ** 2) * white[k]
    sentences = model_verdict(_report(ar1))
    assert sentences[0].startswith('the model does not describe this data: innovations '
                                   'are correlated (0.5')
    assert 'time-correlated measurement error' in sentences[0]
    assert 'alternate' in model_verdict(_report(ar1 * (-1.0) ** np.arange(white.size)))[0]


def test_the_verdict_says_which_way_the_noise_is_wrong():
    white = np.random.default_rng(21).standard_normal(20000)
    assert model_verdict(_report(white, 0.5))[-1].endswith(
        'the noise is set larger than the data show')
    assert model_verdict(_report(white, 2.0))[-1].endswith(
        'the noise is set smaller than the data show')


def _scored(errors: np.ndarray, blocks: np.ndarray) -> SettingScore:
    """Return a SettingScore of these errors (its other figures made up, no truth)."""
    return SettingScore(float(np.sqrt(np.mean(errors ** 2))), 0.95, errors.size, None, 0, 0,
                        0, 1.0, errors, blocks)


def test_a_gain_within_the_held_out_noise_is_refused_and_a_clear_one_is_not():
    rng = np.random.default_rng(14)     # a draw where the smaller RMSE is chance
    blocks = np.repeat(np.arange(30), 50)                    # 30 blocks of 50 predictions
    common = rng.standard_normal(blocks.size)                 # the errors both share
    before = _scored(common + 0.3 * rng.standard_normal(blocks.size), blocks)
    # Errors of their own, a little smaller on the whole but not block by block: the
    # RMSE is below the tie's 0.2 %, the gain within 2 standard errors: refused.
    slight = _scored(common + 0.27 * rng.standard_normal(blocks.size), blocks)
    assert slight.rmse_m < 0.99 * before.rmse_m
    gain, error = held_out_gain(before, slight)
    assert gain == pytest.approx(np.sum(before.errors_m ** 2 - slight.errors_m ** 2))
    sums = np.bincount(blocks, weights=before.errors_m ** 2 - slight.errors_m ** 2)
    assert error == pytest.approx(math.sqrt(30 * np.var(sums, ddof=1)))
    assert 0.0 < gain < GAIN_SIGMAS * error
    reason = worse_reason(Comparison('held-out', before, slight))
    assert reason is not None and 'but within the noise' in reason
    # The same gain in every block (the shared error removed): written.
    clear = _scored(common, blocks)
    assert held_out_gain(before, clear)[0] > GAIN_SIGMAS * held_out_gain(before, clear)[1]
    assert worse_reason(Comparison('held-out', before, clear)) is None
    # Not the same predictions, or one block: no test (the other rules still apply).
    assert held_out_gain(before, _scored(common[:-1], blocks[:-1])) is None
    one = np.zeros(blocks.size, dtype=np.int64)
    assert held_out_gain(_scored(before.errors_m, one), _scored(common, one)) is None


def test_a_tuned_model_far_less_consistent_than_its_start_is_refused():
    """Mean NIS off 1 by more than NIS_FACTOR and further off than the start's: refused."""
    white = np.random.default_rng(22).standard_normal(20000)
    # the mean NIS of e·c is c² (to ~1 % at 20,000 innovations)
    before, far_below, near_below = (_report(white, c) for c in (0.5, 0.2, 0.4))
    reason = inconsistent_reason(before, far_below)            # 0.25 -> 0.04
    assert reason.startswith('the tuned model is inconsistent with its own innovations '
                             '(mean NIS 0.0')
    assert f'{math.sqrt(NIS_FACTOR):.1f}× larger than the errors' in reason
    assert inconsistent_reason(before, near_below) is None     # 0.16: within 10×
    assert inconsistent_reason(far_below, _report(white, 0.25)) is None   # nearer 1
    assert 'smaller than the errors' in inconsistent_reason(_report(white), _report(white, 4.0))
    assert inconsistent_reason(_report(white), _report(white)) is None


def test_an_inconsistent_tuned_model_is_not_written_unless_forced(short_run, monkeypatch,
                                                                  capsys):
    monkeypatch.setattr(tune_rail_module, 'inconsistent_reason',
                        lambda before, after: 'STUB: inconsistent')
    output = short_run / 'inconsistent.yaml'
    assert tune_main([str(short_run / 'run.csv'), '-o', str(output)]) == 0
    assert 'kept the start: STUB: inconsistent; nothing written' in capsys.readouterr().out
    assert not output.exists()
    assert tune_main([str(short_run / 'run.csv'), '-o', str(output), '--force']) == 0
    assert '--force: written although STUB: inconsistent' in capsys.readouterr().out
    assert output.exists()
