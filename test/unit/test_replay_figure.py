"""The replay figure: its numbers computed and checked, and the drawn axes' data."""

import math

from kf_train.filters import chi2_quantile
from kf_train.plots.replay_figure import (
    drawn, later_values, longest_standstill, MAX_DRAWN_POINTS, MIN_STOP_S, replay_figure,
    replay_series, sliding_mean)
import numpy as np
import pytest


def test_later_values_take_the_fix_at_t_plus_the_horizon():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    fixes_t = np.array([0.0, 1.0, 2.04, 3.0, 5.0])
    fixes = np.array([10.0, 11.0, 12.0, np.nan, 15.0])   # a missing fix is skipped
    got = later_values(t, fixes_t, fixes, 2.0, 0.1)
    # t=0 -> 2.04 (within 0.1); t=1 -> 3.0 is NaN, nearest finite 2.04 is 0.96 away: none;
    # t=2 -> 4.0: 5.0 is 1 s away: none; t=3 -> 5.0.
    np.testing.assert_array_equal(got, [12.0, np.nan, np.nan, 15.0])


def test_sliding_mean_over_the_finite_values():
    values = np.array([1.0, np.nan, 3.0, 5.0, np.nan, 7.0])
    got = sliding_mean(values, 2)
    np.testing.assert_array_equal(got, [np.nan, np.nan, 2.0, 4.0, np.nan, 6.0])


def test_longest_standstill_and_none():
    t = np.arange(0.0, 100.0, 0.5)
    v = np.full(t.shape, 10.0)
    v[(t >= 20.0) & (t < 25.0)] = 0.0          # 4.5 s: too short
    v[(t >= 50.0) & (t < 80.0)] = 0.05         # 29.5 s: the longest
    assert longest_standstill(t, v) == (50.0, 79.5)
    assert longest_standstill(t, np.full(t.shape, 3.0)) is None
    v[(t >= 50.0) & (t < 80.0)] = 10.0
    assert longest_standstill(t, v) is None and 4.5 < MIN_STOP_S


def _columns(rows=29_000, horizon_s=2.0, period_s=0.2, seed=5):
    """Return a 98-minute rail-like replay output at 5 Hz on an epoch clock, and fixes."""
    rng = np.random.default_rng(seed)
    t = 1.7e9 + period_s * np.arange(rows)
    v = np.where((np.arange(rows) > 10_000) & (np.arange(rows) < 10_600), 0.0, 20.0)
    truth = np.cumsum(v) * period_s
    fixes = truth + rng.normal(0.0, 1.0, rows)
    sigma = 1.5
    later = np.concatenate([truth[int(horizon_s / period_s):],
                            np.full(int(horizon_s / period_s), np.nan)])
    predicted = later + rng.normal(0.0, sigma, rows)   # an honest ±2σ: σ² = 1.5² ...
    var = np.full(rows, sigma ** 2 + 1.0)               # ... plus the fix's 1 m²
    nis = rng.chisquare(1, rows)
    nis[0] = np.nan
    p = rng.dirichlet(np.ones(4), rows)
    columns = {'t': t, 'position': truth, 'velocity': v, 'predicted_position': predicted,
               'var_predicted_position': var, 'nis': nis}
    columns.update({f'p_{n}': p[:, i] for i, n in enumerate(('stand', 'accelerate',
                                                             'cruise', 'brake'))})
    return columns, (t, fixes)


def test_the_series_of_a_98_minute_replay():
    columns, fixes = _columns()
    s = replay_series(columns, 2.0, fixes)
    assert s.t_s[0] == 0.0 and s.t_s[-1] == pytest.approx(0.2 * 28_999)   # not epoch
    k = 123
    assert s.error_m[k] == columns['predicted_position'][k] - fixes[1][k + 10]
    assert np.isnan(s.error_m[-10:]).all() and np.isfinite(s.error_m[:-10]).all()
    # error ~ N(0, 1.5² + 1²) against σ² = 3.25: ~4.55 % outside; 28,990 rows give a
    # binomial sd of 0.12 %: ±0.6 % is 5 sd.
    assert abs(s.outside - 0.0455) < 0.006
    assert sorted(s.regimes) == ['accelerate', 'brake', 'cruise', 'stand']
    assert s.nis_bounds == pytest.approx((chi2_quantile(0.025, 1), chi2_quantile(0.975, 1)))
    assert s.stop == pytest.approx((0.2 * 10_001, 0.2 * 10_599))
    assert np.nanmean(s.nis_mean) == pytest.approx(1.0, abs=0.05)   # sd ~ 0.0083
    against_estimate = replay_series(columns, 2.0)
    assert against_estimate.against == 'estimate'
    assert against_estimate.error_m[k] == (columns['predicted_position'][k]
                                           - columns['position'][k + 10])


def test_the_drawn_figure_carries_the_series():
    pytest.importorskip('matplotlib')
    columns, fixes = _columns()
    s = replay_series(columns, 2.0, fixes)
    figure = replay_figure('run', s, 2.0)
    axes = figure.axes
    error_line = [line for line in axes[0].get_lines() if 'prediction' in line.get_label()][0]
    x, y = error_line.get_data()
    step = drawn(s.t_s.shape[0]).step
    assert len(x) <= MAX_DRAWN_POINTS and step == math.ceil(29_000 / MAX_DRAWN_POINTS)
    np.testing.assert_array_equal(x, s.t_s[::step])
    np.testing.assert_array_equal(y, s.error_m[::step])
    for ax in axes[:4]:
        assert ax.get_xlabel() == 'time from start [s]' and '[' in ax.get_ylabel()
    assert [area.get_label() for area in axes[1].collections] == list(s.regimes)
    limit = axes[0].get_ylim()[1]     # the 99.5th percentile of the band, not the prior's
    size = np.fmax(np.abs(s.error_m), 2.0 * s.sigma_m)
    assert limit == pytest.approx(1.2 * np.nanpercentile(size, 99.5)) and limit < 10.0
    assert 1.0 in [line.get_ydata()[0] for line in axes[2].get_lines()
                   if line.get_label().startswith('expected')]
    assert 'longest standstill' in axes[3].get_title()
    zoom_x = axes[3].get_lines()[0].get_xdata()
    assert zoom_x.min() >= s.stop[0] - 60.0 and zoom_x.max() <= s.stop[1] + 60.0
    columns['velocity'] = np.full(29_000, 20.0)
    figure = replay_figure('run', replay_series(columns, 2.0, fixes), 2.0)
    assert 'no standstill' in figure.axes[3].get_title()


def test_plot_a_rail_table_replay(tmp_path, capsys):
    """kf-train plot --replay of a rail replay (no preset: the default) with its input."""
    pytest.importorskip('matplotlib')
    from kf_train.cli.plotting import main as plot_main
    from kf_train.cli.replay import main as replay_main
    t = 0.2 * np.arange(1, 601)
    v = np.where((t > 40.0) & (t < 70.0), 0.0, 15.0)
    z = np.cumsum(v) * 0.2 + np.random.default_rng(1).normal(0.0, 1.0, t.size)
    source = tmp_path / 'in.csv'
    source.write_text('t,z_position\n' + ''.join(
        f'{a!r},{b!r}\n' for a, b in zip(t.tolist(), z.tolist())))
    assert replay_main([str(source), '-o', str(tmp_path / 'run.csv')]) == 0
    assert plot_main(['--replay', str(tmp_path / 'run.csv'), '--input', str(source),
                      '-o', str(tmp_path)]) == 0
    (path,) = capsys.readouterr().out.split()
    assert path.endswith('run.png') and (tmp_path / 'run.png').stat().st_size > 10_000
    with pytest.raises(SystemExit):
        plot_main(['--horizon', '2', '-o', str(tmp_path)])
