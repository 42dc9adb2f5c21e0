"""
How a table replay runs: streamed in bounded memory, all in memory, or on Dask.

* ``stream`` (default): :func:`kf_train.replay.stream.stream_replay`, blocks of
  ``block_rows`` rows, any input size, CSV or Parquet.
* ``memory``: the whole table in memory (:func:`kf_train.replay.memory.replay`), CSV
  only; filtered in the same blocks of ``block_rows``, so it writes the bytes of
  ``stream`` for any input size.
* ``dask``: a fleet with an ``id`` column on a Dask cluster
  (:func:`kf_train.replay.fleet_dask.dask_replay`): ``workers`` local processes, or
  ``scheduler`` to join a running cluster.

The options that choose them are :mod:`kf_train.cli.engine_options`.
"""

import contextlib
import gc
from typing import Optional

from kf_train.batch import DEFAULT_BLOCK_ROWS
from kf_train.io import check_output_path
from kf_train.replay.fleet_dask import dask_replay
from kf_train.replay.memory import replay
from kf_train.replay.stream import stream_replay

ENGINES = ('stream', 'memory', 'dask')
CODECS = ('auto', 'polars', 'builtin')


def run_engine(engine: str, preset, input_path: str, output_path: str, filt=None, *,
               horizon_s=None, smooth: bool = False, t0_s: float = 0.0,
               block_rows: int = DEFAULT_BLOCK_ROWS, codec: str = 'auto',
               spill_dir: Optional[str] = None, workers: int = 2,
               scheduler: Optional[str] = None):
    """Run the replay ``engine`` names; return its ReplaySummary (raise InputError)."""
    check_output_path(output_path, dataset=True)
    common = {'horizon_s': horizon_s, 'smooth': smooth, 't0_s': t0_s, 'filt': filt}
    if engine == 'memory':
        return replay(preset, input_path, output_path, block_rows=block_rows,
                      spill_dir=spill_dir, **common)
    if engine == 'dask':
        return dask_replay(preset, input_path, output_path, workers=workers,
                           scheduler=scheduler, **common)
    try:
        with collector_frozen():
            return stream_replay(preset, input_path, output_path, block_rows=block_rows,
                                 codec=codec, spill_dir=spill_dir, **common)
    except OSError as error:              # e.g. the disk filled up: one line, no traceback
        raise ValueError(f'{error.filename or output_path}: {error.strerror or error}'
                         ) from None


@contextlib.contextmanager
def collector_frozen():
    """Run a long replay with the objects that exist now out of the garbage collector's way."""
    # The imports' objects live as long as the run: full collections need not walk them
    # again and again (≈2 % of a long streamed replay's CPU, more of a bag replay's, whose
    # filter makes many small objects). Unfrozen after, so nothing is kept for good.
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
