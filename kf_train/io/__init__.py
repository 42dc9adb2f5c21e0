"""
Floor 3, input and output: CSV codecs (csvio; polars), tables, Parquet and bags.

:mod:`~kf_train.io.tables` reads and writes the replay's CSV tables (an
:class:`InputError` names the line and column), :mod:`~kf_train.io.table_output` the
streamed outputs (CSV, Parquet file or dataset) and :mod:`~kf_train.io.paths` says
what an input path names, checks an output path and writes a file atomically.

The bag modules (``bagio``, ``bagio_output``, ``bagio_simulation``) need ``rosbags``
(the extra ``[bag]``): they are imported when used (``from kf_train.io import bagio``),
not here. :mod:`~kf_train.io.track_geometry` and :mod:`~kf_train.io.track_fixes` (WGS 84
fixes on a track file), :mod:`~kf_train.io.track_network` and
:mod:`~kf_train.io.track_network_live` (a network: the path chosen offline or live) need
``pyproj`` (the extra ``[track]``) once a geometry is built.
"""  # noqa: A005 (see below)

# The name shadows the standard library's io only for code run with kf_train/ itself on
# sys.path, which nothing does: every import of this package is absolute (kf_train.io).

import importlib

from kf_train.io import columnar, csvio
from kf_train.io.csvio import (
    BLOCK_FIELDS, BLOCK_ROWS, Fields, format_labels, format_rows, format_values, parse_labels,
    parse_numbers, parse_rows, split_fields)
from kf_train.io.paths import check_output_path, is_bag, write_atomic
from kf_train.io.table_output import in_background, open_output, Output
from kf_train.io.tables import (
    check_time_range, check_times, decode_text, format_csv, HEADER_LINE, header_names,
    ID_COLUMN, InputError, read_table, required_columns, resolve_columns, Table,
    time_order_error, UTF8_BOM)
from kf_train.io.track_fixes import (
    CROSS_TRACK_MAX_M, CROSS_TRACK_SIGMAS, Fix, fix_from_msg, TRACK_DIRECTIONS, TrackFix,
    TrackFixes)
from kf_train.io.track_geometry import load_track, TrackError, TrackGeometry
from kf_train.io.track_network import is_network_file, TrackNetwork
from kf_train.io.track_network_live import NetworkFixes

__all__ = [
    'bagio', 'bagio_output', 'bagio_simulation', 'BLOCK_FIELDS', 'BLOCK_ROWS', 'check_output_path',
    'check_time_range', 'check_times', 'columnar', 'CROSS_TRACK_MAX_M', 'CROSS_TRACK_SIGMAS',
    'csvio', 'decode_text', 'Fields', 'Fix', 'fix_from_msg', 'format_csv', 'format_labels',
    'format_rows', 'format_values', 'HEADER_LINE', 'header_names', 'ID_COLUMN', 'in_background',
    'InputError', 'is_bag', 'is_network_file', 'load_track', 'NetworkFixes', 'open_output',
    'Output', 'parse_labels', 'parse_numbers', 'parse_rows', 'read_table', 'required_columns',
    'resolve_columns', 'split_fields', 'Table', 'time_order_error', 'TRACK_DIRECTIONS',
    'TrackError', 'TrackFix', 'TrackFixes', 'TrackGeometry', 'TrackNetwork', 'UTF8_BOM',
    'write_atomic',
]

# bagio_mcap, bagio_ros1 and bagio_types, which the bag modules use, import rosbags too.
_LAZY = ('bagio', 'bagio_mcap', 'bagio_output', 'bagio_ros1', 'bagio_simulation',
         'bagio_types')


def __getattr__(name: str):
    """Import the bag modules on first use (PEP 562): they need rosbags."""
    if name in _LAZY:
        return importlib.import_module(f'kf_train.io.{name}')
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
