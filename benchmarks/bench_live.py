"""
Rows 4 and 5 of ``make bench``: the live estimator at kHz rates, and start-up.

Row 4 feeds the estimator from a paced publisher in another process and sets a bare
echo node beside it (the transport's own cost); row 5 measures process start to first
output and peak RSS against bare rclpy nodes with the same publishers.
"""

import os
import signal
import statistics
import subprocess
import sys
import time
from typing import List, Optional, Sequence, Tuple

from bench_children import Child, Domains, helper, HERE, node_command
from bench_common import NS_PER_S, Row, verdict

LIVE_RATES_HZ = (1000, 2000, 5000, 10000)
STARTUP_RATE_HZ = 100.0
DIAGNOSTICS_PERIOD_S = 0.25

# -- row 4: the live estimator --------------------------------------------------------

# Subscription QoS of the estimator and the echo in row 4: best effort (the default)
# with a history deep enough for the publisher's bursts (it catches up after a late
# wake-up, up to tens of messages at once) and for the executor's pauses.
LIVE_QOS_DEPTH = 1000


def _live_trial(domains: Domains, target: str, executor: str, rate_hz: int,
                duration_s: float, signum: int, qos_depth: int = LIVE_QOS_DEPTH,
                preset: Optional[str] = None) -> dict:
    """
    Run one paced-publisher trial against the estimator or the echo node.

    Returns published, delivered and processed counts, the target's CPU share over
    the publishing interval, the latencies seen by the probe and how it exited.
    """
    env = domains.env()
    count = int(rate_hz * duration_s)
    children = []
    try:
        if target == 'estimator':
            command = node_command('estimator') + [
                '--executor', executor, '--ros-args', '-p',
                f'diagnostics_period_s:={DIAGNOSTICS_PERIOD_S}', '-p',
                f'qos_depth:={qos_depth}', '--log-level', 'error']
            if preset is not None:
                command[-2:-2] = ['-p', f'preset:={preset}']
            probe = helper('probe', 'estimate', 'odometry', '--diagnostics')
        else:
            command = helper('echo', executor, qos_depth)
            probe = helper('probe', 'echo', 'measurement')
        node = Child(command, env, target)
        children.append(node)
        probe = Child(probe, env, 'probe')
        children.append(probe)
        probe.wait_for('ready', 30.0)
        publisher = Child(helper('publisher', rate_hz, count), env, 'publisher')
        children.append(publisher)
        publisher.wait_for('start', 30.0)
        cpu0, wall0 = node.cpu_s(), time.monotonic()
        published = publisher.json_result(duration_s * 3 + 30.0)
        cpu1, wall1 = node.cpu_s(), time.monotonic()
        time.sleep(max(1.0, 3 * DIAGNOSTICS_PERIOD_S))  # let the last messages drain
        code, exit_s = node.stop(signum)
        node_result = {}
        if target == 'echo':
            node_result = node.json_result(5.0) if code == 0 else {}
        probe.stop(signal.SIGINT)
        seen = probe.json_result(10.0)
        traceback = 'Traceback' in node.stderr_text()
        return {'published': published['published'], 'max_burst': published['max_burst'],
                'seen': seen, 'node': node_result,
                'cpu': (cpu1 - cpu0) / max(wall1 - wall0, 1e-9), 'code': code,
                'exit_s': exit_s, 'traceback': traceback,
                'signal': signal.Signals(signum).name}
    finally:
        for child in children:
            child.kill()


def row_live(quick: bool, rates: Sequence[int], qos_depth: int = LIVE_QOS_DEPTH) -> List[Row]:
    """Measure row 4: the estimator fed by a paced publisher, beside a bare echo node."""
    domains = Domains()
    duration_s = 1.0 if quick else 2.5
    rows = []
    signals = (signal.SIGINT, signal.SIGTERM)
    for i, rate in enumerate(rates):
        # The transport targets are the train KF's (a closed form: what is measured is
        # the node's plumbing); the default rail IMM costs ~0.1-0.5 ms per fix (more
        # with jittered stamps: docs/rail.md) and is shown once, at the lowest rate.
        trials = [('echo', 'events', None), ('estimator', 'single_threaded', 'train'),
                  ('estimator', 'events', 'train')]
        if i == 0:
            trials.append(('estimator', 'events', None))
        echo_median = None
        for j, (target, executor, preset) in enumerate(trials):
            signum = signals[(i + j) % 2]
            name = target if target == 'echo' else (
                f'estimator (preset {preset})' if preset else 'estimator (defaults: rail IMM)')
            try:
                trial = _live_trial(domains, target, executor, rate, duration_s, signum,
                                    qos_depth, preset)
            except (RuntimeError, TimeoutError, subprocess.TimeoutExpired) as error:
                reason = ' '.join(str(error).split())[:300]
                rows.append(('4', f'live, {rate:,} Hz', f'{name}, {executor} executor, '
                             f'best effort depth {qos_depth:,}', f'failed: {reason}', '-', '-'))
                continue
            published = trial['published']
            seen = trial['seen']
            if target == 'estimator':
                diagnostics = seen.get('diagnostics', {})
                delivered = int(diagnostics.get('received', 0))
                processed = int(diagnostics.get('fused', 0))
                rejected = int(diagnostics.get('rejected', 0))
            else:
                delivered = int(trial['node'].get('received', 0))
                processed = seen['count']
                rejected = 0
            median, p99 = seen['latency_median_ms'], seen['latency_p99_ms']
            exit_text = (f'{trial["signal"]} → exit {trial["code"]} in '
                         f'{trial["exit_s"]:.2f} s')
            if trial['traceback']:
                exit_text += ', TRACEBACK'
            result = (f'delivered {100.0 * delivered / published:.1f}%, processed '
                      f'{100.0 * processed / published:.1f}%'
                      + (f' ({rejected} gated)' if rejected else '')
                      + f' of {published:,}; at the probe {100.0 * seen["count"] / published:.1f}%'
                      f'; CPU {100.0 * trial["cpu"]:.0f}%; latency median {median:.3g} ms, '
                      f'p99 {p99:.3g} ms; {exit_text}')
            clean = trial['code'] == 0 and not trial['traceback']
            if target == 'echo':
                echo_median = median
                ratio, goal = '1.00× echo', f'clean exit: {verdict(clean)}'
            else:
                ratio = '-' if echo_median is None else f'{median / echo_median:.2f}× echo'
                goal = f'clean exit: {verdict(clean)}'
                if preset is None:
                    pass                # the default's own cost: no transport target
                elif executor == 'events' and rate >= 5000:
                    lossless = delivered >= published and processed + rejected >= published
                    goal = f'lossless: {verdict(lossless)}; ' + goal
                if executor == 'events' and echo_median is not None and preset is not None:
                    goal = (f'median ≤1.5× echo: {verdict(median <= 1.5 * echo_median)}; '
                            + goal)
            rows.append(('4', f'live, {rate:,} Hz', f'{name}, {executor} executor, '
                         f'best effort depth {qos_depth:,}', result, ratio, goal))
    return rows


# -- row 5: start-up ------------------------------------------------------------------

def _startup_trial(domains: Domains, which: str) -> Tuple[float, float]:
    """Return (seconds from process start to first output at the probe, peak RSS MiB)."""
    env = domains.env()
    children = []
    try:
        if which in ('estimator', 'bare estimator'):
            probe = Child(helper('probe', 'estimate', 'odometry'), env, 'probe')
            children.append(probe)
            # A sensor that is already streaming when the estimator starts.
            feeder = Child(helper('publisher', STARTUP_RATE_HZ, 0, -1.0), env, 'publisher')
            children.append(feeder)
            feeder.wait_for('up', 30.0)
        else:
            probe = Child(helper('probe', 'measurement', 'measurement'), env, 'probe')
            children.append(probe)
        probe.wait_for('up', 30.0)
        if which == 'estimator':
            command = node_command('estimator')
        elif which == 'simulator':
            command = node_command('simulator') + ['--ros-args', '-p',
                                                   f'rate_hz:={STARTUP_RATE_HZ}']
        elif which == 'bare estimator':
            command = [sys.executable, os.path.join(HERE, 'node_bare_estimator.py')]
        else:
            command = [sys.executable, os.path.join(HERE, 'node_bare_simulator.py'),
                       str(STARTUP_RATE_HZ)]
        node = Child(command, env, which)
        children.append(node)
        first_ns = int(probe.wait_for('first', 30.0).split()[1])
        time.sleep(0.3)
        rss = node.peak_rss_mib()
        node.stop(signal.SIGINT)
        return (first_ns - node.start_ns) / NS_PER_S, rss
    finally:
        for child in children:
            child.kill()


def row_startup(quick: bool) -> List[Row]:
    """Measure row 5: start to first output and peak RSS, nodes against bare rclpy nodes."""
    domains = Domains()
    # DDS discovery now and then misses its first announcements and waits for the
    # next periodic one, seconds later, for the bare nodes as for ours: the fastest of
    # five is each process's own start-up, and is what is compared.
    repeats = 1 if quick else 5
    results = {}
    for which in ('bare estimator', 'estimator', 'bare simulator', 'simulator'):
        times, rss = [], []
        for _ in range(repeats):
            try:
                seconds, mib = _startup_trial(domains, which)
            except (RuntimeError, TimeoutError) as error:
                results[which] = str(error)
                break
            times.append(seconds)
            rss.append(mib)
        else:
            results[which] = (min(times), max(rss), statistics.median(times))
    rows = []
    for node in ('estimator', 'simulator'):
        bare, ours = results[f'bare {node}'], results[node]
        for which, value in ((f'bare {node}', bare), (node, ours)):
            if isinstance(value, str):
                rows.append(('5', 'start-up', which, f'failed: {value[:300]}', '-', '-'))
                continue
            what = 'first estimate' if node == 'estimator' else 'first measurement'
            result = (f'{value[0]:.2f} s to {what} (fastest of {repeats}; median '
                      f'{value[2]:.2f} s); peak RSS {value[1]:.0f} MiB')
            ratio, target = '-', '-'
            if which == node and not isinstance(bare, str):
                extra_s, extra_mib = value[0] - bare[0], value[1] - bare[1]
                ratio = f'{extra_s:+.2f} s, {extra_mib:+.0f} MiB vs bare'
                target = (f'within 0.15 s and 15 MiB: '
                          f'{verdict(extra_s <= 0.15 and extra_mib <= 15.0)}')
            rows.append(('5', 'start-up', which if which != node else f'kf_train {node}',
                         result, ratio, target))
    return rows
