"""
A linear preset over a whole series, vectorised: the numbers of run_series, fast.

:func:`run_linear_series` gives the numbers of :func:`~kf_train.batch.series.run_series`
(to rounding) for linear presets:

* The covariances and gains do not depend on the data. With a repeating dt and
  process noise they converge; once a step changes P by no more than a few units in
  the last place, every later row has that P and gain. With Q = 0 the information
  matrix Y = P⁻¹ follows an affine recursion, Y_k = F⁻ᵀ Y_{k−1} F⁻¹ + Hᵀ R⁻¹ H,
  computed for all rows at once. Other cases run the covariance recursion row by row.
* The mean then follows x_k = A_k x_{k−1} + b_k with A_k = (I − K_k H) F_k and
  b_k = (I − K_k H) B_k u_k + K_k z_k, evaluated by
  :func:`~kf_train.batch.affine.affine_recursion` in chunks.
"""

import math

from kf_train.batch.affine import affine_recursion
from kf_train.batch.series import series_inputs, SeriesResult
from kf_train.batch.soa import (
    entry_add, entry_sub, is_const, soa_const, soa_gain_terms, soa_inv, soa_mm, soa_msub,
    soa_mv, soa_nis, soa_prior_covariance, soa_select, soa_stack, soa_sym, soa_to_stack,
    soa_vector_to_stack)
import numpy as np

# A covariance step smaller than this many units in the last place counts as converged.
CONVERGED_ULPS = 8.0


def _converged(P_new: np.ndarray, P_old: np.ndarray) -> bool:
    """Return whether two covariances differ by no more than a few ulps of their scale."""
    scale = np.sqrt(np.abs(np.outer(np.diag(P_new), np.diag(P_new))))
    return bool(np.all(np.abs(P_new - P_old) <= CONVERGED_ULPS * np.finfo(float).eps * scale))


def _covariances_2x1(F_u, Q_u, inv, H, R, P0, N, steady, missing=None):
    """Return P_post for 2 states and 1 measurement, in plain floats (``missing``: no update)."""
    gaps = set() if missing is None else set(np.flatnonzero(missing).tolist())
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
        if k in gaps:                                            # no measurement: P = P⁻
            out.append((m00, m01, m11))
            p00, p01, p11 = m00, m01, m11
            continue
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


def _covariances_1x1(F_u, Q_u, inv, H, R, P0, N, steady, missing=None):
    """Return P_post for 1 state and 1 measurement, in plain floats (``missing``: no update)."""
    gaps = set() if missing is None else set(np.flatnonzero(missing).tolist())
    rows = zip(F_u[:, 0, 0][inv].tolist(), Q_u[:, 0, 0][inv].tolist())
    h, r = float(H[0, 0]), float(R[0, 0])
    tol = CONVERGED_ULPS * float(np.finfo(float).eps)
    p = float(P0[0, 0])
    out = []
    for k, (f, q) in enumerate(rows):
        m = f * p * f + q                      # P⁻ = F P F + Q
        if k in gaps:                          # no measurement: P = P⁻
            out.append(m)
            p = m
            continue
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


def _covariances_by_loop(F_u, Q_u, inv, H, R, P0, N, missing=None):
    """Return P_post as nested lists, row by row, stopping once P has converged."""
    n = P0.shape[0]
    # From row `steady` on dt never changes again and every row has its measurement,
    # so a converged P stays put.
    changes = np.flatnonzero(inv[1:] != inv[:-1])
    steady = int(changes[-1]) + 1 if changes.size else 0
    if missing is not None:
        steady = max(steady, int(np.flatnonzero(missing)[-1]) + 1)
    if H.shape == (1, 2):
        return _covariances_2x1(F_u, Q_u, inv, H, R, P0, N, steady, missing)
    if H.shape == (1, 1):
        return _covariances_1x1(F_u, Q_u, inv, H, R, P0, N, steady, missing)
    P_post = np.empty((N, n, n))
    eye = np.eye(n)
    P = P0
    for k in range(N):
        F, Q = F_u[inv[k]], Q_u[inv[k]]
        Pp = F @ P @ F.T + Q                     # P⁻ = F P Fᵀ + Q
        Pp = 0.5 * (Pp + Pp.T)
        if missing is not None and missing[k]:   # no measurement: P = P⁻
            P_post[k] = P = Pp
            continue
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


def _covariances_by_information(F_u, inv, H, R, P0, N, keep=None):
    """
    With Q = 0: return P_post as nested lists from the affine information recursion.

    ``keep`` (N,) is 1.0 for a row with its measurement, 0.0 for one without (no
    information added: Y_k = F⁻ᵀ Y_{k−1} F⁻¹); None: every row has one.
    """
    n = P0.shape[0]
    Finv_T = np.swapaxes(np.linalg.inv(F_u), -1, -2)  # F⁻ᵀ per distinct dt
    # Row-major vec(F⁻ᵀ Y F⁻¹) = (F⁻ᵀ ⊗ F⁻ᵀ) vec(Y)
    maps = np.einsum('uij,ukl->uikjl', Finv_T, Finv_T).reshape(-1, n * n, n * n)
    M = H.T @ np.linalg.solve(R, H)                  # Hᵀ R⁻¹ H
    M = 0.5 * (M + M.T)
    Y0 = np.linalg.inv(P0)
    A = maps[0] if maps.shape[0] == 1 else soa_select(maps, inv)
    b = [float(v) for v in M.reshape(n * n)]
    if keep is None:
        b[0] = np.full(N, b[0])  # one array entry fixes N
    else:
        b = [keep * v for v in b]
    Y = affine_recursion(A, b, (0.5 * (Y0 + Y0.T)).reshape(n * n))
    Y = [[np.ascontiguousarray(Y[:, i * n + j]) for j in range(n)] for i in range(n)]
    return soa_sym(soa_inv(soa_sym(Y), N))


def run_linear_series(preset, t_s, z, u=None, *, t0_s: float = 0.0, horizon_s=None,
                      x0=None, P0=None, missing=None, priors: bool = True) -> SeriesResult:
    """
    Filter a series with a linear preset, vectorised; same numbers as run_series.

    Arguments as :func:`run_series`. Reusable on plain arrays (one object's series).
    ``missing`` (N,) flags rows without a measurement (their z is ignored): they are
    predicted, not updated (gain 0; NIS NaN). ``priors`` False leaves x_prior, P_prior
    and F None (only the smoother needs them).
    """
    if not preset.linear:
        raise ValueError(f'preset {preset.name!r} is not linear; use run_series')
    keep = None
    if missing is not None and np.any(missing):
        missing = np.asarray(missing, dtype=bool).reshape(-1)
        z = np.where(missing.reshape(-1, *([1] * (np.ndim(z) - 1))), 0.0, z)
        keep = np.where(missing, 0.0, 1.0)
    else:
        missing = None
    dt, z, u, horizon_s, x0, P0 = series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0)
    N, n, m = dt.shape[0], preset.dim_x, preset.dim_z
    dyn, H, R = preset.dynamics, preset.model.H, preset.model.R
    t_s = np.asarray(t_s, dtype=float)
    if N == 0:
        empty, empty3 = np.empty((0, n)), np.empty((0, n, n))
        return SeriesResult(t_s, empty, empty3, empty, empty3, empty3, horizon_s,
                            empty if horizon_s else None, empty3 if horizon_s else None,
                            np.empty(0))
    if dt[0] > 0.0 and (dt == dt[0]).all():   # one time step (no sort): np.unique's result
        dts, inv = dt[:1].copy(), np.zeros(N, dtype=np.intp)
    else:
        dts, inv = np.unique(dt, return_inverse=True)
        inv = inv.reshape(-1)
    F_u, Q_u = dyn.F_batch(dts), dyn.Q_batch(dts)
    if not np.any(Q_u) and _well_conditioned(P0):
        P = _covariances_by_information(F_u, inv, H, R, P0, N, keep)
    else:
        P = _covariances_by_loop(F_u, Q_u, inv, H, R, P0, N, missing)

    F, Q = soa_select(F_u, inv), soa_select(Q_u, inv)
    Hs, Rs = soa_const(H), soa_const(R)
    # The prior of row k from the posterior of row k − 1 (P0 before row 0).
    P_prev = [[_shift(e, P0[i, j], N) for j, e in enumerate(row)] for i, row in enumerate(P)]
    P_prior = soa_prior_covariance(F, P_prev, Q)       # F P Fᵀ + Q
    K, S, S_inv = soa_gain_terms(P_prior, Hs, Rs, N)   # K = P⁻ Hᵀ S⁻¹
    if keep is not None:                               # no measurement: K = 0
        K = [[keep * e for e in row] for row in K]
    I_KH = soa_msub(soa_const(np.eye(n)), soa_mm(K, Hs))
    A = soa_mm(I_KH, F)                                # A_k = (I − K_k H) F_k
    zs = [np.ascontiguousarray(z[:, i]) for i in range(m)]
    b = soa_mv(K, zs)                                  # b_k = K_k z_k ...
    Bu = None
    if u is not None:
        B = soa_select(dyn.B_batch(dts), inv)
        Bu = soa_mv(B, [np.ascontiguousarray(u[:, i]) for i in range(u.shape[1])])
        b = [entry_add(e, f) for e, f in zip(b, soa_mv(I_KH, Bu))]  # ... + (I − K H) B u
    b = [np.broadcast_to(e, (N,)) if is_const(e) else e for e in b]
    x = affine_recursion(A, b, x0)

    pred_x = pred_P = None
    if horizon_s:
        us = None if u is None else [u[:, i] for i in range(u.shape[1])]
        pred_x, pred_P = predict_ahead(dyn, horizon_s,
                                       [np.ascontiguousarray(x[:, i]) for i in range(n)], P,
                                       us, N)
    x_prev = [_shift(np.ascontiguousarray(x[:, i]), x0[i], N) for i in range(n)]
    x_prior = soa_mv(F, x_prev)                        # x⁻ = F x + B u
    if Bu is not None:
        x_prior = [entry_add(e, f) for e, f in zip(x_prior, Bu)]
    nis = _nis(zs, Hs, x_prior, S, S_inv, N, missing)
    if not priors:
        return SeriesResult(t_s, x, soa_to_stack(P, N), None, None, None, horizon_s, pred_x,
                            pred_P, nis)
    return SeriesResult(t_s, x, soa_to_stack(P, N), soa_vector_to_stack(x_prior, N),
                        soa_to_stack(P_prior, N), soa_to_stack(F, N), horizon_s, pred_x,
                        pred_P, nis)


def _nis(zs: list, Hs: list, x_prior: list, S: list, S_inv: list, N: int,
         missing) -> np.ndarray:
    """Return each row's NIS yᵀ S⁻¹ y, y = z − H x⁻ (NaN for a row without a measurement)."""
    hx = soa_mv(Hs, x_prior)
    y = [entry_sub(z_i, e) for z_i, e in zip(zs, hx)]  # y = z − H x⁻
    nis = np.broadcast_to(soa_nis(y, S, S_inv), (N,))
    if missing is not None:
        return np.where(missing, np.nan, nis)
    return np.ascontiguousarray(nis)


def predict_ahead(dynamics, horizon_s: float, xs: list, P: list, us, N: int):
    """
    Return (x, P) predicted horizon_s ahead of every row, stacked (N, n) and (N, n, n).

    ``xs`` and ``P`` are the rows' estimates as structures of arrays; ``us`` the rows'
    controls (one array per control, held over the horizon) or None.
    """
    pred, pred_P = predict_soa(dynamics, horizon_s, xs, P, us)
    return soa_vector_to_stack(pred, N), soa_to_stack(pred_P, N)


def predict_soa(dynamics, horizon_s: float, xs: list, P: list, us):
    """Return (x, P) predicted horizon_s ahead of every row, as structures of arrays."""
    Fh = soa_const(dynamics.F_batch([horizon_s])[0])
    Qh = soa_const(dynamics.Q_batch([horizon_s])[0])
    pred = soa_mv(Fh, xs)                              # F(h) x (+ B(h) u, control held)
    if us is not None:
        Bh = soa_const(dynamics.B_batch([horizon_s])[0])
        pred = [entry_add(e, f) for e, f in zip(pred, soa_mv(Bh, us))]
    return pred, soa_prior_covariance(Fh, P, Qh)


def _shift(e, first: float, N: int):
    """Return [first, e_0, …, e_{N−2}]: each row's previous value."""
    if is_const(e):
        return e if e == first else np.concatenate([[first], np.full(N - 1, e)])
    return np.concatenate([[first], e[:-1]])


def _well_conditioned(P: np.ndarray) -> bool:
    """Return whether P is safely invertible (the information form needs P0⁻¹)."""
    w = np.linalg.eigvalsh(P)
    return bool(w[0] > 0.0 and w[-1] / w[0] < 1e12)
