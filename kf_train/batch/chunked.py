"""
Filter a table of any length in fixed blocks, each object's state carried across them.

:class:`StreamingReplay` takes rows in pieces of any size (``push``), cuts them into
blocks of ``block_rows`` rows at fixed positions of the stream, filters each block
with the in-memory runners of :mod:`kf_train.batch.series` started from the state
where the previous block left every object (its last time, x and P, or the filter's
snapshot), and returns each block's estimates as soon as it is done. Memory holds
one block and the state of every object seen, never the table.

Why fixed blocks: the vectorised linear path (:func:`run_linear_series`, the lock-step
bank) rounds differently depending on which rows it sees together. Cutting the stream
at fixed positions makes the result a function of the rows and ``block_rows`` only:
the same, bit for bit, whatever pieces the reader hands over (one row at a time, or
a million). A table of at most ``block_rows`` rows is one block, filtered exactly as
the in-memory replay does. The row-by-row paths (EKF presets, ``--filter``) do not
depend on the blocks at all.

With an ``id`` column a block runs as the in-memory bank does
(:func:`kf_train.batch.bank.run_bank`: ids with few rows in lock-step, ids with many
along their own time axis, split by the same cost model), each id starting from its
own carried state.

The RTS smoother needs every later row of an object before it can smooth a row, so
``smooth=True`` spills the forward results to temporary files
(:class:`kf_train.batch.spill.ForwardSpill`, about 160 bytes per row for two states)
and runs the backward pass block by block from the end, each object anchored on its
smoothed row of the next block. Memory stays bounded; disk grows with the rows.
"""

from typing import List, NamedTuple, Optional, Sequence, Tuple

from kf_train.batch.bank import _run_together, _split_objects, group_rows
from kf_train.batch.linear import run_linear_series
from kf_train.batch.series import (
    filter_rows, MAX_ABS_TIME_S, run_series, SeriesError, without_gaps)
from kf_train.filters import (
    as_covariance, as_finite_array, as_vector, NS_PER_S, regime_columns, seconds_to_ns,
    seconds_to_ns_array)
import numpy as np

# The last output column of an input with gaps: 1.0 updated, 0.0 predicted only.
UPDATED_COLUMN = 'updated'
# The NIS yᵀ S⁻¹ y of the row's measurement (as the bag replay's CSV names it); a filter
# with regimes: of the row's position.
NIS_COLUMN = 'nis'
# Rows filtered together: big enough for the vectorised paths to run at full speed,
# small enough that a block's work arrays stay far below the memory budget.
DEFAULT_BLOCK_ROWS = 65536


class RowError(ValueError):
    """A row could not be filtered; ``row`` is its index in the stream (0-based)."""

    def __init__(self, row: int, reason: str, kind: Optional[str] = None,
                 previous: Optional[int] = None, obj: Optional[int] = None):
        """
        Store the stream row, the reason and what kind of error it is.

        ``kind`` is 'range', 't0' or 'order' for a bad time (column t; ``previous`` is
        the stream row of the object's previous row for 'order'), None otherwise;
        ``obj`` is the row's object.
        """
        super().__init__(f'row {row}: {reason}')
        self.row, self.reason, self.kind = row, reason, kind
        self.previous, self.obj = previous, obj


class Rows(NamedTuple):
    """Rows of a stream: times, measurements, controls and object codes."""

    t: np.ndarray
    z: np.ndarray
    u: Optional[np.ndarray]
    codes: Optional[np.ndarray]
    """Each row's object (an index into the stream's labels), or None: one object."""
    missing: Optional[np.ndarray] = None
    """Rows without a measurement (True: predicted, not updated; z ignored), or None."""

    def take(self, start: int, stop: int) -> 'Rows':
        """Return rows [start, stop)."""
        cut = slice(start, stop)
        return Rows(self.t[cut], self.z[cut], None if self.u is None else self.u[cut],
                    None if self.codes is None else self.codes[cut],
                    None if self.missing is None else self.missing[cut])

    @staticmethod
    def join(parts: Sequence['Rows']) -> 'Rows':
        """Return the rows of ``parts`` one after the other."""
        if len(parts) == 1:
            return parts[0]
        cat = np.concatenate
        missing = None
        if any(p.missing is not None for p in parts):
            missing = cat([np.zeros(p.t.shape[0], dtype=bool) if p.missing is None
                           else p.missing for p in parts])
        return Rows(cat([p.t for p in parts]), cat([p.z for p in parts]),
                    None if parts[0].u is None else cat([p.u for p in parts]),
                    None if parts[0].codes is None else cat([p.codes for p in parts]),
                    missing)


class Estimates(NamedTuple):
    """A block's forward results, row by row (as kf_train.batch.series.SeriesResult)."""

    t_s: np.ndarray
    x: np.ndarray
    P: np.ndarray
    x_prior: np.ndarray
    P_prior: np.ndarray
    F: np.ndarray
    predicted_x: Optional[np.ndarray]
    predicted_P: Optional[np.ndarray]
    updated: Optional[np.ndarray] = None
    """1.0 where the row was updated, 0.0 where it had no measurement (a stream with gaps)."""
    regimes: Optional[np.ndarray] = None
    """A preset with regimes (rail): (N, modes + 1), the probabilities, then the NIS."""
    nis: Optional[np.ndarray] = None
    """Any other preset: the NIS of each row's measurement (N,), NaN where it fused none."""


class OutputBlock(NamedTuple):
    """Finished output rows: the id of each row (or None) and the output columns."""

    first_row: int
    codes: Optional[np.ndarray]
    columns: List[np.ndarray]


def resolve_horizon(preset, horizon_s) -> Optional[float]:
    """Return the horizon a run uses: the preset's for None, none for 0."""
    if horizon_s is None:
        return preset.horizon_s
    horizon_s = float(as_finite_array('horizon_s', horizon_s))
    if horizon_s < 0.0:
        raise ValueError(f'horizon_s must be >= 0, got {horizon_s}')
    return horizon_s or None


def output_header(preset, horizon: Optional[float], smooth: bool,
                  gaps: bool = False) -> List[str]:
    """
    Return the output columns after the id: t, states, variances, predicted, smoothed.

    Then ``nis`` (a preset with regimes, rail: after ``p_<regime>`` for each); with
    ``gaps`` (an input with rows without a measurement) a last column ``updated``.
    """
    names = preset.state_names
    header = ['t']
    prefixes = [''] + (['predicted_'] if horizon else []) + (['smoothed_'] if smooth else [])
    for prefix in prefixes:
        header += [prefix + name for name in names]
        header += ['var_' + prefix + name for name in names]
    if has_regimes(preset):
        header += regime_columns(preset.mode_names)
    return header + [NIS_COLUMN] + ([UPDATED_COLUMN] if gaps else [])


def has_regimes(preset) -> bool:
    """Return whether a preset's filter has regimes (the rail IMM), as its outputs show."""
    return bool(getattr(preset, 'mode_names', ()))


def estimate_columns(est: Estimates, smoothed=None) -> List[np.ndarray]:
    """Return the output columns of a block (the order of :func:`output_header`)."""
    columns = [est.t_s]
    pairs = [(est.x, est.P)]
    if est.predicted_x is not None:
        pairs.append((est.predicted_x, est.predicted_P))
    if smoothed is not None:
        pairs.append(smoothed)
    for x, P in pairs:
        n = x.shape[1]
        columns += [x[:, i] for i in range(n)]
        columns += [P[:, i, i] if P.ndim == 3 else P[:, i] for i in range(n)]
    if est.regimes is not None:
        columns += list(est.regimes.T)
    else:
        columns.append(est.nis)
    if est.updated is not None:
        columns.append(est.updated)
    return columns


def check_block_times(t: np.ndarray, first_row: int) -> np.ndarray:
    """Return the times as whole nanoseconds; raise RowError for one out of range."""
    big = np.flatnonzero(np.abs(t) > MAX_ABS_TIME_S)
    if big.size:
        k = int(big[0])
        raise RowError(first_row + k, f'{float(t[k])!r} s is out of range '
                       f'(|t| <= {MAX_ABS_TIME_S:g} s)', 'range')
    return seconds_to_ns_array(t)


class ObjectStates:
    """Where every object of a stream stands: its last time and row, and its estimate."""

    def __init__(self, preset, t0_s: float, filt=None):
        """Start with no object; ``filt`` keeps one filter snapshot per object."""
        n = preset.dim_x
        self.preset, self.filt, self.t0_s = preset, filt, float(t0_s)
        self.t0_ns = seconds_to_ns(self.t0_s)
        self.x0 = as_vector('x0', preset.initial_state, n)
        self.P0 = as_covariance('P0', preset.initial_covariance, n)
        self.seen = np.zeros(0, dtype=bool)
        self.last_ns = np.zeros(0, dtype=np.int64)
        self.last_row = np.zeros(0, dtype=np.int64)
        self.last_t = np.zeros(0)
        self.x = np.zeros((0, n))
        self.P = np.zeros((0, n, n))
        self.snapshots = {}

    def grow(self, count: int) -> None:
        """Make room for objects 0..count−1 (new ones start unseen)."""
        old = self.seen.shape[0]
        if count <= old:
            return
        extra = max(count, 2 * old) - old
        n = self.x.shape[1]
        self.seen = np.concatenate([self.seen, np.zeros(extra, dtype=bool)])
        self.last_ns = np.concatenate([self.last_ns, np.zeros(extra, dtype=np.int64)])
        self.last_row = np.concatenate([self.last_row, np.zeros(extra, dtype=np.int64)])
        self.last_t = np.concatenate([self.last_t, np.zeros(extra)])
        self.x = np.concatenate([self.x, np.zeros((extra, n))])
        self.P = np.concatenate([self.P, np.zeros((extra, n, n))])

    def start(self, obj: int) -> Tuple[float, np.ndarray, np.ndarray]:
        """Return (t0 [s], x0, P0) from which object ``obj`` continues."""
        if self.seen[obj]:
            return float(self.last_t[obj]), self.x[obj], self.P[obj]
        return self.t0_s, self.x0, self.P0

    def time_steps(self, t: np.ndarray, t_ns: np.ndarray, codes: np.ndarray,
                   first_row: int) -> np.ndarray:
        """Return dt [s] per row from its object's previous row; raise RowError."""
        order = np.argsort(codes, kind='stable')
        ts, cs = t_ns[order], codes[order]
        starts = np.ones(cs.shape[0], dtype=bool)
        starts[1:] = cs[1:] != cs[:-1]
        previous = np.empty_like(ts)
        previous[1:] = ts[:-1]
        first_objs = cs[starts]
        previous[starts] = np.where(self.seen[first_objs], self.last_ns[first_objs],
                                    self.t0_ns)
        step = ts - previous
        allowed_zero = starts.copy()
        allowed_zero[starts] = ~self.seen[first_objs]   # an object's very first row: t0
        bad = (step < 0) | ((step == 0) & ~allowed_zero)
        if bad.any():
            where = np.flatnonzero(bad)
            k = int(where[np.argmin(order[where])])
            row, obj = int(order[k]), int(cs[k])
            if starts[k] and not self.seen[obj]:
                raise RowError(first_row + row, f'{float(t[row])!r} is before the initial '
                               f'time t0 = {self.t0_s!r} s', 't0', None, obj)
            if starts[k]:
                prev_row, prev_t = int(self.last_row[obj]), float(self.last_t[obj])
            else:
                prev_row, prev_t = first_row + int(order[k - 1]), float(t[order[k - 1]])
            reason = f"{float(t[row])!r} is not after the previous row's t = {prev_t!r}"
            raise RowError(first_row + row, reason, 'order', prev_row, obj)
        dt = np.empty(t.shape[0])
        dt[order] = step / NS_PER_S
        return dt

    def remember(self, codes: np.ndarray, t: np.ndarray, t_ns: np.ndarray,
                 first_row: int, est: Estimates) -> None:
        """Store every object's last row of a block."""
        if codes.shape[0] and (codes == codes[0]).all():   # one object (no sort)
            objs, rows = codes[:1], np.array([codes.shape[0] - 1])
        else:
            objs, from_end = np.unique(codes[::-1], return_index=True)
            rows = codes.shape[0] - 1 - from_end             # each object's last row
        self.seen[objs] = True
        self.last_ns[objs], self.last_t[objs] = t_ns[rows], t[rows]
        self.last_row[objs] = first_row + rows
        self.x[objs], self.P[objs] = est.x[rows], est.P[rows]


def _as_estimates(result) -> Estimates:
    """Return a SeriesResult's fields as Estimates."""
    return Estimates(result.t_s, result.x, result.P, result.x_prior, result.P_prior,
                     None if result.F is None else np.asarray(result.F), result.predicted_x,
                     result.predicted_P, nis=result.nis)


def run_filter_rows(filt, dt: np.ndarray, z, u, horizon: Optional[float],
                    t: np.ndarray, missing=None) -> Estimates:
    """Predict and update ``filt`` row by row from its current state (no reset)."""
    if getattr(filt, 'partial_rows', False):
        missing = None      # it takes every row, its empty cells NaN (RailSeriesFilter)
    else:
        z, missing = without_gaps(z, missing)
    regimes = nis = None
    if has_regimes(filt.preset):
        regimes = np.empty((dt.shape[0], len(filt.mode_names) + 1))
    else:
        nis = np.empty(dt.shape[0])
    out_x, out_P, prior_x, prior_P, pred_x, pred_P = filter_rows(filt, dt, z, u, horizon,
                                                                 missing, regimes, nis)
    return Estimates(t, out_x, out_P, prior_x, prior_P, filt.preset.dynamics.F_batch(dt),
                     pred_x, pred_P, regimes=regimes, nis=nis)


class BlockFilter:
    """Filter one block of rows from the objects' carried states (the in-memory runners)."""

    def __init__(self, preset, horizon: Optional[float], states: ObjectStates,
                 priors: bool = True):
        """
        Use ``preset`` (and ``states.filt`` when given) with this horizon.

        ``priors`` False: the estimates need not hold the priors and F (no smoother).
        """
        self.preset, self.horizon, self.states = preset, horizon, states
        self.filt, self.priors = states.filt, priors

    def run(self, rows: Rows, first_row: int) -> Estimates:
        """Return the block's estimates; the states move to its last rows."""
        states, N = self.states, rows.t.shape[0]
        z = rows.z.reshape(N, self.preset.dim_z)
        u = None if rows.u is None else rows.u.reshape(N, self.preset.dim_u)
        codes = np.zeros(N, dtype=np.int64) if rows.codes is None else rows.codes
        states.grow(int(codes.max(initial=-1)) + 1)
        t_ns = check_block_times(rows.t, first_row)
        dt = states.time_steps(rows.t, t_ns, codes, first_row)
        missing = rows.missing
        if missing is not None and not missing.any():
            missing = None
        try:
            if rows.codes is None:
                est = self._one(rows.t, dt, z, u, missing)
            else:
                est = self._bank(rows.t, dt, z, u, codes, missing)
        except SeriesError as error:
            raise RowError(first_row + error.row, error.reason) from None
        states.remember(codes, rows.t, t_ns, first_row, est)
        return est

    def _one(self, t, dt, z, u, missing=None) -> Estimates:
        """Filter a block of one object's rows."""
        if self.filt is not None:
            return self._filter_rows(0, dt, z, u, t, missing)
        return self._series(0, t, z, u, missing, self.priors)

    def _series(self, obj: int, t, z, u, missing, priors: bool = True) -> Estimates:
        """Run the preset's series runner over one object's rows from its carried state."""
        t0, x0, P0 = self.states.start(obj)
        options = {'t0_s': t0, 'horizon_s': self.horizon or 0.0, 'x0': x0, 'P0': P0,
                   'missing': missing}
        if self.preset.linear:
            return _as_estimates(run_linear_series(self.preset, t, z, u, priors=priors,
                                                   **options))
        return _as_estimates(run_series(self.preset, t, z, u, **options))

    def _filter_rows(self, obj: int, dt, z, u, t, missing=None) -> Estimates:
        """Run ``filt`` over one object's rows, from its snapshot (or a fresh reset)."""
        states = self.states
        if obj in states.snapshots:
            self.filt.restore(states.snapshots[obj])
        else:
            self.filt.reset(states.x0, states.P0)
        est = run_filter_rows(self.filt, dt, z, u, self.horizon, t, missing)
        states.snapshots[obj] = self.filt.snapshot()
        return est

    def _bank(self, t, dt, z, u, codes, missing=None) -> Estimates:
        """Filter a block of several objects' rows (as run_bank, from carried states)."""
        N, n = t.shape[0], self.preset.dim_x
        objects, local = np.unique(codes, return_inverse=True)
        groups = group_rows(local.reshape(-1))
        out = (np.empty((N, n)), np.empty((N, n, n)), np.empty((N, n)), np.empty((N, n, n)),
               np.empty((N, n)) if self.horizon else None,
               np.empty((N, n, n)) if self.horizon else None, np.empty(N))
        alone = np.arange(objects.shape[0])
        regimes = np.empty((N, len(self.preset.mode_names) + 1)) \
            if has_regimes(self.preset) else None
        if self.filt is None and self.preset.linear:
            alone, together = _split_objects(groups)      # the bank's own cost model
            if missing is not None and together.size:     # objects with gaps: alone
                gappy = np.zeros(objects.shape[0], dtype=bool)
                gappy[local.reshape(-1)[missing]] = True
                alone = np.sort(np.concatenate([alone, together[gappy[together]]]))
                together = together[~gappy[together]]
            if together.size:
                starts = [self.states.start(int(objects[k])) for k in together]
                x0 = np.stack([start[1] for start in starts], axis=1)
                P0 = np.stack([start[2] for start in starts], axis=2)
                dts, inv = np.unique(dt, return_inverse=True)
                _run_together(self.preset, dt, z, u, groups, together, x0, P0,
                              (dts, inv.reshape(-1)), self.horizon, out)
        for k in alone:
            rows = groups.rows(k)
            try:
                est = self._object_rows(int(objects[k]), t[rows], dt[rows], z[rows],
                                        None if u is None else u[rows],
                                        None if missing is None else missing[rows])
            except SeriesError as error:
                raise SeriesError(int(rows[error.row]), error.reason) from None
            for array, value in zip(out, est[1:5] + est[6:8] + (est.nis,)):
                if array is not None and value is not None:
                    array[rows] = value
            if regimes is not None:
                regimes[rows] = est.regimes
        return Estimates(t, *out[:4], self.preset.dynamics.F_batch(dt), *out[4:6],
                         regimes=regimes, nis=None if regimes is not None else out[6])

    def _object_rows(self, obj: int, t, dt, z, u, missing=None) -> Estimates:
        """Filter one object's rows of a block alone."""
        if self.filt is not None:
            return self._filter_rows(obj, dt, z, u, t, missing)
        return self._series(obj, t, z, u, missing)
