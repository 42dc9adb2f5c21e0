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

Nothing here raises on bad text: None means "read it the careful way".
"""

import functools
from typing import List, NamedTuple, Optional, Sequence

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
# Rows formatted per block: small enough for the work arrays to stay in cache.
BLOCK_ROWS = 2048
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


def _scaled(a: np.ndarray, e10: np.ndarray, T: _Tables):
    """Return a·10^(16−e10) as (D, r, H): nearest integer, remainder, half-gap scaled."""
    i = (16 - _K_MIN) - e10
    ph = T.p_hi.take(i)
    bh = T.p_hh.take(i)
    bl = T.p_hl.take(i)
    # Dekker: a·ph = p + err exactly; X = p + err + a·p_lo to ~2^-104 relative.
    p = a * ph
    c = _SPLIT * a
    ah = c - (c - a)
    al = a - ah
    e = ((((ah * bh - p) + ah * bl) + al * bh) + al * bl) + a * T.p_lo.take(i)
    # X >= 1e16 > 2^53, so p is an integer: D = p + rint(e), r = X − D exactly enough.
    re = np.rint(e)
    D = p.astype(np.int64) + re.astype(np.int64)
    return D, e - re, ph


def _shortest(a: np.ndarray, biased: np.ndarray, power_of_two: np.ndarray, T: _Tables):
    """
    Return (digits, e10, undecided) for positive doubles a with biased exponents in range.

    ``digits`` (int64, 10^16..10^17−1) are the shortest digits that read back to a,
    padded with zeros to 17: a ≈ digits·10^(e10−16). ``undecided`` marks numbers whose
    rounding or round-trip test falls too close to its boundary to call here.
    """
    e10 = T.e10.take(biased) + (a >= T.next10.take(biased))  # floor(log10 a) but slivers
    D, r, ph = _scaled(a, e10, T)
    for _ in range(3):                             # the slivers: fix e10, recompute
        off = np.flatnonzero((D < 10 ** 16) | (D >= 10 ** 17))
        if not off.size:
            break
        e10[off] += np.where(D[off] >= 10 ** 17, 1, -1)
        D[off], r[off], ph[off] = _scaled(a[off], e10[off], T)
    H = T.half_gap.take(biased) * ph               # half the gap to the next double
    # Round X to 16 and 15 digits: X/10 = q + f with f = (X mod 10)/10.
    q = D // 10
    f = ((D - 10 * q) + r) / 10.0
    up = f > 0.5
    D16 = q + up
    r16 = f - up
    q = D16 // 10
    f = ((D16 - 10 * q) + r16) / 10.0
    up = f > 0.5
    D15 = q + up
    r15 = f - up
    # A decimal reads back iff it is within half a gap of a (the gap below a power of
    # two is half as wide).
    H16 = H / 10.0
    H15 = H / 100.0
    p = np.flatnonzero(power_of_two)
    close_call = []
    for D_, r_, H_ in ((D16, r16, H16), (D15, r15, H15)):
        if not p.size:
            break
        # Below a power of two the gap is half as wide: when the nearest candidate is
        # below and out of reach, the next one up may still read back.
        r_p, H_p = r_[p], H_[p]
        switch = (r_p > 0.0) & (r_p >= 0.5 * H_p) & (1.0 - r_p < H_p)
        close_call.append(p[np.abs(r_p - 0.5 * H_p) < _EPS * H_p])
        D_[p[switch]] += 1
        r_[p[switch]] -= 1.0
        H_[p] *= np.where(r_[p] > 0.0, 0.5, 1.0)
    m15 = np.abs(r15) - H15
    m16 = np.abs(r16) - H16
    use15 = m15 < 0.0
    use16 = m16 < 0.0
    use16 &= ~use15
    # Too close to call: a round-trip margin within rounding, or a tie between two
    # nearest candidates (|r| ~ 0.5) in the last digit kept. 17 digits always read back.
    undecided = np.abs(m15) < _EPS * H15
    undecided |= (np.abs(m16) < _EPS * H16) & ~use15
    undecided |= (np.abs(r16) > 0.5 - _EPS) & use16
    undecided |= (np.abs(r) > 0.5 - _EPS) & ~use15 & ~use16
    for rows in close_call:
        undecided[rows] = True
    digits = D + use16 * (10 * D16 - D) + use15 * (100 * D15 - D)
    carry = np.flatnonzero(digits >= 10 ** 17)     # …999.7 rounded up to 10…0
    if carry.size:
        digits[carry] //= 10
        e10[carry] += 1
    return digits, e10, undecided


def _digit_words(D: np.ndarray, offset: np.ndarray, T: _Tables):
    """
    Return the 17 digits of D (10^16 <= D < 10^17, or 0) as three words, and their count.

    The digits start at byte ``offset`` (0..6, an array); the bytes below are zero.
    """
    top = D // 10 ** 16
    rest = D - top * 10 ** 16
    mid = rest // 10 ** 8
    lo = rest - mid * 10 ** 8
    a = mid // 10000
    b = mid - a * 10000
    c = lo // 10000
    d = lo - c * 10000
    wm = T.four.take(a) | (T.four.take(b) << np.uint64(32))  # digits 1..8
    wl = T.four.take(c) | (T.four.take(d) << np.uint64(32))  # digits 9..16
    bits = offset.astype(np.uint64) << np.uint64(3)
    s0 = ((top.astype(np.uint64) + np.uint64(_ZERO)) << bits) | (wm << (bits + _U8))
    back = _U56 - bits
    s1 = (wm >> back) | (wl << (bits + _U8))
    s2 = wl >> back
    # Significant digits: 17 less the trailing zeros (four per zero group of four).
    nd = 17 - T.trailing.take(d)
    nd -= T.trailing.take(c) * (d == 0)
    zeros = np.flatnonzero(lo == 0)
    if zeros.size:
        nd[zeros] -= T.trailing[b[zeros]] + T.trailing[a[zeros]] * (b[zeros] == 0)
        nd[zeros] = np.maximum(nd[zeros], 1)
    return [s0, s1, s2], nd


def _insert(words, at: np.ndarray, T: _Tables, code: np.ndarray):
    """Return the words with byte ``code`` (from table ``code[w, n]``) inserted at ``at``."""
    out, carry = [], None
    for w, word in enumerate(words):
        low = T.low[w].take(at)
        high = word & ~low
        new = (word & low) | (high << _U8) | code[w].take(at)
        if carry is not None:
            new |= carry >> _U56
        carry = high
        out.append(new)
    return out


def _format_block(v: np.ndarray, newline: np.ndarray) -> np.ndarray:
    """
    Return every value's repr and its separator (',' or, where ``newline``, a newline).

    The result is (M, W) uint64 words of text, W = 3 or 4: the bytes of row m, zero
    bytes removed, are repr(v[m]) followed by the separator.
    """
    T = _tables()
    M = v.shape[0]
    bits = v.view(np.uint64)
    neg = (bits >> np.uint64(63)).astype(np.int64)
    biased = ((bits >> np.uint64(52)) & np.uint64(0x7FF)).astype(np.int64)
    fast = (biased >= _E_MIN) & (biased <= _E_MAX)
    a = np.abs(v)
    everything_fast = bool(fast.all())
    if not everything_fast:                        # keep the arithmetic benign
        a = np.where(fast, a, 1.0)
        biased = np.where(fast, biased, 1023)
    D, e10, slow = _shortest(a, biased, (bits << np.uint64(12)) == 0, T)
    if not everything_fast:
        zero = v == 0.0
        D[zero] = 0
        e10[zero] = 0
        slow = (slow & fast) | ~(fast | zero)
    # Fixed notation ('123.45', '0.00012') for 1e-4 <= a < 1e16, else '1.2345e-05'.
    fixed = (e10 >= -4) & (e10 <= 15)
    small = fixed & (e10 < 0)                       # '0.' + (lead − 1) zeros + digits
    lead = small * -e10
    # The digits start after the sign (and after '0.000' for small numbers) ...
    words, nd = _digit_words(D, neg + small * (1 + lead), T)
    # ... and a '.' goes in after the integer digits (after the first, in '1.5e-07').
    dot = np.maximum(e10, 0)
    dot *= fixed
    dot += 1 + neg
    dot[small] = 24                                 # none: the prefix holds it
    words = _insert(words, dot, T, T.dot)
    words[0] |= T.prefix.take(neg + 2 * lead)       # '-', '0.', '-0.000', ...
    length = np.where(fixed, np.maximum(nd + 1 + neg, dot + 2), nd + (nd > 1) + neg)
    length[small] = (1 + neg + nd + lead)[small]
    keep = [T.low[w].take(length) for w in range(3)]
    words = [words[w] & keep[w] for w in range(3)]
    sci = ~fixed & ~slow
    if sci.any():                                   # 'e±XX' after the digits
        exponent = np.where(sci, np.clip(e10, -400, 400) + 400, T.suffix.shape[0] - 1)
        tail = T.suffix.take(exponent)              # 0 for the others
        shift = (length & 7).astype(np.uint64) * _U8
        word = length >> 3
        spill = (tail >> np.uint64(1)) >> (np.uint64(63) - shift)
        tail <<= shift
        for w in range(3):
            words[w] |= tail * (word == w)
            if w:
                words[w] |= spill * (word == w - 1)
        length += T.suffix_len.take(exponent)
    at = length + 33 * newline
    wide = bool(length.max(initial=0) >= 24)
    out = np.empty((M, 4 if wide else 3), dtype=np.uint64)
    for w in range(3):
        out[:, w] = (words[w] & T.low[w].take(length)) | T.separator[w].take(at)
    if wide:
        out[:, 3] = T.separator[3].take(at)
    for m in np.flatnonzero(slow):                  # NaN, inf, extremes, ties: repr
        text = (repr(float(v[m])) + ('\n' if newline[m] else ',')).encode('ascii')
        if len(text) > 8 * out.shape[1]:
            out = np.concatenate([out, np.zeros((M, 1), dtype=np.uint64)], axis=1)
        out[m] = np.frombuffer(text.ljust(8 * out.shape[1], b'\0'), dtype='<u8')
    return out


def _squeeze(words: np.ndarray) -> bytes:
    """Return the text in words, zero bytes removed."""
    return words.tobytes().translate(None, b'\0')


def format_values(values) -> List[str]:
    """Return repr() of every double in ``values``, computed vectorised (for tests)."""
    v = np.array(values, dtype=np.float64).reshape(-1)
    text = _squeeze(_format_block(v, np.ones(v.shape, dtype=bool)))
    return text.decode('ascii').split('\n')[:-1]


def format_rows(columns: Sequence[np.ndarray], start: int = 0, stop: Optional[int] = None,
                prefix=None) -> bytes:
    """
    Return rows [start, stop) of the columns as CSV text: repr() numbers, newline ends.

    ``prefix`` = (words, codes) puts ``words[codes[row]]`` (from :func:`format_labels`)
    in front of every row: a text column such as an id.
    """
    columns = [np.asarray(column, dtype=np.float64) for column in columns]
    lengths = {column.shape for column in columns}
    if len(lengths) > 1 or any(len(shape) != 1 for shape in lengths):
        raise ValueError(f'columns must be vectors of one length, got shapes '
                         f'{[column.shape for column in columns]}')
    stop = (len(columns[0]) if columns else 0) if stop is None else stop
    R, C = max(stop - start, 0), len(columns)
    if R == 0 or C == 0:
        return b''
    table = np.empty((R, C))
    for j, column in enumerate(columns):
        table[:, j] = column[start:stop]
    newline = np.zeros((R, C), dtype=bool)
    newline[:, -1] = True
    words = _format_block(table.reshape(-1), newline.reshape(-1)).reshape(R, -1)
    if prefix is not None:
        label_words, codes = prefix
        words = np.concatenate([label_words[codes[start:stop]], words], axis=1)
    return _squeeze(words)


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------

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


def format_labels(labels: Sequence[str], separator: str = ',') -> np.ndarray:
    """Return each label and the separator as zero-padded uint64 words (K, W)."""
    texts = [(label + separator).encode('utf-8') for label in labels]
    W = max([(len(t) + 7) // 8 for t in texts] + [1])
    out = np.zeros((len(texts), W), dtype=np.uint64)
    for k, text in enumerate(texts):
        out[k] = np.frombuffer(text.ljust(8 * W, b'\0'), dtype='<u8')
    return out
