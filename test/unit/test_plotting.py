"""Tests of kf_train.plots (kf-train plot): the figures are built right and written as PNGs."""

import os
import subprocess
import sys

from kf_train.batch import run_series
from kf_train.cli.plotting import main
from kf_train.cli.replay import main as replay_main
from kf_train.plots import (
    build_seed000_figures, measured_states, preset_figure, scenario_figures, seed000_figures)
from kf_train.presets import load_preset, PRESET_NAMES
from kf_train.sim import baselines, train_scenario
from matplotlib import image
import numpy as np
import pytest

PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'


def _assert_png(path, min_bytes=5000):
    """Assert ``path`` is a non-empty PNG that reopens as an RGBA image."""
    with open(path, 'rb') as stream:
        assert stream.read(8) == PNG_SIGNATURE
    assert os.path.getsize(path) > min_bytes
    pixels = image.imread(path)
    assert pixels.ndim == 3 and pixels.shape[0] > 100 and pixels.shape[1] > 100
    assert np.ptp(pixels[..., :3]) > 0  # something was drawn


def _seed000_inputs():
    """Return the seed 000 arguments from the train scenario and its filter."""
    s = train_scenario(seed=1)
    r = run_series(load_preset('train'), s.t_s, s.z)
    return s.t_s, s.z[:, 0], s.truth[:, 0], r.x, r.P, 0.1


def test_seed000_figures_follow_the_seed():
    """Three one-axes figures, with the seed's curves and the seed's baseline formulas."""
    t, z, truth, x, P, dt = _seed000_inputs()
    figures = build_seed000_figures(t, z, truth, x, P, dt)
    assert list(figures) == ['seed000_position', 'seed000_velocity', 'seed000_extrapolation']
    for figure in figures.values():
        assert len(figure.axes) == 1

    position = figures['seed000_position'].axes[0]
    assert [line.get_label() for line in position.get_lines()] == [
        'True position', 'Measurements', 'Kalman estimated displacement']
    np.testing.assert_array_equal(position.get_lines()[1].get_ydata(), z)

    velocity = figures['seed000_velocity'].axes[0]
    lines = {line.get_label(): line for line in velocity.get_lines()}
    raw = baselines.raw_difference_velocity(z, dt)
    np.testing.assert_array_equal(
        lines['Estimated velocity by raw consecutive samples'].get_ydata(), raw[1:])
    np.testing.assert_array_equal(
        lines['Estimated velocity by running average'].get_ydata(),
        baselines.running_average(raw, 5)[1:])
    np.testing.assert_allclose(lines['True velocity'].get_ydata(), 10.0, rtol=1e-12)

    extrapolation = figures['seed000_extrapolation'].axes[0]
    assert extrapolation.get_title() == 'Extrapolation 20 samples ahead (at t = 12)'
    lines = {line.get_label(): line for line in extrapolation.get_lines()}
    kalman = lines['Estimated position by Kalman filter']
    np.testing.assert_allclose(kalman.get_xdata(), t[-11:])
    # From sample k the seed projects (30 − i) samples: to t = 12 s for all 11 samples.
    np.testing.assert_allclose(kalman.get_ydata(), x[-11:, 0] + (12.0 - t[-11:]) * x[-11:, 1],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(lines['True position'].get_ydata(), 120.0, rtol=1e-12)


def test_seed000_figures_writes_three_pngs(tmp_path):
    """seed000_figures(output_dir, …) returns the three PNG paths it wrote."""
    paths = seed000_figures(str(tmp_path / 'report'), *_seed000_inputs())
    assert [os.path.basename(p) for p in paths] == [
        'seed000_position.png', 'seed000_velocity.png', 'seed000_extrapolation.png']
    for path in paths:
        _assert_png(path)


def test_seed000_figures_reject_bad_shapes():
    """Wrong shapes are named."""
    t, z, truth, x, P, dt = _seed000_inputs()
    with pytest.raises(ValueError, match='x_hist must have shape'):
        build_seed000_figures(t, z, truth, x[:, :1], P, dt)
    with pytest.raises(ValueError, match='measured_m must have length'):
        build_seed000_figures(t, z[:-1], truth, x, P, dt)


@pytest.mark.parametrize('name', PRESET_NAMES)
def test_preset_figure_has_one_panel_per_state(name):
    """Each state gets a panel with truth, estimate and its ±2σ band."""
    from kf_train.sim.scenarios import scenario_for_preset
    preset = load_preset(name)
    s = scenario_for_preset(name, 0)
    r = run_series(preset, s.t_s, s.z, s.u)
    measured = measured_states(preset, s.z)
    figure = preset_figure(name, preset.state_names, s.t0_s, preset.initial_state,
                           preset.initial_covariance, s.t_s, r.x, r.P, s.truth, s.truth0,
                           measured)
    assert len(figure.axes) == preset.dim_x
    for i, ax in enumerate(figure.axes):
        labels = [line.get_label() for line in ax.get_lines()]
        assert 'truth' in labels and 'estimate' in labels
        assert ('measurements' in labels) == (i in measured)
        assert len(ax.collections) == 1  # the ±2σ band
    expected_measured = {'range-bearing': {0, 2}, 'cv-position-velocity': {0, 1}}
    assert set(measured) == expected_measured.get(name, {0})


def test_plot_command_writes_every_figure(tmp_path, capsys):
    """kf-train plot --preset … writes the preset figures, the track and seed 000's."""
    out = tmp_path / 'figures'
    assert main(['--output-dir', str(out), '--preset', 'train', '--preset', 'range-bearing',
                 '--seed', '3']) == 0
    written = capsys.readouterr().out.split()
    assert sorted(os.path.basename(p) for p in written) == sorted([
        'train.png', 'seed000_position.png', 'seed000_velocity.png',
        'seed000_extrapolation.png', 'range-bearing.png', 'range-bearing_track.png'])
    for path in written:
        _assert_png(path)


def test_scenario_figures_for_every_preset(tmp_path):
    """Every shipped preset draws (the remaining ones, cheaply, in one go)."""
    for name in PRESET_NAMES:
        if name in ('train', 'range-bearing'):
            continue
        (path,) = scenario_figures(str(tmp_path), name)
        _assert_png(path)


def test_plot_a_replay_output(tmp_path, capsys):
    """--replay draws a replay output with its input's measurements, smoothed too."""
    source, target = tmp_path / 'in.csv', tmp_path / 'run.csv'
    s = train_scenario(seed=2)
    source.write_text('t,z_position\n' + ''.join(
        f'{a!r},{b!r}\n' for a, b in zip(s.t_s.tolist(), s.z[:, 0].tolist())))
    assert replay_main(['--preset', 'train', str(source), '-o', str(target), '--smooth']) == 0
    assert main(['--replay', str(target), '--input', str(source), '-o', str(tmp_path)]) == 0
    (path,) = capsys.readouterr().out.split()
    assert os.path.basename(path) == 'run.png'
    _assert_png(path)
    assert main(['--replay', str(source), '-o', str(tmp_path)]) == 1
    assert 'no state columns' in capsys.readouterr().err
    with pytest.raises(SystemExit) as error:
        main(['--input', str(source)])
    assert error.value.code == 2


def test_plotting_never_imports_pyplot():
    """The figures are drawn on an Agg canvas without pyplot (no display, no globals)."""
    code = ('import sys; from kf_train import plots; '
            'plots.new_figure(); '
            "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot imported'")
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, MPLBACKEND='TkAgg'))
    assert done.returncode == 0, done.stderr
