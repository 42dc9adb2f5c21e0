"""
The RTS smoother over a stream: forward results spilled to disk, smoothed backwards.

A smoothed row needs every later row of its object, so a stream cannot be smoothed
as it is read. :class:`ForwardSpill` appends each block's forward results (one
fixed-size record per row: object, t, x, P, the prior x⁻ and P⁻, F, the
prediction and the NIS) to a temporary file; :func:`smooth_backwards` then reads the blocks from
the last to the first and smooths every object's rows of a block with
:func:`kf_train.batch.smoother.rts_smooth`, anchored on the object's first row of the
next block, already smoothed (the backward recursion needs only that row's smoothed
x, P and its prior and F). A stream of one block is smoothed exactly as the
in-memory replay smooths it. Memory holds one block and one anchor per object; disk
holds 8·(3 + 3n + 3n²) bytes per row (about 160 for two states) plus 16n for the
smoothed means and variances.
"""

import os
from typing import Iterator, List, Optional, Tuple

from kf_train.batch.chunked import Estimates
from kf_train.batch.smoother import rts_smooth
import numpy as np


def _record(n: int, horizon: bool, gaps: bool = False) -> np.dtype:
    """Return the record of one row's forward results (``gaps``: with ``updated``)."""
    fields = [('code', '<i8'), ('t', '<f8'), ('x', '<f8', (n,)), ('P', '<f8', (n, n)),
              ('x_prior', '<f8', (n,)), ('P_prior', '<f8', (n, n)), ('F', '<f8', (n, n))]
    if horizon:
        fields += [('predicted_x', '<f8', (n,)), ('predicted_P', '<f8', (n, n))]
    fields.append(('nis', '<f8'))
    if gaps:
        fields.append(('updated', '<f8'))
    return np.dtype(fields)


class ForwardSpill:
    """A stream's forward results on disk, block by block, and their smoothing."""

    def __init__(self, directory: str, n: int, horizon: bool, gaps: bool = False):
        """Create the spill files in ``directory`` (``gaps``: keep each row's ``updated``)."""
        self.n, self.horizon, self.gaps = n, horizon, gaps
        self.record = _record(n, horizon, gaps)
        self.smoothed_record = np.dtype([('x', '<f8', (n,)), ('var', '<f8', (n,))])
        self.path = os.path.join(directory, 'forward.bin')
        self.smoothed_path = os.path.join(directory, 'smoothed.bin')
        self.stream = open(self.path, 'wb')
        self.blocks: List[Tuple[int, int]] = []     # (first row, rows)
        self.rows = 0

    def append(self, codes: Optional[np.ndarray], est: Estimates) -> None:
        """Append a block's forward results."""
        N = est.t_s.shape[0]
        rec = np.empty(N, dtype=self.record)
        rec['code'] = 0 if codes is None else codes
        for name in ('t', 'x', 'P', 'x_prior', 'P_prior', 'F'):
            rec[name] = getattr(est, 't_s' if name == 't' else name)
        if self.horizon:
            rec['predicted_x'], rec['predicted_P'] = est.predicted_x, est.predicted_P
        rec['nis'] = est.nis
        if self.gaps:
            rec['updated'] = est.updated
        rec.tofile(self.stream)
        self.blocks.append((self.rows, N))
        self.rows += N

    def read(self, first: int, count: int) -> np.ndarray:
        """Return the forward records of rows [first, first + count)."""
        with open(self.path, 'rb') as stream:
            stream.seek(first * self.record.itemsize)
            return np.fromfile(stream, dtype=self.record, count=count)

    def read_smoothed(self, first: int, count: int) -> np.ndarray:
        """Return the smoothed records of rows [first, first + count)."""
        with open(self.smoothed_path, 'rb') as stream:
            stream.seek(first * self.smoothed_record.itemsize)
            return np.fromfile(stream, dtype=self.smoothed_record, count=count)

    def smooth(self, objects: int) -> None:
        """Run the backward pass over every block (``objects``: the number of objects)."""
        self.stream.close()
        anchored = np.zeros(objects, dtype=bool)
        anchor = np.zeros(objects, dtype=self.record)
        with open(self.smoothed_path, 'wb') as out:
            out.truncate(self.rows * self.smoothed_record.itemsize)
            for first, count in reversed(self.blocks):
                rec = self.read(first, count)
                smoothed = np.empty(count, dtype=self.smoothed_record)
                for rows in _rows_by_object(rec['code']):
                    obj = int(rec['code'][rows[0]])
                    part = rec[rows]
                    if anchored[obj]:
                        part = np.concatenate([part, anchor[obj:obj + 1]])
                    xs, Ps = _smooth_rows(part)
                    m = rows.shape[0]
                    smoothed['x'][rows] = xs[:m]
                    smoothed['var'][rows] = np.diagonal(Ps[:m], axis1=1, axis2=2)
                    anchor[obj] = part[0]                   # its prior and F, and
                    anchor['x'][obj], anchor['P'][obj] = xs[0], Ps[0]   # smoothed x, P
                    anchored[obj] = True
                out.seek(first * self.smoothed_record.itemsize)
                smoothed.tofile(out)

    def blocks_out(self) -> Iterator[Tuple[int, Optional[np.ndarray], Estimates,
                                           Tuple[np.ndarray, np.ndarray]]]:
        """Yield (first row, codes, forward estimates, (smoothed x, variances)) per block."""
        for first, count in self.blocks:
            rec = self.read(first, count)
            sm = self.read_smoothed(first, count)
            est = Estimates(rec['t'], rec['x'], rec['P'], rec['x_prior'], rec['P_prior'],
                            rec['F'], rec['predicted_x'] if self.horizon else None,
                            rec['predicted_P'] if self.horizon else None,
                            rec['updated'] if self.gaps else None, nis=rec['nis'])
            yield first, rec['code'], est, (sm['x'], sm['var'])


def _rows_by_object(codes: np.ndarray) -> Iterator[np.ndarray]:
    """Yield the row indices of every object in ``codes``, each in row order."""
    order = np.argsort(codes, kind='stable')
    sorted_codes = codes[order]
    cuts = np.flatnonzero(sorted_codes[1:] != sorted_codes[:-1]) + 1
    yield from np.split(order, cuts)


def _smooth_rows(part: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Return the smoothed (x, P) of one object's rows (the last one already smoothed)."""
    if part.shape[0] == 1:
        return part['x'], part['P']
    result = rts_smooth(part['x'], part['P'], part['x_prior'], part['P_prior'], part['F'])
    return result.x, result.P
