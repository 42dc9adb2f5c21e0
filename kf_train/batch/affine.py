"""
Affine recursions x_k = A_k x_{k−1} + b_k for all rows at once, vectorised by chunks.

The rows are cut into chunks of about √(N/16); within each chunk the recursion runs
from a zero start for all chunks at once, and one short pass in plain floats carries
each chunk's true start state to the next. The vectorised series
(:mod:`~kf_train.batch.linear`) runs its means and, with Q = 0, its information
matrices through it; the RTS smoother (:mod:`~kf_train.batch.smoother`) its
backward pass.
"""

import math

from kf_train.batch.soa import is_const, soa_stack
import numpy as np


def _chunking(N: int):
    """Return (chunk length C, number of chunks): C ≈ √(N/16), the cheapest split here."""
    C = int(min(4096, max(16, math.isqrt(max(N, 1) // 16))))
    return C, -(-N // C)


def _chunked(e, N: int, C: int, nc: int):
    """Return entry e (N,) laid out as (C, nc): row j of chunk c at [j, c]."""
    if is_const(e):
        return e
    e = np.asarray(e, dtype=float)
    if e.shape[0] != C * nc:
        e = np.concatenate([e, np.repeat(e[-1:], C * nc - N)])  # padding, unused
    return np.ascontiguousarray(e.reshape(nc, C).T)


def _carry(M_last: list, y_last: list, x0: np.ndarray, nc: int) -> np.ndarray:
    """Return each chunk's start state: s_{c+1} = M_c s_c + y_c, in plain floats."""
    d = len(x0)
    if d == 2:
        return _carry_2(M_last, y_last, x0)
    if d == 4:
        return _carry_4(M_last, y_last, x0)
    starts = np.empty((nc, d))
    s = [float(v) for v in x0]
    for c in range(nc):
        starts[c] = s
        s = [sum(M_last[c][i][k] * s[k] for k in range(d)) + y_last[c][i] for i in range(d)]
    return starts


def _carry_2(M_last: list, y_last: list, x0: np.ndarray) -> np.ndarray:
    """
    _carry for two states, unrolled: the same operations in the same order.

    sum(M[i][k] * s[k] for k) + y[i] is ((0 + M[i][0] s0) + M[i][1] s1) + y[i], and
    0 + a is a exactly, so these bits are _carry's.
    """
    s0, s1 = float(x0[0]), float(x0[1])
    starts = []
    append = starts.append
    for ((m00, m01), (m10, m11)), (y0, y1) in zip(M_last, y_last):
        append((s0, s1))
        s0, s1 = m00 * s0 + m01 * s1 + y0, m10 * s0 + m11 * s1 + y1
    return np.array(starts, dtype=float).reshape(len(starts), 2)


def _carry_4(M_last: list, y_last: list, x0: np.ndarray) -> np.ndarray:
    """_carry for four states (a 2x2 information matrix), unrolled as _carry_2."""
    s0, s1, s2, s3 = (float(v) for v in x0)
    starts = []
    append = starts.append
    for (r0, r1, r2, r3), (y0, y1, y2, y3) in zip(M_last, y_last):
        append((s0, s1, s2, s3))
        s0, s1, s2, s3 = (r0[0] * s0 + r0[1] * s1 + r0[2] * s2 + r0[3] * s3 + y0,
                          r1[0] * s0 + r1[1] * s1 + r1[2] * s2 + r1[3] * s3 + y1,
                          r2[0] * s0 + r2[1] * s1 + r2[2] * s2 + r2[3] * s3 + y2,
                          r3[0] * s0 + r3[1] * s1 + r3[2] * s2 + r3[3] * s3 + y3)
    return np.array(starts, dtype=float).reshape(len(starts), 4)


def affine_recursion(A, b, x0) -> np.ndarray:
    """
    Return x (N, d) with x_k = A_k x_{k−1} + b_k, k = 0..N−1, from x_{−1} = x0.

    ``A`` is one (d, d) matrix for every row, a stack (N, d, d), or nested lists of
    entries (arrays (N,) or floats); ``b`` is (N, d) or a nested-list vector. The rows
    are cut into chunks; the recursion runs inside every chunk at once from a zero
    start, and one pass over the chunks carries the true start states.
    """
    if isinstance(b, np.ndarray):
        N, d = b.shape
        b = [b[:, i] for i in range(d)]
    else:
        d = len(b)
        N = next(e.shape[0] for e in b if not is_const(e))
    x0 = np.asarray(x0, dtype=float).reshape(d)
    if N == 0:
        return np.empty((0, d))
    C, nc = _chunking(N)
    bt = [np.broadcast_to(_chunked(e, N, C, nc), (C, nc)) for e in b]
    if isinstance(A, np.ndarray) and A.ndim == 2:
        return _constant_recursion(A, bt, x0, C, nc, d, N)
    if isinstance(A, np.ndarray):
        A = soa_stack(A)
    At = [[_chunked(e, N, C, nc) for e in row] for row in A]
    Ms = np.empty((d, d, C, nc))
    ys = np.empty((d, C, nc))
    rng = range(d)
    M = [[(e if is_const(e) else e[0]) for e in row] for row in At]
    y = [bt[i][0] for i in rng]
    for j in range(C):
        if j:
            Aj = [[(e if is_const(e) else e[j]) for e in row] for row in At]
            # M_j = A_j M_{j−1};  y_j = A_j y_{j−1} + b_j
            M = [[sum(Aj[i][k] * M[k][c] for k in rng) for c in rng] for i in rng]
            y = [sum(Aj[i][k] * y[k] for k in rng) + bt[i][j] for i in rng]
        for i in rng:
            ys[i, j] = y[i]
            for k in rng:
                Ms[i, k, j] = M[i][k]
    M_last = Ms[:, :, -1, :].transpose(2, 0, 1).tolist()
    starts = _carry(M_last, ys[:, -1, :].T.tolist(), x0, nc)
    x = np.empty((nc, C, d))
    for i in rng:
        acc = ys[i]
        for k in rng:
            acc = acc + Ms[i, k] * starts[:, k]
        x[:, :, i] = acc.T
    return x.reshape(C * nc, d)[:N]


def _constant_recursion(A: np.ndarray, bt: list, x0: np.ndarray, C: int, nc: int, d: int,
                        N: int) -> np.ndarray:
    """affine_recursion for one A (d, d) for every row: powers of A, one matmul per row."""
    bs = np.stack(bt, axis=1)  # (C, d, nc)
    ys = np.empty((C, d, nc))  # response to b from a zero start, per chunk
    y = bs[0]
    ys[0] = y
    for j in range(1, C):
        y = A @ y + bs[j]
        ys[j] = y
    Ms = np.empty((C, d, d))   # M_j = A^(j+1): chunk start -> row j
    M = A
    for j in range(C):
        Ms[j] = M
        M = A @ M
    M_last = [Ms[-1].tolist()] * nc
    starts = _carry(M_last, ys[-1].T.tolist(), x0, nc)
    x = np.matmul(Ms, starts.T)  # (C, d, nc): M_j s_c for every chunk c
    x += ys
    return x.transpose(2, 0, 1).reshape(C * nc, d)[:N]
