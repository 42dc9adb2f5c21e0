"""``kf-train tune --preset rail`` (the default): the rail IMM's noises by maximum likelihood."""

import csv
import math

from kf_train.batch.noise_likelihood import Segment
from kf_train.batch.rail_likelihood import rail_log_likelihoods, RailNoise
from kf_train.cli import main as kf_train_main
from kf_train.cli.tune import main as tune_main
from kf_train.estimator import StreamEstimator
from kf_train.estimator.live_presets import resolve_preset
from kf_train.filters import chi2_mean_bounds, RailModel, RailModelParameters
from kf_train.presets import load_rail_preset, RailPreset
from kf_train.replay.bag import load_config
from kf_train.sim import sample_rail_model
from kf_train.sim.rail import rail_scenario
from kf_train.tune.climb import derivatives, stencil
from kf_train.tune.validation import score_setting
import numpy as np
import pytest
import yaml

DURATION_S = 240          # 2400 fixes: a few stations of a metro run, ~10 s to tune
SEED, HELD_OUT_SEED = 5, 6


def _tune(capsys, *args):
    """Run ``kf-train tune ARGS``; return (exit code, stdout, stderr)."""
    code = tune_main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _params(path):
    """Return the estimator's ros__parameters of a params file."""
    with open(path, encoding='utf-8') as stream:
        return yaml.safe_load(stream)['estimator']['ros__parameters']


def _segment(seed: int, rows: int = None) -> Segment:
    """Return a metro run of ``seed`` (all of it, or its first rows) with its truth."""
    scenario, _ = rail_scenario(seed=seed, family='metro')
    rows = rows or scenario.t_s.shape[0]
    return Segment(scenario.t_s[:rows], scenario.z[:rows], None, scenario.truth[:rows])


@pytest.fixture(scope='module')
def runs(tmp_path_factory):
    """Simulate one rail run as a CSV and a bag (kf-train simulate); return the directory."""
    directory = tmp_path_factory.mktemp('rail')
    for output in ('run.csv', 'run.mcap'):
        assert kf_train_main(['simulate', '--scenario', 'rail', '--duration', str(DURATION_S),
                              '--seed', str(SEED), '-p', 'rail_gnss_model:=white', '--output',
                              str(directory / output)]) == 0
    return directory


@pytest.fixture(scope='module')
def tuned_csv(runs):
    """Tune the default preset (rail) on the CSV; return (exit code, stdout, params path)."""
    import io
    import sys
    out, stdout = io.StringIO(), sys.stdout
    sys.stdout = out
    try:
        # --force: the defaults are already near this simulator's maximum, so the held-out
        # end shows a tie, which keeps the start (and writes nothing) without it.
        code = tune_main([str(runs / 'run.csv'), '-o', str(runs / 'tuned.yaml'), '--force'])
    finally:
        sys.stdout = stdout
    return code, out.getvalue(), runs / 'tuned.yaml'


def _node_log_likelihood(params: RailModelParameters, segment: Segment, R: float):
    """Return (ℓ, NIS per step) with the node's IMM classes: RailModel predict/update."""
    model = RailModel(params)
    z, t = segment.z[:, 0], segment.t_s
    state = model.first_estimate(z[0], R)
    total, nis = 0.0, []
    for k in range(1, z.shape[0]):
        state = model.predict(state, float(t[k] - t[k - 1]))
        y = z[k] - state.means[:, 0]
        s = state.covariances[:, 0, 0] + R
        with np.errstate(divide='ignore'):
            logs = np.log(state.probabilities) - 0.5 * (y * y / s + np.log(s)
                                                        + math.log(2 * math.pi))
        top = logs.max()
        total += top + math.log(np.exp(logs - top).sum())     # log Σ_j c̄_j N(y_j; s_j)
        state, result = model.update(state, z[k], np.array([[R]]))
        nis.append(result.nis)
    return total, np.array(nis)


def test_the_stacked_likelihood_is_the_node_imms():
    """One pass over K settings gives each setting's ℓ and NIS as the node's IMM does."""
    segment = _segment(7, 1500)
    base = RailModelParameters(noise_window=0)  # the likelihood of a fixed R (no learning)
    settings = [RailNoise(), RailNoise(1e-3, 1e-5, None, 1.3), RailNoise(1e-2, 1e-3, 1e-5, 0.8)]
    result = rail_log_likelihoods(base, [segment], settings, innovations=True)
    for setting, ll, nis in zip(settings, result.log_likelihood, result.nis):
        params = setting.parameters(base)
        expected, expected_nis = _node_log_likelihood(params, segment, params.noise_std_m ** 2)
        # Same equations, other summation orders: each of the 1499 terms agrees to a few
        # ulps of the state (~1e-13 m on positions of ~1e3 m, the filter forgets older
        # rounding), so ℓ (~ -2000) agrees to ~1e-12 relative; 1e-9 leaves a margin of 1000.
        assert ll == pytest.approx(expected, rel=1e-9)
        # NIS = y²/S with y ~ 1 m: the same ~1e-13 m errors, 1e-8 leaves a wide margin.
        np.testing.assert_allclose(nis, expected_nis, rtol=0.0, atol=1e-8)


def test_the_stencil_gives_the_derivatives_of_a_quadratic():
    """Central differences are exact on a quadratic: f, gradient and Hessian."""
    A = np.array([[2.0, 0.5, 0.1], [0.5, 1.0, -0.3], [0.1, -0.3, 3.0]])
    b = np.array([1.0, -2.0, 0.5])
    centre = np.array([0.3, -0.1, 0.2])
    points = centre + stencil(3, 0.01)
    values = np.array([0.5 * p @ A @ p + b @ p for p in points])
    f, g, H = derivatives(values, 3, 0.01)
    # Exact in exact arithmetic; rounding of values ~1 divided by h² = 1e-4: ~1e-12.
    assert f == pytest.approx(0.5 * centre @ A @ centre + b @ centre, abs=1e-12)
    np.testing.assert_allclose(g, A @ centre + b, atol=1e-10)
    np.testing.assert_allclose(H, A, atol=1e-8)


def test_tune_rail_from_a_csv_writes_a_tuned_rail_preset(tuned_csv):
    """The default preset is rail: estimates, checks and a params file pointing at the preset."""
    code, text, path = tuned_csv
    assert code == 0, text
    assert 'preset rail (rail IMM)' in text
    for label in ('acceleration_noise', 'command_noise', 'NIS, mean of',
                  '2-s RMSE against the truth', '2σ coverage'):
        assert label in text, label
    assert '--force: written although' in text and 'predicts no better' in text
    params = _params(path)
    assert set(params) == {'preset', 'measurement_variance'}   # a table carries no R
    preset = resolve_preset(params['preset'])
    assert isinstance(preset, RailPreset) and preset.name == 'rail-tuned'
    # R: the node learns a scale on R online (noise_window), so R sets only where the
    # scale starts and is not fitted (its interval missed the truth on 2 of 3 seeds):
    # the second differences' estimate is written. Its relative sd at 1,350 fixes is
    # ~√(2/1350)·√(22/6) ≈ 7 %; 0.75-1.33 is over 3 of them around the truth, 1.
    assert 'R is not fitted: the node learns a scale on it online' in text
    assert 'measurement_variance [m²]' not in text           # no row: not an estimate
    assert 0.75 <= params['measurement_variance'] <= 1.33
    # The preset keeps σ = √R: R comes back through a square root and a square (2 ulps).
    assert preset.R[0, 0] == pytest.approx(params['measurement_variance'], rel=1e-15)
    after = text.split('NIS, mean of')[1].split('\n')[0]
    assert after.rstrip().endswith('(consistent)'), after


def test_the_params_file_loads_as_the_node_and_replay_load_it(tuned_csv):
    """load_estimator_config (the node's and replay's loader) gives the tuned rail model."""
    _, _, path = tuned_csv
    config = load_config([str(path)], [])
    estimator = StreamEstimator(config.settings)
    tuned = yaml.safe_load(open(_params(path)['preset']))['parameters']
    assert estimator.preset.parameters.acceleration_noise == tuned['acceleration_noise']
    assert estimator.preset.parameters.command_noise == tuned['command_noise']
    assert config.settings.measurement_variance == _params(path)['measurement_variance']


def test_the_tuned_model_predicts_a_held_out_run_no_worse(tuned_csv):
    """On another seed's run the tuned model's 2-s RMSE is the default's, within its noise."""
    _, _, path = tuned_csv
    segment = _segment(HELD_OUT_SEED)
    # The node's own runs (gate, lock-out, learned scale), as tune's validation scores them.
    default = score_setting(load_rail_preset(), [segment])
    tuned = score_setting(_params(path)['preset'], [segment])
    count = tuned.count
    # Margin: 2-s prediction errors are correlated over ~2 s (20 rows), so an RMSE over
    # `count` rows rests on ~count/20 independent errors: relative sd 1/√(2·count/20).
    # The two filters' errors on the same run are positively correlated, so their
    # difference has at most √2 times that sd; allow 3 of them.
    margin = 3.0 * math.sqrt(2.0) / math.sqrt(2.0 * count / 20.0)
    assert tuned.truth_rmse_m <= default.truth_rmse_m * (1.0 + margin)
    assert tuned.rmse_m <= default.rmse_m * (1.0 + margin)
    assert tuned.resets == 0 and tuned.reacquisitions == 0
    # The mean NIS of the fused fixes (the gate rejects ~0.3 % of a Gaussian's: it
    # lowers the mean by < 0.01, inside these bounds' width of ~0.1 at ~1,800 fixes).
    low, high = chi2_mean_bounds(count, 1, 0.99)
    assert low - 0.01 <= tuned.mean_nis <= high


def test_a_wrong_start_moves_the_right_way(runs, capsys):
    """Noises 100x too large come down to where the defaults' start goes; ℓ goes up."""
    with open(load_rail_preset().source, encoding='utf-8') as stream:
        data = yaml.safe_load(stream)
    data['parameters']['acceleration_noise'] = 1e-2
    data['parameters']['command_noise'] = 1e-2
    wrong = runs / 'wrong.yaml'
    wrong.write_text(yaml.safe_dump(data))
    # --force: what is tested is where the estimates go, not whether the held-out gain
    # is large enough to write them (2.08 -> 2.03 m here, within its noise).
    code, text, err = _tune(capsys, runs / 'run.csv', '--config', wrong, '-o',
                            runs / 'w.yaml', '--fix-r', '1.0', '--force')
    assert code == 0, err
    tuned = yaml.safe_load(open(_params(runs / 'w.yaml')['preset']))['parameters']
    # The data cannot tell either noise from 0 here (one-sided intervals), so what is
    # held is the start's independence: the same maximum as from the defaults (to the
    # printed 4 digits), and far below the wrong start (the data reject it jointly).
    # (From the defaults the gain is too small to write a file: the printed estimates.)
    code, printed, err = _tune(capsys, runs / 'run.csv', '-o', runs / 'd.yaml', '--fix-r',
                               '1.0')
    assert code == 0, err
    for name in ('acceleration_noise', 'command_noise'):
        row = next(x for x in printed.splitlines() if f' {name} ' in x)
        reference = float(row.split()[3])
        assert tuned[name] == pytest.approx(reference, rel=2e-3, abs=1e-12), row
        assert tuned[name] < 0.5 * data['parameters'][name]
    line = next(x for x in text.splitlines() if x.startswith('log-likelihood'))
    before, after = (float(v) for v in
                     line.replace(',', '').split()[2::2])   # 'before X after Y'
    assert after > before
    nis_line = next(x for x in text.splitlines() if x.startswith('NIS'))
    assert 'before' in nis_line and nis_line.rstrip().endswith('(consistent)')


def test_tune_a_bag_then_replay_it_with_the_params_passes_the_nis_check(runs, capsys):
    """Issue 14's round trip on rail: tune the bag, replay it with the params, NIS consistent."""
    code, text, err = _tune(capsys, runs / 'run.mcap', '-o', runs / 'bag.yaml', '--force')
    assert code == 0, err
    assert 'R = 1, as the messages carry it' in text
    params = _params(runs / 'bag.yaml')
    assert set(params) == {'preset'}            # the messages' R stays the node's
    assert kf_train_main(['replay', str(runs / 'run.mcap'), '--params-file',
                          str(runs / 'bag.yaml'), '-o', str(runs / 'replayed.csv')]) == 0
    with open(runs / 'replayed.csv', newline='', encoding='utf-8') as stream:
        nis = np.array([float(row['nis']) for row in csv.DictReader(stream) if row['nis']])
    low, high = chi2_mean_bounds(nis.size, 1, 0.99)
    assert nis.size >= DURATION_S * 10 - 2
    assert low <= float(np.mean(nis)) <= high


@pytest.mark.parametrize('args, message', [
    (['--fix-q', '1'], '--fix-q does not apply to the rail preset'),
    (['--horizon', '1'], '--horizon does not apply to the rail preset'),
    (['--rail-noises', 'bogus'], "'bogus' is not one of"),
    (['--initialization', 'prior'], '--initialization prior does not apply'),
    (['--fix-r', '1', '2'], '--fix-r takes one variance'),
    (['--preset', 'train', '--rail-noises', 'command_noise'], 'applies to the rail preset'),
])
def test_options_that_do_not_apply_are_refused(runs, capsys, args, message):
    """Usage errors: exit 2 with one line."""
    with pytest.raises(SystemExit) as exit_info:
        tune_main([str(runs / 'run.csv'), '-o', str(runs / 'x.yaml')] + args)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert message in err and err.strip().splitlines()[-1].startswith('kf-train tune: error')


def test_bad_input_is_one_line(tmp_path, capsys):
    """A table without z_position, or one that does not vary: exit 1, one line, no file."""
    (tmp_path / 'bad.csv').write_text('t,z\n0.1,1\n0.2,2\n0.3,3\n')
    code, _, err = _tune(capsys, tmp_path / 'bad.csv', '-o', tmp_path / 'p.yaml')
    assert code == 1 and len(err.strip().splitlines()) == 1 and 'z_position' in err
    (tmp_path / 'flat.csv').write_text('t,z_position\n' + ''.join(
        f'{k / 10},5.0\n' for k in range(1, 50)))
    code, _, err = _tune(capsys, tmp_path / 'flat.csv', '-o', tmp_path / 'p.yaml')
    assert code == 1 and len(err.strip().splitlines()) == 1 and 'do not vary' in err
    assert not (tmp_path / 'p.yaml').exists()
    code, _, err = _tune(capsys, tmp_path / 'flat.csv', '-o', tmp_path / 'no' / 'p.yaml')
    assert code == 1 and len(err.strip().splitlines()) == 1 and 'does not exist' in err
    code, _, err = _tune(capsys, tmp_path / 'flat.csv', '-o', '-')
    assert code == 1 and len(err.strip().splitlines()) == 1 and '--preset-output' in err


def test_the_fit_finds_a_known_maximum_and_its_intervals():
    """On ℓ quadratic in log θ, the fit returns exp(m) and exp(m ± z·s) (the Wald interval)."""
    from kf_train.tune import fit_rail_noise
    m = np.array([math.log(3e-4), math.log(2e-5), math.log(1.1)])
    sd = np.array([0.3, 0.5, 0.02])
    names = ['acceleration_noise', 'command_noise', 'measurement_variance']

    def likelihoods(settings):
        with np.errstate(divide='ignore'):     # the boundary check sets a noise to 0
            v = np.log([[getattr(s, n) for n in names] for s in settings])
        return -0.5 * np.sum(((v - m) / sd) ** 2, axis=1)
    start = RailNoise(1e-4, 1e-4, 1e-6, 1.0)
    fit = fit_rail_noise(likelihoods, names, start, start, rows=1000)
    z = 1.959963984540054
    for estimate, centre, s in zip(fit.estimates, m, sd):
        # The stencil is exact on a quadratic; Newton's answer is limited by gtol (1e-7
        # per row of 1000 rows: |Δv| <= 1e-4·s²) and rounding: 1e-6 relative is ample.
        assert estimate.value == pytest.approx(math.exp(centre), rel=1e-6)
        assert estimate.low == pytest.approx(math.exp(centre - z * s), rel=1e-6)
        assert estimate.high == pytest.approx(math.exp(centre + z * s), rel=1e-6)


def test_a_noise_the_data_cannot_tell_from_zero_gets_zero_and_a_bound():
    """ℓ = −c·q_a falls from q_a = 0: q_a = 0, bound where c·q_a = χ²₁(0.90)/2."""
    from kf_train.tune import fit_rail_noise
    c = 1000.0

    def likelihoods(settings):
        return np.array([-c * s.acceleration_noise - (
            0.5 * ((math.log(s.command_noise) - math.log(5e-5)) / 0.4) ** 2
            if s.command_noise > 0.0 else math.inf) for s in settings])
    start = RailNoise(1e-4, 1e-4, 1e-6, 1.0)
    fit = fit_rail_noise(likelihoods, ['acceleration_noise', 'command_noise'], start, start,
                         rows=1000)
    q_a, q_l = fit.estimates
    assert fit.setting.acceleration_noise == 0.0 and q_a.value == 0.0 and q_a.low == 0.0
    # χ²₁(0.90)/2 = 1.3528; the bound is interpolated linearly in log θ between tenths of
    # a decade of a function linear in θ: error below (10^0.1 − 1)²/8 ≈ 1 %.
    assert q_a.high == pytest.approx(1.3527717 / c, rel=0.02)
    assert q_l.value == pytest.approx(5e-5, rel=1e-4)


def _sample_rail_model(params: RailModelParameters, rows: int, seed: int) -> Segment:
    """Return a Segment drawn from the rail IMM's own model (kf_train.sim.sample_rail_model)."""
    t, z = sample_rail_model(params, rows, seed)
    return Segment(t, z[:, None])


def test_a_run_drawn_from_the_model_never_reverses():
    """sample_rail_model keeps the filter's rules: no reversal, any slow regime may stop."""
    import dataclasses
    # Large noises make reversals likely (the old sampler ran seed 7 at -9 m/s); a
    # measurement σ of 1 nm shows the true position's steps.
    params = dataclasses.replace(RailModelParameters(), acceleration_noise=3e-2,
                                 command_noise=3e-3, noise_std_m=1e-9)
    for seed in range(4):
        _, z = sample_rail_model(params, 3000, seed)
        # Each step moves by v·dt plus the noise's share; v >= 0 holds the true position
        # non-decreasing, and the measurement adds at most ~1e-8 m per step.
        assert np.diff(z).min() > -1e-7, seed
        assert z[-1] > z[0] + 10.0, seed                           # it does run


def test_noises_the_data_carry_are_found_from_a_start_100x_too_small():
    """On data from the model itself, q_ℓ comes up from 1/100 of the truth; truth inside."""
    from kf_train.tune import fit_rail_noise
    import dataclasses
    truth = dataclasses.replace(RailModelParameters(), acceleration_noise=3e-3,
                                command_noise=3e-4)
    segment = _sample_rail_model(truth, 4000, seed=2)
    base = RailModelParameters()
    start = RailNoise(3e-5, 3e-6, base.capability_noise, 1.0)
    fit = fit_rail_noise(lambda s: rail_log_likelihoods(base, [segment], s).log_likelihood,
                         ['acceleration_noise', 'command_noise', 'measurement_variance'],
                         start, start, rows=3999)
    q_a, q_l, R = fit.estimates
    assert q_l.low > 10.0 * start.command_noise                   # moved up, and bounded
    # One seeded run: each 95 % interval holds its truth (for this seed; the intervals'
    # coverage over many runs is not what this test measures).
    assert q_l.low <= 3e-4 <= q_l.high
    assert q_a.low <= 3e-3 <= q_a.high
    assert R.low <= 1.0 <= R.high


def test_estimate_r_fits_a_tables_r_although_the_node_learns_its_scale(runs, capsys):
    assert tune_main([str(runs / 'run.csv'), '-o', str(runs / 'with-r.yaml'), '--force',
                      '--estimate-r']) == 0
    text = capsys.readouterr().out
    assert 'measurement_variance [m²]' in text and 'R is not fitted' not in text
    row = next(line for line in text.splitlines() if 'measurement_variance [m²]' in line)
    assert _params(runs / 'with-r.yaml')['measurement_variance'] == pytest.approx(
        float(row.split()[3]), rel=1e-3)                      # the estimate, 4 digits
