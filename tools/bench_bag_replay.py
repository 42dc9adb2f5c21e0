#!/usr/bin/env python3
"""
Time ``kf-train replay BAG`` on a bag of N measurements (default 100 000: 10⁴ s at 10 Hz).

    .venv/bin/python tools/bench_bag_replay.py [--count N]

Writes an MCAP bag of seed-000-like measurements (tools/bench_bagio.py's writer), then
replays it through the estimator node's session (default parameters) into a CSV and
into an MCAP bag, and prints the wall time, the measurements per second, the speed
against real time (10 Hz) and the peak memory (tracemalloc) of each. Figures only;
nothing is asserted (the issue's goal: >= 1000x real time, flat memory).
"""

import argparse
import os
from pathlib import Path
import sys
import tempfile
import time
import tracemalloc

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_bagio import write_input  # noqa: E402
from kf_train.cli import bag_replay  # noqa: E402

RATE_HZ = 10.0


def main(argv=None) -> int:
    """Write the input bag, replay it twice, print one line per output."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--count', type=int, default=100_000)
    parser.add_argument('--no-memory', action='store_true',
                        help='skip tracemalloc (it slows Python down)')
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as directory:
        bag = Path(directory) / 'in'
        seconds = write_input(bag, args.count)
        print(f'wrote {args.count} measurements in {seconds:.2f} s')
        config = bag_replay.load_config([], [])
        for output in ('out.csv', 'out.mcap'):
            started = time.perf_counter()
            summary = bag_replay.replay_bag(str(bag), str(Path(directory) / output), config)
            wall = time.perf_counter() - started
            line = (f'replay -> {output:8s} {summary.measurements} measurements, '
                    f'{summary.estimates} estimates: {wall:.2f} s, '
                    f'{summary.measurements / wall:,.0f} measurements/s, '
                    f'{summary.measurements / RATE_HZ / wall:,.0f}x real time')
            if not args.no_memory:
                tracemalloc.start()
                bag_replay.replay_bag(str(bag), str(Path(directory) / ('m' + output)), config)
                peak = tracemalloc.get_traced_memory()[1]
                tracemalloc.stop()
                line += f', peak memory {peak / 1e6:.1f} MB'
            print(line)
    return 0


if __name__ == '__main__':
    sys.exit(main())
