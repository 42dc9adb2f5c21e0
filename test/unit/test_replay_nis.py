"""
The ``nis`` column of the linear presets' table replays: the NIS each filter computed.

Every way ``kf-train replay`` runs a linear preset (the vectorised series in blocks,
an ``id`` column in lock-step or alone, ``--filter``, ``--smooth``, rows without a
measurement; streamed or in memory, CSV or Parquet) writes yᵀ S⁻¹ y of the row's
measurement. It is held to the row-by-row numpy reference (``run_series``:
``kalman.update``'s UpdateResult.nis) and, for the train preset, to the streaming
estimator's, on seeded series with jittered stamps and an outlier (a table replay has
no gate: the outlier is fused, and its large NIS written).
"""

from kf_train.batch import bank, filter_table, output_header, run_series
from kf_train.cli.replay import main
from kf_train.estimator import EstimatorSettings, StreamEstimator
from kf_train.filters import make_filter
from kf_train.io import read_table
from kf_train.presets import load_preset, PRESET_NAMES
from kf_train.replay.bag import csv_header
import numpy as np
import pytest

LINEAR = [name for name in PRESET_NAMES if load_preset(name).linear]
T0_NS = 100_000_000_000            # the prior holds at t0 = 100 s
# The paths' bound on the states, relative to max(1, |value|) (test_replay._close).
EPS_X = 1e-9


def _series(preset, rows: int, seed: int, t0_ns: int = T0_NS):
    """Return (stamps [ns], t [s], z, u): jittered stamps (±20 % of a period), an outlier."""
    rng = np.random.default_rng(seed)
    period_ns = round(preset.nominal_period_s * 1e9)
    jitter = rng.integers(-period_ns // 5, period_ns // 5, rows)
    stamps = t0_ns + np.cumsum(period_ns + jitter)
    stamps[0] = t0_ns + period_ns   # one nominal period after the prior (its 'prior' mode)
    t = stamps / 1e9
    R = preset.model.R
    z = 10.0 * (t - t0_ns / 1e9)[:, None] * np.ones(preset.dim_z)
    z = z + rng.standard_normal((rows, preset.dim_z)) @ np.linalg.cholesky(R).T
    z[rows // 2] += 30.0 * np.sqrt(np.diag(R))     # a 30 σ outlier: fused, a large NIS
    u = rng.standard_normal((rows, preset.dim_u)) if preset.dim_u else None
    return stamps, t, z, u


def _close_nis(got, expected, z, R):
    """
    Assert |Δ NIS| within what the states' rounding bound allows; NaN where expected.

    NIS = |w|², w = S^(−1/2) y, y = z − H x⁻. The paths agree on x⁻ within
    EPS_X·max(1, |x⁻|); |x⁻| is within a factor 2 of the row's |z| here (a 30 σ
    outlier aside, which only shrinks it), so δy <= δ = 2·EPS_X·max(1, |z|) and
    |δw| <= δ / √r, r = R's smallest eigenvalue (S >= R). Then
    |Δ NIS| <= 2 √NIS δ/√r + δ²/r, plus 2·EPS_X·NIS for S's own rounding; the bound
    used is twice that.
    """
    got, expected = np.asarray(got), np.asarray(expected)
    assert got.shape == expected.shape
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    fused = ~np.isnan(expected)
    r = float(np.linalg.eigvalsh(R)[0])
    delta = 2.0 * EPS_X * np.maximum(1.0, np.max(np.abs(z), axis=1))[fused]
    e = expected[fused]
    bound = 2.0 * (2.0 * np.sqrt(e) * delta / np.sqrt(r) + delta * delta / r + 2 * EPS_X * e)
    error = np.abs(got[fused] - e)
    assert np.all(error <= bound), float(np.max(error / bound))


def _nis_column(preset, columns, smooth=False, horizon=None, gaps=False):
    """Return the ``nis`` column of filter_table's output."""
    header = output_header(preset, horizon, smooth, gaps)
    return columns[header.index('nis')]


def test_the_reference_is_the_streaming_estimators_nis():
    """run_series' NIS (kalman.update) equals StreamEstimator's for the same rows."""
    preset = load_preset('train')
    stamps, t, z, _ = _series(preset, 300, 1)
    estimator = StreamEstimator(EstimatorSettings(preset='train', gate_probability=1.0,
                                                  initialization='prior'))
    R = float(preset.model.R[0, 0])
    live = [estimator.process(int(s), float(z_k[0]), R).update.nis for s, z_k in zip(stamps, z)]
    reference = run_series(preset, t, z, t0_s=T0_NS / 1e9).nis
    _close_nis(live, reference, z, preset.model.R)
    assert reference[150] > 100.0                   # the outlier's, fused (no gate)
    # ... and the vectorised path the replay runs (blocks of 37 rows and one block).
    for block_rows in (37, 300):
        columns = filter_table(preset, t, z, t0_s=T0_NS / 1e9, block_rows=block_rows)
        _close_nis(_nis_column(preset, columns, horizon=preset.horizon_s), live, z,
                   preset.model.R)


@pytest.mark.parametrize('name', LINEAR)
def test_every_engine_writes_the_filters_nis(name):
    """The series in blocks, --filter kf, --smooth and gaps: the reference's NIS."""
    preset = load_preset(name)
    stamps, t, z, u = _series(preset, 500, LINEAR.index(name))
    t0_s, R, horizon = T0_NS / 1e9, preset.model.R, preset.horizon_s
    reference = run_series(preset, t, z, u, t0_s=t0_s)
    assert np.all(np.isfinite(reference.nis))       # every row fused, the first too
    for block_rows in (64, 500):
        columns = filter_table(preset, t, z, u, t0_s=t0_s, block_rows=block_rows)
        _close_nis(_nis_column(preset, columns, horizon=horizon), reference.nis, z, R)
    columns = filter_table(preset, t, z, u, t0_s=t0_s, filt=make_filter(preset, 'kf'))
    _close_nis(_nis_column(preset, columns, horizon=horizon), reference.nis, z, R)
    columns = filter_table(preset, t, z, u, t0_s=t0_s, smooth=True, block_rows=64)
    _close_nis(_nis_column(preset, columns, smooth=True, horizon=horizon), reference.nis, z, R)
    missing = np.zeros(t.shape[0], dtype=bool)
    missing[[0, 7, 8, 300]] = True                  # no measurement: NaN, as the rail table
    gappy = run_series(preset, t, z, u, t0_s=t0_s, missing=missing)
    assert np.array_equal(np.isnan(gappy.nis), missing)
    columns = filter_table(preset, t, z, u, t0_s=t0_s, missing=missing, block_rows=64)
    _close_nis(_nis_column(preset, columns, horizon=horizon, gaps=True), gappy.nis, z, R)


@pytest.mark.parametrize('name', LINEAR)
@pytest.mark.parametrize('split', ['lock-step', 'alone'])
def test_a_fleet_writes_each_objects_nis(monkeypatch, name, split):
    """An id column: objects in lock-step or each alone, each its own series' NIS."""
    monkeypatch.setattr(bank, 'LOCKSTEP_STEP_S' if split == 'lock-step' else 'SERIES_CALL_S',
                        0.0)
    preset = load_preset(name)
    parts = [_series(preset, count, 10 + k, T0_NS) for k, count in enumerate([40, 3, 17, 1, 9])]
    codes = np.concatenate([np.full(part[1].shape[0], k) for k, part in enumerate(parts)])
    t = np.concatenate([part[1] for part in parts])
    z = np.concatenate([part[2] for part in parts])
    u = None if preset.dim_u == 0 else np.concatenate([part[3] for part in parts])
    order = np.argsort(t, kind='stable')             # the objects' rows interleaved
    t, z, codes = t[order], z[order], codes[order]
    u = None if u is None else u[order]
    columns = filter_table(preset, t, z, u, codes, t0_s=T0_NS / 1e9, block_rows=25)
    got = _nis_column(preset, columns, horizon=preset.horizon_s)
    for k in range(len(parts)):
        rows = np.flatnonzero(codes == k)
        alone = run_series(preset, t[rows], z[rows], None if u is None else u[rows],
                           t0_s=T0_NS / 1e9)
        _close_nis(got[rows], alone.nis, z[rows], preset.model.R)


def _write_input(path, t, z, ids=None):
    """Write a replay input (t as repr writes it, so the file holds the same doubles)."""
    lines = [('id,' if ids is not None else '') + 't,z_position']
    for k in range(t.shape[0]):
        lines.append(('' if ids is None else f'{ids[k]},') + f'{float(t[k])!r},{float(z[k, 0])!r}')
    path.write_text('\n'.join(lines) + '\n')


def _run(args):
    """Run kf-train replay; return the output's header and its numeric columns by name."""
    assert main(args) == 0
    output = args[args.index('-o') + 1]
    with open(output) as stream:
        header = stream.readline().strip().split(',')
    return header, read_table(output, [(h,) for h in header if h != 'id'], ids=True).columns


@pytest.mark.parametrize('extra', [[], ['--engine', 'memory'], ['--codec', 'builtin']])
def test_the_csv_outputs_carry_the_column(tmp_path, extra):
    """kf-train replay --preset train writes nis last, the doubles of filter_table."""
    preset = load_preset('train')
    _, t, z, _ = _series(preset, 400, 2)
    _write_input(tmp_path / 'in.csv', t, z)
    out = str(tmp_path / 'out.csv')
    header, columns = _run(['--preset', 'train', str(tmp_path / 'in.csv'), '-o', out, '--t0',
                            repr(T0_NS / 1e9), '--block-rows', '100'] + extra)
    assert header[-1] == 'nis'
    expected = filter_table(preset, t, z, t0_s=T0_NS / 1e9, block_rows=100)
    np.testing.assert_array_equal(columns['nis'],
                                  _nis_column(preset, expected, horizon=preset.horizon_s))
    # With an id column: the bank's NIS, the id first and nis last.
    ids = np.where(np.arange(t.shape[0]) % 3 == 0, 'A', 'B')
    _write_input(tmp_path / 'fleet.csv', t, z, ids)
    header, columns = _run(['--preset', 'train', str(tmp_path / 'fleet.csv'), '-o', out,
                            '--t0', repr(T0_NS / 1e9)] + extra)
    assert header[0] == 'id' and header[-1] == 'nis'
    for label in ('A', 'B'):
        rows = np.flatnonzero(ids == label)
        alone = run_series(preset, t[rows], z[rows], t0_s=T0_NS / 1e9)
        _close_nis(columns['nis'][rows], alone.nis, z[rows], preset.model.R)


def test_parquet_carries_the_column(tmp_path):
    """Parquet in and out: the same nis as the CSV replay."""
    pl = pytest.importorskip('polars')
    preset = load_preset('train')
    _, t, z, _ = _series(preset, 300, 3)
    pl.DataFrame({'t': t, 'z_position': z[:, 0]}).write_parquet(tmp_path / 'in.parquet')
    assert main(['--preset', 'train', str(tmp_path / 'in.parquet'), '-o',
                 str(tmp_path / 'out.parquet'), '--t0', repr(T0_NS / 1e9)]) == 0
    got = pl.read_parquet(tmp_path / 'out.parquet')
    assert got.columns[-1] == 'nis'
    expected = filter_table(preset, t, z, t0_s=T0_NS / 1e9)
    np.testing.assert_array_equal(got['nis'].to_numpy(),
                                  _nis_column(preset, expected, horizon=preset.horizon_s))


def test_the_table_and_the_bag_csv_name_the_same_columns():
    """A linear preset's table replay and its bag replay's CSV: the same header."""
    preset = load_preset('train')
    assert output_header(preset, preset.horizon_s, False) == csv_header(preset.state_names)
