"""
Floor 3, input and output: CSV codecs (csvio; polars), Parquet and bags.

The bag modules (``bagio``, ``bagio_output``, ``bagio_simulation``) need ``rosbags``
(the extra ``[bag]``): they are imported when used (``from kf_train.io import bagio``),
not here.
"""  # noqa: A005 (see below)

# The name shadows the standard library's io only for code run with kf_train/ itself on
# sys.path, which nothing does: every import of this package is absolute (kf_train.io).

import importlib

from kf_train.io import columnar, csvio
from kf_train.io.csvio import (
    BLOCK_FIELDS, BLOCK_ROWS, Fields, format_labels, format_rows, format_values, parse_labels,
    parse_numbers, parse_rows, split_fields)

__all__ = [
    'bagio', 'bagio_output', 'bagio_simulation', 'BLOCK_FIELDS', 'BLOCK_ROWS', 'columnar',
    'csvio', 'Fields', 'format_labels', 'format_rows', 'format_values', 'parse_labels',
    'parse_numbers', 'parse_rows', 'split_fields',
]

_LAZY = ('bagio', 'bagio_output', 'bagio_simulation')


def __getattr__(name: str):
    """Import the bag modules on first use (PEP 562): they need rosbags."""
    if name in _LAZY:
        return importlib.import_module(f'kf_train.io.{name}')
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
