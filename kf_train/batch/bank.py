"""
A bank of independent objects: rows tagged with an id, each object its own series.

Every object's rows form its own series from the initial estimate at ``t0_s`` (times
must increase per object; rows of different objects may interleave), and row k's
result equals filtering that object's rows alone. :func:`run_bank` runs linear presets
as a vectorised bank: objects with few rows in lock-step (all objects' k-th rows in
one numpy step), objects with many rows each along its own time axis
(:func:`~kf_train.batch.linear.run_linear_series`), split where a cost model says it
is cheapest.
"""

from typing import NamedTuple, Optional

from kf_train.batch.linear import predict_ahead, run_linear_series
from kf_train.batch.series import (
    MAX_ABS_TIME_S, run_filter_series, run_series, series_inputs, series_outputs, SeriesError,
    SeriesResult)
from kf_train.batch.soa import (
    entry_add, soa_const, soa_gain, soa_madd, soa_mm, soa_msub, soa_mv,
    soa_prior_covariance, soa_select, soa_stack, soa_sym, soa_t, soa_to_stack)
from kf_train.filters import as_finite_array, NS_PER_S, seconds_to_ns, seconds_to_ns_array
import numpy as np

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
    t_ns = seconds_to_ns_array(t)
    order = groups.order
    ts = t_ns[order]
    previous = np.empty_like(ts)
    previous[1:] = ts[:-1]
    first = groups.starts[groups.counts > 0]
    previous[first] = seconds_to_ns(t0)
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


def _lockstep_rows(groups: Groups, objects: np.ndarray):
    """
    Return (objects, counts, active, offsets, rows) of a lock-step over ``objects``.

    The objects are sorted by row count, most first, so that the ones still running at
    step k are always a prefix (``active[k]`` of them); the row of (step k, slot s) is
    ``rows[offsets[k] + s]``: the rows, step-major.
    """
    counts = groups.counts[objects]
    perm = np.argsort(-counts, kind='stable')
    objects, counts = objects[perm], counts[perm]
    K = objects.shape[0]
    steps = int(counts[0]) if K else 0
    active = np.searchsorted(-counts, -np.arange(steps), side='left')  # #{count > k}
    offsets = np.concatenate([[0], np.cumsum(active)])
    slot = np.repeat(np.arange(K), counts)
    k_of = np.arange(slot.shape[0]) - np.repeat(np.cumsum(counts) - counts, counts)
    rows = np.empty(slot.shape[0], dtype=np.int64)
    rows[offsets[k_of] + slot] = groups.order[np.repeat(groups.starts[objects], counts) + k_of]
    return objects, counts, active, offsets, rows


def _lockstep_linear(preset, dt, z, u, groups: Groups, objects: np.ndarray, x0, P0, out,
                     unique_dt):
    """
    Filter ``objects`` (codes) of a linear preset in lock-step; fill ``out`` row-wise.

    Step k corrects the k-th row of every object that has one, all at once: the state
    of object s lives in column s of (n, K) arrays (:func:`_lockstep_rows`). ``out``
    is (x, P, x_prior, P_prior), each written step-major; returns the rows in that
    order. ``unique_dt`` is np.unique(dt, return_inverse=True).
    """
    n, m = preset.dim_x, preset.dim_z
    # One initial estimate for every object, or one each: x0 (n, K), P0 (n, n, K) in the
    # order of ``objects`` (a stream's objects carry their state from the previous block).
    x0, P0 = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
    if x0.ndim == 2:
        order = np.argsort(-groups.counts[objects], kind='stable')   # as _lockstep_rows
        x0, P0 = x0[:, order], P0[:, :, order]
    objects, counts, active, offsets, rows = _lockstep_rows(groups, objects)
    K = objects.shape[0]
    steps = int(counts[0]) if K else 0
    if steps == 0:
        return
    dyn = preset.dynamics
    dts, inv = unique_dt
    inv = inv[rows]
    Q_u = dyn.Q_batch(dts)
    B_u = dyn.B_batch(dts) if u is not None else None
    dt_rows = dt[rows]
    z_rows = np.ascontiguousarray(z[rows].T)
    u_rows = None if u is None else np.ascontiguousarray(u[rows].T)
    Hs, Rs = soa_const(preset.model.H), soa_const(preset.model.R)
    eye = soa_const(np.eye(n))
    x_state = np.array(x0) if x0.ndim == 2 else np.repeat(x0[:, None], K, axis=1)
    P_state = np.array(P0) if P0.ndim == 3 else np.repeat(P0[:, :, None], K, axis=2)
    out_x, out_P, out_xp, out_Pp = out
    for k in range(steps):
        a, lo, hi = int(active[k]), int(offsets[k]), int(offsets[k + 1])
        F = _transition(dyn.A, dt_rows[lo:hi], n)
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
            xp = [entry_add(e, f) for e, f in zip(xp, soa_mv(B, [u_rows[i, lo:hi] for i in range(
                u_rows.shape[0])]))]
        Pp = soa_prior_covariance(F, P, Q)                   # P⁻ = F P Fᵀ + Q
        K_gain = soa_gain(Pp, Hs, Rs, a)                     # K = P⁻ Hᵀ S⁻¹
        hx = soa_mv(Hs, xp)
        y = [z_rows[i, lo:hi] - hx[i] for i in range(m)]      # y = z − H x⁻
        xn = [entry_add(e, f) for e, f in zip(xp, soa_mv(K_gain, y))]   # x = x⁻ + K y
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


def _transition(A: np.ndarray, d: np.ndarray, n: int) -> list:
    """Return F = I + dt·A for the dt of a step, entry by entry (constant where A is 0)."""
    return [[(1.0 if i == j else 0.0) if A[i, j] == 0.0 else (
        d if A[i, j] == 1.0 else d * A[i, j]) for j in range(n)] for i in range(n)]


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
    dt, z, u, horizon_s, x0, P0 = series_inputs(owner, t_arr, z, u, t0_s, horizon_s, x0, P0,
                                                dt=dt)
    N = dt.shape[0]
    out = series_outputs(N, owner.dim_x, horizon_s)
    alone = np.arange(groups.counts.shape[0])
    dts, inv = np.unique(dt, return_inverse=True)
    inv = inv.reshape(-1)
    if filt is None and fast and preset.linear:
        alone, together = _split_objects(groups)
        if together.size:
            _run_together(owner, dt, z, u, groups, together, x0, P0, (dts, inv), horizon_s,
                          out)
    for k in alone:
        rows = groups.rows(k)
        u_k = None if u is None else u[rows]
        run = (run_filter_series if filt is not None else
               run_linear_series if fast and preset.linear else run_series)
        try:
            result = run(preset if filt is None else filt, t_arr[rows], z[rows], u_k,
                         t0_s=t0_s, horizon_s=horizon_s or 0.0, x0=x0, P0=P0)
        except SeriesError as error:
            raise SeriesError(int(rows[error.row]), error.reason) from None
        out[0][rows], out[1][rows] = result.x, result.P
        out[2][rows], out[3][rows] = result.x_prior, result.P_prior
        if horizon_s:
            out[4][rows], out[5][rows] = result.predicted_x, result.predicted_P
    F = soa_to_stack(soa_select(owner.dynamics.F_batch(dts), inv), N)
    return SeriesResult(t_arr, out[0], out[1], out[2], out[3], np.array(F), horizon_s, out[4],
                        out[5])


def _split_objects(groups: Groups):
    """
    Return (alone, together): the objects to run one by one and those in lock-step.

    Objects sorted by rows, most first: the first s run alone, the rest in lock-step
    for counts[s] steps. Cost: s calls + counts[s] steps; the cheapest s is taken.
    """
    K = groups.counts.shape[0]
    by_rows = np.argsort(-groups.counts, kind='stable')
    counts = np.concatenate([groups.counts[by_rows], [0]])
    cost = np.arange(K + 1) * SERIES_CALL_S + counts * LOCKSTEP_STEP_S
    split = int(np.argmin(cost))
    return by_rows[:split], by_rows[split:]


def _run_together(preset, dt, z, u, groups: Groups, together, x0, P0, unique_dt, horizon_s,
                  out) -> None:
    """Filter ``together`` in lock-step into ``out`` (x, P, priors, predictions), by row."""
    out_x, out_P, out_xp, out_Pp, pred_x, pred_P = out
    rows = _lockstep_linear(preset, dt, z, u, groups, together, x0, P0,
                            (out_x, out_P, out_xp, out_Pp), unique_dt)
    # The lock-step results were written step-major: put them in row order.
    for array in (out_x, out_P, out_xp, out_Pp):
        array[rows] = array[:rows.shape[0]].copy()
    bad = rows[~(np.all(np.isfinite(out_x[rows]), axis=1)
                 & np.all(np.isfinite(out_P[rows]), axis=(1, 2)))]
    if bad.size:
        raise SeriesError(int(bad.min()), 'the filter diverged (non-finite estimate)')
    if horizon_s:
        # The predictions to t + horizon_s of these rows, each row's control held.
        us = None if u is None else [u[rows, i] for i in range(u.shape[1])]
        pred_x[rows], pred_P[rows] = predict_ahead(
            preset.dynamics, horizon_s,
            [np.ascontiguousarray(out_x[rows, i]) for i in range(preset.dim_x)],
            soa_stack(out_P[rows]), us, rows.shape[0])
