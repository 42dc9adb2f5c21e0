"""
CSV text to doubles, correctly rounded like ``float()``, vectorised (see :mod:`.csvio`).

Each field is loaded as three 64-bit words, its sign and '.' are found and removed
with byte tricks, the digits are summed eight at a time, and one double-double
product scales them by 10^q; a result within rounding of a half-way point, an
exponent or an odd field goes to ``float()``. Anything that is not plain returns
None: the caller then reads it the careful way.
"""

import functools
from typing import NamedTuple, Optional, Sequence

from kf_train.io.csv_tables import _EPS, _K_MIN, _SPLIT, _Tables, _tables, _U56, _U8
import numpy as np

_ONES = np.uint64(0x0101010101010101)
_HIGHS = np.uint64(0x8080808080808080)
_ASCII_ZEROS = np.uint64(0x3030303030303030)
_LONGEST_FIELD = 24
# Field blocks parsed at a time: work arrays stay in cache.
BLOCK_FIELDS = 8192


@functools.lru_cache(maxsize=1)
def _allowed_bytes() -> np.ndarray:
    """Return a table of the bytes a plain decimal number may contain."""
    table = np.zeros(256, dtype=bool)
    for c in b'0123456789.-+eE':
        table[c] = True
    return table


def _shift_up(words, nbytes: np.ndarray):
    """Return the words moved up by ``nbytes`` (array, 0..7) bytes, carrying across."""
    bits = nbytes.astype(np.uint64) * _U8
    back = np.uint64(63) - bits
    out = [words[0] << bits]
    for w in range(1, len(words)):
        # (x >> 1) >> (63 − bits) is x >> (64 − bits), also for bits = 0
        out.append((words[w] << bits) | ((words[w - 1] >> np.uint64(1)) >> back))
    return out


def _shift_down(words, nbytes: np.ndarray):
    """Return the words moved down by ``nbytes`` (array, 0..7) bytes, carrying across."""
    bits = nbytes.astype(np.uint64) * _U8
    back = np.uint64(63) - bits
    out = []
    for w in range(len(words)):
        new = words[w] >> bits
        if w + 1 < len(words):
            new |= (words[w + 1] << np.uint64(1)) << back   # << (64 − bits), safely
        out.append(new)
    return out


def _first_byte(flags) -> np.ndarray:
    """Return the index of the lowest byte with its top bit set in flags (words), or 99."""
    first = np.full(flags[0].shape, 99, dtype=np.int64)
    for w in range(len(flags) - 1, -1, -1):
        f = flags[w]
        # The lowest flag alone, 2^(8j+7), moved to 2^(8j); times bytes (7, 6, …, 0) its
        # top byte is j.
        lowest = (f & (~f + np.uint64(1))) >> np.uint64(7)
        j = ((lowest * np.uint64(0x0001020304050607)) >> _U56).astype(np.int64)
        first = np.where(f != 0, 8 * w + j, first)
    return first


def _zero_bytes(word):
    """Return, per word, the top bit set in the lowest zero byte (and maybe above it)."""
    return (word - _ONES) & ~word & _HIGHS


def _eight_digits(x):
    """Return the value of eight digit bytes (0..9 each, first byte most significant)."""
    x = (x * np.uint64(10) + (x >> np.uint64(8))) & np.uint64(0x00FF00FF00FF00FF)
    x = (x * np.uint64(100) + (x >> np.uint64(16))) & np.uint64(0x0000FFFF0000FFFF)
    return (x * np.uint64(10000) + (x >> np.uint64(32))) & np.uint64(0xFFFFFFFF)


def _parse_fields(u64: np.ndarray, starts: np.ndarray, lengths: np.ndarray, T: _Tables):
    """
    Return (values, ok) for the fields at ``starts`` with ``lengths`` (1..24 bytes).

    ``ok`` is False where this reader cannot vouch for the value (an exponent, too
    many digits, a near-tie in the rounding, stray characters): parse those again.
    """
    n = lengths
    words = [u64[starts + 8 * w] & T.low[w].take(n) for w in range(3)]
    first = words[0] & np.uint64(0xFF)
    neg = first == ord('-')
    signed = neg | (first == ord('+'))
    if signed.any():
        words = _shift_down(words, signed)
        n = n - signed
    # Anything but digits and one '.' (an exponent, a second sign) goes to float().
    dot_flags = [_zero_bytes(w ^ np.uint64(0x2E2E2E2E2E2E2E2E)) for w in words]
    dot = np.minimum(_first_byte(dot_flags), n)            # n: no '.'
    has_dot = dot < n
    # Delete the '.': the bytes above it move down by one.
    low = [T.low[w].take(dot) for w in range(3)]
    high = [words[w] & ~T.low[w].take(dot + 1) for w in range(3)]
    words = [(words[w] & low[w]) | (high[w] >> _U8) | (
        (high[w + 1] << _U56) if w < 2 else np.uint64(0)) for w in range(3)]
    nd = n - has_dot                                       # digit count
    x = [(words[w] ^ _ASCII_ZEROS) & T.low[w].take(nd) for w in range(3)]
    ok = nd >= 1
    for w in range(3):                                     # every byte a digit 0..9
        ok &= ((x[w] | (x[w] + np.uint64(0x7676767676767676))) & _HIGHS) == 0
    # Right-align the digits in 24 bytes (leading zero digits fill the gap).
    gap = np.clip(_LONGEST_FIELD - nd, 0, _LONGEST_FIELD - 1)
    x = _shift_up(x, gap % 8)
    move = gap // 8
    x = [np.where(move == 0, x[2], np.where(move == 1, x[1], x[0])),
         np.where(move == 0, x[1], np.where(move == 1, x[0], 0)),
         np.where(move == 0, x[0], 0)]
    x = [x[2], x[1], x[0]]                                 # word 0: the top digits
    v0, v1, v2 = (_eight_digits(w).astype(np.int64) for w in x)
    ok &= v0 < 90                                          # at most ~18 digits
    D = v0 * 10 ** 16 + v1 * 10 ** 8 + v2
    q = -(n - dot - 1) * has_dot                           # digits after the '.'
    return _to_double(D, q, neg, ok, T)


def _to_double(D: np.ndarray, q: np.ndarray, neg: np.ndarray, ok: np.ndarray, T: _Tables):
    """
    Return (D·10^q correctly rounded, with the sign, ok) for 0 <= D < 10^18, |q| <= 24.

    The product is a double-double; where it falls too close to a half-way point
    between two doubles to round with certainty, ``ok`` is cleared.
    """
    d_hi = D.astype(np.float64)
    d_lo = (D - d_hi.astype(np.int64)).astype(np.float64)  # exact: |d_lo| <= 64
    i = q - _K_MIN
    ph = T.p_hi[i]
    p = d_hi * ph
    c = _SPLIT * d_hi
    dh = c - (c - d_hi)
    dl = d_hi - dh
    bh, bl = T.p_hh[i], T.p_hl[i]
    low = ((((dh * bh - p) + dh * bl) + dl * bh) + dl * bl) + (d_hi * T.p_lo[i] + d_lo * ph)
    s = p + low
    t = low - (s - p)                                      # s + t = p + low exactly
    # s rounds the exact value correctly unless that is within rounding of a half-way
    # point: half a gap away (a quarter of the gap above, just below a power of two).
    bits = s.view(np.uint64)
    biased = (bits >> np.uint64(52)).astype(np.int64)
    half_gap = ((np.maximum(biased, 54) - 53).astype(np.uint64) << np.uint64(52)).view(
        np.float64)
    below_power = (t < 0.0) & ((bits << np.uint64(12)) == 0)
    half_gap = half_gap - 0.5 * half_gap * below_power
    ok = ok & ((np.abs(t) < half_gap * (1.0 - _EPS)) | (D == 0))
    return np.where(neg, -s, s), ok


class Fields(NamedTuple):
    """Where the fields of a CSV body are: byte offsets, one row per CSV row."""

    starts: np.ndarray
    """(rows, ncols) offset of every field."""
    ends: np.ndarray
    """(rows, ncols) offset just past every field."""


def split_fields(body: bytes, ncols: int) -> Optional[Fields]:
    """
    Return where the fields of ``body`` are, or None unless it is plain.

    Plain: rows of exactly ``ncols`` comma-separated fields, each row ending in a newline
    (none after the last), no quotes. Anything else (quoted fields, blank lines, a
    wrong field count) is None: read it with the csv module instead.
    """
    if not body:
        return Fields(np.empty((0, ncols), dtype=np.int64), np.empty((0, ncols), np.int64))
    buf = np.frombuffer(body, dtype=np.uint8)
    separators = np.flatnonzero((buf == ord(',')) | (buf == ord('\n')))
    if (separators.size + 1) % ncols or body.find(b'"') >= 0:
        return None
    rows = (separators.size + 1) // ncols
    newlines = np.flatnonzero(buf[separators] == ord('\n'))
    if not np.array_equal(newlines, np.arange(ncols - 1, separators.size, ncols)):
        return None
    starts = np.empty(separators.size + 1, dtype=np.int64)
    starts[0] = 0
    starts[1:] = separators + 1
    ends = np.empty_like(starts)
    ends[:-1] = separators
    ends[-1] = buf.shape[0]
    return Fields(starts.reshape(rows, ncols), ends.reshape(rows, ncols))


def parse_numbers(body: bytes, starts: np.ndarray, ends: np.ndarray) -> Optional[np.ndarray]:
    """
    Return the decimal numbers in the fields body[starts:ends] (any shape), or None.

    Each is converted exactly as ``float()`` would. None: a field is empty or not a
    plain decimal number (spaces, '_', 'nan', ...); read those carefully.
    """
    shape = starts.shape
    starts, ends = starts.reshape(-1), ends.reshape(-1)
    if not starts.size:
        return np.empty(shape)
    lengths = ends - starts
    if lengths.min() < 1:
        return None                                        # an empty cell
    T = _tables()
    L = len(body)
    padded = np.zeros(L + 32, dtype=np.uint8)
    padded[:L] = np.frombuffer(body, dtype=np.uint8)
    u64 = np.ndarray(shape=(L + 25,), dtype='<u8', buffer=padded, strides=(1,))
    values = np.empty(starts.shape[0])
    ok = np.empty(starts.shape[0], dtype=bool)
    for b in range(0, starts.shape[0], BLOCK_FIELDS):
        n = lengths[b:b + BLOCK_FIELDS]
        values[b:b + BLOCK_FIELDS], ok[b:b + BLOCK_FIELDS] = _parse_fields(
            u64, starts[b:b + BLOCK_FIELDS], np.minimum(n, _LONGEST_FIELD), T)
        ok[b:b + BLOCK_FIELDS] &= n <= _LONGEST_FIELD
    plain = _allowed_bytes()
    for f in np.flatnonzero(~ok):                          # exponents, ties, oddities
        text = body[starts[f]:ends[f]]
        if not plain[np.frombuffer(text, dtype=np.uint8)].all():
            return None                                    # e.g. spaces, '_', 'inf'
        try:
            values[f] = float(text)
        except ValueError:
            return None
    return values.reshape(shape)


def parse_rows(body: bytes, ncols: int, columns: Optional[Sequence[int]] = None
               ) -> Optional[np.ndarray]:
    """
    Return the numbers of a plain CSV body (no header) as (rows, len(columns)), or None.

    ``columns`` (default all) are converted, each exactly as ``float()`` would; see
    :func:`split_fields` and :func:`parse_numbers` for what None means.
    """
    fields = split_fields(body, ncols)
    if fields is None:
        return None
    columns = list(range(ncols)) if columns is None else list(columns)
    return parse_numbers(body, fields.starts[:, columns], fields.ends[:, columns])


def parse_labels(body: bytes, starts: np.ndarray, ends: np.ndarray):
    """
    Return (codes (N,), labels) for text fields: row i holds ``labels[codes[i]]``.

    Labels are sorted; None when a field is empty or has surrounding whitespace or
    non-ASCII bytes (read those carefully).
    """
    N = starts.shape[0]
    if N == 0:
        return np.empty(0, dtype=np.int64), []
    lengths = ends - starts
    width = int(lengths.max())
    if lengths.min() < 1:
        return None
    buf = np.frombuffer(body, dtype=np.uint8)
    index = starts[:, None] + np.arange(width)
    inside = np.arange(width) < lengths[:, None]
    cells = np.where(inside, buf[np.minimum(index, len(body) - 1)], 0).astype(np.uint8)
    first = cells[:, 0]
    last = cells[np.arange(N), lengths - 1]
    blank = b' \t'
    if (np.isin(first, list(blank)).any() or np.isin(last, list(blank)).any()
            or (cells >= 0x80).any()):
        return None
    if width <= 8:
        # Short labels as big-endian integers: numeric order is text order.
        padded = np.zeros((N, 8), dtype=np.uint8)
        padded[:, :width] = cells
        keys, codes = np.unique(padded.view('>u8').reshape(-1).astype(np.uint64),
                                return_inverse=True)
        labels = [int(k).to_bytes(8, 'big').rstrip(b'\0').decode('ascii') for k in keys]
        return codes.reshape(-1).astype(np.int64), labels
    keys = np.ascontiguousarray(cells).view(f'S{width}').reshape(-1)
    labels, codes = np.unique(keys, return_inverse=True)
    return codes.reshape(-1).astype(np.int64), [label.decode('ascii') for label in labels]
