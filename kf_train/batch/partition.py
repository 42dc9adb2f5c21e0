"""
Filter one partition of a fleet log: the function to hand ``map_partitions``.

:func:`filter_partition` takes a table (pandas DataFrame, or a pyarrow Table) holding
every row of one or more trains, each train's rows in time order, and returns the
replay's estimates for it as a pandas DataFrame: the id column, then the columns
``kf-train replay`` writes, one row per input row in the same order. A partition is one
block of :class:`kf_train.batch.stream.StreamingReplay`, so its numbers are those of
``kf-train replay --engine memory`` on the same rows.

With Dask (``pip install 'kf_train[dask]'``), partitions that each hold whole trains::

    import dask.dataframe as dd
    from kf_train.batch.partition import filter_partition, partition_meta

    fleet = dd.read_parquet('fleet/')                 # columns id, t, z_position
    fleet = fleet.shuffle(on='id')                    # every train in one partition
    estimates = fleet.map_partitions(filter_partition, 'train',
                                     meta=partition_meta('train'))
    estimates.to_parquet('estimates/')

``kf-train replay --engine dask`` does this (and keeps each train's rows in input order
through the shuffle). pandas is imported on first use: it comes with Dask.
"""

from typing import List, Optional, Union

from kf_train.batch.chunked import output_header, resolve_horizon, RowError
from kf_train.batch.stream import filter_table
from kf_train.presets import load_preset, Preset
import numpy as np

ID_COLUMN = 'id'


def _preset(preset: Union[str, Preset]) -> Preset:
    """Return a preset given by name or as a Preset (a name pickles smaller)."""
    return load_preset(preset) if isinstance(preset, str) else preset


def _column(frame, names) -> np.ndarray:
    """Return the first of ``names`` present in the frame, as float64."""
    for name in names:
        if name in frame.columns:
            return frame[name].to_numpy(dtype=float)
    raise ValueError(f"missing column '{names[0]}'; the partition has: "
                     f"{', '.join(map(str, frame.columns))}")


def partition_meta(preset: Union[str, Preset], *, horizon_s=None, smooth: bool = False,
                   id_column: str = ID_COLUMN):
    """Return an empty DataFrame with :func:`filter_partition`'s columns (Dask's meta)."""
    import pandas as pd
    owner = _preset(preset)
    header = output_header(owner, resolve_horizon(owner, horizon_s), smooth)
    columns = {id_column: pd.Series([], dtype=pd.StringDtype())}
    columns.update({name: pd.Series([], dtype=float) for name in header})
    return pd.DataFrame(columns)


def filter_partition(frame, preset: Union[str, Preset], *, horizon_s=None,
                     t0_s: float = 0.0, smooth: bool = False, filt=None,
                     id_column: str = ID_COLUMN, keep: Optional[List[str]] = None):
    """
    Return the estimates of every train in ``frame`` (a pandas DataFrame).

    ``frame``: pandas DataFrame or pyarrow Table with ``id_column``, ``t`` [s] and the
    preset's measurement (and control) columns; each id's rows in time order, ids in
    any interleaving; other columns are ignored (``keep`` copies some to the output,
    e.g. a row key). ``preset`` is a preset name or a Preset; ``horizon_s``, ``t0_s``,
    ``smooth`` and ``filt`` are the options of ``kf-train replay``. Raises ValueError
    naming the id and the time of a bad row.
    """
    import pandas as pd
    if not isinstance(frame, pd.DataFrame):
        frame = frame.to_pandas()
    owner = _preset(preset if filt is None else filt.preset)
    t = _column(frame, ['t'])
    z = np.column_stack([_column(frame, names) for names in owner.measurement_columns()]
                        ) if len(frame) else np.empty((0, owner.dim_z))
    u = None
    if owner.dim_u:
        u = np.column_stack([_column(frame, [name]) for name in owner.control_columns()]
                            ) if len(frame) else np.empty((0, owner.dim_u))
    labels = frame[id_column].astype(str).str.strip()
    codes, names = pd.factorize(labels, sort=True)
    unmeasured = ~np.isfinite(z).all(axis=1)
    if unmeasured.any():    # an empty cell arrives here as NaN: no gaps on Dask (yet)
        k = int(np.argmax(unmeasured))
        raise ValueError(f"id '{labels.iloc[k]}', t = {float(t[k])!r}: empty or non-finite "
                         'measurement; rows without a measurement need --engine stream')
    try:
        columns = filter_table(owner, t, z, u, codes, horizon_s=horizon_s, t0_s=t0_s,
                               filt=filt, smooth=smooth, block_rows=max(len(frame), 1))
    except RowError as error:
        raise ValueError(f"id '{labels.iloc[error.row]}', t = {float(t[error.row])!r}: "
                         f'{error.reason}') from None
    header = output_header(owner, resolve_horizon(owner, horizon_s), smooth)
    out = {id_column: labels.astype(pd.StringDtype()).to_numpy()}
    out.update(zip(header, columns))
    for name in keep or []:
        out[name] = frame[name].to_numpy()
    return pd.DataFrame(out, index=frame.index)
