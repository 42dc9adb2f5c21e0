"""
What every benchmark row shares: the model's constants, timing, the table and its header.

Benchmarks print figures; they assert nothing (see bench.py).
"""

import datetime
import math
import os
import platform
import time
from typing import Callable, List, Sequence, Tuple

Q_DENSITY = 0.5        # white-noise acceleration of the benchmark model [m²/s³]
DT_S = 0.1
R_M2 = 1.0
TRAIN_SPEED_MPS = 10.0
NS_PER_S = 1_000_000_000

Row = Tuple[str, str, str, str, str, str]
"""One table row: (row, measurement, case, result, ratio, target)."""


def header() -> List[str]:
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


def table(rows: Sequence[Row]) -> List[str]:
    """Return a markdown table of the rows."""
    head = ('Row', 'Measurement', 'Case', 'Result', 'Ratio', 'Target')
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    lines += ['| ' + ' | '.join(cell.replace('|', '/') for cell in row) + ' |'
              for row in rows]
    return lines


def us(seconds: float) -> str:
    """Format a duration given in seconds as µs."""
    return f'{seconds * 1e6:.3g} µs'


def verdict(ok: bool) -> str:
    """Return 'met' or 'MISSED'."""
    return 'met' if ok else 'MISSED'


def best_of(function: Callable[[], None], repeats: int) -> float:
    """Return the shortest of ``repeats`` timed calls [s]."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def percentile(sorted_values: Sequence[float], fraction: float) -> float:
    """Return the nearest-rank percentile of sorted values."""
    if not sorted_values:
        return math.nan
    index = min(len(sorted_values) - 1, max(0, math.ceil(fraction * len(sorted_values)) - 1))
    return sorted_values[index]
