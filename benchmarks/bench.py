"""
``make bench``: kf_train's performance, measured side by side in one run, as one table.

Rows (``--rows``, default all that exist):

1. Core update cost of the 2-state train model on identical data: a reference closed
   form written here (the CPython floor), kf_train's fast path (per call and whole
   series), its generic n-state path (functions and class) and filterpy.
2. Replay throughput (kf_train.cli.replay, called as it is) on a 10⁶-row series, in
   rows/s: in memory and from CSV to CSV for every 1-D preset, and the id column (a
   bank of 10³ objects × 10³ rows on their own clocks), each with Δ, its largest
   difference from the plain row-by-row path.
3. The bank: N independent objects (rows tagged by id) filtered at once, in ns per
   object-row as N grows.
4. The live estimator: a paced publisher in another process at 1, 2, 5 and 10 kHz;
   delivered and processed %, the estimator's CPU (from /proc), latency from
   measurement publish to estimate receipt (median, p99), and beside it a bare echo
   node (same QoS, republishes each message): the transport's own cost.
5. Start-up: process start to first output, and peak RSS, for each node and for a
   bare rclpy node with the same publishers.
6. The filter family on the range-bearing seed: µs per update of EKF, UKF, the
   regularised particle filter and the bootstrap one, each as a ratio to the UKF.
7. Offline at scale: peak RSS of the streamed replay at 10⁶ and 10⁷ rows, CSV and
   Parquet throughput, 200 000 rows against a plain filterpy script, the bank beside
   simdkalman at 10⁵ and 10⁶ filters, and ``--engine dask``.
8. Live fleet capacity: one estimator per train at 10 Hz, its CPU share and memory.
9. Bags: ``kf-train replay BAG`` on 10⁵ measurements (10⁴ s at 10 Hz) into CSV and
   MCAP, default and seed-000 parameters: real-time factor, CPU, peak RSS (and at a
   tenth of the data: flat memory), where the CPU goes (filter against the replay's
   own overhead), and ``kf-train simulate`` writing the input.
10. The rail preset (the default since issue 11): µs per measurement of the rail IMM
   next to the train's KF, and issue 11's targets on 16 unseen rail runs, every run
   a row: 2-s RMSE against hindsight-tuned filterpy CV/CA/IMM, 2σ coverage
   (bench_rail.py; ``--rail-full`` tunes the baselines on the full grids).
11. ``kf-train tune`` of the rail default on a 30,000-fix simulated bag: the fit's time
   and the whole command's (bench_tune.py).

Benchmarks print figures; they assert nothing. Every child process runs in its own
ROS domain on localhost and is killed at the end whatever happens. The table is also
written to ``--output`` (default out/bench.md) for docs/performance.md. ``--quick`` shortens
every measurement (a smoke test, not figures to quote).

This directory is not installed with kf_train (it imports filterpy, a test and
benchmark oracle): ``make bench`` runs this file, ``kf-train bench`` too from a source
checkout. Rows 1-3 are in bench_core.py, rows 4-5 in bench_live.py, row 6 in
bench_filters.py, rows 7-8 in bench_scale.py, row 9 in bench_bag.py, row 10 in
bench_rail.py, row 11 in bench_tune.py, the child processes in bench_children.py and the
helper nodes are the node_*.py files.
"""

import argparse
import os
import sys
import time
from typing import List, Optional

# The modules beside this file, also when it is loaded by path (kf-train bench, tests).
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_bag import rows_bag  # noqa: E402, I100
from bench_common import header, percentile, Row, table  # noqa: E402
from bench_core import row_bank, row_core, row_replay  # noqa: E402
from bench_filters import row_filters  # noqa: E402
from bench_live import LIVE_QOS_DEPTH, LIVE_RATES_HZ, row_live, row_startup  # noqa: E402
from bench_rail import rows_rail  # noqa: E402
from bench_scale import rows_live_fleet, rows_scale  # noqa: E402
from bench_tune import rows_tune  # noqa: E402

__all__ = ['main', 'percentile', 'ROWS']

ROWS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11)


def _parse(argv: List[str]) -> argparse.Namespace:
    """Parse the command line."""
    parser = argparse.ArgumentParser(
        prog='kf-train bench',
        description='Measure kf_train side by side and print one table (make bench).')
    parser.add_argument('--quick', action='store_true',
                        help='short runs: checks that everything works, not figures')
    parser.add_argument('--rows', default=','.join(str(r) for r in ROWS),
                        help='comma-separated rows to measure (default: %(default)s)')
    parser.add_argument('--rates', default=','.join(str(r) for r in LIVE_RATES_HZ),
                        help='row 4 publisher rates [Hz] (default: %(default)s)')
    parser.add_argument('--qos-depth', type=int, default=LIVE_QOS_DEPTH,
                        help='row 4: subscription depth of the estimator and the echo, '
                             'best effort (default: %(default)s)')
    parser.add_argument('--rail-full', action='store_true',
                        help='row 10: tune the filterpy baselines on the full grids '
                             '(slower the first time; cached in out/rail_baselines.json)')
    parser.add_argument('--output', default=os.path.join('out', 'bench.md'),
                        help="also write the table here ('' for nowhere; "
                             'default: %(default)s)')
    args = parser.parse_args(argv)
    try:
        args.rows = sorted({int(r) for r in args.rows.split(',') if r.strip()})
        args.rates = [int(r) for r in args.rates.split(',') if r.strip()]
    except ValueError:
        parser.error('--rows and --rates take comma-separated integers')
    unknown = [r for r in args.rows if r not in ROWS]
    if unknown:
        parser.error(f'unknown rows {unknown}: rows are {list(ROWS)}')
    if not args.rates or min(args.rates) <= 0:
        parser.error('--rates must be positive')
    if not 1 <= args.qos_depth <= 100_000:
        parser.error('--qos-depth must be in [1, 100000]')
    return args


def main(argv: Optional[List[str]] = None) -> int:
    """Run the benchmark; return the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = _parse(argv)
    except SystemExit as stop:  # --help, or a bad command line (argparse printed why)
        return int(stop.code or 0)
    lines = header()
    print('\n'.join(lines), flush=True)
    started = time.monotonic()
    rows: List[Row] = []
    measure = {1: lambda: row_core(args.quick), 2: lambda: row_replay(args.quick),
               3: lambda: row_bank(args.quick),
               4: lambda: row_live(args.quick, args.rates, args.qos_depth),
               5: lambda: row_startup(args.quick),
               6: lambda: row_filters(args.quick),
               7: lambda: rows_scale(args.quick),
               8: lambda: rows_live_fleet(args.quick),
               9: lambda: rows_bag(args.quick),
               10: lambda: rows_rail(args.quick, args.rail_full),
               11: lambda: rows_tune(args.quick)}
    for row in args.rows:
        print(f'measuring row {row} ...', file=sys.stderr, flush=True)
        rows += measure[row]()
    lines.append(f'Measured in {time.monotonic() - started:.0f} s'
                 + (' (--quick: not figures to quote)' if args.quick else '') + '.')
    text = '\n'.join(lines[-1:] + [''] + table(rows))
    print(text, flush=True)
    if args.output:
        directory = os.path.dirname(args.output)
        if directory:
            os.makedirs(directory, exist_ok=True)
        with open(args.output, 'w') as output:
            output.write('\n'.join(lines[:-1] + [''] + [text]) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
