"""
Fast, exact CSV numbers: float64 columns to and from text, vectorised with numpy.

:func:`format_rows` writes a table of doubles as CSV text in which every number is
the string Python's ``repr`` gives (the shortest that reads back to the same
double), at a fraction of ``repr``'s cost. Per number: one double-double product
a·10^k gives 17 correctly rounded digits; the same arithmetic tells whether 15 or 16
of them already read back (the shortest form); the text is assembled in 64-bit words
(eight characters at a time) and the unused bytes are squeezed out at the end.
Numbers whose rounding or round-trip test falls too close to a boundary to decide in
this arithmetic (exact ties), non-finite values and magnitudes beyond 1e±280 are
formatted by ``repr`` itself, so the output is always exactly ``repr``'s.

:func:`parse_rows` (:func:`split_fields` then :func:`parse_numbers`) reads a plain CSV
body (decimal numbers, commas and newlines) into a float64 table, correctly rounded
like ``float()``: each field is loaded as three 64-bit words, its sign and '.' are
found and removed with byte tricks, the digits are summed eight at a time, and one
double-double product scales them by 10^q; a result within rounding of a half-way
point between two doubles, an exponent or an odd field goes to ``float()``. For
anything that is not plain (quotes, blank lines, a wrong field count, text that is
not a number) the readers return None, so that the caller can fall back to a careful
reader that names the line and the column of whatever is wrong.
:func:`parse_labels` and :func:`format_labels` do the same for a text column (an id).

Nothing here raises on bad text: None means "read it the careful way". The writer
is :mod:`~kf_train.io.csv_format`, the reader :mod:`~kf_train.io.csv_parse`, their
shared tables :mod:`~kf_train.io.csv_tables`; this module is the codec's one name.
"""

from kf_train.io.csv_format import BLOCK_ROWS, format_labels, format_rows, format_values
from kf_train.io.csv_parse import (
    BLOCK_FIELDS, Fields, parse_labels, parse_numbers, parse_rows, split_fields)

__all__ = [
    'BLOCK_FIELDS', 'BLOCK_ROWS', 'Fields', 'format_labels', 'format_rows', 'format_values',
    'parse_labels', 'parse_numbers', 'parse_rows', 'split_fields',
]
