"""
Floor 5, the replay engines: a preset's filter or the node's session over recorded data.

* :mod:`~kf_train.replay.stream`: a CSV or Parquet table in bounded memory, block by
  block (``kf-train replay``'s default engine);
* :mod:`~kf_train.replay.memory`: the whole table in memory (``--engine memory``), and
  :func:`run_preset` over arrays;
* :mod:`~kf_train.replay.fleet_dask`: a fleet on a Dask cluster (``--engine dask``;
  dask imported when used);
* :mod:`~kf_train.replay.bag`: the estimator node's session over a rosbag2 bag. It
  needs rosbags (the extra ``[bag]``): imported when used (``from kf_train.replay
  import bag``), not here;
* :mod:`~kf_train.replay.fix_table`: a CSV of GNSS fixes (t, lat, lon) on a track
  file, through the same session (imported when used, as ``bag``);
* :mod:`~kf_train.replay.engines` chooses among the table engines;
  :mod:`~kf_train.replay.progress` draws a progress bar (tqdm, when installed).
"""

import importlib

from kf_train.replay.engines import CODECS, collector_frozen, ENGINES, run_engine
from kf_train.replay.fleet_dask import dask_replay
from kf_train.replay.memory import (
    check_bank_times, load_any_preset, output_columns, replay, ReplaySummary, run_preset,
    smooth_bank)
from kf_train.replay.progress import counted, Progress
from kf_train.replay.stream import input_columns, is_parquet, stream_replay

__all__ = [
    'bag', 'check_bank_times', 'CODECS', 'collector_frozen', 'counted', 'dask_replay',
    'ENGINES', 'fix_table', 'input_columns', 'is_parquet', 'load_any_preset',
    'output_columns', 'Progress', 'replay', 'ReplaySummary', 'run_engine', 'run_preset',
    'smooth_bank', 'stream_replay',
]

_LAZY = ('bag', 'fix_table')


def __getattr__(name: str):
    """Import the bag replay on first use (PEP 562): it needs rosbags."""
    if name in _LAZY:
        return importlib.import_module(f'kf_train.replay.{name}')
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
