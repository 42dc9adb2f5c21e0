"""
Doubles to CSV text, exactly as ``repr`` writes them, vectorised (see :mod:`.csvio`).

Per number: one double-double product a·10^k gives 17 correctly rounded digits; the
same arithmetic tells whether 15 or 16 of them already read back (the shortest form);
the text is assembled in 64-bit words (eight characters at a time) and the unused
bytes are squeezed out at the end. Undecidable ties, non-finite values and magnitudes
beyond 1e±280 are formatted by ``repr`` itself.
"""

from typing import List, Optional, Sequence

from kf_train.io.csv_tables import (
    _E_MAX, _E_MIN, _EPS, _K_MIN, _SPLIT, _Tables, _tables, _U56, _U8, _ZERO)
import numpy as np

# Rows formatted per block: small enough for the work arrays to stay in cache.
BLOCK_ROWS = 2048


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


def format_labels(labels: Sequence[str], separator: str = ',') -> np.ndarray:
    """Return each label and the separator as zero-padded uint64 words (K, W)."""
    texts = [(label + separator).encode('utf-8') for label in labels]
    W = max([(len(t) + 7) // 8 for t in texts] + [1])
    out = np.zeros((len(texts), W), dtype=np.uint64)
    for k, text in enumerate(texts):
        out[k] = np.frombuffer(text.ljust(8 * W, b'\0'), dtype='<u8')
    return out
