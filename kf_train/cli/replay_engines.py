"""
How ``kf-train replay`` runs: streamed in bounded memory, all in memory, or on Dask.

* ``--engine stream`` (default): :func:`kf_train.cli.replay_stream.stream_replay`,
  blocks of ``--block-rows`` rows, any input size, CSV or Parquet.
* ``--engine memory``: the whole table in memory (:func:`kf_train.cli.replay.replay`),
  CSV only; filtered in the same blocks of ``--block-rows``, so it writes the bytes
  of ``stream`` for any input size.
* ``--engine dask``: a fleet with an ``id`` column on a Dask cluster
  (:func:`kf_train.cli.fleet_dask.dask_replay`): ``--workers N`` local processes, or
  ``--scheduler ADDRESS`` to join a running cluster.
"""

import argparse
import contextlib
import gc
import os

from kf_train.batch import DEFAULT_BLOCK_ROWS
from kf_train.io import check_output_path

ENGINES = ('stream', 'memory', 'dask')
CODECS = ('auto', 'polars', 'builtin')


def add_engine_options(parser: argparse.ArgumentParser) -> None:
    """Add --engine, --block-rows, --codec, --spill-dir, --workers and --scheduler."""
    group = parser.add_argument_group('size and engines')
    group.add_argument('--engine', choices=ENGINES, default='stream',
                       help='stream (default): bounded memory, any size; memory: the '
                            'whole table at once; dask: a fleet on a Dask cluster')
    group.add_argument('--block-rows', metavar='N', type=int, default=DEFAULT_BLOCK_ROWS,
                       help='rows filtered together (default %(default)s); the numbers '
                            'depend on it, never on how the input is read')
    group.add_argument('--codec', choices=CODECS, default='auto',
                       help='CSV reader and writer: polars (the [fast] extra; auto uses it '
                            'when installed) or builtin; both write the same bytes')
    group.add_argument('--spill-dir', metavar='DIR', default=None,
                       help='where --smooth keeps the forward pass (default: the '
                            "system's temporary directory)")
    group.add_argument('--workers', metavar='N', type=int, default=2,
                       help='dask: local worker processes (default %(default)s)')
    group.add_argument('--scheduler', metavar='ADDRESS', default=None,
                       help='dask: join the cluster whose scheduler is at ADDRESS '
                            '(e.g. tcp://10.0.0.5:8786) instead of starting workers here')


def check_engine_options(parser: argparse.ArgumentParser, args) -> None:
    """Refuse inconsistent engine options (usage errors, exit 2)."""
    if args.block_rows < 1:
        parser.error(f'--block-rows must be >= 1, got {args.block_rows}')
    if args.workers < 1:
        parser.error(f'--workers must be >= 1, got {args.workers}')
    if args.scheduler is not None and args.engine != 'dask':
        parser.error('--scheduler needs --engine dask')
    if args.engine == 'memory' and any(
            path != '-' and (path.endswith('.parquet') or os.path.isdir(path)
                             or path.endswith(os.sep)) for path in (args.input, args.output)):
        parser.error('--engine memory reads and writes CSV only; Parquet streams '
                     '(--engine stream)')


def run_engine(args, preset, filt):
    """Run the replay the options ask for; return its ReplaySummary (raise InputError)."""
    check_output_path(args.output, dataset=True)
    common = {'horizon_s': args.horizon, 'smooth': args.smooth, 't0_s': args.t0, 'filt': filt}
    if args.engine == 'memory':
        from kf_train.cli.replay import replay
        return replay(preset, args.input, args.output, block_rows=args.block_rows,
                      spill_dir=args.spill_dir, **common)
    if args.engine == 'dask':
        from kf_train.cli.fleet_dask import dask_replay
        return dask_replay(preset, args.input, args.output, workers=args.workers,
                           scheduler=args.scheduler, **common)
    from kf_train.cli.replay_stream import stream_replay
    try:
        with collector_frozen():
            return stream_replay(preset, args.input, args.output, block_rows=args.block_rows,
                                 codec=args.codec, spill_dir=args.spill_dir, **common)
    except OSError as error:              # e.g. the disk filled up: one line, no traceback
        raise ValueError(f'{error.filename or args.output}: {error.strerror or error}'
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
