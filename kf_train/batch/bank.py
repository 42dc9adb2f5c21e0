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

from typing import NamedTuple, Optional, Tuple, Union

from kf_train.batch.linear import predict_soa, run_linear_series
from kf_train.batch.series import (
    MAX_ABS_TIME_S, run_filter_series, run_series, series_inputs, series_outputs, SeriesError,
    SeriesResult)
from kf_train.batch.soa import (
    entry_add, soa_const, soa_gain_terms, soa_madd, soa_mm, soa_msub, soa_mv, soa_nis,
    soa_prior_covariance, soa_sym, soa_t)
from kf_train.batch.tape import Tape, trace
from kf_train.filters import as_finite_array, NS_PER_S, seconds_to_ns, seconds_to_ns_array
import numpy as np

# Cost model for choosing, per object, between the lock-step bank (one numpy step
# for all objects' k-th rows) and the per-object vectorised series: seconds per
# lock-step step, and per call of run_linear_series (both measured on the 2-core
# test host, to within a factor of two; they only steer the split).
LOCKSTEP_STEP_S = 1.5e-4
SERIES_CALL_S = 2e-3
# Objects per lock-step block: each block runs through all its steps while its
# intermediates (14-20 buffers of this length, ~1 MiB) stay in the CPU's cache. CPU time
# per object-row, 10⁵ objects × 4 rows (train, 2-core host): blocks of 1,024: 183 ns;
# 4,096: 126; 8,192: 131; 16,384: 141; 65,536: 195; 262,144 (no blocks): 199.
LOCKSTEP_BLOCK = 8192


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
        tally = np.bincount(ids)
        present = tally > 0
        labels = np.flatnonzero(present)
        if labels.shape[0] == tally.shape[0]:    # ids 0..K−1 all present: codes = ids
            codes = ids.astype(np.int64)
        else:
            codes = (np.cumsum(present) - 1)[ids].astype(np.int64)
        counts = tally[present].astype(np.int64)
    else:
        labels, codes = np.unique(ids, return_inverse=True)
        codes = codes.reshape(-1).astype(np.int64)
        counts = np.bincount(codes, minlength=labels.shape[0]).astype(np.int64)
    order = stable_argsort(codes)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    return Groups(codes, labels, order, starts, counts)


def stable_argsort(keys: np.ndarray) -> np.ndarray:
    """
    Return np.argsort(keys, kind='stable') for non-negative integer keys, sooner.

    numpy sorts 16-bit integers by radix (linear time) and wider ones by timsort: keys
    below 2³² are sorted as two 16-bit digits, low then high (a stable sort by the high
    digit keeps the low digit's order: the same permutation). 4·10⁶ shuffled keys of
    10⁶ objects: 0.55 s by timsort, 0.06 s by the two radix passes (2-core test host).
    """
    if keys.size == 0 or keys.dtype.kind not in 'iu' or keys.min() < 0:
        return np.argsort(keys, kind='stable')
    if np.count_nonzero(keys[1:] < keys[:-1]) < 64:
        # A few ascending runs (ids in turn, step after step): timsort merges them in
        # near-linear time (4 runs of 10⁶: 0.03 s, the radix passes 0.3 s).
        return np.argsort(keys, kind='stable')
    top = int(keys.max())
    if top < 1 << 16:
        return np.argsort(keys.astype(np.uint16), kind='stable')
    if top >= 1 << 32:
        return np.argsort(keys, kind='stable')
    order = np.argsort((keys & 0xFFFF).astype(np.uint16), kind='stable')
    return order[np.argsort((keys[order] >> 16).astype(np.uint16), kind='stable')]


def _by_count(counts: np.ndarray) -> np.ndarray:
    """Return np.argsort(-counts, kind='stable'): most rows first, ties in code order."""
    if counts.size == 0 or counts.min() == counts.max():
        return np.arange(counts.shape[0])
    return stable_argsort(counts.max() - counts)


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
    # Fewer passes over the rows than the plain form (max |t| without an |t| array, no
    # array of previous times or of first-row flags): 40 → 30 ns per row at 4·10⁶ rows.
    if t.size and max(abs(float(t.max())), abs(float(t.min())), abs(t0)) > MAX_ABS_TIME_S:
        raise ValueError(f'times must be within ±{MAX_ABS_TIME_S:g} s')
    t_ns = seconds_to_ns_array(t)
    order = groups.order
    ts = t_ns[order]
    first = groups.starts[groups.counts > 0]
    dt_ns = np.empty_like(ts)
    np.subtract(ts[1:], ts[:-1], out=dt_ns[1:])
    dt_ns[first] = ts[first] - seconds_to_ns(t0)
    bad = dt_ns <= 0
    bad[first] = dt_ns[first] < 0                    # the first row may sit at t0
    if bad.any():
        where = np.flatnonzero(bad)
        k = int(where[np.argmin(order[where])])      # the earliest row in the table
        row = int(order[k])
        label = groups.labels[groups.codes[row]].item()
        if k in set(first.tolist()):
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
    perm = _by_count(groups.counts[objects])
    objects = objects[perm]
    counts = groups.counts[objects]
    K = objects.shape[0]
    steps = int(counts[0]) if K else 0
    active = np.searchsorted(-counts, -np.arange(steps), side='left')  # #{count > k}
    offsets = np.concatenate([[0], np.cumsum(active)])
    # Step k's rows: the k-th of each of its objects (a gather per step, not per row).
    starts = groups.starts[objects]
    rows = np.concatenate([groups.order[starts[:int(active[k])] + k] for k in range(steps)]
                          + [np.zeros(0, dtype=np.int64)])
    return objects, counts, active, offsets, rows


class _Step(NamedTuple):
    """What every lock-step block shares: the preset's constants and the rows' inputs."""

    preset: object
    dt: np.ndarray
    z: np.ndarray
    u: Optional[np.ndarray]
    rows: np.ndarray
    active: np.ndarray
    offsets: np.ndarray
    counts: np.ndarray
    Q: object
    """Q(dt) as constants (one dt for all rows) or per distinct dt (k, n, n)."""
    B: object
    inv: Optional[np.ndarray]
    """Each row's index into the distinct dt (None: one dt)."""
    horizon_s: Optional[float]
    in_order: bool
    """Whether the step-major rows are the table's rows in order (0, 1, ...)."""
    tape: object
    """The step's :class:`~kf_train.batch.tape.Tape` (or :class:`_Untraced`)."""


def _step_tape(preset, Q, B, p: int, per_row: bool, horizon_s) -> Union[Tape, '_Untraced']:
    """Return the tape of the lock-step's Kalman step (traced once per call)."""
    n, m = preset.dim_x, preset.dim_z
    # The step's arguments: True for an array input, constants as they are.
    shape_Q = [[True] * n for _ in range(n)] if per_row else Q
    shape_B = None if B is None else ([[True] * p for _ in range(n)] if per_row else B)
    shape = [[True] * n, [[True] * n for _ in range(n)], True, shape_Q, shape_B,
             [True] * p if p else None, [True] * m]
    try:
        return trace(lambda *args: _kalman_step(preset, horizon_s, None, *args), shape)
    except TypeError:       # S⁻¹ beyond 2x2 (np.linalg.inv) is not traced: run untraced
        return _Untraced(preset, horizon_s, shape)


def _lockstep_linear(preset, dt, z, u, groups: Groups, objects: np.ndarray, x0, P0, out,
                     unique_dt, horizon_s=None) -> np.ndarray:
    """
    Filter ``objects`` (codes) of a linear preset in lock-step; fill ``out`` by row.

    Step k corrects the k-th row of every object that has one, all at once: the state
    of object s lives in column s of (n, K) arrays (:func:`_lockstep_rows`). The
    objects run in blocks of LOCKSTEP_BLOCK columns, each block through all its steps,
    so that every intermediate stays in the CPU's cache (the arithmetic of a column does
    not depend on its block). ``out`` is (x, P, x_prior, P_prior, predicted x,
    predicted P, NIS), each written step-major; returns the rows in that order.
    ``unique_dt`` is np.unique(dt, return_inverse=True).
    """
    # One initial estimate for every object, or one each: x0 (n, K), P0 (n, n, K) in the
    # order of ``objects`` (a stream's objects carry their state from the previous block).
    x0, P0 = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
    if x0.ndim == 2:
        order = _by_count(groups.counts[objects])                    # as _lockstep_rows
        x0, P0 = x0[:, order], P0[:, :, order]
    objects, counts, active, offsets, rows = _lockstep_rows(groups, objects)
    K = objects.shape[0]
    if K == 0 or counts[0] == 0:
        return rows
    dyn = preset.dynamics
    dts, inv = unique_dt
    Q_u = dyn.Q_batch(dts)
    B_u = dyn.B_batch(dts) if u is not None else None
    if dts.shape[0] == 1:       # one dt: Q and B as constants (zeros and ones skipped)
        Q, B, inv = soa_const(Q_u[0]), None if B_u is None else soa_const(B_u[0]), None
    else:
        Q, B = Q_u, B_u
    tape = _step_tape(preset, Q, B, 0 if u is None else u.shape[1], inv is not None, horizon_s)
    step = _Step(preset, dt, z, u, rows, active, offsets, counts, Q, B, inv, horizon_s,
                 _in_order(rows), tape)
    for c0 in range(0, K, LOCKSTEP_BLOCK):
        c1 = min(K, c0 + LOCKSTEP_BLOCK)
        x_state = (np.array(x0[:, c0:c1]) if x0.ndim == 2 else
                   np.repeat(x0[:, None], c1 - c0, axis=1))
        P_state = (np.array(P0[:, :, c0:c1]) if P0.ndim == 3 else
                   np.repeat(P0[:, :, None], c1 - c0, axis=2))
        _lockstep_block(step, c0, c1, x_state, P_state, out)
    return rows


def _in_order(rows: np.ndarray) -> bool:
    """Return whether ``rows`` is 0, 1, ..., R−1."""
    R = rows.shape[0]
    return bool(R == 0 or (rows[0] == 0 and rows[-1] == R - 1
                           and np.all(rows[1:] > rows[:-1])))


def _kalman_step(preset, horizon_s, N, x, P, d, Q, B, u, z) -> list:
    """
    Return one lock-step's outputs, flat: x, P, x⁻, P⁻ (the predictions ahead), the NIS.

    The entries are arrays (one column per object) or symbols (:func:`tape.trace`);
    Q and B are constants (Python floats) where every row has the same one.
    """
    n, m = preset.dim_x, preset.dim_z
    Hs, Rs = soa_const(preset.model.H), soa_const(preset.model.R)
    F = _transition(preset.dynamics.A, d, n)
    xp = soa_mv(F, x)                                   # x⁻ = F x + B u
    if B is not None:
        xp = [entry_add(e, f) for e, f in zip(xp, soa_mv(B, u))]
    Pp = soa_prior_covariance(F, P, Q)                   # P⁻ = F P Fᵀ + Q
    K_gain, S, S_inv = soa_gain_terms(Pp, Hs, Rs, N)     # K = P⁻ Hᵀ S⁻¹
    hx = soa_mv(Hs, xp)
    y = [z[i] - hx[i] for i in range(m)]                 # y = z − H x⁻
    xn = [entry_add(e, f) for e, f in zip(xp, soa_mv(K_gain, y))]   # x = x⁻ + K y
    I_KH = soa_msub(soa_const(np.eye(n)), soa_mm(K_gain, Hs))
    Pn = soa_sym(soa_madd(soa_mm(soa_mm(I_KH, Pp), soa_t(I_KH)),
                          soa_mm(soa_mm(K_gain, Rs), soa_t(K_gain))))  # Joseph form
    outputs = [xn, Pn, xp, Pp]
    if horizon_s:
        # The prediction to t + horizon_s, each row's control held.
        outputs += list(predict_soa(preset.dynamics, horizon_s, xn, Pn, u))
    outputs.append([soa_nis(y, S, S_inv)])              # NIS = yᵀ S⁻¹ y
    return [e for part in outputs for row in part for e in (row if isinstance(row, list)
                                                            else [row])]


def _lockstep_block(step: _Step, c0: int, c1: int, x_state, P_state, out) -> None:
    """Run the objects c0..c1−1 through their steps, writing ``out`` step-major."""
    preset = step.preset
    n, m = preset.dim_x, preset.dim_z
    p = 0 if step.u is None else step.u.shape[1]
    per_row, tape = step.inv is not None, step.tape
    size = c1 - c0
    buffers = tape.buffers(size)
    targets = [target for target in out if target is not None]
    stages = [np.empty((size,) + target.shape[1:]) for target in targets]
    x_next, P_next = np.empty_like(x_state), np.empty_like(P_state)
    for k in range(int(step.counts[c0])):
        a = min(int(step.active[k]), c1) - c0          # this block's objects at step k
        lo = int(step.offsets[k]) + c0
        # The rows in table order (one clock, ids in turn) are read as views, not gathered.
        r = slice(lo, lo + a) if step.in_order else step.rows[lo:lo + a]
        inputs = [x_state[i, :a] for i in range(n)]
        inputs += [P_state[i, j, :a] for i in range(n) for j in range(n)]
        inputs.append(step.dt[r])
        if per_row:
            idx = step.inv[r]
            inputs += [step.Q[:, i, j][idx] for i in range(n) for j in range(n)]
            if step.B is not None:
                inputs += [step.B[:, i, j][idx] for i in range(n) for j in range(p)]
        inputs += [step.u[r, i] for i in range(p)]
        inputs += [step.z[r, i] for i in range(m)]
        values = tape.replay(inputs, buffers, a)
        # Stacked in the cache, then copied whole: 2.5× faster than writing each entry
        # into the (N, n, n) outputs with a stride (0.53 → 0.2 s for 4·10⁶ rows).
        column = 0
        for stage, target in zip(stages, targets):
            flat = stage[:a].reshape(a, -1)
            for c in range(flat.shape[1]):
                flat[:, c] = values[column + c]
            column += flat.shape[1]
            target[lo:lo + a] = stage[:a]
        for i in range(n):
            x_next[i, :a] = values[i]
            for j in range(n):
                P_next[i, j, :a] = values[n + n * i + j]
        x_state, x_next, P_state, P_next = x_next, x_state, P_next, P_state


class _Untraced:
    """The step run on the arrays themselves, as a tape would replay it."""

    def __init__(self, preset, horizon_s, shape):
        """Keep the step's constants and its arguments' shape."""
        self.preset, self.horizon_s, self.shape = preset, horizon_s, shape

    def buffers(self, size: int) -> list:
        """Return an empty list: the step allocates its arrays as it goes."""
        return []

    def replay(self, inputs, buffers, a: int) -> list:
        """Return the outputs for the flat ``inputs`` (as Tape.replay)."""
        flat = iter(inputs)

        def fill(leaf: object) -> object:
            if isinstance(leaf, list):
                return [fill(e) for e in leaf]
            return next(flat) if leaf is True else leaf

        args = [fill(argument) for argument in self.shape]
        return _kalman_step(self.preset, self.horizon_s, a, *args)


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
    ``groups``, from :func:`group_rows` of the ids, saves grouping them again. With one
    dt for every row, the result's F is a read-only view of one matrix.
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
    out = series_outputs(N, owner.dim_x, horizon_s) + (np.empty(N),)
    alone = np.arange(groups.counts.shape[0])
    dts, inv = unique_steps(dt)
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
        out[6][rows] = result.nis
    F_u = owner.dynamics.F_batch(dts)
    # One dt: F is one matrix, a read-only view for every row (as run_linear_series
    # gives it), not 32 bytes written per row (0.1-0.4 s at 4·10⁶ rows).
    F = np.broadcast_to(F_u[0], (N,) + F_u.shape[1:]) if dts.shape[0] == 1 else F_u[inv]
    return SeriesResult(t_arr, out[0], out[1], out[2], out[3], F, horizon_s, out[4], out[5],
                        out[6])


def unique_steps(dt: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return np.unique(dt, return_inverse=True), the inverse flat, sooner for one dt.

    A bank on one clock has a single dt: found by min = max (two passes, 0.01 s for
    4·10⁶ rows) rather than by sorting (0.3 s).
    """
    if dt.size and dt.min() == dt.max():
        return dt[:1].copy(), np.zeros(dt.shape[0], dtype=np.intp)
    dts, inv = np.unique(dt, return_inverse=True)
    return dts, inv.reshape(-1)


def _split_objects(groups: Groups):
    """
    Return (alone, together): the objects to run one by one and those in lock-step.

    Objects sorted by rows, most first: the first s run alone, the rest in lock-step
    for counts[s] steps. Cost: s calls + counts[s] steps; the cheapest s is taken.
    """
    K = groups.counts.shape[0]
    by_rows = _by_count(groups.counts)
    counts = np.concatenate([groups.counts[by_rows], [0]])
    cost = np.arange(K + 1) * SERIES_CALL_S + counts * LOCKSTEP_STEP_S
    split = int(np.argmin(cost))
    return by_rows[:split], by_rows[split:]


def _run_together(preset, dt, z, u, groups: Groups, together, x0, P0, unique_dt, horizon_s,
                  out) -> None:
    """Filter ``together`` in lock-step into ``out`` (x, P, priors, predictions, NIS)."""
    rows = _lockstep_linear(preset, dt, z, u, groups, together, x0, P0, out, unique_dt,
                            horizon_s)
    R = rows.shape[0]
    # Every entry finite when the sums are (a NaN or ±inf makes its sum non-finite);
    # only then (rarely) each row is checked: 4·10⁶ rows' all() cost ~0.2 s, the sums 0.02.
    if not (np.isfinite(out[0][:R].sum()) and np.isfinite(out[1][:R].sum())):
        bad = rows[~(np.all(np.isfinite(out[0][:R]), axis=1)
                     & np.all(np.isfinite(out[1][:R]), axis=(1, 2)))]
        if bad.size:
            raise SeriesError(int(bad.min()), 'the filter diverged (non-finite estimate)')
    if not _in_order(rows):
        _to_row_order(rows, out)


def _to_row_order(rows: np.ndarray, out) -> None:
    """
    Move the lock-step's results, written step-major at 0..R−1, to their ``rows``.

    Gathered (the table's rows in order, each reading its place) rather than scattered:
    10⁶ shuffled rows of (2, 2) take 60-90 ns each, 135-210 scattered (2-core host).
    """
    R, N = rows.shape[0], out[0].shape[0]
    place = np.empty(N, dtype=np.intp)
    place[rows] = np.arange(R)
    targets = None
    if R < N:       # some rows are not the lock-step's: only its own, in table order
        mine = np.zeros(N, dtype=bool)
        mine[rows] = True
        targets = np.flatnonzero(mine)
        place = place[targets]
    for array in out:
        if array is not None:
            moved = np.take(array[:R], place, axis=0)
            if targets is None:
                array[...] = moved
            else:
                array[targets] = moved
