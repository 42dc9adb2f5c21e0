"""
``make soak``: the simulator and the estimator at 1 kHz for a long time, measured.

    python benchmarks/soak.py --duration 3600          # make soak (SOAK_S=3600)
    python benchmarks/soak.py --duration 20 --json soak.json   # the CI-sized run

Both nodes run as a user runs them (``simulator``/``estimator`` with ``--executor
events``, the estimator's defaults but for its preset, which follows the scenario, and
``--qos-depth``, its measurement queue: 10 by default, ``make bench`` row 4 uses 1000),
with a probe node (node_soak_probe.py) on ``measurement`` and ``estimate``. Every
``--sample-s`` the resident set size and CPU time of both nodes are read from /proc.
At the end it prints the windows' latencies and one summary line:

* RSS slope [MB/h] of each node: a least-squares line through the samples after the
  warm-up (WARM_UP_FRACTION of the run, at most WARM_UP_S), its standard error beside
  it ("flat" means the slope is within noise);
* dropped: samples the estimator never received (the simulator's count, from the
  probe's stamp sequence, minus the estimator's ``received``), and estimates lost
  on the way to the probe (gaps in their stamp sequence beyond those and the gate's
  rejections);
* latency percentiles per window, first / last / worst: an estimate's arrival at the
  probe minus its measurement's (the estimator's own delay, transport included); and
  the simulator's lag (a measurement's arrival minus its stamp: on a loaded machine
  the simulator falls behind its schedule, and the stamps with it);
* CPU share of each node; NaN (non-finite estimates) count; exit codes.

The targets (issue 21): RSS slope ≤ 1 MB/h, no drops on the events executor, no NaN,
no crash. Exit code 0 when the run completed (every process up to the end and exiting
0), whatever the figures; 1 otherwise.
"""

import argparse
import json
import math
import signal
import statistics
import sys
import time
from typing import List, Sequence, Tuple

from bench_children import Child, Domains, helper, node_command

DEFAULT_RATE_HZ = 1000.0
STARTUP_TIMEOUT_S = 60.0
DRAIN_S = 2.5  # after the simulator stops: the last estimates and a diagnostics status
WARM_UP_FRACTION = 0.2
WARM_UP_S = 600.0
"""The RSS slope leaves out the first 20 % of the run, at most 10 minutes: start-up,
the first allocations and the allocator's arenas filling (in a 300-s run at 1 kHz the
estimator's RSS rose 0.8 MB from 60 s to 200 s, then stayed flat to the end)."""


def rss_mb(child: Child) -> float:
    """Return the process's resident set size [MB] (VmRSS)."""
    with open(f'/proc/{child.process.pid}/status') as status:
        for line in status:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    return math.nan


def slope_per_hour(times_s: Sequence[float], values: Sequence[float]) -> Tuple[float, float]:
    """Return the least-squares slope of values over time [unit/h] and its standard error."""
    n = len(times_s)
    if n < 3:
        return math.nan, math.nan
    mean_t = math.fsum(times_s) / n
    mean_v = math.fsum(values) / n
    sxx = math.fsum((t - mean_t) ** 2 for t in times_s)
    if sxx == 0.0:
        return math.nan, math.nan
    slope = math.fsum((t - mean_t) * (v - mean_v) for t, v in zip(times_s, values)) / sxx
    residuals = math.fsum((v - mean_v - slope * (t - mean_t)) ** 2
                          for t, v in zip(times_s, values))
    error = math.sqrt(residuals / (n - 2) / sxx)
    return slope * 3600.0, error * 3600.0


def parse_args(argv: List[str]) -> argparse.Namespace:
    """Return the options, with the sampling derived from the duration when not given."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=3600.0, help='seconds of load')
    parser.add_argument('--rate', type=float, default=DEFAULT_RATE_HZ, help='rate_hz')
    parser.add_argument('--scenario', default='train', help='scenario = preset')
    parser.add_argument('--executor', default='events', choices=('events', 'single_threaded'))
    parser.add_argument('--sample-s', type=float, default=0.0, help='RSS/CPU sample period')
    parser.add_argument('--window-s', type=float, default=0.0, help='latency window')
    parser.add_argument('--qos-depth', type=int, default=0,
                        help="estimator's qos_depth (0: its default, 10)")
    parser.add_argument('--json', default='', help='also write the results here')
    args = parser.parse_args(argv)
    args.sample_s = args.sample_s or min(max(args.duration / 360.0, 0.5), 10.0)
    args.window_s = args.window_s or min(max(args.duration / 12.0, 2.0), 300.0)
    return args


def run_soak(args: argparse.Namespace) -> dict:
    """Run the nodes and the probe for ``args.duration``; return every figure."""
    env = Domains().env()
    executor = ['--executor', args.executor]
    children = []
    try:
        depth = ['-p', f'qos_depth:={args.qos_depth}'] if args.qos_depth else []
        estimator = Child(node_command('estimator') + executor + [
            '--ros-args', '-p', f'preset:={args.scenario}'] + depth, env, 'estimator')
        children.append(estimator)
        probe = Child(helper('soak_probe', args.rate, args.window_s), env, 'probe')
        children.append(probe)
        # Two subscribers to wait for before the first sample: the estimator, the probe.
        simulator = Child(node_command('simulator') + executor + [
            '--ros-args', '-p', f'scenario:={args.scenario}', '-p', f'rate_hz:={args.rate}',
            '-p', 'min_subscribers:=2'], env, 'simulator')
        children.append(simulator)
        probe.wait_for('ready', STARTUP_TIMEOUT_S)
        samples = _sample(args, (estimator, simulator))
        alive = all(child.process.poll() is None for child in children)
        sim_code, _ = simulator.stop(signal.SIGINT)
        time.sleep(DRAIN_S)
        probe.stop(signal.SIGINT)
        seen = probe.json_result(10.0)
        est_code, _ = estimator.stop(signal.SIGINT)
        return {'args': vars(args), 'samples': samples, 'probe': seen, 'alive': alive,
                'exit': {'estimator': est_code, 'simulator': sim_code},
                'traceback': any('Traceback' in child.stderr_text() for child in children)}
    finally:
        for child in children:
            child.kill()


def _sample(args: argparse.Namespace, nodes: Sequence[Child]) -> List[list]:
    """Read [t, RSS, CPU] of each node every sample_s for the duration."""
    samples = []
    start = time.monotonic()
    while True:
        now = time.monotonic() - start
        if any(node.process.poll() is not None for node in nodes):
            break
        samples.append([round(now, 3)] + [value for node in nodes
                                          for value in (rss_mb(node), node.cpu_s())])
        if now >= args.duration:
            break
        time.sleep(max(min(args.sample_s, args.duration - now), 0.0))
    return samples


def summarise(result: dict) -> dict:
    """Return the figures of a run: slopes, drops, latencies, CPU, NaN, verdict."""
    samples = result['samples']
    duration = samples[-1][0] - samples[0][0] if len(samples) > 1 else math.nan
    # The warm-up (imports, first allocations, DDS discovery) is not a leak.
    warm = [row for row in samples if row[0] >= min(WARM_UP_S, WARM_UP_FRACTION * duration)]
    figures = {'duration_s': duration}
    for i, name in enumerate(('estimator', 'simulator')):
        slope, error = slope_per_hour([row[0] for row in warm], [row[1 + 2 * i] for row in warm])
        figures[f'{name}_rss_slope_mb_h'] = slope
        figures[f'{name}_rss_slope_error_mb_h'] = error
        figures[f'{name}_rss_mb'] = [samples[0][1 + 2 * i], samples[-1][1 + 2 * i]]
        figures[f'{name}_cpu'] = ((samples[-1][2 + 2 * i] - samples[0][2 + 2 * i])
                                  / duration if duration > 0 else math.nan)
    probe = result['probe']
    diagnostics = probe.get('diagnostics', {})
    received = int(diagnostics.get('received', 0))
    rejected = int(diagnostics.get('rejected', 0))
    figures['published'] = probe['measurement']['span']
    figures['received'] = received
    figures['dropped_input'] = max(probe['measurement']['span'] - received, 0)
    # An estimate is missing for each measurement the estimator never got or gated.
    figures['dropped_output'] = max(
        probe['estimate']['lost'] - rejected - figures['dropped_input'], 0)
    figures['rejected'] = rejected
    figures['nan'] = probe['nan']
    windows = [w for w in probe['windows'] if w['count']]
    # The window cut by the stop holds the last few estimates only: not a window.
    if len(windows) > 1 and windows[-1]['count'] < 0.5 * statistics.median(
            w['count'] for w in windows):
        windows.pop()
    figures['windows'] = windows
    figures['completed'] = bool(result['alive'] and not result['traceback']
                                and result['exit'] == {'estimator': 0, 'simulator': 0})
    return figures


def summary_line(args: argparse.Namespace, figures: dict) -> str:
    """Return the one-line summary."""
    windows = figures['windows']

    def lat(window):
        return '{:.2f}/{:.2f}'.format(window['p50_ms'], window['p99_ms'])
    worst = max((w['p99_ms'] for w in windows), default=math.nan)
    latency = (f'latency p50/p99 ms first {lat(windows[0])}, last {lat(windows[-1])}, worst '
               f'p99 {worst:.2f}' if windows else 'no estimates')
    f = figures
    rss = f['estimator_rss_mb']
    return (f'soak: {f["duration_s"]:.0f} s at {args.rate:g} Hz ({args.scenario}, '
            f'{args.executor}): RSS slope estimator {f["estimator_rss_slope_mb_h"]:+.2f}±'
            f'{f["estimator_rss_slope_error_mb_h"]:.2f} MB/h ({rss[0]:.0f}->{rss[1]:.0f} MB), '
            f'simulator {f["simulator_rss_slope_mb_h"]:+.2f}±'
            f'{f["simulator_rss_slope_error_mb_h"]:.2f} MB/h; dropped {f["dropped_input"]} of '
            f'{f["published"]} in, {f["dropped_output"]} out ({f["rejected"]} gated); '
            f'{latency}; CPU estimator {100 * f["estimator_cpu"]:.0f} %, simulator '
            f'{100 * f["simulator_cpu"]:.0f} %; NaN {f["nan"]}; '
            f'{"completed" if f["completed"] else "FAILED"}')


def main(argv: List[str]) -> int:
    """Run the soak, print the windows and the summary line; 0 if it completed."""
    args = parse_args(argv)
    result = run_soak(args)
    if len(result['samples']) < 2 or not result['probe']['windows']:
        print(f"soak: FAILED: no run (exit codes {result['exit']})")
        return 1
    figures = summarise(result)
    for window in figures['windows']:
        print(f"  t {window['t_s']:8.1f} s: {window['count']:7d} estimates, latency p50 "
              f"{window['p50_ms']:.2f} ms, p99 {window['p99_ms']:.2f} ms, max "
              f"{window['max_ms']:.2f} ms; simulator lag {window['stamp_lag_ms']:.0f} ms")
    print(summary_line(args, figures), flush=True)
    if args.json:
        with open(args.json, 'w') as stream:
            json.dump({'figures': figures, 'run': result}, stream)
    return 0 if figures['completed'] else 1


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
