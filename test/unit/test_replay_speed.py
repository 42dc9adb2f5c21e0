"""``kf-train replay --preset rail`` with a measured speed: columns z_velocity, var_z_velocity."""

import csv
import math

from kf_train.cli import main as kf_train_main
from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.sim.rail import rail_scenario
import numpy as np
import pytest

NS = 1_000_000_000
DEPARTURE = slice(450, 850)
"""Rows 45-85 s of the run: standing, then accelerating to ~30 m/s."""


@pytest.fixture(scope='module')
def table(tmp_path_factory):
    """Return (path, rows) of a CSV of 400 epochs of a departure; some lack a cell."""
    scenario, run = rail_scenario(7, 'regional')
    t, z = scenario.t_s[DEPARTURE], scenario.z[DEPARTURE, 0]
    speed = run.state_at(t).velocity_mps + 0.1 * np.random.default_rng(3).standard_normal(400)
    rows = []
    for k in range(400):
        position = '' if k % 7 == 3 and k % 5 != 2 else repr(float(z[k]))   # never both
        velocity, variance = (repr(float(speed[k])), '0.01') if k % 5 != 2 else ('', '')
        rows.append({'t': repr(float(t[k])), 'z_position': position, 'z_velocity': velocity,
                     'var_z_velocity': variance})
    path = tmp_path_factory.mktemp('speed') / 'in.csv'
    with open(path, 'w', newline='') as handle:
        writer = csv.DictWriter(handle, ['t', 'z_position', 'z_velocity', 'var_z_velocity'])
        writer.writeheader()
        writer.writerows(rows)
    return path, rows


def _replay(path, output, *more):
    """Run kf-train replay --preset rail; return the output rows."""
    assert kf_train_main(['replay', '--preset', 'rail', str(path), '--output', str(output)]
                         + list(more)) == 0
    with open(output, newline='') as handle:
        return list(csv.DictReader(handle))


def test_speeds_in_a_table_are_the_estimators_process_velocity(table, tmp_path):
    """Row by row: the position, then the speed of its stamp, as StreamEstimator fuses them."""
    path, rows = table
    out = _replay(path, tmp_path / 'out.csv')
    assert out == _replay(path, tmp_path / 'memory.csv', '--engine', 'memory')
    estimator = StreamEstimator(EstimatorSettings(gate_probability=1.0))
    compared = 0
    for row, written in zip(rows, out):
        stamp = round(float(row['t']) * NS)
        if row['z_position']:
            estimator.process(stamp, float(row['z_position']), 1.0)
        if row['z_velocity'] and estimator.initialized:
            estimator.process_velocity(stamp, float(row['z_velocity']),
                                       float(row['var_z_velocity']))
        if estimator.initialized:
            x, P = estimator.state
            # The same arithmetic, but for the text round trip of the times and the
            # writer's layout: to a few units in the last place.
            assert [float(written[name]) for name in ('position', 'velocity')] == \
                pytest.approx(x[:2].tolist(), rel=1e-13, abs=1e-13)
            assert float(written['var_velocity']) == pytest.approx(P[1, 1], rel=1e-13)
            compared += 1
    assert compared > 390
    # Every row here had a position or a speed: each was updated by what it had.
    assert {r['updated'] for r in out} == {'1.0'}


def test_the_speeds_make_the_velocity_estimate_better(table, tmp_path):
    """The same table without its speed columns: the velocity is less accurate."""
    path, rows = table
    scenario, run = rail_scenario(7, 'regional')
    true_speed = run.state_at(scenario.t_s[DEPARTURE]).velocity_mps.tolist()
    positions = tmp_path / 'positions.csv'
    with open(positions, 'w', newline='') as handle:
        writer = csv.DictWriter(handle, ['t', 'z_position'], extrasaction='ignore')
        writer.writeheader()
        writer.writerows(rows)
    alone = _replay(positions, tmp_path / 'alone.csv')
    fused = _replay(path, tmp_path / 'fused.csv')
    assert 'updated' in alone[0]
    errors = [[float(r['velocity']) - truth for r, truth in zip(out[100:], true_speed[100:])]
              for out in (alone, fused)]
    # Speeds of σ 0.1 m/s at 4 rows in 5 pin the velocity to a few cm/s (measured RMS
    # 0.03 m/s); positions of σ 1 m at 10 Hz alone give a few tenths (measured: 0.27).
    rms = [math.sqrt(np.mean(np.square(e))) for e in errors]
    assert rms[1] < 0.12 < rms[0]


def test_a_speed_without_its_variance_is_refused(tmp_path, capsys):
    """An empty var_z_velocity beside a speed, or no such column: one error line."""
    path = tmp_path / 'bad.csv'
    output = tmp_path / 'out.csv'
    path.write_text('t,z_position,z_velocity,var_z_velocity\n0.1,1.0,2.0,0.01\n'
                    '0.2,2.0,2.0,\n')
    assert kf_train_main(['replay', '--preset', 'rail', str(path), '--output',
                          str(output)]) == 1
    assert 'line 3' in capsys.readouterr().err and not output.exists()
    path.write_text('t,z_position,z_velocity\n0.1,1.0,2.0\n')
    assert kf_train_main(['replay', '--preset', 'rail', str(path), '--output',
                          str(output)]) == 1
    assert "missing column 'var_z_velocity'" in capsys.readouterr().err
    assert not output.exists()
