"""Tests of kf-train compare: the Monte-Carlo comparison of the filter family."""

import math

from kf_train import cli
from kf_train.batch import run_series
from kf_train.cli.compare import main
from kf_train.evaluate import anees_bounds, derived_seed, nees, run_comparison
from kf_train.filters import FilterOptions, psd_factor
from kf_train.plots import comparison_figure
from kf_train.presets import load_preset
from kf_train.sim import scenario_for_preset
import numpy as np
import pytest
from scipy import stats

SMALL = FilterOptions(particles=200)


def test_small_range_bearing_comparison_matches_an_independent_recomputation():
    """Three runs: every filter reported; the EKF's RMSE and ANEES recomputed by hand."""
    comparison = run_comparison('range-bearing', runs=3, seed=5, options=SMALL)
    assert [s.kind for s in comparison.summaries] == ['ekf', 'ukf', 'pf']
    preset = load_preset('range-bearing')
    G0 = psd_factor('P0', preset.initial_covariance, 4)
    squared, nees_rows = [], []
    for r in range(3):
        scenario = scenario_for_preset('range-bearing', 5 + r)
        rng = np.random.default_rng(derived_seed(5, r, 1))
        x0 = scenario.truth0 + G0 @ rng.standard_normal(4)
        result = run_series(preset, scenario.t_s, scenario.z, x0=x0)
        e = result.x - scenario.truth
        squared.append(e[:, 0] ** 2 + e[:, 2] ** 2)
        nees_rows.append([ek @ np.linalg.inv(Pk) @ ek for ek, Pk in zip(e, result.P)])
    ekf = comparison.summaries[0]
    assert ekf.runs_ok == 3 and ekf.runs_failed == 0
    assert ekf.rmse_position_m == pytest.approx(math.sqrt(np.mean(squared)), rel=1e-12)
    assert ekf.final_rmse_position_m == pytest.approx(
        math.sqrt(np.mean(np.array(squared)[:, -1])), rel=1e-12)
    # The same run; NEES by inverse here, by solve in the module: eᵀP⁻¹e moves by <=
    # ~n·u·κ(P) relative, κ <= ~1.1e5 on this preset: <= 5e-11, a margin of 20.
    np.testing.assert_allclose(ekf.anees_per_row, np.mean(nees_rows, axis=0), rtol=1e-9)
    for s in comparison.summaries:
        assert s.seconds_per_step > 0.0
        assert s.rmse_per_row_m.shape == comparison.t_s.shape
    assert 'resample_count' in comparison.summaries[2].diagnostics
    assert comparison.summaries[2].diagnostics['measurement_initialisations'] == 3


@pytest.mark.parametrize('runs,dim', [(1, 1), (3, 4), (100, 4), (200, 2)])
def test_anees_bounds_are_the_chi2_quantiles(runs, dim):
    """runs·ANEES ~ χ²(runs·n): the bounds are its 0.5% and 99.5% quantiles over runs."""
    low, high = anees_bounds(runs, dim)
    assert low == pytest.approx(stats.chi2.ppf(0.005, runs * dim) / runs, rel=1e-9)
    assert high == pytest.approx(stats.chi2.ppf(0.995, runs * dim) / runs, rel=1e-9)


def test_the_kf_is_consistent_where_it_is_exact():
    """
    On the car seed (the KF is the exact posterior) the last row's ANEES is χ²-plausible.

    The initial estimates are drawn from N(truth, P0), so the final errors of the runs
    are independent N(0, P): runs·ANEES ~ χ²(runs·2); the test's false-alarm probability
    is 1e-3 (two-sided). The UKF gives the same numbers.
    """
    runs = 60
    comparison = run_comparison('car', runs=runs, seed=1, kinds=['kf', 'ukf'])
    kf, ukf = comparison.summaries
    total = runs * kf.anees_per_row[-1]
    assert stats.chi2.ppf(5e-4, 2 * runs) <= total <= stats.chi2.isf(5e-4, 2 * runs)
    np.testing.assert_allclose(ukf.anees_per_row, kf.anees_per_row, rtol=1e-8)
    assert ukf.rmse_position_m == pytest.approx(kf.rmse_position_m, rel=1e-9)


def test_comparisons_are_reproducible():
    """The same seed gives the same numbers, the particle filter included."""
    a, b = (run_comparison('range-bearing', runs=2, seed=3, options=SMALL, initial=initial)
            for initial in ('preset', 'preset'))
    for x, y in zip(a.summaries, b.summaries):
        assert x.rmse_position_m == y.rmse_position_m
        np.testing.assert_array_equal(x.anees_per_row, y.anees_per_row)
    c = run_comparison('range-bearing', runs=2, seed=4, options=SMALL, initial='preset')
    assert c.summaries[2].rmse_position_m != a.summaries[2].rmse_position_m
    d, e = (run_comparison('range-bearing', runs=2, seed=3, options=SMALL,
                           kinds=['bootstrap-pf']) for _ in range(2))
    np.testing.assert_array_equal(d.summaries[0].anees_per_row, e.summaries[0].anees_per_row)


def test_nees_is_infinite_for_a_singular_covariance():
    """A collapsed (singular) covariance with a nonzero error is reported as inf."""
    out = nees(np.array([[1.0, 0.0], [0.0, 0.0]]), np.array([np.eye(2), np.zeros((2, 2))]))
    assert out[0] == 1.0 and math.isinf(out[1])


def test_command_prints_and_writes_the_figure_and_curves(tmp_path, capsys):
    """kf-train compare (through the umbrella) prints the table, writes PNG and CSV."""
    assert cli.main(['compare', '--preset', 'range-bearing', '--runs', '2',
                     '--particles', '100', '--seed', '7', '--output-dir', str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for text in ('ekf', 'ukf', 'pf', 'RMSE pos [m]', 'mean ANEES', 'µs/row',
                 'measurement_initialisations 2'):
        assert text in out
    png = tmp_path / 'compare-range-bearing.png'
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    header = (tmp_path / 'compare-range-bearing.csv').read_text().splitlines()[0]
    assert header == ('t,rmse_position_ekf,anees_ekf,rmse_position_ukf,anees_ukf,'
                      'rmse_position_pf,anees_pf')
    figure = comparison_figure(run_comparison('robot', runs=2, options=SMALL,
                                              kinds=['kf', 'pf', 'bootstrap-pf']))
    assert len(figure.axes) == 2


def test_command_errors(tmp_path, capsys):
    """Bad counts exit 2 (usage); filters that do not apply exit 1 with a message."""
    for argv in (['--runs', '0'], ['--seed', '-1'], ['--particles', '0']):
        with pytest.raises(SystemExit) as exit_info:
            main(argv + ['--output-dir', str(tmp_path)])
        assert exit_info.value.code == 2
    assert main(['--filters', 'kf', '--runs', '1', '--output-dir', str(tmp_path)]) == 1
    assert "filter 'kf' needs a linear one" in capsys.readouterr().err
    assert main(['--filters', 'ukf,bogus', '--runs', '1', '--output-dir', str(tmp_path)]) == 1
    assert 'filter must be one of' in capsys.readouterr().err
