"""
``kf-train replay FIXES.csv --track FILE``: GNSS fixes from a table, on a track, offline.

The table is CSV with a header: ``t`` (the fix's time [s]), ``lat`` and ``lon`` (WGS 84
[deg]; an empty cell: a fix without a position, ignored and counted) and, optionally,
``accuracy_m`` (the fix's horizontal standard deviation [m], as receivers report hAcc;
the variance is its square east and north; empty or absent: ``fix_variance_m2``). Other
columns are ignored. Each row becomes a :class:`kf_train.io.Fix` and goes through the
estimator node's session exactly as a NavSatFix from a bag does
(:mod:`kf_train.replay.bag`, the node's parameters, ``-p`` and ``--params-file``), its
time as stamp and record time: the outputs (CSV or MCAP) are the bag replay's.

A ``--track`` file that is a network (a FeatureCollection of several LineStrings), for
a table or a bag: the path is chosen live, fix by fix, as the node does
(:mod:`kf_train.io.track_network_live`).
"""

import csv
import math
from typing import Iterator, List

from kf_train.filters import NS_PER_S
from kf_train.io import Fix
import numpy as np

TIME, LAT, LON, ACCURACY = 't', 'lat', 'lon', 'accuracy_m'


def _number(text: str, path: str, line: int, column: str) -> float:
    """Return a cell's number (NaN for an empty cell); ValueError naming line and column."""
    text = text.strip()
    if not text:
        return math.nan
    try:
        return float(text)
    except ValueError:
        raise ValueError(f'{path}: line {line}, column {column}: not a number: '
                         f'{text[:40]!r}') from None


class FixTable:
    """A CSV of fixes read as a bag's NavSatFix topic (what BagRun reads of a bag)."""

    control_count = velocity_count = 0
    velocity_topic = None

    def __init__(self, path: str) -> None:
        """Read and check the table (ValueError naming the line); keep its fixes."""
        self.path = self.measurement_topic = path
        try:
            with open(path, newline='', encoding='utf-8-sig') as stream:
                self.fixes = self._read(csv.reader(stream))
        except OSError as error:
            raise ValueError(f'cannot read {path}: {error.strerror or error}') from None
        except UnicodeDecodeError as error:
            raise ValueError(f'{path}: not UTF-8 text ({error.reason})') from None
        self.measurement_count = len(self.fixes)

    def _read(self, rows) -> List[Fix]:
        """Return the fixes of the rows (after the header)."""
        header = [name.strip() for name in next(rows, [])]
        missing = [name for name in (TIME, LAT, LON) if name not in header]
        if missing:
            raise ValueError(f'{self.path}: a fix table needs the columns t, lat, lon '
                             f'(missing: {", ".join(missing)}); got {",".join(header)}')
        where = {name: header.index(name) for name in (TIME, LAT, LON, ACCURACY)
                 if name in header}
        fixes = []
        for line, row in enumerate(rows, start=2):
            if not row:
                continue
            if len(row) != len(header):
                raise ValueError(f'{self.path}: line {line}: {len(row)} fields, the header '
                                 f'has {len(header)}')
            value = {name: _number(row[i], self.path, line, name) for name, i in where.items()}
            if not math.isfinite(value[TIME]):
                raise ValueError(f'{self.path}: line {line}, column t: a finite time is needed')
            stamp_ns = round(value[TIME] * NS_PER_S)
            accuracy_m = value.get(ACCURACY, math.nan)
            covariance = (np.eye(2) * accuracy_m ** 2 if math.isfinite(accuracy_m)
                          and accuracy_m > 0.0 else None)
            fixes.append(Fix(stamp_ns, '', math.isfinite(value[LAT] + value[LON]),
                             value[LAT], value[LON], covariance, stamp_ns))
        return fixes

    def messages(self) -> Iterator[Fix]:
        """Yield the fixes in the table's order (its time is their record time)."""
        return iter(self.fixes)


def replay_fix_table(table_path: str, output_path: str, config):
    """Replay a fix table with the node configuration ``config``; ValueError (one line)."""
    from kf_train.replay import bag     # the node's session replay; needs rosbags
    if config.options.measurement_type != 'navsatfix':
        raise ValueError('a fix table needs --track FILE (measurement_type navsatfix)')
    return bag.replay_source(FixTable(table_path), output_path, config)
