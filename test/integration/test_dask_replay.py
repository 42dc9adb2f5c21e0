"""
kf-train replay --engine dask on a LocalCluster of 2 worker processes (loopback only).

The fleet's trains all have the same number of rows, so the bank runs every train
alone (run_linear_series on its whole series) both in one process and in each Dask
partition: the results must be equal bit for bit, not just close.
"""

import os

from kf_train.batch import filter_partition
from kf_train.cli.replay import main
import numpy as np
import pytest

pl = pytest.importorskip('polars')
pytest.importorskip('dask.distributed')
pd = pytest.importorskip('pandas')


def _fleet(trains=12, rows=400, seed=0):
    """Return a fleet log: trains with their own clocks, rows interleaved in time."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([rng.uniform(0, 1) + np.cumsum(rng.uniform(0.05, 0.15, rows))
                        for _ in range(trains)])
    ids = np.repeat([f'T{k:02d}' for k in range(trains)], rows)
    order = np.argsort(t, kind='stable')
    t, ids = t[order], ids[order]
    return pl.DataFrame({'id': ids, 't': t, 'z_position': 10.0 * t + rng.normal(0, 1, t.size)})


def test_dask_equals_the_single_process_replay(tmp_path):
    """Parquet dataset in, Parquet dataset and CSV out: equal to kf-train replay."""
    fleet = _fleet()
    (tmp_path / 'in').mkdir()
    for k in range(3):          # three files: trains are split across them
        fleet[k * 1600:(k + 1) * 1600].write_parquet(tmp_path / 'in' / f'p{k}.parquet')
    fleet.write_csv(tmp_path / 'in.csv')
    assert main(['--preset', 'train', str(tmp_path / 'in.csv'),
                 '-o', str(tmp_path / 'one.csv'), '--block-rows', '100000']) == 0
    single = pl.read_csv(tmp_path / 'one.csv', schema_overrides={'id': pl.String})
    assert main(['--preset', 'train', str(tmp_path / 'in'), '-o', str(tmp_path / 'out'),
                 '--engine', 'dask', '--workers', '2']) == 0
    got = pl.read_parquet(tmp_path / 'out' / '*.parquet')
    key = ['id', 't']
    assert got.columns == single.columns
    assert got.sort(key).equals(single.sort(key))
    assert main(['--preset', 'train', str(tmp_path / 'in'), '-o', str(tmp_path / 'o.csv'),
                 '--engine', 'dask', '--workers', '2']) == 0
    csv = pl.read_csv(tmp_path / 'o.csv', schema_overrides={'id': pl.String})
    assert csv.sort(key).equals(single.sort(key))
    assert sorted(os.listdir(tmp_path)) == ['in', 'in.csv', 'o.csv', 'one.csv', 'out']


def test_dask_rail_writes_the_columns_of_every_other_path(tmp_path):
    """The rail preset on Dask: the regimes and the NIS, equal to the single process."""
    fleet = _fleet(trains=3, rows=100)
    fleet.write_csv(tmp_path / 'in.csv')
    assert main(['--preset', 'rail', str(tmp_path / 'in.csv'), '-o', str(tmp_path / 'one.csv')]
                ) == 0
    single = pl.read_csv(tmp_path / 'one.csv', schema_overrides={'id': pl.String})
    assert single.columns[-5:] == ['p_stand', 'p_accelerate', 'p_cruise', 'p_brake', 'nis']
    assert main(['--preset', 'rail', str(tmp_path / 'in.csv'), '-o', str(tmp_path / 'o.csv'),
                 '--engine', 'dask', '--workers', '1']) == 0
    got = pl.read_csv(tmp_path / 'o.csv', schema_overrides={'id': pl.String})
    key = ['id', 't']
    assert got.columns == single.columns
    assert got.sort(key).equals(single.sort(key))     # nis as the text 'nan' in both


def test_partition_function_and_its_errors():
    """filter_partition on a pandas frame; a bad row names its id and time."""
    frame = _fleet(3, 50).to_pandas()
    out = filter_partition(frame, 'train')
    assert list(out.columns[:3]) == ['id', 't', 'position']
    assert (out['id'].to_numpy() == frame['id'].to_numpy()).all()
    bad = frame.copy()
    bad.loc[bad.index[0], 't'] = -1.0
    with pytest.raises(ValueError, match=r"id 'T\d\d', t = -1.0: -1.0 is before the initial"):
        filter_partition(bad, 'train')


def test_dask_needs_an_id_column(tmp_path, capsys):
    """No id column: one line saying what the dask engine needs, exit 1."""
    pl.DataFrame({'t': [0.1, 0.2], 'z_position': [1.0, 2.0]}).write_parquet(
        tmp_path / 'in.parquet')
    assert main(['--preset', 'train', str(tmp_path / 'in.parquet'), '-o',
                 str(tmp_path / 'out'), '--engine', 'dask', '--workers', '1']) == 1
    err = capsys.readouterr().err
    assert 'the dask engine needs the columns id, t, z_position' in err, err
    assert err.count('\n') == 1


def test_nodes_import_no_columnar_or_dask_library():
    """The nodes never import polars, pyarrow, pandas or Dask (start-up and footprint)."""
    import subprocess
    import sys
    code = ('import sys, kf_train.ros.estimator_node, kf_train.ros.simulator_node\n'
            'print(sorted({m.split(".")[0] for m in sys.modules} & {"polars", "pyarrow", '
            '"pandas", "dask", "distributed"}))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120, check=True)
    assert result.stdout.strip() == '[]'
