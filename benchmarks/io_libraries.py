"""
pyarrow against polars on our tables: the measurement behind kf_train[fast]'s choice.

    python benchmarks/io_libraries.py [ROWS]      # default 1,000,000

For a replay output (t and 8 estimate columns of the train preset, 9 float64 columns)
and a replay input (t, z_position), it times each library's CSV and Parquet read and
write (best of 3, one process, wall clock), and checks what the replay needs besides
speed: that the CSV text of every double is repr()'s (or by how many values it
differs) and that reading repr() text back gives the same doubles. Needs both
libraries installed; prints a markdown table (docs/scale.md quotes one run).
"""

import io
import os
import sys
import tempfile
import time

import numpy as np


def _best(function, repeats: int = 3) -> float:
    """Return the shortest of ``repeats`` timed calls [s]."""
    best = float('inf')
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def _tables(rows: int):
    """Return (input columns, output columns) shaped like a train replay's."""
    from kf_train.batch.stream import filter_table
    from kf_train.presets.loader import load_preset
    rng = np.random.default_rng(0)
    t = np.round(np.arange(1, rows + 1) * 0.1, 1)
    z = 10.0 * t + rng.normal(0.0, 1.0, rows)
    preset = load_preset('train')
    out = filter_table(preset, t, z)
    names = ['t', 'position', 'velocity', 'var_position', 'var_velocity',
             'predicted_position', 'predicted_velocity', 'var_predicted_position',
             'var_predicted_velocity']
    return {'t': t, 'z_position': z}, dict(zip(names, out))


def _text_checks(write_csv, read_csv, values: np.ndarray):
    """Return (values whose text differs from repr, whether repr text reads back exactly)."""
    text = write_csv(values).decode().split('\n')[1:-1]
    expected = [repr(v) for v in values.tolist()]
    differ = sum(a != b for a, b in zip(text, expected))
    body = ('v\n' + '\n'.join(expected) + '\n').encode()
    back = read_csv(body)
    return differ, bool(np.array_equal(back.view(np.uint64), values.view(np.uint64)))


def main(argv) -> int:
    """Measure and print the table."""
    import polars as pl
    import pyarrow as pa
    import pyarrow.csv as pa_csv
    import pyarrow.parquet as pq
    rows = int(argv[0]) if argv else 1_000_000
    inputs, outputs = _tables(rows)
    rng = np.random.default_rng(1)
    random_bits = rng.integers(0, 2 ** 64, 200_000, dtype=np.uint64).view(np.float64)
    estimates = np.concatenate(list(outputs.values()))[:200_000]
    special = np.array([0.0, -0.0, 5e-324, 1e308, 1e-5, 1e-7])
    probe = np.concatenate([random_bits, estimates, special])
    probe = probe[np.isfinite(probe)]
    lines = ['| library | CSV read, 2 columns | CSV write, 9 columns | Parquet read, 9 '
             'columns | Parquet write, 9 columns | CSV text ≠ repr (of %d) | repr text '
             'reads back exactly |' % probe.size, '|---|---|---|---|---|---|---|']
    with tempfile.TemporaryDirectory() as directory:
        path = os.path.join(directory, '{}')
        pl.DataFrame(inputs).write_csv(path.format('in.csv'))
        arrow_out, polars_out = pa.table(outputs), pl.DataFrame(outputs)

        def arrow_csv(values):
            sink = io.BytesIO()
            pa_csv.write_csv(pa.table({'v': values}), sink)
            return sink.getvalue()

        def arrow_read(body):
            return pa_csv.read_csv(io.BytesIO(body)).column('v').to_numpy()

        def polars_csv(values):
            return pl.DataFrame({'v': values}).write_csv().encode()

        def polars_read(body):
            return pl.read_csv(body, schema={'v': pl.Float64})['v'].to_numpy()

        timings = {
            'pyarrow': (
                lambda: pa_csv.read_csv(path.format('in.csv')),
                lambda: pa_csv.write_csv(arrow_out, path.format('a.csv')),
                lambda: pq.read_table(path.format('a.parquet')),
                lambda: pq.write_table(arrow_out, path.format('a.parquet')),
                arrow_csv, arrow_read),
            'polars': (
                lambda: pl.read_csv(path.format('in.csv')),
                lambda: polars_out.write_csv(path.format('p.csv')),
                lambda: pl.read_parquet(path.format('p.parquet')),
                lambda: polars_out.write_parquet(path.format('p.parquet')),
                polars_csv, polars_read)}
        for name, (read_csv, write_csv, read_pq, write_pq, text, back) in timings.items():
            write_pq()                               # the file the read times
            cells = [f'{rows / _best(f):,.0f} rows/s' for f in (read_csv, write_csv, read_pq,
                                                                write_pq)]
            differ, exact = _text_checks(text, back, probe)
            lines.append(f'| {name} {(pa if name == "pyarrow" else pl).__version__} | '
                         + ' | '.join(cells) + f' | {differ:,} | {exact} |')
    print(f'{rows:,} rows, {os.cpu_count()} CPUs, load average '
          f'{" ".join(f"{v:.2f}" for v in os.getloadavg())}')
    print('\n'.join(lines))
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
