"""Floor 3, input and output: CSV codecs (csvio; polars) and Parquet."""  # noqa: A005 (see below)

# The name shadows the standard library's io only for code run with kf_train/ itself on
# sys.path, which nothing does: every import of this package is absolute (kf_train.io).

from kf_train.io import columnar, csvio
from kf_train.io.csvio import (
    BLOCK_FIELDS, BLOCK_ROWS, Fields, format_labels, format_rows, format_values, parse_labels,
    parse_numbers, parse_rows, split_fields)

__all__ = [
    'BLOCK_FIELDS', 'BLOCK_ROWS', 'columnar', 'csvio', 'Fields', 'format_labels', 'format_rows',
    'format_values', 'parse_labels', 'parse_numbers', 'parse_rows', 'split_fields',
]
