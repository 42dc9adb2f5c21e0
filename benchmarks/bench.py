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
3. A fleet of N independent filters stepped at once: ns per filter-step as N grows.
4. The live estimator: a paced publisher in another process at 1, 2, 5 and 10 kHz;
   delivered and processed %, the estimator's CPU (from /proc), latency from
   measurement publish to estimate receipt (median, p99), and beside it a bare echo
   node (same QoS, republishes each message): the transport's own cost.
5. Start-up: process start to first output, and peak RSS, for each node and for a
   bare rclpy node with the same publishers.
6. Offline at scale (benchmarks/scale.py): peak RSS of the streamed replay at 10⁶ and
   10⁷ rows, CSV and Parquet throughput, 200 000 rows against a plain filterpy script,
   the fleet beside simdkalman at 10⁵ and 10⁶ filters, and ``--engine dask``.
7. Live fleet capacity (benchmarks/scale.py): one estimator per train at 10 Hz, its
   CPU share and memory.

Benchmarks print figures; they assert nothing. Every child process runs in its own
ROS domain on localhost and is killed at the end whatever happens. The table is also
written to ``--output`` (default out/bench.md) for the README. ``--quick`` shortens
every measurement (a smoke test, not figures to quote).
"""

import argparse
import datetime
import json
import math
import os
import platform
import queue
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence, Tuple

ROWS = (1, 2, 3, 4, 5, 6, 7)
LIVE_RATES_HZ = (1000, 2000, 5000, 10000)
Q_DENSITY = 0.5        # white-noise acceleration of the benchmark model [m²/s³]
DT_S = 0.1
R_M2 = 1.0
TRAIN_SPEED_MPS = 10.0
STARTUP_RATE_HZ = 100.0
DIAGNOSTICS_PERIOD_S = 0.25
NS_PER_S = 1_000_000_000

Row = Tuple[str, str, str, str, str, str]
"""One table row: (row, measurement, case, result, ratio, target)."""


# -- the table ------------------------------------------------------------------------

def _header() -> List[str]:
    """Return the lines above the table: date, machine and versions."""
    import importlib.metadata
    import numpy

    def version(dist: str) -> str:
        try:
            return importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            return 'not installed'

    cpu = platform.processor() or 'unknown CPU'
    try:
        with open('/proc/cpuinfo') as cpuinfo:
            for line in cpuinfo:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    load = ' '.join(f'{v:.2f}' for v in os.getloadavg())
    now = datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')
    rmw = os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp (default)')
    return [
        f'kf_train benchmark, {now}',
        f'Machine: {cpu}, {os.cpu_count()} cores, Linux {platform.release()}; '
        f'load average at start {load}',
        f'Python {platform.python_version()}, numpy {numpy.__version__}, rclpy '
        f'{version("rclpy")}, filterpy {version("filterpy")}, RMW {rmw}',
    ]


def _table(rows: Sequence[Row]) -> List[str]:
    """Return a markdown table of the rows."""
    head = ('Row', 'Measurement', 'Case', 'Result', 'Ratio', 'Target')
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    lines += ['| ' + ' | '.join(cell.replace('|', '/') for cell in row) + ' |'
              for row in rows]
    return lines


def _us(seconds: float) -> str:
    """Format a duration given in seconds as µs."""
    return f'{seconds * 1e6:.3g} µs'


def _verdict(ok: bool) -> str:
    """Return 'met' or 'MISSED'."""
    return 'met' if ok else 'MISSED'


def _best_of(function: Callable[[], None], repeats: int) -> float:
    """Return the shortest of ``repeats`` timed calls [s]."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


# -- row 1: the 2-state update --------------------------------------------------------

def _train_data(n: int) -> List[float]:
    """Return n seeded position measurements of a train at 10 m/s, sampled every DT_S."""
    import numpy as np
    rng = np.random.default_rng(2024)
    t = DT_S * np.arange(1, n + 1)
    return (TRAIN_SPEED_MPS * t + rng.normal(0.0, math.sqrt(R_M2), n)).tolist()


def _floor(zs: List[float], dt: float, R: float, q00: float, q01: float,
           q11: float) -> Tuple[float, ...]:
    """
    Filter ``zs`` with the textbook closed form in local floats: the CPython floor.

    Predict and update of the 2-state constant-velocity model with H = [1, 0], no
    checks, no statistics, nothing stored: as cheap as CPython allows.
    """
    x0, x1, p00, p01, p11 = 0.0, 5.0, 1.0, 0.0, 1.0
    for z in zs:
        x0 = x0 + dt * x1
        p00 = p00 + dt * (2.0 * p01 + dt * p11) + q00
        p01 = p01 + dt * p11 + q01
        p11 = p11 + q11
        s = p00 + R
        k0 = p00 / s
        k1 = p01 / s
        y = z - x0
        x0 = x0 + k0 * y
        x1 = x1 + k1 * y
        p11 = p11 - k1 * p01
        p01 = p01 - k0 * p01
        p00 = p00 - k0 * p00
    return x0, x1, p00, p01, p11


def row_core(quick: bool) -> List[Row]:
    """Measure row 1: one predict+update of the 2-state train model, five ways."""
    import filterpy.kalman
    from kf_train.filters import kalman
    from kf_train.filters.fast import FastTrainFilter
    from kf_train.filters.models import constant_velocity_F, POSITION_H, WhiteNoiseAcceleration
    import numpy as np

    n_fast, n_slow = (4000, 500) if quick else (40000, 4000)
    repeats = 3 if quick else 7
    zs = _train_data(n_fast)
    slow = zs[:n_slow]
    noise = WhiteNoiseAcceleration(Q_DENSITY)
    F, Q, H, R = constant_velocity_F(DT_S), noise(DT_S), POSITION_H, np.array([[R_M2]])
    x0, P0 = np.array([0.0, 5.0]), np.eye(2)
    q00, q01, q11 = Q[0, 0], Q[0, 1], Q[1, 1]
    results = {}

    def floor():
        results['floor'] = _floor(zs, DT_S, R_M2, float(q00), float(q01), float(q11))

    def fast_step():
        fast = FastTrainFilter(x0, P0, noise)
        step, dt, r = fast.step, DT_S, R_M2  # locals, as the floor has them
        for z in zs:
            step(z, dt, r)
        results['fast'] = fast.state

    def generic_functions():
        x, P = x0, P0
        for z in slow:
            x, P = kalman.predict(x, P, F, Q)
            x, P, _ = kalman.update(x, P, z, H, R)
        results['functions'] = (x, P)

    def generic_class():
        kf = kalman.KalmanFilter(x0, P0)
        for z in slow:
            kf.predict(F, Q)
            kf.update(z, H, R)
        results['class'] = (kf.x, kf.P)

    def filterpy_kf():
        kf = filterpy.kalman.KalmanFilter(dim_x=2, dim_z=1)
        kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x0.copy(), P0.copy(), F, Q, H, R
        for z in slow:
            kf.predict()
            kf.update(z)
        results['filterpy'] = (kf.x.ravel(), kf.P)

    cases = [('floor', floor, n_fast), ('fast', fast_step, n_fast),
             ('functions', generic_functions, n_slow), ('class', generic_class, n_slow),
             ('filterpy', filterpy_kf, n_slow)]
    per_step = {}
    for _ in range(3):  # interleaved, three times: each case's best of 3·repeats
        for name, function, n in cases:
            per_step[name] = min(per_step.get(name, math.inf),
                                 _best_of(function, repeats) / n)

    # The same numbers? Check every path against the generic one on the slow prefix.
    fast = FastTrainFilter(x0, P0, noise)
    for z in slow:
        fast.step(z, DT_S, R_M2)
    x_ref, P_ref = results['functions']
    scale = max(1.0, float(np.max(np.abs(x_ref))))
    deviation = {
        'fast': max(np.max(np.abs(fast.x - x_ref)) / scale, np.max(np.abs(fast.P - P_ref))),
        'class': max(np.max(np.abs(results['class'][0] - x_ref)) / scale,
                     np.max(np.abs(results['class'][1] - P_ref))),
        'filterpy': max(np.max(np.abs(results['filterpy'][0] - x_ref)) / scale,
                        np.max(np.abs(results['filterpy'][1] - P_ref))),
    }
    floor_s, filterpy_s = per_step['floor'], per_step['filterpy']
    what = 'predict+update, 2-state'

    def ratio(name: str) -> str:
        return (f'{per_step[name] / floor_s:.2f}× floor; '
                f'{filterpy_s / per_step[name]:.1f}× faster than filterpy')

    fast_ok = per_step['fast'] <= 2.0 * floor_s and filterpy_s >= 20.0 * per_step['fast']
    rows = [
        ('1', what, 'reference closed form (the floor, in this file)',
         _us(floor_s), '1.00× floor', '-'),
        ('1', what, 'kf_train fast path: FastTrainFilter.step() per measurement',
         f'{_us(per_step["fast"])}; Δ vs generic {deviation["fast"]:.1e}', ratio('fast'),
         f'≤2× floor, ≥20× filterpy: {_verdict(fast_ok)}'),
        ('1', what, 'kf_train generic n-state path: kalman.predict + kalman.update',
         _us(per_step['functions']), ratio('functions'),
         f'no slower than filterpy: {_verdict(per_step["functions"] <= filterpy_s)}'),
        ('1', what, 'kf_train generic n-state path: KalmanFilter.predict/update',
         f'{_us(per_step["class"])}; Δ vs functions {deviation["class"]:.1e}',
         ratio('class'),
         f'no slower than filterpy: {_verdict(per_step["class"] <= filterpy_s)}'),
        ('1', what, f'filterpy {_dist_version("filterpy")} KalmanFilter.predict/update',
         f'{_us(filterpy_s)}; Δ vs kf_train {deviation["filterpy"]:.1e}',
         f'{filterpy_s / floor_s:.1f}× floor', '-'),
    ]
    return rows


def _dist_version(dist: str) -> str:
    """Return an installed distribution's version."""
    import importlib.metadata
    return importlib.metadata.version(dist)


# -- row 2: replay throughput ---------------------------------------------------------

def row_replay(quick: bool) -> List[Row]:
    """
    Measure row 2: kf_train.cli.replay in memory and CSV to CSV (1-D presets), and the bank.

    Every case prints Δ: the largest difference of its results from the plain
    row-by-row path (run_series; per id for the bank), relative to max(1, |value|).
    """
    from kf_train.cli import replay
    from kf_train.io import csvio
    from kf_train.presets.loader import available_presets, load_preset
    from kf_train.batch.series import run_bank, run_series
    import numpy as np

    n = 100_000 if quick else 1_000_000
    m = 2000                             # rows checked against the plain loop
    rng = np.random.default_rng(3)
    t = 0.1 * np.arange(1, n + 1)
    z = (TRAIN_SPEED_MPS * t + rng.normal(0.0, 1.0, n)).reshape(-1, 1)

    def deviation(result, reference, rows=slice(None)) -> float:
        return max(_delta(result.x[rows], reference.x), _delta(result.P[rows], reference.P))

    presets = [load_preset(name) for name in available_presets()]
    presets = [p for p in presets if p.dim_z == 1 and p.linear]
    controls = {p.name: rng.normal(0.0, 0.1, (n, p.dim_u)) for p in presets if p.dim_u}
    rows = []
    for preset in presets:
        u = controls.get(preset.name)
        seconds = _best_of(lambda: replay.run_preset(preset, t, z, u), 1 if quick else 3)
        fast = replay.run_preset(preset, t[:m], z[:m], None if u is None else u[:m])
        loop = run_series(preset, t[:m], z[:m], None if u is None else u[:m])
        rate = n / seconds
        rows.append(('2', 'replay, in memory', f'preset {preset.name}, {n:,} rows',
                     f'{rate:,.0f} rows/s; Δ vs loop path {deviation(fast, loop):.1e}', '-',
                     f'≥10⁶ rows/s: {_verdict(rate >= 1e6)}'))
    with tempfile.TemporaryDirectory() as directory:
        target = os.path.join(directory, 'out.csv')
        for preset in presets:
            u = controls.get(preset.name)
            source = os.path.join(directory, f'{preset.name}.csv')
            columns = [t, z[:, 0]] + ([] if u is None else [u[:, 0]])
            with open(source, 'wb') as stream:
                stream.write(('t,z_position' + (',u' if u is not None else '') + '\n').encode())
                stream.write(csvio.format_rows(columns))
            seconds = _fresh_best_of(lambda: replay.replay(preset, source, target), target,
                                     1 if quick else 2)
            header, _ = replay.output_columns(preset, replay.run_preset(
                preset, t[:1], z[:1], None if u is None else u[:1]))
            out = replay.read_table(target, [(h,) for h in header]).columns
            written = np.column_stack([out[name] for name in preset.state_names])
            in_memory = replay.run_preset(preset, t, z, u)
            exact = np.array_equal(written, in_memory.x)  # the text round trip
            loop = run_series(preset, t[:m], z[:m], None if u is None else u[:m])
            variances = np.column_stack([out['var_' + name] for name in preset.state_names])
            delta = max(_delta(written[:m], loop.x), _delta(
                variances[:m], np.diagonal(loop.P, axis1=1, axis2=2)))
            rate = n / seconds
            rows.append(('2', 'replay, CSV to CSV', f'preset {preset.name}, {n:,} rows, '
                         f'{len(header)} output columns',
                         f'{rate:,.0f} rows/s; Δ vs loop path {delta:.1e}; text round trip '
                         f'{"exact" if exact else "NOT EXACT"}', '-',
                         f'≥3·10⁵ rows/s: {_verdict(rate >= 3e5)}'))
        rows += _bank_rows(replay, csvio, load_preset('train'), directory, quick, run_bank,
                           run_series, deviation)
    return rows


def _fresh_best_of(function: Callable[[], None], output: str, repeats: int) -> float:
    """
    Return the shortest of ``repeats`` timed calls [s], ``output`` deleted before each.

    Replacing an existing 10⁸-byte output makes the file system free the old one
    (~0.3 s here), a cost of the disk rather than of the replay.
    """
    best = math.inf
    for _ in range(repeats):
        if os.path.exists(output):
            os.unlink(output)
        best = min(best, _best_of(function, 1))
    return best


def _delta(a, b) -> float:
    """Return max |a − b| / max(1, |b|)."""
    import numpy as np
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b) / np.maximum(1.0, np.abs(b)), initial=0.0))


def _bank_rows(replay, csvio, preset, directory: str, quick: bool, run_bank, run_series,
               deviation) -> List[Row]:
    """Measure the id column: objects with their own irregular clocks, rows interleaved."""
    import numpy as np
    ids_n, per_id = (300, 300) if quick else (1000, 1000)
    n = ids_n * per_id
    rng = np.random.default_rng(5)
    # Each object samples every 0.1 s ± 20 % from its own start; rows sorted by time.
    t = np.cumsum(0.1 * rng.uniform(0.8, 1.2, (ids_n, per_id)), axis=1)
    t += rng.uniform(0.0, 1.0, (ids_n, 1))
    ids = np.repeat(np.arange(ids_n), per_id)
    t = t.reshape(-1)
    order = np.argsort(t, kind='stable')
    t, ids = t[order], ids[order]
    z = (TRAIN_SPEED_MPS * t + rng.normal(0.0, 1.0, n)).reshape(-1, 1)
    seconds = _best_of(lambda: run_bank(preset, t, z, None, ids), 1 if quick else 2)
    bank = run_bank(preset, t, z, None, ids)
    delta = 0.0
    for k in range(0, ids_n, max(1, ids_n // 5)):        # five ids, alone, row by row
        rows = np.flatnonzero(ids == k)
        delta = max(delta, deviation(bank, run_series(preset, t[rows], z[rows]), rows))
    result = [('2', 'replay, id column, in memory',
               f'preset train, {ids_n:,} ids × {per_id:,} rows, own clocks, interleaved',
               f'{n / seconds:,.0f} rows/s; Δ vs each id alone {delta:.1e}', '-', '-')]
    source = os.path.join(directory, 'bank.csv')
    target = os.path.join(directory, 'bank_out.csv')
    with open(source, 'wb') as stream:
        stream.write(b'id,t,z_position\n')
        stream.write(csvio.format_rows([t, z[:, 0]], prefix=(csvio.format_labels(
            [f'train{k}' for k in range(ids_n)]), ids)))
    seconds = _fresh_best_of(lambda: replay.replay(preset, source, target), target, 1)
    table = replay.read_table(target, [('t',), ('position',), ('var_position',)], ids=True)
    exact = bool(np.array_equal(table.columns['position'], bank.x[:, 0]))
    result.append(('2', 'replay, id column, CSV to CSV', f'preset train, {ids_n:,} ids × '
                   f'{per_id:,} rows', f'{n / seconds:,.0f} rows/s; text round trip '
                   f'{"exact" if exact else "NOT EXACT"}; Δ as in memory', '-', '-'))
    return result


# -- row 3: the fleet -----------------------------------------------------------------

def row_fleet(quick: bool) -> List[Row]:
    """Measure row 3: N filters stepped at once, shared and per-filter dt and R."""
    from kf_train.filters.fast import FastTrainFilter
    from kf_train.batch.fleet import TrainFleet
    from kf_train.filters.models import WhiteNoiseAcceleration
    import numpy as np

    noise = WhiteNoiseAcceleration(Q_DENSITY)
    rows = []
    for variant in ('shared dt and R', 'per-filter z, dt and R'):
        previous = None
        for n in (1, 1000, 1_000_000):
            rng = np.random.default_rng(n)
            x0 = np.column_stack([rng.normal(0.0, 1.0, n), rng.normal(10.0, 1.0, n)])
            fleet = TrainFleet(x0, np.eye(2), noise, R=R_M2)
            zs = [rng.normal(0.0, 1.0, n) + k for k in range(4)]
            if variant == 'shared dt and R':
                dts, Rs = [DT_S] * 4, [R_M2] * 4
            else:
                dts = [DT_S * (1.0 + 0.1 * rng.random(n)) for _ in range(4)]
                Rs = [R_M2 * (1.0 + rng.random(n)) for _ in range(4)]
            repeats = max(3, min(2000 if not quick else 200, 2_000_000 // n))
            if quick:
                repeats = max(2, repeats // 10)
            calls = iter(range(10 ** 9))

            def one_step():
                k = next(calls) % 4
                fleet.step(zs[k], dts[k], Rs[k])
            one_step()  # the first step touches the second set of arrays: page faults
            per_step = _best_of(one_step, repeats)
            # Equality: the first, middle and last filters against FastTrainFilter.
            check = FastTrainFilter(x0[n - 1], np.eye(2), noise, R=R_M2)
            fleet = TrainFleet(x0, np.eye(2), noise, R=R_M2)
            for k in range(4):
                fleet.step(zs[k], dts[k], Rs[k])
                check.step(float(zs[k][n - 1]), _item(dts[k], n - 1), _item(Rs[k], n - 1))
            deviation = max(abs(a - b) for a, b in zip(fleet.filter_state(n - 1), check.state))
            ns = per_step / n * 1e9
            growth = '-' if previous is None else (
                f'{per_step / previous[1]:.3g}× the time for {n // previous[0]}× the filters')
            target = '-'
            if n == 1_000_000:
                target = f'≤25 ns per filter-step: {_verdict(ns <= 25.0)}'
            rows.append(('3', f'fleet step, {variant}', f'N = {n:,}',
                         f'{ns:.3g} ns per filter-step ({_us(per_step)} per step); '
                         f'Δ vs FastTrainFilter {deviation:.1e}', growth, target))
            previous = (n, per_step)
    return rows


def _item(value, i: int) -> float:
    """Return entry i of an array, or a scalar."""
    return float(value[i]) if hasattr(value, '__len__') else float(value)


# -- child processes ------------------------------------------------------------------

class Child:
    """A child process whose stdout lines are collected by a thread; stderr to a file."""

    def __init__(self, argv: List[str], env: Dict[str, str], name: str):
        """Start ``argv``."""
        self.name = name
        self.stderr = tempfile.TemporaryFile(mode='w+')
        self.start_ns = time.time_ns()
        self.process = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE,
                                        stderr=self.stderr, text=True)
        self.lines: 'queue.Queue[str]' = queue.Queue()
        self.all_lines: List[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        """Collect stdout lines."""
        for line in self.process.stdout:
            line = line.rstrip('\n')
            self.all_lines.append(line)
            self.lines.put(line)

    def wait_for(self, prefix: str, timeout_s: float) -> str:
        """Return the first new stdout line starting with ``prefix``; raise on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                raise TimeoutError(f'{self.name}: no {prefix!r} line within {timeout_s} s; '
                                   f'stderr: {self.stderr_text()[-400:]!r}')
            try:
                line = self.lines.get(timeout=min(remaining, 0.2))
            except queue.Empty:
                if self.process.poll() is not None and self.lines.empty():
                    raise RuntimeError(f'{self.name} exited with {self.process.returncode} '
                                       f'before {prefix!r}; stderr: '
                                       f'{self.stderr_text()[-400:]!r}') from None
                continue
            if line.startswith(prefix):
                return line

    def json_result(self, timeout_s: float) -> dict:
        """Wait for the process to end; return the last JSON line it printed."""
        self.process.wait(timeout=timeout_s)
        self._reader.join(timeout=2.0)
        for line in reversed(self.all_lines):
            if line.startswith('{'):
                return json.loads(line)
        raise RuntimeError(f'{self.name} printed no result; stderr: '
                           f'{self.stderr_text()[-400:]!r}')

    def stderr_text(self) -> str:
        """Return everything the process wrote to stderr so far."""
        self.stderr.flush()
        self.stderr.seek(0)
        return self.stderr.read()

    def cpu_s(self) -> float:
        """Return the process's user + system CPU time so far [s], from /proc."""
        with open(f'/proc/{self.process.pid}/stat') as stat:
            fields = stat.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')

    def peak_rss_mib(self) -> float:
        """Return the process's peak resident set size [MiB] (VmHWM)."""
        with open(f'/proc/{self.process.pid}/status') as status:
            for line in status:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1]) / 1024.0
        return math.nan

    def stop(self, signum: int, timeout_s: float = 10.0) -> Tuple[Optional[int], float]:
        """Send ``signum``; return (exit code or None if it had to be killed, seconds)."""
        start = time.monotonic()
        if self.process.poll() is None:
            self.process.send_signal(signum)
        try:
            code = self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            code = None
        return code, time.monotonic() - start

    def kill(self) -> None:
        """Kill the process if it still runs."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()


class Domains:
    """Hands out ROS domain ids for the children, one per trial."""

    def __init__(self):
        """Start from a base derived from the process id."""
        self._next = os.getpid() % 100

    def env(self) -> Dict[str, str]:
        """Return an environment confined to a fresh domain on localhost."""
        self._next = self._next % 100 + 1
        env = dict(os.environ)
        env.update(ROS_DOMAIN_ID=str(self._next), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                   PYTHONUNBUFFERED='1')
        env.pop('ROS_STATIC_PEERS', None)
        return env


def _node_command(node: str) -> List[str]:
    """Return the command that starts a kf_train node as a user would."""
    script = shutil.which(node, path=os.path.dirname(sys.executable))
    if script is not None:
        return [script]
    return [sys.executable, '-m', f'kf_train.ros.{node}_node']


def _helper(role: str, *args) -> List[str]:
    """Return the command of one of this module's helper processes."""
    return [sys.executable, os.path.abspath(__file__), role] + [str(a) for a in args]


def _percentile(sorted_values: Sequence[float], fraction: float) -> float:
    """Return the nearest-rank percentile of sorted values."""
    if not sorted_values:
        return math.nan
    index = min(len(sorted_values) - 1, max(0, math.ceil(fraction * len(sorted_values)) - 1))
    return sorted_values[index]


# -- row 4: the live estimator --------------------------------------------------------

# Subscription QoS of the estimator and the echo in row 4: best effort (the default)
# with a history deep enough for the publisher's bursts (it catches up after a late
# wake-up, up to tens of messages at once) and for the executor's pauses.
LIVE_QOS_DEPTH = 1000


def _live_trial(domains: Domains, target: str, executor: str, rate_hz: int,
                duration_s: float, signum: int, qos_depth: int = LIVE_QOS_DEPTH) -> dict:
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
            command = _node_command('estimator') + [
                '--executor', executor, '--ros-args', '-p',
                f'diagnostics_period_s:={DIAGNOSTICS_PERIOD_S}', '-p',
                f'qos_depth:={qos_depth}', '--log-level', 'error']
            probe = _helper('_probe', 'estimate', 'odometry', '--diagnostics')
        else:
            command = _helper('_echo', executor, qos_depth)
            probe = _helper('_probe', 'echo', 'measurement')
        node = Child(command, env, target)
        children.append(node)
        probe = Child(probe, env, 'probe')
        children.append(probe)
        probe.wait_for('ready', 30.0)
        publisher = Child(_helper('_publisher', rate_hz, count), env, 'publisher')
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
        trials = [('echo', 'events'), ('estimator', 'single_threaded'),
                  ('estimator', 'events')]
        echo_median = None
        for j, (target, executor) in enumerate(trials):
            signum = signals[(i + j) % 2]
            try:
                trial = _live_trial(domains, target, executor, rate, duration_s, signum,
                                    qos_depth)
            except (RuntimeError, TimeoutError, subprocess.TimeoutExpired) as error:
                reason = ' '.join(str(error).split())[:300]
                rows.append(('4', f'live, {rate:,} Hz', f'{target}, {executor} executor, '
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
                ratio, goal = '1.00× echo', f'clean exit: {_verdict(clean)}'
            else:
                ratio = '-' if echo_median is None else f'{median / echo_median:.2f}× echo'
                goal = f'clean exit: {_verdict(clean)}'
                if executor == 'events' and rate >= 5000:
                    lossless = delivered >= published and processed + rejected >= published
                    goal = f'lossless: {_verdict(lossless)}; ' + goal
                if executor == 'events' and echo_median is not None:
                    goal = (f'median ≤1.5× echo: {_verdict(median <= 1.5 * echo_median)}; '
                            + goal)
            rows.append(('4', f'live, {rate:,} Hz', f'{target}, {executor} executor, '
                         f'best effort depth {qos_depth:,}', result, ratio, goal))
    return rows


# -- row 5: start-up ------------------------------------------------------------------

BARE_ESTIMATOR = """
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
rclpy.init()
node = Node('estimator')
estimate = node.create_publisher(Odometry, 'estimate', 10)
node.create_publisher(Odometry, 'prediction', 10)
node.create_publisher(Vector3Stamped, 'innovation', 10)
node.create_publisher(DiagnosticArray, '/diagnostics', 10)
def on_measurement(msg):
    out = Odometry()
    out.header = msg.header
    estimate.publish(out)
node.create_subscription(PoseWithCovarianceStamped, 'measurement', on_measurement,
                         QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
executor = SingleThreadedExecutor()
executor.add_node(node)
try:
    executor.spin()
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""

BARE_SIMULATOR = """
import sys
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
rclpy.init()
node = Node('simulator')
measurement = node.create_publisher(PoseWithCovarianceStamped, 'measurement', 10)
truth = node.create_publisher(Odometry, 'ground_truth', 10)
def on_timer():
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = node.get_clock().now().to_msg()
    measurement.publish(msg)
    truth.publish(Odometry(header=msg.header))
node.create_timer(1.0 / float(sys.argv[1]), on_timer)
executor = SingleThreadedExecutor()
executor.add_node(node)
try:
    executor.spin()
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""


def _startup_trial(domains: Domains, which: str) -> Tuple[float, float]:
    """Return (seconds from process start to first output at the probe, peak RSS MiB)."""
    env = domains.env()
    children = []
    try:
        if which in ('estimator', 'bare estimator'):
            probe = Child(_helper('_probe', 'estimate', 'odometry'), env, 'probe')
            children.append(probe)
            # A sensor that is already streaming when the estimator starts.
            feeder = Child(_helper('_publisher', STARTUP_RATE_HZ, 0, -1.0), env, 'publisher')
            children.append(feeder)
            feeder.wait_for('up', 30.0)
        else:
            probe = Child(_helper('_probe', 'measurement', 'measurement'), env, 'probe')
            children.append(probe)
        probe.wait_for('up', 30.0)
        if which == 'estimator':
            command = _node_command('estimator')
        elif which == 'simulator':
            command = _node_command('simulator') + ['--ros-args', '-p',
                                                    f'rate_hz:={STARTUP_RATE_HZ}']
        elif which == 'bare estimator':
            command = [sys.executable, '-c', BARE_ESTIMATOR]
        else:
            command = [sys.executable, '-c', BARE_SIMULATOR, str(STARTUP_RATE_HZ)]
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
                          f'{_verdict(extra_s <= 0.15 and extra_mib <= 15.0)}')
            rows.append(('5', 'start-up', which if which != node else f'kf_train {node}',
                         result, ratio, target))
    return rows


# -- helper processes -----------------------------------------------------------------

def _publisher_main(argv: List[str]) -> int:
    """
    Publish ``count`` (0: until SIGINT) paced measurements of a train at ``rate_hz``.

    Publishing starts ``settle_s`` (default 0.5) after the first subscriber is seen,
    or at once for a negative ``settle_s``.
    """
    import random

    from kf_train.ros import messages
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    rate_hz, count = float(argv[0]), int(argv[1])
    settle_s = float(argv[2]) if len(argv) > 2 else 0.5  # < 0: do not wait for anyone
    rclpy.init()
    node = Node('bench_publisher')
    # Best effort, as a sensor driver publishes (rclpy's qos_profile_sensor_data): a
    # reliable writer stalls publish() for milliseconds at a time at these rates, and
    # the stream would come out in bursts.
    publisher = node.create_publisher(
        PoseWithCovarianceStamped, 'measurement',
        QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    print('up', flush=True)
    published = max_burst = 0
    start_ns = end_ns = time.time_ns()
    try:
        while settle_s >= 0.0 and publisher.get_subscription_count() < 1:
            time.sleep(0.005)
        time.sleep(max(settle_s, 0.0))  # let the subscriber's side of the match settle
        rng = random.Random(7)
        print('start', flush=True)
        period_ns = NS_PER_S / rate_hz
        start_ns = last_ns = time.time_ns()
        next_ns = float(start_ns)
        while count == 0 or published < count:
            now_ns = time.time_ns()
            burst = published
            while next_ns <= now_ns and (count == 0 or published < count):
                stamp_ns = max(time.time_ns(), last_ns + 1)
                position = TRAIN_SPEED_MPS * (stamp_ns - start_ns) / NS_PER_S + rng.gauss(
                    0.0, math.sqrt(R_M2))
                publisher.publish(messages.to_measurement_msg(stamp_ns, 'odom', position,
                                                              R_M2))
                last_ns = stamp_ns
                published += 1
                next_ns += period_ns
            max_burst = max(max_burst, published - burst)
            delay_s = (next_ns - time.time_ns()) / NS_PER_S
            if delay_s > 0.0:
                time.sleep(delay_s)
        end_ns = time.time_ns()
    except KeyboardInterrupt:
        end_ns = time.time_ns()
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    print(json.dumps({'published': published, 'start_ns': start_ns, 'end_ns': end_ns,
                      'max_burst': max_burst}), flush=True)
    return 0


def _probe_main(argv: List[str]) -> int:
    """Record the stamp and arrival time of every message on a topic until SIGINT."""
    from kf_train.ros import messages
    from kf_train.ros.runner import run
    from rclpy.node import Node
    from rclpy.qos import QoSProfile

    topic, kind = argv[0], argv[1]
    with_diagnostics = '--diagnostics' in argv
    if kind == 'odometry':
        from nav_msgs.msg import Odometry as message_type
    else:
        from geometry_msgs.msg import PoseWithCovarianceStamped as message_type
    stamps: List[int] = []
    arrivals: List[int] = []
    diagnostics: Dict[str, str] = {}

    def make_node() -> Node:
        node = Node('bench_probe')

        def on_message(data: bytes) -> None:
            arrivals.append(time.time_ns())
            stamps.append(messages.stamp_ns_from_serialized(data))
            if len(arrivals) == 1:
                print(f'first {arrivals[0]}', flush=True)

        # Raw (serialized) messages: the probe reads only the stamp, so that its own
        # cost on this shared CPU stays small.
        subscription = node.create_subscription(message_type, topic, on_message,
                                                QoSProfile(depth=1000), raw=True)
        if with_diagnostics:
            from diagnostic_msgs.msg import DiagnosticArray

            def on_diagnostics(msg) -> None:
                for status in msg.status:
                    if status.name.endswith(': filter'):
                        diagnostics.update((v.key, v.value) for v in status.values)
            node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics,
                                     QoSProfile(depth=10))
        announced = []

        def on_timer() -> None:
            if not announced and subscription.get_publisher_count() >= 1:
                announced.append(True)
                print('ready', flush=True)
        node.create_timer(0.02, on_timer)
        print('up', flush=True)
        return node

    code = run(make_node, ['bench_probe'], executor='events')
    latencies = sorted((a - s) / 1e6 for a, s in zip(arrivals, stamps))
    print(json.dumps({
        'count': len(latencies), 'latency_median_ms': _percentile(latencies, 0.5),
        'latency_p99_ms': _percentile(latencies, 0.99), 'diagnostics': diagnostics}),
        flush=True)
    return code


def _echo_main(argv: List[str]) -> int:
    """Republish every measurement on ``echo``: the transport's own cost."""
    from kf_train.ros.runner import run
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    received = [0]

    def make_node() -> Node:
        node = Node('bench_echo')
        publisher = node.create_publisher(PoseWithCovarianceStamped, 'echo', 10)

        def on_message(msg) -> None:
            received[0] += 1
            publisher.publish(msg)
        # The estimator's subscription QoS in row 4: best effort, depth as given.
        node.create_subscription(
            PoseWithCovarianceStamped, 'measurement', on_message,
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT))
        return node

    depth = int(argv[1]) if len(argv) > 1 else 10
    code = run(make_node, ['bench_echo'], executor=argv[0] if argv else 'events')
    print(json.dumps({'received': received[0]}), flush=True)
    return code


HELPERS = {'_publisher': _publisher_main, '_probe': _probe_main, '_echo': _echo_main}


# -- main -----------------------------------------------------------------------------

def _scale_module():
    """Return benchmarks/scale.py (rows 6 and 7), loaded beside this file."""
    import importlib.util
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'scale.py')
    spec = importlib.util.spec_from_file_location('kf_train_bench_scale', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
    """Run the benchmark (or one of its helper processes); return the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in HELPERS:
        return HELPERS[argv[0]](argv[1:])
    try:
        args = _parse(argv)
    except SystemExit as stop:  # --help, or a bad command line (argparse printed why)
        return int(stop.code or 0)
    header = _header()
    print('\n'.join(header), flush=True)
    started = time.monotonic()
    rows: List[Row] = []
    scale = _scale_module()
    measure = {1: lambda: row_core(args.quick), 2: lambda: row_replay(args.quick),
               3: lambda: row_fleet(args.quick),
               4: lambda: row_live(args.quick, args.rates, args.qos_depth),
               5: lambda: row_startup(args.quick),
               6: lambda: scale.rows_scale(args.quick),
               7: lambda: scale.rows_live_fleet(args.quick, sys.modules[__name__])}
    for row in args.rows:
        print(f'measuring row {row} ...', file=sys.stderr, flush=True)
        rows += measure[row]()
    header.append(f'Measured in {time.monotonic() - started:.0f} s'
                  + (' (--quick: not figures to quote)' if args.quick else '') + '.')
    text = '\n'.join(header[-1:] + [''] + _table(rows))
    print(text, flush=True)
    if args.output:
        directory = os.path.dirname(args.output)
        if directory:
            os.makedirs(directory, exist_ok=True)
        with open(args.output, 'w') as output:
            output.write('\n'.join(header[:-1] + [''] + [text]) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
