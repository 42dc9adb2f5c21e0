"""
``kf-train replay --engine dask``: a fleet log filtered on a Dask cluster.

The log (a Parquet file or dataset directory, or CSV files: a glob works) must have an
``id`` column. Dask reads it in partitions, each row gets a key that remembers where it
was (partition, row), a shuffle brings every train's rows into one partition, and
:func:`kf_train.batch.partition.filter_partition` filters each partition with its rows
back in input order. OUTPUT: a directory (a Parquet dataset, one file per partition;
each train's rows in input order within its partition) or a .csv file (the rows of a
train together, in input order).

``--workers N`` starts a local cluster of N single-threaded worker processes on this
machine (loopback only); ``--scheduler ADDRESS`` joins a running cluster instead (see
docs/scale.md: "A fleet on a Dask cluster"). Needs ``pip install 'kf_train[dask]'``.
"""

import logging
import os
import shutil
import tempfile
import time

from kf_train.batch import filter_partition, partition_meta
from kf_train.io import ID_COLUMN, InputError, required_columns
from kf_train.replay.memory import ReplaySummary
from kf_train.replay.stream import is_parquet

KEY = '_kf_train_row'
# Rows per partition and above: enough to hold a 2**40-row partition's row numbers.
_PARTITION_STRIDE = 1 << 40
DASK_HINT = "install the dask extra: pip install 'kf_train[dask]'"


def _with_key(partition, partition_info=None):
    """Return the partition with a column KEY: partition number·2^40 + row, input order."""
    import numpy as np
    number = 0 if partition_info is None else partition_info['number']
    key = number * _PARTITION_STRIDE + np.arange(len(partition), dtype=np.int64)
    return partition.assign(**{KEY: key})


def _filter_in_order(partition, preset, options):
    """Filter a shuffled partition with every train's rows back in input order."""
    ordered = partition.sort_values(KEY, kind='stable')
    return filter_partition(ordered, preset, keep=[KEY], **options)


def _read(dd, path: str, columns):
    """Return the input as a Dask DataFrame with ``columns``."""
    if is_parquet(path):
        return dd.read_parquet(path, columns=columns)
    return dd.read_csv(path, usecols=columns, dtype={'id': str}, blocksize='64MB')


def _client(workers: int, scheduler):
    """Return a Dask client: of the cluster at ``scheduler``, or a new local one."""
    from dask.distributed import Client, LocalCluster
    if scheduler is not None:
        return Client(scheduler), None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           host='127.0.0.1', dashboard_address=None,
                           silence_logs=logging.ERROR)
    return Client(cluster), cluster


def dask_replay(preset, input_path: str, output_path: str, *, workers: int = 2,
                scheduler=None, horizon_s=None, smooth: bool = False, t0_s: float = 0.0,
                filt=None) -> ReplaySummary:
    """Replay a fleet log on Dask; raise InputError for bad input."""
    try:
        import dask.dataframe as dd
    except ImportError:
        raise InputError(f'--engine dask: {DASK_HINT}') from None
    start = time.perf_counter()
    owner = preset if filt is None else filt.preset
    needed = [names[0] for names in required_columns(owner)]
    options = {'horizon_s': horizon_s, 't0_s': t0_s, 'smooth': smooth, 'filt': filt}
    for name in ('distributed', 'distributed.shuffle'):
        logging.getLogger(name).setLevel(logging.ERROR)   # the shuffle logs at WARNING
    client, cluster = _client(workers, scheduler)
    try:
        try:
            frame = _read(dd, input_path, [ID_COLUMN] + needed)
        except (ValueError, KeyError, OSError) as error:
            raise InputError(f'{input_path}: {error} (the dask engine needs the '
                             f'columns id, {", ".join(needed)})') from None
        keyed = frame.map_partitions(_with_key, meta=frame._meta.assign(**{KEY: 0}))
        shuffled = keyed.shuffle(on=ID_COLUMN,
                                 npartitions=max(frame.npartitions, 2 * workers))
        meta = partition_meta(owner, horizon_s=horizon_s, smooth=smooth).assign(**{KEY: 0})
        estimates = shuffled.map_partitions(_filter_in_order, owner, options, meta=meta)
        rows = _write(estimates, output_path)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    header = list(meta.columns.drop(KEY))
    return ReplaySummary(rows, header, time.perf_counter() - start)


def _write(estimates, output_path: str) -> int:
    """Write the estimates (a directory: Parquet dataset; else one CSV); return the rows."""
    import dask
    if '://' in output_path:              # an object store: written in place, not renamed
        written = estimates.drop(columns=[KEY])
        counts = written.map_partitions(len)
        dask.compute(written.to_parquet(output_path, write_index=False, compute=False))
        return int(counts.sum().compute())
    target = output_path.rstrip(os.sep)
    parent = os.path.dirname(os.path.abspath(target))
    temporary = tempfile.mkdtemp(dir=parent, prefix='.' + os.path.basename(target),
                                 suffix='.tmp')
    try:
        if output_path.endswith('.csv'):
            ordered = estimates.map_partitions(lambda p: p.sort_values(
                ['id', KEY], kind='stable')).drop(columns=[KEY])
            part = os.path.join(temporary, 'out.csv')
            # NaN (a row's nis when it fused no position) as the other CSV writers: 'nan'.
            ordered.to_csv(part, single_file=True, index=False, na_rep='nan')
            rows = int(dask.compute(ordered.map_partitions(len).sum())[0])
            os.replace(part, target)
            return rows
        written = estimates.drop(columns=[KEY])
        counts = written.map_partitions(len)
        dask.compute(written.to_parquet(temporary, write_index=False, compute=False))
        rows = int(counts.sum().compute())
        if os.path.exists(target):
            shutil.rmtree(target)
        os.rename(temporary, target)
        return rows
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
