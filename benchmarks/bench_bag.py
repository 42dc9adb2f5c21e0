"""
``make bench`` row 9: ``kf-train replay BAG`` speed and memory, and ``kf-train simulate``.

The input is ``kf-train simulate --duration 10000 --output in.mcap``: 10⁵ train
measurements (10⁴ s at 10 Hz) beside their ground truth, the simulator node's default
noise. Every figure below is measured in a child process:

* ``kf-train replay in.mcap`` into a CSV and into an MCAP bag, with the estimator's
  default parameters and with seed 000's (``preset:=train, initialization:=prior,
  gate_probability:=1.0``): wall time and CPU time of the command (start-up
  included), the real-time factor (10⁴ s of data / wall time; the issue's goal is
  >= 1000x, <= 10 s) and the peak RSS;
* where the time goes, CPU seconds (best of 2) of one process over the same bag:
  reading the bag (:class:`kf_train.io.bagio.BagInput`), the filter alone
  (:meth:`StreamEstimator.process` on the decoded messages), the node's session around
  it (:class:`kf_train.ros.session.EstimatorSession`), the ``/diagnostics`` statuses
  (one per ``diagnostics_period_s`` of record time), and the whole replay into CSV
  and into MCAP; the replay overhead is the whole replay minus the filter;
* memory stays flat: the peak RSS of the MCAP replay of a bag ten times shorter;
* ``kf-train simulate`` writing the input bag (wall, CPU).

``python benchmarks/bench_bag.py`` runs the row alone (``--quick`` on 10³ s);
``python benchmarks/bench_bag.py --split BAG [-p NAME:=VALUE ...]`` is the child
that prints the split as JSON. Figures only; nothing is asserted.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from typing import List

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_common import Row, verdict  # noqa: E402, I100
from bench_scale import _kf_train, _measured  # noqa: E402

RATE_HZ = 10.0
SEED_000 = ('preset:=train', 'initialization:=prior', 'gate_probability:=1.0')
PARAMETER_SETS = (('default parameters (rail IMM)', ()),
                  ('seed 000 parameters (train KF, suggested q on)', SEED_000))
GOAL_RTF = 1000.0
GOAL_S = 10.0


def _simulate(directory: str, duration_s: float, name: str) -> tuple:
    """Write a train run of ``duration_s`` as an MCAP bag; return (path, measurement)."""
    path = os.path.join(directory, name)
    run = _measured(_kf_train() + ['simulate', '--duration', f'{duration_s:g}', '--output',
                                   path])
    return path, run


def _replay(bag: str, output: str, parameters) -> dict:
    """Replay ``bag`` into ``output`` in a child; its measurement, and the replay's own s."""
    argv = _kf_train() + ['replay', bag, '--output', output]
    for parameter in parameters:
        argv += ['-p', parameter]
    run = _measured(argv)
    found = re.search(r'\(([0-9.]+) s, [0-9]+ measurements/s\)', run['stderr'])
    run['replay_s'] = float(found.group(1)) if found else float('nan')
    return run


def _replay_rows(directory: str, bag: str, data_s: float, count: int) -> List[Row]:
    """One row per output and parameter set."""
    rows = []
    for label, parameters in PARAMETER_SETS:
        for output in ('out.csv', 'out.mcap'):
            target = os.path.join(directory, output)
            run = _replay(bag, target, parameters)
            os.unlink(target)
            rtf = data_s / run['wall']
            met = rtf >= GOAL_RTF and run['wall'] <= GOAL_S
            rows.append((
                '9', f'kf-train replay BAG, {count:,} measurements ({data_s:g} s at 10 Hz)',
                f'{label} -> {output.split(".")[1].upper()}',
                f'{run["wall"]:.2f} s wall, {run["cpu"]:.2f} s CPU (start-up included; '
                f'replay itself {run["replay_s"]:.2f} s); peak RSS {run["rss_mib"]:.0f} MiB',
                f'{rtf:,.0f}x real time ({data_s / run["cpu"]:,.0f}x per CPU second)',
                f'>= {GOAL_RTF:g}x, <= {GOAL_S:g} s: {verdict(met)}'))
    return rows


def _split_rows(bag: str, count: int) -> List[Row]:
    """Where the time goes (one child per parameter set)."""
    rows = []
    for label, parameters in PARAMETER_SETS:
        argv = [sys.executable, os.path.abspath(__file__), '--split', bag]
        for parameter in parameters:
            argv += ['-p', parameter]
        done = subprocess.run(argv, capture_output=True, text=True, timeout=3600)
        if done.returncode != 0:
            rows.append(('9', 'bag replay split', label, f'failed: {done.stderr[-300:]}',
                         '-', '-'))
            continue
        s = json.loads(done.stdout)

        def per(seconds):
            return f'{seconds / count * 1e6:.1f} µs'

        session = s['session'] - s['filter']
        rows.append((
            '9', 'bag replay: where the CPU goes (one process, per measurement)', label,
            f'filter {per(s["filter"])}; reading the bag {per(s["read"])}; session around '
            f'the filter {per(session)}; CSV rows {per(s["csv"] - s["session"] - s["read"])}'
            f'; MCAP messages {per(s["mcap"] - s["session"] - s["read"] - s["diagnostics"])}'
            f' + /diagnostics statuses {per(s["diagnostics"])}',
            f'overhead (replay - filter): CSV {per(s["csv"] - s["filter"])}, MCAP '
            f'{per(s["mcap"] - s["filter"])}', '-'))
    return rows


def rows_bag(quick: bool) -> List[Row]:
    """Measure row 9."""
    data_s = 1000.0 if quick else 10_000.0
    count = round(data_s * RATE_HZ)
    with tempfile.TemporaryDirectory(prefix='kf_bench_bag_') as directory:
        bag, run = _simulate(directory, data_s, 'in.mcap')
        rows = [('9', 'kf-train simulate -> MCAP (measurement, ground_truth)',
                 f'train, {data_s:g} s at 10 Hz', f'{run["wall"]:.2f} s wall, '
                 f'{run["cpu"]:.2f} s CPU', f'{data_s / run["wall"]:,.0f}x real time', '-')]
        rows += _replay_rows(directory, bag, data_s, count)
        small, _ = _simulate(directory, data_s / 10, 'small.mcap')
        sizes = []
        for path in (small, bag):
            target = os.path.join(directory, 'memory.mcap')
            sizes.append(_replay(path, target, ())['rss_mib'])
            os.unlink(target)
        rows.append(('9', 'bag replay memory, MCAP output', f'{count // 10:,} vs {count:,} '
                     'measurements', f'peak RSS {sizes[0]:.0f} vs {sizes[1]:.0f} MiB',
                     f'{sizes[1] - sizes[0]:+.0f} MiB for 10x the data',
                     f'flat: {verdict(sizes[1] - sizes[0] < 20)}'))
        rows += _split_rows(bag, count)
    return rows


def split(bag: str, parameters: List[str], repeats: int = 2) -> dict:
    """Return CPU seconds of reading, the filter, the session and both replays of ``bag``."""
    best = {}
    for _ in range(repeats):   # the shortest of each: a shared machine's load only adds
        for part, seconds in _split_once(bag, parameters).items():
            best[part] = min(seconds, best.get(part, seconds))
    return best


def _split_once(bag: str, parameters: List[str]) -> dict:
    """Return CPU seconds of each part once (see :func:`split`)."""
    from kf_train.replay import bag as bag_replay
    from kf_train.estimator import Rejected, StreamEstimator
    from kf_train.io import bagio
    from kf_train.ros.session import EstimatorSession
    config = bag_replay.load_config([], parameters)
    cpu = time.process_time
    preset = StreamEstimator(config.settings).preset
    kinds = bagio.expected_types(preset.measurement_names, preset.control_names)
    started = cpu()
    with bagio.BagInput(bag, *kinds) as source:
        messages = list(source.messages())
    result = {'read': cpu() - started}
    estimator = StreamEstimator(config.settings)
    started = cpu()
    for m in messages:
        try:
            if type(m) is bagio.Measurement:
                estimator.process(m.stamp_ns, m.position_m, m.variance_m2,
                                  frame_id=m.frame_id, now_ns=m.record_ns)
            else:
                estimator.add_control(m.stamp_ns, [m.value], now_ns=m.record_ns)
        except Rejected:
            pass
    result['filter'] = cpu() - started
    clock = [0]
    session = EstimatorSession(config, lambda: clock[0] / 1e9)
    started = cpu()
    for m in messages:
        clock[0] = m.record_ns
        if type(m) is bagio.Measurement:
            session.on_measurement(m, m.record_ns)
        else:
            session.on_control(m, m.record_ns)
    result['session'] = cpu() - started
    # /diagnostics statuses (kf_train.ros.diagnostics) as many as the MCAP replay builds.
    period_ns = round(config.options.diagnostics_period_s * 1e9)
    statuses = (messages[-1].record_ns - messages[0].record_ns) // period_ns if messages else 0
    started = cpu()
    for _ in range(statuses):
        session.diagnostics(clock[0])
    result['diagnostics'] = cpu() - started
    with tempfile.TemporaryDirectory(prefix='kf_bench_split_') as directory:
        for output in ('csv', 'mcap'):
            started = cpu()
            bag_replay.replay_bag(bag, os.path.join(directory, f'out.{output}'), config)
            result[output] = cpu() - started
    return result


def main(argv=None) -> int:
    """Run row 9 alone and print it, or (--split) print the split of one bag as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--quick', action='store_true')
    parser.add_argument('--split', metavar='BAG')
    parser.add_argument('-p', dest='parameter', action='append', default=[])
    parser.add_argument('--repeats', type=int, default=2, help='--split: best of this many')
    args = parser.parse_args(argv)
    if args.split:
        print(json.dumps(split(args.split, args.parameter, args.repeats)))
        return 0
    from bench_common import table
    print('\n'.join(table(rows_bag(args.quick))))
    return 0


if __name__ == '__main__':
    sys.exit(main())
