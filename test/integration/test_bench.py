"""
Smoke tests of ``make bench`` (benchmarks/bench.py) and of the nodes' import weight.

The benchmark asserts nothing about speed and neither do these tests: they check that
``--quick`` runs every row end to end (the live rows with real node processes) and
prints one table with its header, and that the node modules do not import scipy or
matplotlib, which would add about 0.8 s and 60 MiB to every node's start-up.
"""

import importlib.util
import json
import os
import subprocess
import sys

from kf_train.filters import numba_available
import pytest
from ros_helpers import isolated_env

BENCH_TIMEOUT_S = 600.0
# The benchmark is not part of the installed package: load it from the source tree.
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
BENCH = os.path.join(REPO, 'benchmarks', 'bench.py')
_spec = importlib.util.spec_from_file_location('bench', BENCH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_quick_bench_prints_one_table_with_every_row(tmp_path, domain_id):
    """--quick measures rows 1 to 11 (one live rate) and prints and saves one table."""
    output = tmp_path / 'out' / 'bench.md'
    result = subprocess.run(
        [sys.executable, BENCH, '--quick', '--rates', '2000',
         '--output', str(output)],
        capture_output=True, text=True, timeout=BENCH_TIMEOUT_S, env=isolated_env(domain_id))
    assert result.returncode == 0, result.stderr[-2000:]
    out = result.stdout
    for expected in ('Machine: ', ' cores', 'Python ', 'numpy ', 'rclpy ', 'filterpy ',
                     '| Row | Measurement | Case | Result | Ratio | Target |'):
        assert expected in out, expected
    table = [line for line in out.splitlines() if line.startswith('| ')]
    assert len([line for line in out.splitlines() if line.startswith('| Row |')]) == 1
    rows = {line.split('|')[1].strip() for line in table[1:]}
    assert rows == {'1', '2', '3', '4', '5', '6', '7', '8', '9', '10a', '10b', '11'}
    assert not [line for line in table if 'failed:' in line], table
    assert 'NOT EXACT' not in out, [line for line in table if 'NOT EXACT' in line]
    # Every live trial got through and exited (the echo, the train KF on both
    # executors, the rail default at the lowest rate); every start-up was measured.
    live = [line for line in table if line.startswith('| 4 |')]
    assert len(live) == 4 and all('latency median' in line for line in live), live
    assert sum('(defaults: rail IMM)' in line for line in live) == 1, live
    assert all('exit 0' in line for line in live), live
    startup = [line for line in table if line.startswith('| 5 |')]
    assert len(startup) == 4 and all('peak RSS' in line for line in startup), startup
    filters = [line for line in table if line.startswith('| 6 |')]
    assert len(filters) == 6 and all('× the UKF' in line for line in filters), filters
    # Row 7: every scale figure with its target; row 8: the live estimator's share.
    scale = '\n'.join(line for line in table if line.startswith('| 7 |'))
    for expected in ('<250 MiB', '≥1,000,000 rows/s', '≥5,000,000 rows/s', '≥10×', '≥20×',
                     'LocalCluster', 'equal to one process', 'same bytes as polars'):
        assert expected in scale, expected
    live_fleet = [line for line in table if line.startswith('| 8 |')]
    assert len(live_fleet) == 1 and 'estimators per core' in live_fleet[0], live_fleet
    # Row 9: the bag replay into CSV and MCAP, both parameter sets, memory and the split.
    bags = [line for line in table if line.startswith('| 9 |')]
    replays = [line for line in bags if 'kf-train replay BAG' in line]
    assert len(replays) == 4 and all('x real time' in line and 'peak RSS' in line
                                     for line in replays), replays
    assert sum('where the CPU goes' in line and 'filter' in line for line in bags) == 2
    assert any('flat:' in line for line in bags), bags
    # Row 10: the rail IMM's cost (exact grid, jittered stamps) beside the KF's, and one
    # target row per run (2 runs).
    rail = [line for line in table if line.startswith(('| 10a |', '| 10b |'))]
    # The compiled rail IMM (numba, the jit extra) adds its two rows beside the reference.
    compiled = 2 if numba_available() else 0
    assert len([line for line in rail if '× the closed-form KF' in line]) == 4 + compiled, rail
    assert sum('jittered' in line for line in rail) == 1 + compiled // 2, rail
    assert sum('faster than the numpy reference' in line for line in rail) == compiled, rail
    runs = [line for line in rail if 'unseen run' in line]
    assert len(runs) == 2 and all('2σ coverage' in line and 'the best (' in line
                                  for line in runs), runs
    # Row 11: the rail tune, the fit and the whole command.
    tune = [line for line in table if line.startswith('| 11 |')]
    assert len(tune) == 2 and all(' s (' in line for line in tune), tune
    # The file holds the header and the same table.
    saved = output.read_text()
    assert saved.splitlines()[0].startswith('kf_train benchmark, ')
    assert [line for line in saved.splitlines() if line.startswith('| ')] == table


@pytest.mark.parametrize('argv', [['--rows', '12'], ['--rows', 'x'], ['--rates', '0'],
                                  ['--bogus']])
def test_bad_command_line_exits_2(argv, capsys):
    """An unknown row, a bad rate or option: exit 2 with argparse's message."""
    assert bench.main(argv) == 2
    assert 'kf-train bench' in capsys.readouterr().err


def test_help_exits_0(capsys):
    """--help documents the options."""
    assert bench.main(['--help']) == 0
    out = capsys.readouterr().out
    for option in ('--quick', '--rows', '--rates', '--output'):
        assert option in out


def test_percentile_is_nearest_rank():
    """The latency percentiles are nearest-rank: an observed value, never interpolated."""
    values = list(range(1, 101))
    assert bench.percentile(values, 0.5) == 50
    assert bench.percentile(values, 0.99) == 99
    assert bench.percentile([7.0], 0.99) == 7.0
    assert bench.percentile([], 0.5) != bench.percentile([], 0.5)  # NaN


def test_nodes_do_not_import_scipy_or_matplotlib():
    """Importing either node module (and so the runner and the core) pulls in neither."""
    code = ('import json, sys\n'
            'import kf_train.ros.estimator_node, kf_train.ros.simulator_node\n'
            'print(json.dumps(sorted(m for m in sys.modules\n'
            '                 if m.split(".")[0] in ("scipy", "matplotlib"))))\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120, env=dict(os.environ, PYTHONDONTWRITEBYTECODE='1'))
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == []
