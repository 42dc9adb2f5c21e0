"""
The options that choose how ``kf-train replay`` runs (:mod:`kf_train.replay.engines`).

``--engine stream`` (default), ``memory`` or ``dask``, with ``--block-rows``,
``--codec``, ``--spill-dir``, ``--workers`` and ``--scheduler``.
"""

import argparse
import os

from kf_train.batch import DEFAULT_BLOCK_ROWS
from kf_train.replay import CODECS, ENGINES


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
