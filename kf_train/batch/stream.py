"""
A replay of any length in bounded memory: rows in, estimates out, block by block.

:class:`StreamingReplay` is the engine behind ``kf-train replay``: a reader pushes rows
in pieces of any size, the engine cuts them into fixed blocks
(:mod:`kf_train.batch.chunked`) and hands back each block's output columns. With
``smooth`` the forward results go to a :class:`kf_train.batch.spill.ForwardSpill` and
the output comes at :meth:`StreamingReplay.finish`, after the backward pass.

:func:`filter_table` runs the same engine on arrays already in memory (one Dask
partition, a test), so that every way of running a replay gives the same numbers.
"""

import shutil
import tempfile
from typing import Iterator, List, Optional, Sequence

from kf_train.batch.chunked import (
    BlockFilter, DEFAULT_BLOCK_ROWS, estimate_columns, ObjectStates, output_header,
    OutputBlock, resolve_horizon, Rows)
from kf_train.batch.spill import ForwardSpill
from kf_train.filters import PARTICLE_KINDS
import numpy as np


class GapsFound(Exception):
    """Rows without a measurement reached an engine made without ``gaps``: start again."""


class StreamingReplay:
    """Filter rows pushed in pieces; return the estimates block by block."""

    def __init__(self, preset, *, horizon_s=None, t0_s: float = 0.0, filt=None,
                 smooth: bool = False, block_rows: int = DEFAULT_BLOCK_ROWS,
                 spill_dir: Optional[str] = None, gaps: bool = False):
        """
        Filter with ``preset`` (or ``filt``, a filter of its family, row by row).

        ``horizon_s`` None uses the preset's, 0 none; ``t0_s`` is when the initial
        estimate holds; ``smooth`` adds the RTS-smoothed columns (spilling the forward
        pass under ``spill_dir``, default the system's temporary directory);
        ``block_rows`` (>= 1) is the block length. ``gaps``: the input may have rows
        without a measurement (``Rows.missing``); the output then ends with a column
        ``updated`` (1.0 updated, 0.0 predicted only).
        """
        if smooth and filt is not None and filt.kind in PARTICLE_KINDS:
            raise ValueError('--smooth needs a Gaussian filter (kf, ekf or ukf): the RTS '
                             'smoother does not apply to particles')
        if int(block_rows) < 1:
            raise ValueError(f'block_rows must be >= 1, got {block_rows}')
        owner = preset if filt is None else filt.preset
        self.preset, self.block_rows, self.smooth = owner, int(block_rows), smooth
        self.horizon = resolve_horizon(owner, horizon_s)
        self.gaps = gaps
        self.header = output_header(owner, self.horizon, smooth, gaps)
        self.states = ObjectStates(owner, t0_s, filt)
        self.filter = BlockFilter(owner, self.horizon, self.states, priors=smooth)
        self.pending: List[Rows] = []
        self.pending_rows = 0
        self.rows_in = 0           # rows pushed so far
        self.rows_done = 0         # rows filtered so far
        self.has_codes = False     # whether the rows carry object codes
        self._spill_dir = spill_dir
        self._temporary: Optional[str] = None
        self.spill: Optional[ForwardSpill] = None

    def push(self, rows: Rows) -> List[OutputBlock]:
        """Take more rows; return the output of every block they complete."""
        if rows.missing is not None and not self.gaps and rows.missing.any():
            raise GapsFound('rows without a measurement need StreamingReplay(gaps=True)')
        if rows.t.shape[0]:
            self.pending.append(rows)
            self.pending_rows += rows.t.shape[0]
            self.rows_in += rows.t.shape[0]
        out = []
        while self.pending_rows >= self.block_rows:
            out += self._run(self._take(self.block_rows))
        return out

    def finish(self) -> Iterator[OutputBlock]:
        """
        Filter what is left; yield the rest of the output (all of it when smoothing).

        When smoothing, the blocks are read back from the spill one at a time as the
        caller takes them: iterate, do not make a list of them.
        """
        yield from self._run(self._take(self.pending_rows)) if self.pending_rows else []
        if self.spill is None:
            return
        self.spill.smooth(self.states.seen.shape[0])
        for first, codes, est, smoothed in self.spill.blocks_out():
            yield OutputBlock(first, codes if self.has_codes else None,
                              estimate_columns(est, smoothed))

    def close(self) -> None:
        """Remove the spill files, if any."""
        if self._temporary is not None:
            shutil.rmtree(self._temporary, ignore_errors=True)
            self._temporary = self.spill = None

    def __enter__(self) -> 'StreamingReplay':
        """Return the engine; :meth:`close` on exit."""
        return self

    def __exit__(self, *exc) -> None:
        """Remove the spill files."""
        self.close()

    def _take(self, count: int) -> Rows:
        """Remove and return the first ``count`` pending rows."""
        rows = Rows.join(self.pending)
        self.pending = [rows.take(count, rows.t.shape[0])] if count < rows.t.shape[0] else []
        self.pending_rows -= count
        return rows.take(0, count) if count < rows.t.shape[0] else rows

    def _run(self, rows: Rows) -> List[OutputBlock]:
        """Filter one block; return its output (none yet when smoothing)."""
        first = self.rows_done
        self.has_codes = rows.codes is not None
        est = self.filter.run(rows, first)
        if self.gaps:
            missing = rows.missing
            if missing is not None and getattr(self.filter.filt, 'partial_rows', False):
                # Rows with an empty cell (a fix without its speed) updated what they had.
                missing = ~np.isfinite(rows.z.reshape(rows.t.shape[0], -1)).any(axis=1)
            est = est._replace(updated=np.ones(rows.t.shape[0]) if missing is None
                               else np.where(missing, 0.0, 1.0))
        self.rows_done += rows.t.shape[0]
        if not self.smooth:
            return [OutputBlock(first, rows.codes, estimate_columns(est))]
        if self.spill is None:
            self._temporary = tempfile.mkdtemp(prefix='kf-train-smooth-', dir=self._spill_dir)
            self.spill = ForwardSpill(self._temporary, self.preset.dim_x,
                                      self.horizon is not None, self.gaps)
        self.spill.append(rows.codes, est)
        return []


def filter_table(preset, t, z, u=None, codes: Optional[Sequence[int]] = None, *,
                 horizon_s=None, t0_s: float = 0.0, filt=None, smooth: bool = False,
                 block_rows: int = DEFAULT_BLOCK_ROWS, missing=None,
                 spill_dir: Optional[str] = None) -> List[np.ndarray]:
    """
    Return the output columns (as :func:`kf_train.batch.chunked.output_header`) of a table.

    ``codes`` (one int per row, or None for one object) tells the objects apart; the
    table runs through :class:`StreamingReplay` in blocks of ``block_rows``, so the
    numbers equal those of a streamed replay of the same rows. ``missing`` (one bool per
    row, or None) flags rows without a measurement; given, the last column is
    ``updated`` (see :class:`StreamingReplay`).
    """
    owner = preset if filt is None else filt.preset
    t = np.asarray(t, dtype=float).reshape(-1)
    # The widths from the preset: an empty partition has no row to infer them from.
    z = np.asarray(z, dtype=float).reshape(t.shape[0], owner.dim_z)
    u = None if u is None else np.asarray(u, dtype=float).reshape(t.shape[0], owner.dim_u)
    codes = None if codes is None else np.asarray(codes, dtype=np.int64).reshape(-1)
    if missing is not None:
        missing = np.asarray(missing, dtype=bool).reshape(-1)
    with StreamingReplay(preset, horizon_s=horizon_s, t0_s=t0_s, filt=filt, smooth=smooth,
                         block_rows=block_rows, gaps=missing is not None,
                         spill_dir=spill_dir) as engine:
        blocks = engine.push(Rows(t, z, u, codes, missing)) + list(engine.finish())
    width = len(engine.header)
    if not blocks:
        return [np.empty(0) for _ in range(width)]
    return [np.concatenate([block.columns[j] for block in blocks]) for j in range(width)]
