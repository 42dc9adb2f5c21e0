"""
Rows 1 to 3 of ``make bench``: the 2-state update, replay throughput, the bank.

Each row compares kf_train's paths side by side on identical data and prints, beside
every figure, Δ: its largest difference from the plain path it must equal.
"""

import math
import os
import tempfile
from typing import Callable, List, Tuple

from bench_common import best_of, DT_S, Q_DENSITY, R_M2, Row, TRAIN_SPEED_MPS, us, verdict


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
    from kf_train.filters import WhiteNoiseAcceleration

    n_fast, n_slow = (4000, 500) if quick else (40000, 4000)
    repeats = 3 if quick else 7
    zs = _train_data(n_fast)
    slow = zs[:n_slow]
    noise = WhiteNoiseAcceleration(Q_DENSITY)
    results = {}
    cases = _core_cases(zs, slow, noise, results)
    per_step = {}
    for _ in range(3):  # interleaved, three times: each case's best of 3·repeats
        for name, function, n in cases:
            per_step[name] = min(per_step.get(name, math.inf),
                                 best_of(function, repeats) / n)
    return _core_rows(per_step, _core_deviations(slow, noise, results))


def _core_cases(zs: List[float], slow: List[float], noise, results: dict) -> list:
    """Return the cases of row 1 as (name, function, steps); each stores its result."""
    import filterpy.kalman
    from kf_train.filters import (
        constant_velocity_F, FastTrainFilter, kalman, POSITION_H)
    import numpy as np

    F, Q, H, R = constant_velocity_F(DT_S), noise(DT_S), POSITION_H, np.array([[R_M2]])
    x0, P0 = np.array([0.0, 5.0]), np.eye(2)
    series = np.array(zs)
    q00, q01, q11 = Q[0, 0], Q[0, 1], Q[1, 1]

    def floor():
        results['floor'] = _floor(zs, DT_S, R_M2, float(q00), float(q01), float(q11))

    def fast_step():
        fast = FastTrainFilter(x0, P0, noise)
        step, dt, r = fast.step, DT_S, R_M2  # locals, as the floor has them
        for z in zs:
            step(z, dt, r)
        results['fast'] = fast.state

    def fast_run():
        results['run'] = FastTrainFilter(x0, P0, noise).run(series, DT_S, R_M2)

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

    n_fast, n_slow = len(zs), len(slow)
    return [('floor', floor, n_fast), ('fast', fast_step, n_fast), ('run', fast_run, n_fast),
            ('functions', generic_functions, n_slow), ('class', generic_class, n_slow),
            ('filterpy', filterpy_kf, n_slow)]


def _core_deviations(slow: List[float], noise, results: dict) -> dict:
    """Return each path's largest difference from the generic one on the slow prefix."""
    from kf_train.filters import FastTrainFilter
    import numpy as np

    fast = FastTrainFilter(np.array([0.0, 5.0]), np.eye(2), noise)
    for z in slow:
        fast.step(z, DT_S, R_M2)
    x_ref, P_ref = results['functions']
    scale = max(1.0, float(np.max(np.abs(x_ref))))
    return {
        'fast': max(np.max(np.abs(fast.x - x_ref)) / scale, np.max(np.abs(fast.P - P_ref))),
        'class': max(np.max(np.abs(results['class'][0] - x_ref)) / scale,
                     np.max(np.abs(results['class'][1] - P_ref))),
        'filterpy': max(np.max(np.abs(results['filterpy'][0] - x_ref)) / scale,
                        np.max(np.abs(results['filterpy'][1] - P_ref))),
    }


def _core_rows(per_step: dict, deviation: dict) -> List[Row]:
    """Return row 1's table rows from the per-step times and the deviations."""
    floor_s, filterpy_s = per_step['floor'], per_step['filterpy']
    what = 'predict+update, 2-state'

    def ratio(name: str) -> str:
        return (f'{per_step[name] / floor_s:.2f}× floor; '
                f'{filterpy_s / per_step[name]:.1f}× faster than filterpy')

    fast_ok = per_step['fast'] <= 2.0 * floor_s and filterpy_s >= 20.0 * per_step['fast']
    return [
        ('1', what, 'reference closed form (the floor, in this file)',
         us(floor_s), '1.00× floor', '-'),
        ('1', what, 'kf_train fast path: FastTrainFilter.step() per measurement',
         f'{us(per_step["fast"])}; Δ vs generic {deviation["fast"]:.1e}', ratio('fast'),
         f'≤2× floor, ≥20× filterpy: {verdict(fast_ok)}'),
        ('1', what, 'kf_train fast path: FastTrainFilter.run() per row (whole series)',
         us(per_step['run']), ratio('run'), '-'),
        ('1', what, 'kf_train generic n-state path: kalman.predict + kalman.update',
         us(per_step['functions']), ratio('functions'),
         f'no slower than filterpy: {verdict(per_step["functions"] <= filterpy_s)}'),
        ('1', what, 'kf_train generic n-state path: KalmanFilter.predict/update',
         f'{us(per_step["class"])}; Δ vs functions {deviation["class"]:.1e}',
         ratio('class'),
         f'no slower than filterpy: {verdict(per_step["class"] <= filterpy_s)}'),
        ('1', what, f'filterpy {_dist_version("filterpy")} KalmanFilter.predict/update',
         f'{us(filterpy_s)}; Δ vs kf_train {deviation["filterpy"]:.1e}',
         f'{filterpy_s / floor_s:.1f}× floor', '-'),
    ]


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
    from kf_train.batch import run_bank, run_series
    from kf_train.batch.stream import filter_table
    from kf_train.replay import memory as replay
    from kf_train.io import csvio, read_table
    from kf_train.presets import available_presets, load_preset
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
        seconds = best_of(lambda: replay.run_preset(preset, t, z, u), 1 if quick else 3)
        fast = replay.run_preset(preset, t[:m], z[:m], None if u is None else u[:m])
        loop = run_series(preset, t[:m], z[:m], None if u is None else u[:m])
        rate = n / seconds
        rows.append(('2', 'replay, in memory', f'preset {preset.name}, {n:,} rows',
                     f'{rate:,.0f} rows/s; Δ vs loop path {deviation(fast, loop):.1e}', '-',
                     f'≥10⁶ rows/s: {verdict(rate >= 1e6)}'))
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
            out = read_table(target, [(h,) for h in header]).columns
            written = np.column_stack([out[name] for name in preset.state_names])
            # The text round trip: the numbers read back are those the replay computed
            # (in its blocks, as every engine does: kf_train.batch.stream.filter_table).
            computed = dict(zip(header, filter_table(preset, t, z[:, :1], u)))
            exact = all(np.array_equal(out[name], computed[name]) for name in header)
            loop = run_series(preset, t[:m], z[:m], None if u is None else u[:m])
            variances = np.column_stack([out['var_' + name] for name in preset.state_names])
            delta = max(_delta(written[:m], loop.x), _delta(
                variances[:m], np.diagonal(loop.P, axis1=1, axis2=2)))
            rate = n / seconds
            rows.append(('2', 'replay, CSV to CSV', f'preset {preset.name}, {n:,} rows, '
                         f'{len(header)} output columns',
                         f'{rate:,.0f} rows/s; Δ vs loop path {delta:.1e}; text round trip '
                         f'{"exact" if exact else "NOT EXACT"}', '-',
                         f'≥3·10⁵ rows/s: {verdict(rate >= 3e5)}'))
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
        best = min(best, best_of(function, 1))
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
    seconds = best_of(lambda: run_bank(preset, t, z, None, ids), 1 if quick else 2)
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
    from kf_train.io import read_table
    table = read_table(target, [('t',), ('position',), ('var_position',)], ids=True)
    exact = bool(np.array_equal(table.columns['position'], bank.x[:, 0]))
    result.append(('2', 'replay, id column, CSV to CSV', f'preset train, {ids_n:,} ids × '
                   f'{per_id:,} rows', f'{n / seconds:,.0f} rows/s; text round trip '
                   f'{"exact" if exact else "NOT EXACT"}; Δ as in memory', '-', '-'))
    return result


# -- row 3: the bank -------------------------------------------------------------------

def bench_preset():
    """Return the benchmark's train as a preset: white-noise acceleration Q_DENSITY, R_M2."""
    from kf_train.presets import preset_from_mapping
    return preset_from_mapping({
        'name': 'bench-train', 'states': ['position', 'velocity'],
        'measurements': ['position'], 'motion': 'constant_velocity',
        'process_noise': {'continuous': [[0.0, 0.0], [0.0, Q_DENSITY]]}, 'R': [[R_M2]],
        'initial_state': [0.0, TRAIN_SPEED_MPS], 'initial_covariance': [1.0, 1.0],
        'nominal_period_s': DT_S})


def row_bank(quick: bool) -> List[Row]:
    """Measure row 3: N objects at once in the bank (kf_train.batch.bank), 4 rows each."""
    from kf_train.batch import run_bank, run_series
    import numpy as np

    preset = bench_preset()
    rows = []
    for variant in ('shared dt', 'per-object dt'):
        previous = None
        for n in (1, 1000, 100_000 if quick else 1_000_000):
            rng = np.random.default_rng(n)
            if variant == 'shared dt':
                t = np.repeat(DT_S * np.arange(1, 5), n)
                ids = np.tile(np.arange(n), 4)
            else:  # each object on its own clock; rows in time order
                t = np.cumsum(DT_S * (1.0 + 0.1 * rng.random((n, 4))), axis=1).reshape(-1)
                ids = np.repeat(np.arange(n), 4)
                order = np.argsort(t, kind='stable')
                t, ids = t[order], ids[order]
            z = (TRAIN_SPEED_MPS * t + rng.normal(0.0, 1.0, t.shape[0])).reshape(-1, 1)
            seconds = best_of(lambda: run_bank(preset, t, z, None, ids),
                              1 if quick or n >= 100_000 else 3)
            # Equality: the last object against its own series, row by row.
            mine = np.flatnonzero(ids == n - 1)
            result = run_bank(preset, t, z, None, ids)
            alone = run_series(preset, t[mine], z[mine])
            deviation = max(_delta(result.x[mine], alone.x), _delta(result.P[mine], alone.P))
            ns = seconds / (4 * n) * 1e9
            growth = '-' if previous is None else (
                f'{seconds / previous[1]:.3g}× the time for {n // previous[0]}× the objects')
            rows.append(('3', f'bank, {variant}', f'N = {n:,} objects × 4 rows',
                         f'{ns:,.0f} ns per object-row ({seconds * 1e3:,.1f} ms per call); '
                         f'Δ vs the object alone {deviation:.1e}', growth, '-'))
            previous = (n, seconds)
    return rows
