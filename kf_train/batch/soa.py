"""
Stacks of small matrices as structures of arrays, and the Kalman steps written with them.

A stack of N (a, b) matrices is held as nested lists [[entry]] where each entry is
either an array (N,) (contiguous, fast to combine) or a Python float, the same for
every row. Constant zeros and ones are skipped, so a product with H = [1, 0] or
F = [[1, dt], [0, 1]] costs only its non-trivial terms. The 1x1 and 2x2 inverses are
written out (:func:`soa_inv`). These hand-written helpers live here only; the
vectorised series (:mod:`~kf_train.batch.linear`) and the bank
(:mod:`~kf_train.batch.bank`) both use them.
"""

import numpy as np


def is_const(e) -> bool:
    """Return whether an entry is a constant (a Python float)."""
    return isinstance(e, float)


def entry_mul(a, b):
    """Return a·b, skipping constant zeros and ones."""
    if is_const(a):
        if a == 0.0:
            return 0.0
        if a == 1.0:
            return b
    if is_const(b):
        if b == 0.0:
            return 0.0
        if b == 1.0:
            return a
    return a * b


def entry_add(a, b):
    """Return a + b, skipping constant zeros."""
    if is_const(a) and a == 0.0:
        return b
    if is_const(b) and b == 0.0:
        return a
    return a + b


def entry_sub(a, b):
    """Return a − b, skipping constant zeros."""
    if is_const(b) and b == 0.0:
        return a
    return a - b


def soa_const(M) -> list:
    """Return a constant matrix as nested lists of floats."""
    M = np.asarray(M, dtype=float)
    return [[float(v) for v in row] for row in M]


def soa_stack(S: np.ndarray) -> list:
    """Return a stack (N, a, b) as nested lists of contiguous (N,) arrays."""
    return [[np.ascontiguousarray(S[:, i, j]) for j in range(S.shape[2])]
            for i in range(S.shape[1])]


def soa_select(M_u: np.ndarray, inv: np.ndarray) -> list:
    """Return per-row matrices M_u[inv]: constants when every row has the same one."""
    if M_u.shape[0] == 1:
        return soa_const(M_u[0])
    return [[M_u[:, i, j][inv] for j in range(M_u.shape[2])] for i in range(M_u.shape[1])]


def soa_to_stack(A: list, N: int) -> np.ndarray:
    """Return nested-list matrices as a stack (N, a, b)."""
    if all(is_const(e) for row in A for e in row):
        return np.broadcast_to(np.array(A), (N, len(A), len(A[0])))  # read-only view
    return np.stack([np.broadcast_to(e, (N,)) for row in A for e in row], axis=-1).reshape(
        N, len(A), len(A[0]))


def soa_vector_to_stack(v: list, N: int) -> np.ndarray:
    """Return a nested-list vector as an array (N, a)."""
    out = np.empty((N, len(v)))
    for i, e in enumerate(v):
        out[:, i] = e
    return out


def soa_mm(A: list, B: list) -> list:
    """Return A @ B."""
    out = []
    for row in A:
        out_row = []
        for j in range(len(B[0])):
            acc = 0.0
            for k, a in enumerate(row):
                acc = entry_add(acc, entry_mul(a, B[k][j]))
            out_row.append(acc)
        out.append(out_row)
    return out


def soa_mv(A: list, v: list) -> list:
    """Return A @ v for a nested-list vector v."""
    out = []
    for row in A:
        acc = 0.0
        for a, e in zip(row, v):
            acc = entry_add(acc, entry_mul(a, e))
        out.append(acc)
    return out


def soa_t(A: list) -> list:
    """Return Aᵀ."""
    return [list(col) for col in zip(*A)]


def soa_madd(A: list, B: list) -> list:
    """Return A + B."""
    return [[entry_add(a, b) for a, b in zip(ra, rb)] for ra, rb in zip(A, B)]


def soa_msub(A: list, B: list) -> list:
    """Return A − B."""
    return [[entry_sub(a, b) for a, b in zip(ra, rb)] for ra, rb in zip(A, B)]


def soa_sym(A: list) -> list:
    """Return (A + Aᵀ) / 2, exactly symmetric."""
    n = len(A)
    out = [[None] * n for _ in range(n)]
    for i in range(n):
        out[i][i] = A[i][i]
        for j in range(i + 1, n):
            e = entry_add(A[i][j], A[j][i])
            e = 0.5 * e
            out[i][j] = out[j][i] = e
    return out


def soa_inv(A: list, N: int) -> list:
    """Return A⁻¹ (closed forms for 1x1 and 2x2)."""
    n = len(A)
    if n == 1:
        return [[1.0 / A[0][0]]]
    if n == 2:
        (a, b), (c, d) = A
        det = entry_sub(entry_mul(a, d), entry_mul(b, c))
        inv_det = 1.0 / det
        return [[entry_mul(d, inv_det), entry_mul(-b, inv_det)],
                [entry_mul(-c, inv_det), entry_mul(a, inv_det)]]
    return soa_stack(np.linalg.inv(soa_to_stack(A, N)))


def soa_prior_covariance(F: list, P: list, Q: list) -> list:
    """Return P⁻ = F P Fᵀ + Q, exactly symmetric."""
    return soa_sym(soa_madd(soa_mm(soa_mm(F, P), soa_t(F)), Q))


def soa_gain(P_prior: list, H: list, R: list, N: int) -> list:
    """Return the Kalman gain K = P⁻ Hᵀ S⁻¹ with S = H P⁻ Hᵀ + R (exactly symmetric)."""
    return soa_gain_terms(P_prior, H, R, N)[0]


def soa_gain_terms(P_prior: list, H: list, R: list, N: int) -> tuple:
    """Return (K, S, S⁻¹): the Kalman gain and the innovation covariance it inverts."""
    PHt = soa_mm(P_prior, soa_t(H))
    S = soa_sym(soa_madd(soa_mm(H, PHt), R))           # S = H P⁻ Hᵀ + R
    S_inv = soa_inv(S, N)
    return soa_mm(PHt, S_inv), S, S_inv                # K = P⁻ Hᵀ S⁻¹


def soa_nis(y: list, S: list, S_inv: list):
    """
    Return the NIS yᵀ S⁻¹ y of innovations ``y`` (a nested-list vector).

    A scalar measurement takes y² / s, the formula of :func:`kf_train.filters.kalman.update`
    (the streaming estimator's), so both round alike.
    """
    if len(y) == 1:
        return entry_mul(y[0], y[0]) / S[0][0]          # NIS = y² / s
    total = 0.0
    for i, row in enumerate(S_inv):
        total = entry_add(total, entry_mul(y[i], soa_mv([row], y)[0]))  # yᵢ (S⁻¹ y)ᵢ
    return total
