"""
``make bench`` rows 7 and 8: offline replay at scale, and how many trains one machine tracks.

Row 7 (offline, every figure from a child process, start-up included unless said):

* peak RSS of ``kf-train replay`` streaming 10⁶ and 10⁷ rows (polars and built-in
  codecs) against the in-memory engine, and its bytes per row;
* CSV to CSV and Parquet to Parquet throughput on the train preset (10 output columns);
* 200 000 rows: ``kf-train replay`` against ``benchmarks/filterpy_replay.py``;
* simdkalman beside the bank (kf_train.batch.run_bank, objects in lock-step) on the
  same 2-state problem, 10⁵ and 10⁶ filters, ns per filter-step;
* ``--engine dask`` on a LocalCluster of 2 workers: rows/s, and equality with the
  single-process replay.

Row 8 (live): one estimator per train (namespaces) is the design; a paced publisher
feeds one estimator at 10 Hz and the row reports its CPU share and memory (RSS, and
PSS, which counts shared libraries once), hence estimators per core and per GiB.

Wall-clock figures on a shared machine move with its load: each row also gives the
child's CPU time (user + system), which moves less.
"""

import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from typing import List, Tuple

from bench_common import best_of, DT_S, Q_DENSITY, R_M2, Row

# Runs a command and prints its wall time, CPU time and peak RSS (its own rusage).
_MEASURE = r"""
import json, resource, subprocess, sys, time
start = time.perf_counter()
done = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
wall = time.perf_counter() - start
use = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({'wall': wall, 'cpu': use.ru_utime + use.ru_stime,
                  'rss_mib': use.ru_maxrss / 1024.0, 'code': done.returncode,
                  'stderr': done.stderr.decode(errors='replace')[-400:]}))
"""


def _measured(command: List[str]) -> dict:
    """Run ``command`` in a child; return wall [s], cpu [s], peak RSS [MiB], exit code."""
    done = subprocess.run([sys.executable, '-c', _MEASURE] + command, capture_output=True,
                          text=True, timeout=3600)
    result = json.loads(done.stdout)
    if result['code'] != 0:
        raise RuntimeError(f'{command[:3]} failed: {result["stderr"]}')
    return result


def _kf_train() -> List[str]:
    """Return the kf-train command of this environment."""
    script = os.path.join(os.path.dirname(sys.executable), 'kf-train')
    return [script] if os.path.exists(script) else [sys.executable, '-m', 'kf_train.cli']


def _digest(path: str) -> str:
    """Return the SHA-256 of a file (or of a directory's files, by name)."""
    digest = hashlib.sha256()
    paths = [path] if os.path.isfile(path) else [os.path.join(path, name) for name in
                                                 sorted(os.listdir(path))]
    for name in paths:
        with open(name, 'rb') as stream:
            for block in iter(lambda: stream.read(1 << 20), b''):
                digest.update(block)
    return digest.hexdigest()


def _train_log(directory: str, rows: int) -> Tuple[str, str]:
    """Write a train log of ``rows`` (t every 0.1 s, noisy positions) as CSV and Parquet."""
    import numpy as np
    import polars as pl
    rng = np.random.default_rng(rows)
    t = np.round(np.arange(1, rows + 1) * 0.1, 1)
    frame = pl.DataFrame({'t': t, 'z_position': 10.0 * t + rng.normal(0.0, 1.0, rows)})
    csv = os.path.join(directory, f'train-{rows}.csv')
    parquet = os.path.join(directory, f'train-{rows}.parquet')
    frame.write_csv(csv)                 # polars writes these numbers as repr() does
    frame.write_parquet(parquet, row_group_size=65536)
    return csv, parquet


def _byte_compile() -> str:
    """
    Write kf_train's byte code (``__pycache__``) as ``pip install`` does; return a note.

    A regular install byte-compiles the package, and numpy, polars and filterpy come
    compiled from their wheels; an editable checkout run with PYTHONDONTWRITEBYTECODE
    (as this machine's sessions are) would instead compile ≈60 kf_train modules from
    source at every start (≈0.1-0.2 s), a cost no user's install has.
    """
    import compileall
    import kf_train
    package = os.path.dirname(os.path.abspath(kf_train.__file__))
    done = compileall.compile_dir(package, quiet=1, workers=1)
    return 'byte code written' if done else 'byte code NOT written'


def _load() -> str:
    """Return the 1-minute load average, for the rows whose wall time it moves."""
    return f'load {os.getloadavg()[0]:.1f}'


def _rate(rows: int, seconds: float) -> str:
    """Format a throughput."""
    return f'{rows / seconds:,.0f} rows/s'


def _memory_rows(directory: str, quick: bool) -> List[Row]:
    """Peak RSS of the streamed replay at two sizes, and of the in-memory one."""
    sizes = (10 ** 4, 10 ** 5) if quick else (10 ** 6, 10 ** 7)
    rows, digests = [], {}
    for size in sizes:
        csv, _ = _train_log(directory, size)
        for codec in ('auto', 'builtin'):
            if codec == 'builtin' and size == sizes[-1] and quick is False and size > 10 ** 6:
                pass
            out = os.path.join(directory, f'out-{codec}-{size}.csv')
            run = _measured(_kf_train() + ['replay', '--preset', 'train', csv, '-o', out,
                                           '--codec', codec])
            digests[codec, size] = _digest(out)
            os.unlink(out)
            name = 'polars' if codec == 'auto' else 'built-in'
            same = ''
            if codec == 'builtin':
                same = '; same bytes as polars' if digests['auto', size] == digests[
                    codec, size] else '; BYTES DIFFER from polars'
            rows.append(('7', 'replay memory, train preset', f'stream, {name} CSV, {size:,} '
                         'rows', f'peak RSS {run["rss_mib"]:.0f} MiB{same}',
                         f'{run["rss_mib"] * 2 ** 20 / size:.0f} B/row',
                         f'<250 MiB: {"met" if run["rss_mib"] < 250 else "MISSED"}'))
    csv = os.path.join(directory, f'train-{sizes[0]}.csv')
    out = os.path.join(directory, 'memory.csv')
    run = _measured(_kf_train() + ['replay', '--preset', 'train', csv, '-o', out, '--engine',
                                   'memory'])
    # More rows than one block (65 536): the in-memory engine must still write the
    # stream's bytes (both filter in the same blocks).
    same = _digest(out) == digests['auto', sizes[0]]
    os.unlink(out)
    per_row = run['rss_mib'] * 2 ** 20 / sizes[0]
    rows.append(('7', 'replay memory, train preset', f'in memory (--engine memory), '
                 f'{sizes[0]:,} rows', f'peak RSS {run["rss_mib"]:.0f} MiB; '
                 f'{"same bytes as the stream" if same else "BYTES DIFFER from the stream"}',
                 f'{per_row:.0f} B/row',
                 f'stream = memory byte for byte: {"met" if same else "MISSED"}'))
    return rows


def _throughput_rows(directory: str, quick: bool) -> List[Row]:
    """
    CSV to CSV and Parquet to Parquet, train preset, 10 output columns, at two sizes.

    The target is wall-clock rows/s with the process start-up (≈0.5 s of imports)
    included; the larger size shows the rate once start-up is amortised. The ratio is
    rows/s over the target (≥1.00× is met); the CPU-time rate says what the code does
    on a machine whose load steals wall time.
    """
    rows = []
    for size in ((10 ** 5,) if quick else (10 ** 6, 10 ** 7)):
        csv, parquet = _train_log(directory, size)
        for label, source, target, extra, goal in (
                ('CSV to CSV, polars', csv, 'o.csv', [], 1e6),
                ('CSV to CSV, built-in (no extra)', csv, 'o.csv', ['--codec', 'builtin'],
                 None),
                ('Parquet to Parquet', parquet, 'o.parquet', [], 5e6)):
            if goal is None and size > 10 ** 6:
                continue
            out = os.path.join(directory, target)
            run = _measured(_kf_train() + ['replay', '--preset', 'train', source, '-o', out]
                            + extra)
            os.unlink(out)
            rate, cpu_rate = size / run['wall'], size / run['cpu']
            target_text = '-' if goal is None else (
                f'≥{goal:,.0f} rows/s: {rate / goal:.2f}× '
                f'{"met" if rate >= goal else "MISSED"} (CPU-time rate '
                f'{cpu_rate / goal:.2f}×)')
            rows.append(('7', 'replay throughput, train preset, 10 output columns',
                         f'{label}, {size:,} rows, process start-up included',
                         f'{_rate(size, run["wall"])} wall; {_rate(size, run["cpu"])} of CPU '
                         f'time; {_load()}', f'{run["cpu"] / run["wall"]:.2f} CPUs busy',
                         target_text))
        os.unlink(csv)
        os.unlink(parquet)
    return rows


def _filterpy_rows(directory: str, quick: bool) -> List[Row]:
    """200 000 rows: kf-train replay against the plain filterpy script, processes."""
    size = 20_000 if quick else 200_000
    csv, _ = _train_log(directory, size)
    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'filterpy_replay.py')
    ours = _measured(_kf_train() + ['replay', '--preset', 'train', csv, '-o',
                                    os.path.join(directory, 'k.csv')])
    theirs = _measured([sys.executable, script, csv, os.path.join(directory, 'f.csv')])
    import numpy as np
    a = np.loadtxt(os.path.join(directory, 'k.csv'), delimiter=',', skiprows=1)
    b = np.loadtxt(os.path.join(directory, 'f.csv'), delimiter=',', skiprows=1)
    delta = float(np.max(np.abs(a - b) / np.maximum(1.0, np.abs(b))))
    ratio = theirs['wall'] / ours['wall']
    return [('7', f'replay vs filterpy script, {size:,} rows', 'kf-train replay --preset '
             'train (process)', f'{ours["wall"]:.2f} s wall, {ours["cpu"]:.2f} s CPU; Δ vs '
             f'filterpy {delta:.1e}; {_load()}', f'{ratio:.1f}× faster (CPU: '
             f'{theirs["cpu"] / ours["cpu"]:.1f}×)',
             f'≥10×: {ratio / 10:.2f}× {"met" if ratio >= 10 else "MISSED"}'),
            ('7', f'replay vs filterpy script, {size:,} rows', 'filterpy_replay.py (loadtxt, '
             'predict/update loop, savetxt)', f'{theirs["wall"]:.2f} s wall, '
             f'{theirs["cpu"]:.2f} s CPU', '1.0×', '-')]


def _simdkalman_rows(quick: bool) -> List[Row]:
    """Measure the bank beside simdkalman on one 2-state problem: ns per filter-step."""
    import numpy as np
    import simdkalman
    from bench_core import bench_preset
    from kf_train.batch import run_bank
    preset = bench_preset()
    dt, q, r, steps = DT_S, Q_DENSITY, R_M2, 4
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
    rows = []
    for n in ((10 ** 3, 10 ** 4) if quick else (10 ** 5, 10 ** 6)):
        rng = np.random.default_rng(n)
        # Every filter from the preset's x0 (the bank takes one initial estimate).
        x0 = np.tile(preset.initial_state, (n, 1))
        z = x0[:, :1] + 10.0 * dt * np.arange(1, steps + 1) + rng.normal(0.0, 1.0, (n, steps))
        kf = simdkalman.KalmanFilter(state_transition=F, process_noise=Q,
                                     observation_model=np.array([[1.0, 0.0]]),
                                     observation_noise=r)

        # simdkalman's first step updates the prior at step 0 (no predict): give it the
        # prior predicted one step, so both run predict-then-update from x0, P0 = I.
        def simd():
            return kf.compute(z, 0, initial_value=(x0 @ F.T)[:, :, None],
                              initial_covariance=F @ F.T + Q, filtered=True, smoothed=False,
                              covariances=True, observations=False)

        # The bank's rows: step-major, object k's rows at dt, 2 dt, ... (ids 0..n-1).
        t = np.repeat(dt * np.arange(1, steps + 1), n)
        ids = np.tile(np.arange(n), steps)
        # Best of two each: the first call of a process also pays the kernel for its
        # fresh output pages (here ~200 ns per 112 bytes written, ~25 ns on reused pages).
        theirs = best_of(simd, 2) / (n * steps)
        ours = best_of(lambda: run_bank(preset, t, z.T.reshape(-1, 1), None, ids), 2) / (
            n * steps)
        result, bank = simd(), run_bank(preset, t, z.T.reshape(-1, 1), None, ids)
        delta = float(np.max(np.abs(result.filtered.states.mean[:, -1, :] - bank.x[-n:])))
        ratio = theirs / ours
        rows.append(('7', 'bank vs simdkalman, 2-state, predict+update', f'N = {n:,} filters, '
                     f'{steps} steps', f'run_bank {ours * 1e9:.3g} ns, simdkalman '
                     f'{theirs * 1e9:.3g} ns per filter-step; Δ {delta:.1e}; {_load()}',
                     f'{ratio:.2g}× simdkalman', f'≥20×: {"met" if ratio >= 20 else "MISSED"}'))
    return rows


def _dask_rows(directory: str, quick: bool) -> List[Row]:
    """kf-train replay --engine dask, LocalCluster of 2 workers, against one process."""
    import numpy as np
    import polars as pl
    trains, per = (20, 500) if quick else (200, 5000)
    rng = np.random.default_rng(7)
    t = np.concatenate([rng.uniform(0, 1) + np.arange(1, per + 1) * 0.1 for _ in range(trains)])
    ids = np.repeat([f'T{k:04d}' for k in range(trains)], per)
    order = np.argsort(t, kind='stable')
    frame = pl.DataFrame({'id': ids[order], 't': t[order]}).with_columns(
        z_position=pl.col('t') * 10.0 + rng.normal(0.0, 1.0, t.size))
    source = os.path.join(directory, 'fleet')
    os.makedirs(source, exist_ok=True)
    for k in range(4):
        part = frame[k * t.size // 4:(k + 1) * t.size // 4]
        part.write_parquet(os.path.join(source, f'part-{k}.parquet'))
    single_out = os.path.join(directory, 'single.parquet')
    single = _measured(_kf_train() + ['replay', '--preset', 'train', source, '-o', single_out,
                                      '--block-rows', str(t.size)])
    dask_out = os.path.join(directory, 'dask-out')
    run = _measured(_kf_train() + ['replay', '--preset', 'train', source, '-o', dask_out,
                                   '--engine', 'dask', '--workers', '2'])
    got = pl.read_parquet(os.path.join(dask_out, '*.parquet')).sort(['id', 't'])
    expected = pl.read_parquet(single_out).sort(['id', 't'])
    same = 'equal to one process' if got.equals(expected) else 'DIFFERS from one process'
    return [('7', f'--engine dask, {trains} trains × {per:,} rows (Parquet dataset)',
             'LocalCluster, 2 worker processes', f'{_rate(t.size, run["wall"])} wall incl. '
             f'cluster start; {same}', f'one process: {_rate(t.size, single["wall"])}', '-')]


# Row 7's parts, by name (KF_TRAIN_BENCH_SCALE=throughput,filterpy runs only those).
_PARTS = ('memory', 'throughput', 'filterpy', 'dask', 'simdkalman')


def _parts() -> Tuple[str, ...]:
    """Return the parts of row 7 to measure (all unless KF_TRAIN_BENCH_SCALE names some)."""
    chosen = os.environ.get('KF_TRAIN_BENCH_SCALE', '')
    names = tuple(p.strip() for p in chosen.split(',') if p.strip())
    return tuple(p for p in _PARTS if p in names) if names else _PARTS


def rows_scale(quick: bool) -> List[Row]:
    """Measure row 7."""
    rows: List[Row] = []
    chosen = _parts()
    rows.append(('7', 'kf_train start-up', 'the package as installed', _byte_compile(),
                 '-', '-'))
    with tempfile.TemporaryDirectory(prefix='kf-train-bench-') as directory:
        for part in (_memory_rows, _throughput_rows, _filterpy_rows, _dask_rows):
            if part.__name__.split('_')[1] not in chosen:
                continue
            try:
                rows += part(directory, quick)
            except (RuntimeError, ImportError, subprocess.TimeoutExpired) as error:
                rows.append(('7', part.__name__.strip('_').replace('_', ' '), '-',
                             f'failed: {" ".join(str(error).split())[:300]}', '-', '-'))
    try:
        rows += _simdkalman_rows(quick) if 'simdkalman' in chosen else []
    except ImportError as error:
        rows.append(('7', 'bank vs simdkalman', '-', f'failed: {error}', '-', '-'))
    return rows


def _pss_mib(pid: int) -> float:
    """Return a process's proportional set size [MiB] (shared pages split among users)."""
    try:
        with open(f'/proc/{pid}/smaps_rollup') as rollup:
            for line in rollup:
                if line.startswith('Pss:'):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float('nan')


def rows_live_fleet(quick: bool) -> List[Row]:
    """Measure row 8: one estimator fed at 10 Hz, its CPU share and memory."""
    from bench_children import Child, Domains, helper, node_command
    domains = Domains()
    env = domains.env()
    duration_s = 3.0 if quick else 20.0
    children = []
    try:
        node = Child(node_command('estimator') + [
            '--executor', 'events', '--ros-args', '--log-level', 'error'], env, 'estimator')
        children.append(node)
        probe = Child(helper('probe', 'estimate', 'odometry'), env, 'probe')
        children.append(probe)
        probe.wait_for('ready', 30.0)
        publisher = Child(helper('publisher', 10, int(10 * duration_s)), env, 'publisher')
        children.append(publisher)
        publisher.wait_for('start', 30.0)
        time.sleep(1.0)                  # past start-up: steady state only
        cpu0, wall0 = node.cpu_s(), time.monotonic()
        publisher.json_result(duration_s * 3 + 30.0)
        cpu = (node.cpu_s() - cpu0) / (time.monotonic() - wall0)
        rss, pss = node.peak_rss_mib(), _pss_mib(node.process.pid)
        probe.stop(2)
        seen = probe.json_result(10.0)
    except (RuntimeError, TimeoutError, subprocess.TimeoutExpired) as error:
        return [('8', 'live fleet, one estimator per train', '-',
                 f'failed: {" ".join(str(error).split())[:300]}', '-', '-')]
    finally:
        for child in children:
            child.kill()
    per_core = 1.0 / max(cpu, 1e-6)
    return [('8', 'live fleet: one estimator per train (namespaces), 10 Hz each',
             f'one estimator, events executor, {duration_s:.0f} s',
             f'CPU {100 * cpu:.2f}% of a core; peak RSS {rss:.0f} MiB, PSS {pss:.0f} MiB; '
             f'{seen["count"]} estimates at the probe',
             f'≈{per_core:,.0f} estimators per core by CPU; ≈{1024 / pss:.0f} per GiB by PSS',
             '-')]
