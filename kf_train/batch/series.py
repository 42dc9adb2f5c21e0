"""
Run a preset over a whole time series: a generic loop and a vectorised fast path.

Both take times ``t_s`` (N,), measurements ``z`` (N, m) and, when the preset has a
control input, ``u`` (N, p), where row k's control acts over the interval that ends
at ``t_s[k]``. The initial estimate holds at ``t0_s``; each row is predicted to from
the previous time and then corrected, exactly as the seeds do.

Times are rounded to whole nanoseconds first (as ROS stamps are), so that a sampling
period repeats exactly: ``t = k·0.1`` written as text gives dt = 0.1 s for every row,
not a mix of 0.09999999999999964 and 0.10000000000000142.

:func:`run_series` works for every preset (linear or EKF) and calls the model's
``predict`` and ``update`` row by row. :func:`run_linear_series` gives the same
numbers (to rounding) for linear presets, fast:

* The covariances and gains do not depend on the data. With a repeating dt and
  process noise they converge; once a step changes P by no more than a few units in
  the last place, every later row has that P and gain. With Q = 0 the information
  matrix Y = P⁻¹ follows an affine recursion, Y_k = F⁻ᵀ Y_{k−1} F⁻¹ + Hᵀ R⁻¹ H,
  computed for all rows at once. Other cases run the covariance recursion row by row.
* The mean then follows x_k = A_k x_{k−1} + b_k with A_k = (I − K_k H) F_k and
  b_k = (I − K_k H) B_k u_k + K_k z_k, evaluated by :func:`affine_recursion` in
  chunks: within each chunk the recursion runs from zero for all chunks at once, and
  one short pass carries each chunk's start state to the next.
"""

import math
from typing import NamedTuple, Optional

from kf_train.filters.validation import as_covariance, as_finite_array, as_vector
import numpy as np

NS_PER_S = 1_000_000_000
# |t| beyond this (~292 years) overflows int64 nanoseconds.
MAX_ABS_TIME_S = 9.2e9
# A covariance step smaller than this many units in the last place counts as converged.
CONVERGED_ULPS = 8.0


class SeriesResult(NamedTuple):
    """Estimates of a series; row k is the estimate after the measurement at t_s[k]."""

    t_s: np.ndarray
    """Times (N,) [s], as given."""
    x: np.ndarray
    """Corrected (posterior) means (N, n)."""
    P: np.ndarray
    """Corrected covariances (N, n, n)."""
    x_prior: np.ndarray
    """Predicted (prior) means at t_s[k], before its measurement (N, n)."""
    P_prior: np.ndarray
    """Predicted covariances (N, n, n)."""
    F: np.ndarray
    """Transition matrix from the previous time to t_s[k] (N, n, n): what RTS needs."""
    horizon_s: Optional[float]
    """The prediction horizon, or None."""
    predicted_x: Optional[np.ndarray]
    """Means predicted to t_s[k] + horizon_s (N, n), holding row k's control."""
    predicted_P: Optional[np.ndarray]
    """Covariances predicted to t_s[k] + horizon_s (N, n, n)."""


class SeriesError(ValueError):
    """A row of a series could not be filtered; ``row`` is its index."""

    def __init__(self, row: int, reason: str):
        """Store the row index and the reason."""
        super().__init__(f'row {row}: {reason}')
        self.row = row
        self.reason = reason


def time_steps_s(t_s, t0_s: float = 0.0) -> np.ndarray:
    """
    Return dt (N,) [s] between whole-nanosecond times: t_s[0] − t0_s, then differences.

    t_s[0] may equal t0_s (a measurement at the prior's time); later times must
    increase. The ValueError names the first offending index.
    """
    t = as_finite_array('t_s', t_s)
    if t.ndim != 1:
        raise ValueError(f't_s must be a vector, got shape {t.shape}')
    t0 = as_finite_array('t0_s', t0_s)
    if t0.ndim != 0:
        raise ValueError(f't0_s must be a scalar, got shape {t0.shape}')
    if t.size and max(float(np.max(np.abs(t))), abs(float(t0))) > MAX_ABS_TIME_S:
        raise ValueError(f'times must be within ±{MAX_ABS_TIME_S:g} s')
    t_ns = np.rint(t * NS_PER_S).astype(np.int64)
    t0_ns = int(round(float(t0) * NS_PER_S))
    dt_ns = np.diff(t_ns, prepend=t0_ns)
    if dt_ns.size and dt_ns[0] < 0:
        raise ValueError(f't_s[0] = {float(t[0])!r} is before t0_s = {float(t0)!r}')
    bad = np.flatnonzero(dt_ns[1:] <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise ValueError(f't_s[{k}] = {float(t[k])!r} is not after t_s[{k - 1}] = '
                         f'{float(t[k - 1])!r} '
                         '(times must increase by at least 1 ns)')
    return dt_ns / NS_PER_S


def _series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0, dt=None):
    """Validate the inputs; return (dt, z (N, m), u (N, p) or None, horizon, x0, P0)."""
    dt = time_steps_s(t_s, t0_s) if dt is None else dt
    N = dt.shape[0]
    m, p, n = preset.dim_z, preset.dim_u, preset.dim_x
    z = as_finite_array('z', z)
    if z.ndim == 1 and m == 1:
        z = z[:, None]
    if z.shape != (N, m):
        raise ValueError(f'z must have shape ({N}, {m}), got {z.shape}')
    if p:
        if u is None:
            raise ValueError(f'u ({", ".join(preset.control_names)}) is required by '
                             f'preset {preset.name!r}')
        u = as_finite_array('u', u)
        if u.ndim == 1 and p == 1:
            u = u[:, None]
        if u.shape != (N, p):
            raise ValueError(f'u must have shape ({N}, {p}), got {u.shape}')
    elif u is not None:
        raise ValueError(f'preset {preset.name!r} has no control input, but u was given')
    if horizon_s is None:
        horizon_s = preset.horizon_s
    else:
        horizon_s = float(as_finite_array('horizon_s', horizon_s))
        if horizon_s < 0.0:
            raise ValueError(f'horizon_s must be >= 0, got {horizon_s}')
        horizon_s = horizon_s or None  # 0 turns prediction off
    x0 = as_vector('x0', preset.initial_state if x0 is None else x0, n)
    P0 = as_covariance('P0', preset.initial_covariance if P0 is None else P0, n)
    return dt, z, u, horizon_s, x0, P0


def run_series(preset, t_s, z, u=None, *, t0_s: float = 0.0, horizon_s=None, x0=None,
               P0=None) -> SeriesResult:
    """
    Filter a series row by row with the preset's model (any preset, linear or EKF).

    ``horizon_s`` None uses the preset's horizon, 0 turns prediction off. ``x0``,
    ``P0`` override the preset's initial estimate.
    """
    dt, z, u, horizon_s, x, P = _series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0)
    N, n = dt.shape[0], preset.dim_x
    model = preset.model
    out_x, out_P = np.empty((N, n)), np.empty((N, n, n))
    prior_x, prior_P = np.empty((N, n)), np.empty((N, n, n))
    pred_x = np.empty((N, n)) if horizon_s else None
    pred_P = np.empty((N, n, n)) if horizon_s else None
    for k in range(N):
        u_k = None if u is None else u[k]
        try:
            x, P = model.predict(x, P, dt[k], u_k)   # x⁻ = F x + B u, P⁻ = F P Fᵀ + Q
            prior_x[k], prior_P[k] = x, P
            x, P, _ = model.update(x, P, z[k])        # x = x⁻ + K y, Joseph P
            out_x[k], out_P[k] = x, P
            if horizon_s:
                pred_x[k], pred_P[k] = model.predict(x, P, horizon_s, u_k)
        except ValueError as error:
            raise SeriesError(k, str(error)) from None
    F = preset.dynamics.F_batch(dt)
    return SeriesResult(np.asarray(t_s, dtype=float), out_x, out_P, prior_x, prior_P, F,
                        horizon_s, pred_x, pred_P)


# ---------------------------------------------------------------------------
# Stacks of small matrices as structures of arrays
#
# A stack of N (a, b) matrices is held as nested lists [[entry]] where each entry is
# either an array (N,) (contiguous, fast to combine) or a Python float, the same for
# every row. Constant zeros and ones are skipped, so a product with H = [1, 0] or
# F = [[1, dt], [0, 1]] costs only its non-trivial terms.
# ---------------------------------------------------------------------------

def _is_const(e) -> bool:
    """Return whether an entry is a constant (a Python float)."""
    return isinstance(e, float)


def _mul(a, b):
    """Return a·b, skipping constant zeros and ones."""
    if _is_const(a):
        if a == 0.0:
            return 0.0
        if a == 1.0:
            return b
    if _is_const(b):
        if b == 0.0:
            return 0.0
        if b == 1.0:
            return a
    return a * b


def _add(a, b):
    """Return a + b, skipping constant zeros."""
    if _is_const(a) and a == 0.0:
        return b
    if _is_const(b) and b == 0.0:
        return a
    return a + b


def _sub(a, b):
    """Return a − b, skipping constant zeros."""
    if _is_const(b) and b == 0.0:
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
    if all(_is_const(e) for row in A for e in row):
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
                acc = _add(acc, _mul(a, B[k][j]))
            out_row.append(acc)
        out.append(out_row)
    return out


def soa_mv(A: list, v: list) -> list:
    """Return A @ v for a nested-list vector v."""
    out = []
    for row in A:
        acc = 0.0
        for a, e in zip(row, v):
            acc = _add(acc, _mul(a, e))
        out.append(acc)
    return out


def soa_t(A: list) -> list:
    """Return Aᵀ."""
    return [list(col) for col in zip(*A)]


def soa_madd(A: list, B: list) -> list:
    """Return A + B."""
    return [[_add(a, b) for a, b in zip(ra, rb)] for ra, rb in zip(A, B)]


def soa_msub(A: list, B: list) -> list:
    """Return A − B."""
    return [[_sub(a, b) for a, b in zip(ra, rb)] for ra, rb in zip(A, B)]


def soa_sym(A: list) -> list:
    """Return (A + Aᵀ) / 2, exactly symmetric."""
    n = len(A)
    out = [[None] * n for _ in range(n)]
    for i in range(n):
        out[i][i] = A[i][i]
        for j in range(i + 1, n):
            e = _add(A[i][j], A[j][i])
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
        det = _sub(_mul(a, d), _mul(b, c))
        inv_det = 1.0 / det
        return [[_mul(d, inv_det), _mul(-b, inv_det)],
                [_mul(-c, inv_det), _mul(a, inv_det)]]
    return soa_stack(np.linalg.inv(soa_to_stack(A, N)))


# ---------------------------------------------------------------------------
# Affine recursions x_k = A_k x_{k-1} + b_k, vectorised by chunks
# ---------------------------------------------------------------------------

def _chunking(N: int):
    """Return (chunk length C, number of chunks): C ≈ √(N/16), the cheapest split here."""
    C = int(min(4096, max(16, math.isqrt(max(N, 1) // 16))))
    return C, -(-N // C)


def _chunked(e, N: int, C: int, nc: int):
    """Return entry e (N,) laid out as (C, nc): row j of chunk c at [j, c]."""
    if _is_const(e):
        return e
    e = np.asarray(e, dtype=float)
    if e.shape[0] != C * nc:
        e = np.concatenate([e, np.repeat(e[-1:], C * nc - N)])  # padding, unused
    return np.ascontiguousarray(e.reshape(nc, C).T)


def _carry(M_last: list, y_last: list, x0: np.ndarray, nc: int) -> np.ndarray:
    """Return each chunk's start state: s_{c+1} = M_c s_c + y_c, in plain floats."""
    d = len(x0)
    starts = np.empty((nc, d))
    s = [float(v) for v in x0]
    for c in range(nc):
        starts[c] = s
        s = [sum(M_last[c][i][k] * s[k] for k in range(d)) + y_last[c][i] for i in range(d)]
    return starts


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
        N = next(e.shape[0] for e in b if not _is_const(e))
    x0 = np.asarray(x0, dtype=float).reshape(d)
    if N == 0:
        return np.empty((0, d))
    C, nc = _chunking(N)
    bt = [np.broadcast_to(_chunked(e, N, C, nc), (C, nc)) for e in b]
    if isinstance(A, np.ndarray) and A.ndim == 2:
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
    if isinstance(A, np.ndarray):
        A = soa_stack(A)
    At = [[_chunked(e, N, C, nc) for e in row] for row in A]
    Ms = np.empty((d, d, C, nc))
    ys = np.empty((d, C, nc))
    rng = range(d)
    M = [[(e if _is_const(e) else e[0]) for e in row] for row in At]
    y = [bt[i][0] for i in rng]
    for j in range(C):
        if j:
            Aj = [[(e if _is_const(e) else e[j]) for e in row] for row in At]
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


# ---------------------------------------------------------------------------
# The vectorised linear filter
# ---------------------------------------------------------------------------

def _converged(P_new: np.ndarray, P_old: np.ndarray) -> bool:
    """Return whether two covariances differ by no more than a few ulps of their scale."""
    scale = np.sqrt(np.abs(np.outer(np.diag(P_new), np.diag(P_new))))
    return bool(np.all(np.abs(P_new - P_old) <= CONVERGED_ULPS * np.finfo(float).eps * scale))


def _covariances_2x1(F_u, Q_u, inv, H, R, P0, N, steady):
    """Return P_post for 2 states and 1 measurement, in plain floats."""
    rows = zip(*(M_u[:, i, j][inv].tolist() for M_u, i, j in (
        (F_u, 0, 0), (F_u, 0, 1), (F_u, 1, 0), (F_u, 1, 1),
        (Q_u, 0, 0), (Q_u, 0, 1), (Q_u, 1, 1))))
    h0, h1 = H[0].tolist()
    r = float(R[0, 0])
    tol = CONVERGED_ULPS * float(np.finfo(float).eps)
    p00, p01, p11 = float(P0[0, 0]), float(P0[0, 1]), float(P0[1, 1])
    out = []
    for k, (f00, f01, f10, f11, q00, q01, q11) in enumerate(rows):
        a, b = f00 * p00 + f01 * p01, f00 * p01 + f01 * p11      # first row of F P
        c, d = f10 * p00 + f11 * p01, f10 * p01 + f11 * p11      # second row of F P
        m00 = a * f00 + b * f01 + q00                            # P⁻ = F P Fᵀ + Q
        m01 = 0.5 * ((a * f10 + b * f11) + (c * f00 + d * f01)) + q01
        m11 = c * f10 + d * f11 + q11
        g0, g1 = m00 * h0 + m01 * h1, m01 * h0 + m11 * h1        # P⁻ Hᵀ
        s = h0 * g0 + h1 * g1 + r                                # S = H P⁻ Hᵀ + R
        k0, k1 = g0 / s, g1 / s                                  # K = P⁻ Hᵀ / S
        # Joseph form (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ, written out
        i00, i01, i10, i11 = 1.0 - k0 * h0, -k0 * h1, -k1 * h0, 1.0 - k1 * h1
        e00, e01 = i00 * m00 + i01 * m01, i00 * m01 + i01 * m11
        e10, e11 = i10 * m00 + i11 * m01, i10 * m01 + i11 * m11
        n00 = e00 * i00 + e01 * i01 + k0 * r * k0
        n01 = 0.5 * ((e00 * i10 + e01 * i11) + (e10 * i00 + e11 * i01)) + k0 * r * k1
        n11 = e10 * i10 + e11 * i11 + k1 * r * k1
        out.append((n00, n01, n11))
        if k > steady and abs(n00 - p00) <= tol * abs(n00) and abs(n11 - p11) <= tol * abs(
                n11) and abs(n01 - p01) <= tol * math.sqrt(abs(n00 * n11)):
            out.extend([(n00, n01, n11)] * (N - k - 1))
            break
        p00, p01, p11 = n00, n01, n11
    out = np.array(out).reshape(N, 3)
    return [[out[:, 0].copy(), out[:, 1].copy()], [out[:, 1].copy(), out[:, 2].copy()]]


def _covariances_1x1(F_u, Q_u, inv, H, R, P0, N, steady):
    """Return P_post for 1 state and 1 measurement, in plain floats."""
    rows = zip(F_u[:, 0, 0][inv].tolist(), Q_u[:, 0, 0][inv].tolist())
    h, r = float(H[0, 0]), float(R[0, 0])
    tol = CONVERGED_ULPS * float(np.finfo(float).eps)
    p = float(P0[0, 0])
    out = []
    for k, (f, q) in enumerate(rows):
        m = f * p * f + q                      # P⁻ = F P F + Q
        s = h * m * h + r                      # S = H P⁻ H + R
        g = m * h / s                          # K
        e = 1.0 - g * h
        p_new = e * m * e + g * r * g          # Joseph form
        out.append(p_new)
        if k > steady and abs(p_new - p) <= tol * abs(p_new):
            out.extend([p_new] * (N - k - 1))
            break
        p = p_new
    return [[np.array(out)]]


def _covariances_by_loop(F_u, Q_u, inv, H, R, P0, N):
    """Return P_post as nested lists, row by row, stopping once P has converged."""
    n = P0.shape[0]
    changes = np.flatnonzero(inv[1:] != inv[:-1])
    if H.shape == (1, 2):
        return _covariances_2x1(F_u, Q_u, inv, H, R, P0, N,
                                int(changes[-1]) + 1 if changes.size else 0)
    if H.shape == (1, 1):
        return _covariances_1x1(F_u, Q_u, inv, H, R, P0, N,
                                int(changes[-1]) + 1 if changes.size else 0)
    P_post = np.empty((N, n, n))
    # From row `steady` on dt never changes again, so a converged P stays put.
    changes = np.flatnonzero(inv[1:] != inv[:-1])
    steady = int(changes[-1]) + 1 if changes.size else 0
    eye = np.eye(n)
    P = P0
    for k in range(N):
        F, Q = F_u[inv[k]], Q_u[inv[k]]
        Pp = F @ P @ F.T + Q                     # P⁻ = F P Fᵀ + Q
        Pp = 0.5 * (Pp + Pp.T)
        S = H @ Pp @ H.T + R                     # S = H P⁻ Hᵀ + R
        K = np.linalg.solve(0.5 * (S + S.T), H @ Pp).T  # K = P⁻ Hᵀ S⁻¹
        I_KH = eye - K @ H
        P_new = I_KH @ Pp @ I_KH.T + K @ R @ K.T  # Joseph form
        P_new = 0.5 * (P_new + P_new.T)
        P_post[k] = P_new
        if k > steady and _converged(P_new, P):
            P_post[k + 1:] = P_new
            break
        P = P_new
    return soa_stack(P_post)


def _covariances_by_information(F_u, inv, H, R, P0, N):
    """With Q = 0: return P_post as nested lists from the affine information recursion."""
    n = P0.shape[0]
    Finv_T = np.swapaxes(np.linalg.inv(F_u), -1, -2)  # F⁻ᵀ per distinct dt
    # Row-major vec(F⁻ᵀ Y F⁻¹) = (F⁻ᵀ ⊗ F⁻ᵀ) vec(Y)
    maps = np.einsum('uij,ukl->uikjl', Finv_T, Finv_T).reshape(-1, n * n, n * n)
    M = H.T @ np.linalg.solve(R, H)                  # Hᵀ R⁻¹ H
    M = 0.5 * (M + M.T)
    Y0 = np.linalg.inv(P0)
    A = maps[0] if maps.shape[0] == 1 else soa_select(maps, inv)
    b = [float(v) for v in M.reshape(n * n)]
    b[0] = np.full(N, b[0])  # one array entry fixes N
    Y = affine_recursion(A, b, (0.5 * (Y0 + Y0.T)).reshape(n * n))
    Y = [[np.ascontiguousarray(Y[:, i * n + j]) for j in range(n)] for i in range(n)]
    return soa_sym(soa_inv(soa_sym(Y), N))


def run_linear_series(preset, t_s, z, u=None, *, t0_s: float = 0.0, horizon_s=None,
                      x0=None, P0=None) -> SeriesResult:
    """
    Filter a series with a linear preset, vectorised; same numbers as run_series.

    Arguments as :func:`run_series`. Reusable on plain arrays (one object's series).
    """
    if not preset.linear:
        raise ValueError(f'preset {preset.name!r} is not linear; use run_series')
    dt, z, u, horizon_s, x0, P0 = _series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0)
    N, n, m = dt.shape[0], preset.dim_x, preset.dim_z
    dyn, H, R = preset.dynamics, preset.model.H, preset.model.R
    t_s = np.asarray(t_s, dtype=float)
    if N == 0:
        empty, empty3 = np.empty((0, n)), np.empty((0, n, n))
        return SeriesResult(t_s, empty, empty3, empty, empty3, empty3, horizon_s,
                            empty if horizon_s else None, empty3 if horizon_s else None)
    dts, inv = np.unique(dt, return_inverse=True)
    inv = inv.reshape(-1)
    F_u, Q_u = dyn.F_batch(dts), dyn.Q_batch(dts)
    if not np.any(Q_u) and _well_conditioned(P0):
        P = _covariances_by_information(F_u, inv, H, R, P0, N)
    else:
        P = _covariances_by_loop(F_u, Q_u, inv, H, R, P0, N)

    F, Q = soa_select(F_u, inv), soa_select(Q_u, inv)
    Hs, Rs = soa_const(H), soa_const(R)
    # The prior of row k from the posterior of row k − 1 (P0 before row 0).
    P_prev = [[_shift(e, P0[i, j], N) for j, e in enumerate(row)] for i, row in enumerate(P)]
    P_prior = soa_sym(soa_madd(soa_mm(soa_mm(F, P_prev), soa_t(F)), Q))  # F P Fᵀ + Q
    PHt = soa_mm(P_prior, soa_t(Hs))
    S = soa_sym(soa_madd(soa_mm(Hs, PHt), Rs))         # S = H P⁻ Hᵀ + R
    K = soa_mm(PHt, soa_inv(S, N))                     # K = P⁻ Hᵀ S⁻¹
    I_KH = soa_msub(soa_const(np.eye(n)), soa_mm(K, Hs))
    A = soa_mm(I_KH, F)                                # A_k = (I − K_k H) F_k
    zs = [np.ascontiguousarray(z[:, i]) for i in range(m)]
    b = soa_mv(K, zs)                                  # b_k = K_k z_k ...
    Bu = None
    if u is not None:
        B = soa_select(dyn.B_batch(dts), inv)
        Bu = soa_mv(B, [np.ascontiguousarray(u[:, i]) for i in range(u.shape[1])])
        b = [_add(e, f) for e, f in zip(b, soa_mv(I_KH, Bu))]  # ... + (I − K H) B u
    b = [np.broadcast_to(e, (N,)) if _is_const(e) else e for e in b]
    x = affine_recursion(A, b, x0)
    x_prev = [_shift(np.ascontiguousarray(x[:, i]), x0[i], N) for i in range(n)]
    x_prior = soa_mv(F, x_prev)                        # x⁻ = F x + B u
    if Bu is not None:
        x_prior = [_add(e, f) for e, f in zip(x_prior, Bu)]

    pred_x = pred_P = None
    if horizon_s:
        Fh = soa_const(dyn.F_batch([horizon_s])[0])
        Qh = soa_const(dyn.Q_batch([horizon_s])[0])
        xs = [np.ascontiguousarray(x[:, i]) for i in range(n)]
        pred = soa_mv(Fh, xs)                          # F(h) x (+ B(h) u, control held)
        if u is not None:
            Bh = soa_const(dyn.B_batch([horizon_s])[0])
            pred = [_add(e, f) for e, f in zip(pred, soa_mv(Bh, [u[:, i] for i in range(
                u.shape[1])]))]
        pred_x = soa_vector_to_stack(pred, N)
        pred_P = soa_to_stack(soa_sym(soa_madd(soa_mm(soa_mm(Fh, P), soa_t(Fh)), Qh)), N)
    return SeriesResult(t_s, x, soa_to_stack(P, N), soa_vector_to_stack(x_prior, N),
                        soa_to_stack(P_prior, N), soa_to_stack(F, N), horizon_s, pred_x,
                        pred_P)


def _shift(e, first: float, N: int):
    """Return [first, e_0, …, e_{N−2}]: each row's previous value."""
    if _is_const(e):
        return e if e == first else np.concatenate([[first], np.full(N - 1, e)])
    return np.concatenate([[first], e[:-1]])


def _well_conditioned(P: np.ndarray) -> bool:
    """Return whether P is safely invertible (the information form needs P0⁻¹)."""
    w = np.linalg.eigvalsh(P)
    return bool(w[0] > 0.0 and w[-1] / w[0] < 1e12)


# ---------------------------------------------------------------------------
# Any filter of the family (kf_train.filters.family): the replay's --filter
# ---------------------------------------------------------------------------

def run_filter_series(filt, t_s, z, u=None, *, t0_s: float = 0.0, horizon_s=None, x0=None,
                      P0=None) -> SeriesResult:
    """
    Filter a series row by row with a filter from ``filters.make_filter``.

    The filter is reset to (x0, P0), the preset's initial estimate by default, and
    then predicts and updates every row, as :func:`run_series` does; x and P are
    the filter's mean and covariance (for the particle filter, the particles').
    """
    preset = filt.preset
    dt, z, u, horizon_s, x0, P0 = _series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0)
    N, n = dt.shape[0], preset.dim_x
    filt.reset(x0, P0)
    out_x, out_P = np.empty((N, n)), np.empty((N, n, n))
    prior_x, prior_P = np.empty((N, n)), np.empty((N, n, n))
    pred_x = np.empty((N, n)) if horizon_s else None
    pred_P = np.empty((N, n, n)) if horizon_s else None
    for k in range(N):
        u_k = None if u is None else u[k]
        try:
            filt.predict(dt[k], u_k)
            prior_x[k], prior_P[k] = filt.mean, filt.covariance
            filt.update(z[k])
            out_x[k], out_P[k] = filt.mean, filt.covariance
            if horizon_s:
                pred_x[k], pred_P[k] = filt.predict_ahead(horizon_s, u_k)
        except ValueError as error:
            raise SeriesError(k, str(error)) from None
    return SeriesResult(np.asarray(t_s, dtype=float), out_x, out_P, prior_x, prior_P,
                        preset.dynamics.F_batch(dt), horizon_s, pred_x, pred_P)


# ---------------------------------------------------------------------------
# A bank of independent objects: rows tagged with an id
# ---------------------------------------------------------------------------

# Cost model for choosing, per object, between the lock-step bank (one numpy step
# for all objects' k-th rows) and the per-object vectorised series: seconds per
# lock-step step, and per call of run_linear_series (both measured on the 2-core
# test host, to within a factor of two; they only steer the split).
LOCKSTEP_STEP_S = 1.5e-4
SERIES_CALL_S = 2e-3


class Groups(NamedTuple):
    """The rows of a table grouped by object id."""

    codes: np.ndarray
    """Each row's object, 0..K−1 (N,)."""
    labels: np.ndarray
    """Each object's id as given (K,), in code order."""
    order: np.ndarray
    """Row indices grouped by object, in row order within each object (N,)."""
    starts: np.ndarray
    """Where each object's rows start in ``order`` (K,)."""
    counts: np.ndarray
    """Rows per object (K,)."""

    def rows(self, k: int) -> np.ndarray:
        """Return the row indices of object k, in row order."""
        return self.order[self.starts[k]:self.starts[k] + self.counts[k]]


def group_rows(ids) -> Groups:
    """Return the rows grouped by ``ids`` (N,): any labels numpy can sort."""
    ids = np.asarray(ids)
    if ids.ndim != 1:
        raise ValueError(f'ids must be a vector, got shape {ids.shape}')
    if ids.dtype.kind in 'iu' and ids.size and 0 <= ids.min() and ids.max() < 4 * ids.size:
        # Small non-negative integers (codes): no sort needed to find the distinct ones.
        present = np.bincount(ids) > 0
        labels = np.flatnonzero(present)
        rank = np.cumsum(present) - 1
        codes = rank[ids].astype(np.int64)
    else:
        labels, codes = np.unique(ids, return_inverse=True)
        codes = codes.reshape(-1).astype(np.int64)
    order = np.argsort(codes, kind='stable')
    counts = np.bincount(codes, minlength=labels.shape[0]).astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    return Groups(codes, labels, order, starts, counts)


class TimeOrderError(ValueError):
    """A row's time is not after its object's previous row (or before t0)."""

    def __init__(self, message: str, row: int, previous: Optional[int]):
        """Store the offending row, and its object's previous row (None: t0)."""
        super().__init__(message)
        self.row = row
        self.previous = previous


def bank_time_steps(t_s, groups: Groups, t0_s: float = 0.0) -> np.ndarray:
    """
    Return dt (N,) [s], per row, from its object's previous row (or t0_s for the first).

    Every object's times must increase by at least 1 ns; its first may equal t0_s. The
    :class:`TimeOrderError` names the first offending row (by index) and its object's
    previous row.
    """
    t = as_finite_array('t_s', t_s)
    if t.ndim != 1 or t.shape[0] != groups.codes.shape[0]:
        raise ValueError(f't_s must be a vector of {groups.codes.shape[0]} times, got '
                         f'shape {t.shape}')
    t0 = float(as_finite_array('t0_s', t0_s))
    if t.size and max(float(np.max(np.abs(t))), abs(t0)) > MAX_ABS_TIME_S:
        raise ValueError(f'times must be within ±{MAX_ABS_TIME_S:g} s')
    t_ns = np.rint(t * NS_PER_S).astype(np.int64)
    order = groups.order
    ts = t_ns[order]
    previous = np.empty_like(ts)
    previous[1:] = ts[:-1]
    first = groups.starts[groups.counts > 0]
    previous[first] = int(round(t0 * NS_PER_S))
    dt_ns = ts - previous
    is_first = np.zeros(ts.shape[0], dtype=bool)
    is_first[first] = True
    bad = (dt_ns < 0) | ((dt_ns == 0) & ~is_first)   # the first row may sit at t0
    if bad.any():
        where = np.flatnonzero(bad)
        k = int(where[np.argmin(order[where])])      # the earliest row in the table
        row = int(order[k])
        label = groups.labels[groups.codes[row]].item()
        if is_first[k]:
            raise TimeOrderError(f't_s[{row}] = {float(t[row])!r} is before t0_s = {t0!r} '
                                 f'(id {label!r})', row, None)
        prev = int(order[k - 1])
        raise TimeOrderError(f't_s[{row}] = {float(t[row])!r} is not after t_s[{prev}] = '
                             f'{float(t[prev])!r}, the previous row of id {label!r} (times '
                             'must increase by at least 1 ns per id)', row, prev)
    dt = np.empty(t.shape[0])
    dt[order] = dt_ns / NS_PER_S
    return dt


def _lockstep_linear(preset, dt, z, u, groups: Groups, objects: np.ndarray, x0, P0, out,
                     unique_dt):
    """
    Filter ``objects`` (codes) of a linear preset in lock-step; fill ``out`` row-wise.

    Step k corrects the k-th row of every object that has one, all at once: the state
    of object s lives in column s of (n, K) arrays, the objects sorted by row count so
    that the ones still running are always a prefix. ``out`` is (x, P, x_prior,
    P_prior), each indexed by row; ``unique_dt`` is np.unique(dt, return_inverse=True).
    """
    n, m = preset.dim_x, preset.dim_z
    counts = groups.counts[objects]
    perm = np.argsort(-counts, kind='stable')
    objects, counts = objects[perm], counts[perm]
    K = objects.shape[0]
    steps = int(counts[0]) if K else 0
    if steps == 0:
        return
    active = np.searchsorted(-counts, -np.arange(steps), side='left')  # #{count > k}
    offsets = np.concatenate([[0], np.cumsum(active)])
    # Row of (step k, slot s) at offsets[k] + s: the rows, step-major.
    slot = np.repeat(np.arange(K), counts)
    k_of = np.arange(slot.shape[0]) - np.repeat(np.cumsum(counts) - counts, counts)
    rows = np.empty(slot.shape[0], dtype=np.int64)
    rows[offsets[k_of] + slot] = groups.order[np.repeat(groups.starts[objects], counts) + k_of]

    dyn = preset.dynamics
    A = dyn.A
    dts, inv = unique_dt
    inv = inv[rows]
    Q_u = dyn.Q_batch(dts)
    B_u = dyn.B_batch(dts) if u is not None else None
    dt_rows = dt[rows]
    z_rows = np.ascontiguousarray(z[rows].T)
    u_rows = None if u is None else np.ascontiguousarray(u[rows].T)
    Hs, Rs = soa_const(preset.model.H), soa_const(preset.model.R)
    eye = soa_const(np.eye(n))
    Ht, Rt = soa_t(Hs), Rs
    # One initial estimate for every object, or one each: x0 (n, K), P0 (n, n, K) in the
    # order of ``objects`` (a stream's objects carry their state from the previous block).
    x0, P0 = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
    x_state = np.array(x0[:, perm]) if x0.ndim == 2 else np.repeat(x0[:, None], K, axis=1)
    P_state = (np.array(P0[:, :, perm]) if P0.ndim == 3
               else np.repeat(P0[:, :, None], K, axis=2))
    out_x, out_P, out_xp, out_Pp = out
    for k in range(steps):
        a, lo, hi = int(active[k]), int(offsets[k]), int(offsets[k + 1])
        d = dt_rows[lo:hi]
        # F = I + dt·A, entry by entry (constant where A is zero)
        F = [[(1.0 if i == j else 0.0) if A[i, j] == 0.0 else (
            d if A[i, j] == 1.0 else d * A[i, j]) for j in range(n)] for i in range(n)]
        if dts.shape[0] == 1:
            Q = soa_const(Q_u[0])
            B = None if B_u is None else soa_const(B_u[0])
        else:
            idx = inv[lo:hi]
            Q = [[Q_u[:, i, j][idx] for j in range(n)] for i in range(n)]
            B = None if B_u is None else [[B_u[:, i, j][idx] for j in range(B_u.shape[2])]
                                          for i in range(n)]
        x = [x_state[i, :a] for i in range(n)]
        P = [[P_state[i, j, :a] for j in range(n)] for i in range(n)]
        xp = soa_mv(F, x)                                   # x⁻ = F x + B u
        if B is not None:
            xp = [_add(e, f) for e, f in zip(xp, soa_mv(B, [u_rows[i, lo:hi] for i in range(
                u_rows.shape[0])]))]
        Pp = soa_sym(soa_madd(soa_mm(soa_mm(F, P), soa_t(F)), Q))   # P⁻ = F P Fᵀ + Q
        PHt = soa_mm(Pp, Ht)
        S = soa_sym(soa_madd(soa_mm(Hs, PHt), Rt))            # S = H P⁻ Hᵀ + R
        K_gain = soa_mm(PHt, soa_inv(S, a))                   # K = P⁻ Hᵀ S⁻¹
        hx = soa_mv(Hs, xp)
        y = [z_rows[i, lo:hi] - hx[i] for i in range(m)]      # y = z − H x⁻
        xn = [_add(e, f) for e, f in zip(xp, soa_mv(K_gain, y))]   # x = x⁻ + K y
        I_KH = soa_msub(eye, soa_mm(K_gain, Hs))
        Pn = soa_sym(soa_madd(soa_mm(soa_mm(I_KH, Pp), soa_t(I_KH)),
                              soa_mm(soa_mm(K_gain, Rs), soa_t(K_gain))))  # Joseph form
        for i in range(n):
            out_xp[lo:hi, i] = xp[i]
            out_x[lo:hi, i] = xn[i]
            x_state[i, :a] = xn[i]
            for j in range(n):
                out_Pp[lo:hi, i, j] = Pp[i][j]
                out_P[lo:hi, i, j] = Pn[i][j]
                P_state[i, j, :a] = Pn[i][j]
    return rows


def run_bank(preset, t_s, z, u=None, ids=None, *, t0_s: float = 0.0, horizon_s=None,
             x0=None, P0=None, fast: bool = True, filt=None,
             groups: Optional[Groups] = None) -> SeriesResult:
    """
    Filter a table of independent objects, rows tagged by ``ids``; rows stay in order.

    Every object's rows form its own series from the initial estimate at ``t0_s``
    (times must increase per object; rows of different objects may interleave), and
    row k's result equals filtering that object's rows alone with :func:`run_series`
    (or ``filt`` with :func:`run_filter_series`). Linear presets (``fast``) run as a
    vectorised bank: objects with few rows in lock-step (all objects' k-th rows in one
    numpy step), objects with many rows each along its own time axis
    (:func:`run_linear_series`), split where a cost model says it is cheapest. Other
    presets and filters run object by object. A :class:`SeriesError` names the row.
    ``groups``, from :func:`group_rows` of the ids, saves grouping them again.
    """
    t_arr = np.asarray(t_s, dtype=float)
    if groups is None:
        groups = group_rows(np.zeros(t_arr.shape[0], dtype=np.int64) if ids is None else ids)
    if groups.codes.shape[0] != t_arr.reshape(-1).shape[0]:
        raise ValueError(f'ids must have one entry per row ({t_arr.shape[0]}), got '
                         f'{groups.codes.shape[0]}')
    dt = bank_time_steps(t_arr, groups, t0_s)
    owner = preset if filt is None else filt.preset
    dt, z, u, horizon_s, x0, P0 = _series_inputs(owner, t_arr, z, u, t0_s, horizon_s, x0, P0,
                                                 dt=dt)
    N, n = dt.shape[0], owner.dim_x
    out_x, out_P = np.empty((N, n)), np.empty((N, n, n))
    out_xp, out_Pp = np.empty((N, n)), np.empty((N, n, n))
    pred_x = np.empty((N, n)) if horizon_s else None
    pred_P = np.empty((N, n, n)) if horizon_s else None
    K = groups.counts.shape[0]
    alone = np.arange(K)
    dts, inv = np.unique(dt, return_inverse=True)
    inv = inv.reshape(-1)
    if filt is None and fast and preset.linear:
        # Objects sorted by rows, most first: the first s run alone, the rest in
        # lock-step for counts[s] steps. Cost: s calls + counts[s] steps.
        by_rows = np.argsort(-groups.counts, kind='stable')
        counts = np.concatenate([groups.counts[by_rows], [0]])
        cost = np.arange(K + 1) * SERIES_CALL_S + counts * LOCKSTEP_STEP_S
        split = int(np.argmin(cost))
        alone, together = by_rows[:split], by_rows[split:]
        if together.size:
            rows = _lockstep_linear(owner, dt, z, u, groups, together, x0, P0,
                                    (out_x, out_P, out_xp, out_Pp), (dts, inv))
            # The lock-step results were written step-major: put them in row order.
            for array in (out_x, out_P, out_xp, out_Pp):
                array[rows] = array[:rows.shape[0]].copy()
            bad = rows[~(np.all(np.isfinite(out_x[rows]), axis=1)
                         & np.all(np.isfinite(out_P[rows]), axis=(1, 2)))]
            if bad.size:
                raise SeriesError(int(bad.min()), 'the filter diverged (non-finite '
                                  'estimate)')
            if horizon_s:
                _bank_horizon(owner, rows, u, horizon_s, out_x, out_P, pred_x, pred_P)
    for k in alone:
        rows = groups.rows(k)
        t_k = t_arr[rows]
        u_k = None if u is None else u[rows]
        try:
            if filt is not None:
                result = run_filter_series(filt, t_k, z[rows], u_k, t0_s=t0_s,
                                           horizon_s=horizon_s or 0.0, x0=x0, P0=P0)
            elif fast and preset.linear:
                result = run_linear_series(preset, t_k, z[rows], u_k, t0_s=t0_s,
                                           horizon_s=horizon_s or 0.0, x0=x0, P0=P0)
            else:
                result = run_series(preset, t_k, z[rows], u_k, t0_s=t0_s,
                                    horizon_s=horizon_s or 0.0, x0=x0, P0=P0)
        except SeriesError as error:
            raise SeriesError(int(rows[error.row]), error.reason) from None
        out_x[rows], out_P[rows] = result.x, result.P
        out_xp[rows], out_Pp[rows] = result.x_prior, result.P_prior
        if horizon_s:
            pred_x[rows], pred_P[rows] = result.predicted_x, result.predicted_P
    F = soa_to_stack(soa_select(owner.dynamics.F_batch(dts), inv), N)
    return SeriesResult(t_arr, out_x, out_P, out_xp, out_Pp, np.array(F), horizon_s, pred_x,
                        pred_P)


def _bank_horizon(preset, rows, u, horizon_s, x, P, pred_x, pred_P) -> None:
    """Fill the predictions to t + horizon_s of ``rows`` (the row's control held)."""
    dyn, n = preset.dynamics, preset.dim_x
    Fh = soa_const(dyn.F_batch([horizon_s])[0])
    Qh = soa_const(dyn.Q_batch([horizon_s])[0])
    xs = [np.ascontiguousarray(x[rows, i]) for i in range(n)]
    pred = soa_mv(Fh, xs)                              # F(h) x (+ B(h) u)
    if u is not None:
        Bh = soa_const(dyn.B_batch([horizon_s])[0])
        pred = [_add(e, f) for e, f in zip(pred, soa_mv(Bh, [u[rows, i] for i in range(
            u.shape[1])]))]
    N = rows.shape[0]
    pred_x[rows] = soa_vector_to_stack(pred, N)
    Ps = soa_stack(P[rows])
    pred_P[rows] = soa_to_stack(soa_sym(soa_madd(soa_mm(soa_mm(Fh, Ps), soa_t(Fh)), Qh)), N)
