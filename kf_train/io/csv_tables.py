"""
The CSV codec's shared arithmetic: powers of ten as double-doubles, byte tables.

Both directions scale by 10^k with one double-double product (Dekker's split) and
assemble or take apart text eight bytes at a time in uint64 words; the tables they
share are built once, on first use (:func:`_tables`). Private to
:mod:`kf_train.io`: :mod:`~kf_train.io.csv_format` and :mod:`~kf_train.io.csv_parse`
import them.
"""

import functools
from typing import NamedTuple

import numpy as np

# Powers 10^k in the double-double table.
_K_MIN, _K_MAX = -300, 300
# Biased binary exponents the vectorised formatter handles: 2^-930 .. 2^930, about
# 1e±280, so that the products a·10^k and their Dekker splits never overflow.
_E_MIN, _E_MAX = 1023 - 930, 1023 + 929
# A rounding or round-trip decision closer than this (relative) to its boundary is
# left to repr: the double-double products are good to ~1e-14 absolute on ~1e17.
_EPS = 1e-9
# Dekker's splitting constant, 2^27 + 1.
_SPLIT = 134217729.0
_U8 = np.uint64(8)
_U56 = np.uint64(56)
_ZERO, _DOT, _MINUS = (ord(c) for c in '0.-')


class _Tables(NamedTuple):
    """Lookup tables, built on first use."""

    p_hi: np.ndarray
    """10^k rounded to a double, k = _K_MIN.._K_MAX."""
    p_lo: np.ndarray
    """10^k − p_hi, rounded."""
    p_hh: np.ndarray
    """Dekker's split of p_hi: high half."""
    p_hl: np.ndarray
    """Dekker's split of p_hi: low half."""
    e10: np.ndarray
    """floor(log10(2^(E−1023))) for every biased exponent E."""
    next10: np.ndarray
    """10^(e10[E] + 1) rounded to a double."""
    half_gap: np.ndarray
    """2^(E−1023−53): half the spacing of the doubles with biased exponent E."""
    four: np.ndarray
    """'0000'..'9999' as little-endian uint64 (four bytes used)."""
    trailing: np.ndarray
    """Trailing zero digits of 0..9999 as four digits (4 for 0)."""
    low: np.ndarray
    """low[w, n]: the bytes of word w below global byte n, as a mask (n = 0..32)."""
    dot: np.ndarray
    """dot[w, n]: '.' at global byte n, in word w."""
    separator: np.ndarray
    """separator[w, 33·s + n]: ',' (s = 0) or '\\n' (s = 1) at global byte n, in word w."""
    prefix: np.ndarray
    """prefix[neg + 2·lead]: '-'·neg, then for lead > 0 '0.' + '0'·(lead − 1): word 0."""
    suffix: np.ndarray
    """'e±XX[X]' for decimal exponents −400..400, as uint64; then an empty one."""
    suffix_len: np.ndarray
    """Length of each suffix."""


@functools.lru_cache(maxsize=1)
def _tables() -> _Tables:
    """Return the lookup tables."""
    ks = range(_K_MIN, _K_MAX + 1)
    hi, lo = np.empty(len(ks)), np.empty(len(ks))
    for i, k in enumerate(ks):
        # Integer arithmetic: int -> float and int / int round correctly.
        if k >= 0:
            power = 10 ** k
            hi[i] = float(power)
            lo[i] = float(power - int(hi[i]))
        else:
            power = 10 ** -k
            hi[i] = 1 / power
            num, den = float(hi[i]).as_integer_ratio()     # hi = num/den
            lo[i] = (den - num * power) / (power * den)     # 10^k − hi
    c = _SPLIT * hi
    hh = c - (c - hi)                               # 26 + 27 bits: exact products
    biased = np.arange(2048)
    e2 = biased - 1023
    e10 = (e2 * 78913) >> 18                        # floor(e2·log10 2), exact here
    next10 = hi[np.clip(e10 + 1, _K_MIN, _K_MAX) - _K_MIN]
    half_gap = np.ldexp(1.0, np.clip(e2 - 53, -1074, 1023).astype(np.int32))
    i = np.arange(10000)
    four = sum((_ZERO + (i // 10 ** (3 - j)) % 10) << (8 * j) for j in range(4)).astype(
        np.uint64)
    trailing = sum((i % 10 ** j == 0).astype(np.int64) for j in range(1, 5))
    low = np.zeros((4, 33), dtype=np.uint64)
    dot = np.zeros((4, 33), dtype=np.uint64)
    separator = np.zeros((4, 2, 33), dtype=np.uint64)
    for n in range(33):
        for w in range(4):
            below = min(max(n - 8 * w, 0), 8)
            low[w, n] = (1 << (8 * below)) - 1
            if 0 <= n - 8 * w < 8:
                dot[w, n] = _DOT << (8 * (n - 8 * w))
                separator[w, 0, n] = ord(',') << (8 * (n - 8 * w))
                separator[w, 1, n] = ord('\n') << (8 * (n - 8 * w))
    prefix = np.zeros(10, dtype=np.uint64)
    for neg in range(2):
        for lead in range(5):
            text = '-' * neg + ('0.' + '0' * (lead - 1) if lead else '')
            prefix[neg + 2 * lead] = int.from_bytes(text.encode('ascii'), 'little')
    exponents = range(-400, 401)
    texts = [f'e{x:+03d}'.encode('ascii') for x in exponents] + [b'']
    suffix = np.array([int.from_bytes(t, 'little') for t in texts], dtype=np.uint64)
    suffix_len = np.array([len(t) for t in texts], dtype=np.int64)
    return _Tables(hi, lo, hh, hi - hh, e10, next10, half_gap, four, trailing, low, dot,
                   separator.reshape(4, 66), prefix, suffix, suffix_len)
