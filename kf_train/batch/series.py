"""
Run a preset over a whole time series, row by row: the reference the fast paths match.

Every series function takes times ``t_s`` (N,), measurements ``z`` (N, m) and, when the
preset has a control input, ``u`` (N, p), where row k's control acts over the
interval that ends at ``t_s[k]``. The initial estimate holds at ``t0_s``; each row is
predicted to from the previous time and then corrected, exactly as the seeds do.

Times are rounded to whole nanoseconds first (as ROS stamps are), so that a sampling
period repeats exactly: ``t = k·0.1`` written as text gives dt = 0.1 s for every row,
not a mix of 0.09999999999999964 and 0.10000000000000142.

:func:`run_series` works for every preset (linear or EKF) and calls the model's
``predict`` and ``update`` row by row; :func:`run_filter_series` does the same with
any filter of :func:`kf_train.filters.make_filter`. The fast paths beside this module
give the same numbers (to rounding): :mod:`~kf_train.batch.linear` (linear presets,
vectorised along time) and :mod:`~kf_train.batch.bank` (many objects, rows tagged by
id).
"""

from typing import NamedTuple, Optional, Tuple

from kf_train.filters import (
    as_covariance, as_finite_array, as_scalar, as_vector, NS_PER_S, seconds_to_ns,
    seconds_to_ns_array)
import numpy as np

# |t| beyond this (~292 years) overflows int64 nanoseconds.
MAX_ABS_TIME_S = 9.2e9


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
    nis: Optional[np.ndarray] = None
    """The NIS yᵀ S⁻¹ y of row k's measurement (N,), NaN where the row fused none."""


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
    t0 = as_scalar('t0_s', t0_s)
    if t.size and max(float(np.max(np.abs(t))), abs(t0)) > MAX_ABS_TIME_S:
        raise ValueError(f'times must be within ±{MAX_ABS_TIME_S:g} s')
    t_ns = seconds_to_ns_array(t)
    t0_ns = seconds_to_ns(t0)
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


def series_outputs(N: int, n: int, horizon_s) -> Tuple[Optional[np.ndarray], ...]:
    """Return empty (x, P, prior x, prior P, predicted x, predicted P) for N rows, n states."""
    return (np.empty((N, n)), np.empty((N, n, n)), np.empty((N, n)), np.empty((N, n, n)),
            np.empty((N, n)) if horizon_s else None, np.empty((N, n, n)) if horizon_s else None)


def series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0, dt=None):
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


def without_gaps(z, missing):
    """Return (z with 0 on rows flagged ``missing``, the flags or None when there is none)."""
    if missing is None or not np.any(missing):
        return z, None
    missing = np.asarray(missing, dtype=bool).reshape(-1)
    return np.where(missing.reshape(-1, *([1] * (np.ndim(z) - 1))), 0.0, z), missing


def run_series(preset, t_s, z, u=None, *, t0_s: float = 0.0, horizon_s=None, x0=None,
               P0=None, missing=None) -> SeriesResult:
    """
    Filter a series row by row with the preset's model (any preset, linear or EKF).

    ``horizon_s`` None uses the preset's horizon, 0 turns prediction off. ``x0``,
    ``P0`` override the preset's initial estimate. Rows flagged in ``missing`` (N,)
    have no measurement: they are predicted, not updated (x = x⁻, P = P⁻).
    """
    z, missing = without_gaps(z, missing)
    dt, z, u, horizon_s, x, P = series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0)
    N, model = dt.shape[0], preset.model
    out_x, out_P, prior_x, prior_P, pred_x, pred_P = series_outputs(N, preset.dim_x, horizon_s)
    nis = np.full(N, np.nan)
    for k in range(N):
        u_k = None if u is None else u[k]
        try:
            x, P = model.predict(x, P, dt[k], u_k)   # x⁻ = F x + B u, P⁻ = F P Fᵀ + Q
            prior_x[k], prior_P[k] = x, P
            if missing is None or not missing[k]:
                x, P, result = model.update(x, P, z[k])    # x = x⁻ + K y, Joseph P
                nis[k] = result.nis
            out_x[k], out_P[k] = x, P
            if horizon_s:
                pred_x[k], pred_P[k] = model.predict(x, P, horizon_s, u_k)
        except ValueError as error:
            raise SeriesError(k, str(error)) from None
    F = preset.dynamics.F_batch(dt)
    return SeriesResult(np.asarray(t_s, dtype=float), out_x, out_P, prior_x, prior_P, F,
                        horizon_s, pred_x, pred_P, nis)


def run_filter_series(filt, t_s, z, u=None, *, t0_s: float = 0.0, horizon_s=None, x0=None,
                      P0=None) -> SeriesResult:
    """
    Filter a series row by row with a filter from ``kf_train.filters.make_filter``.

    The filter is reset to (x0, P0), the preset's initial estimate by default, and
    then predicts and updates every row, as :func:`run_series` does; x and P are
    the filter's mean and covariance (for the particle filter, the particles').
    """
    preset = filt.preset
    dt, z, u, horizon_s, x0, P0 = series_inputs(preset, t_s, z, u, t0_s, horizon_s, x0, P0)
    filt.reset(x0, P0)
    nis = np.empty(dt.shape[0])
    out_x, out_P, prior_x, prior_P, pred_x, pred_P = filter_rows(filt, dt, z, u, horizon_s,
                                                                 nis=nis)
    return SeriesResult(np.asarray(t_s, dtype=float), out_x, out_P, prior_x, prior_P,
                        preset.dynamics.F_batch(dt), horizon_s, pred_x, pred_P, nis)


def filter_rows(filt, dt: np.ndarray, z, u, horizon_s, missing=None, regimes=None,
                nis=None):
    """
    Predict and update ``filt`` row by row from its current state (no reset).

    Return (posterior x, P, prior x, P, predicted x, P), the predictions None without a
    horizon; a step's ValueError becomes a SeriesError naming the row. Rows flagged in
    ``missing`` are predicted, not updated. ``regimes`` (N, 1 + modes), for a filter of
    regimes (:class:`~kf_train.batch.RailSeriesFilter`), receives each row's regime
    probabilities and the NIS of its position (NaN where the row fused none); ``nis``
    (N,), for any other filter, the NIS of each row's update (NaN where it had none).
    """
    N = dt.shape[0]
    out_x, out_P, prior_x, prior_P, pred_x, pred_P = series_outputs(
        N, filt.preset.dim_x, horizon_s)
    for k in range(N):
        u_k = None if u is None else u[k]
        try:
            filt.predict(dt[k], u_k)
            prior_x[k], prior_P[k] = filt.mean, filt.covariance
            updated = missing is None or not missing[k]
            if updated:
                result = filt.update(z[k])
            if nis is not None:   # (a filter of regimes returns None when it starts)
                nis[k] = result.nis if updated and result is not None else np.nan
            out_x[k], out_P[k] = filt.mean, filt.covariance
            if horizon_s:
                pred_x[k], pred_P[k] = filt.predict_ahead(horizon_s, u_k)
            if regimes is not None:
                regimes[k, :-1] = filt.mode_probabilities
                regimes[k, -1] = filt.position_nis if updated else np.nan
        except ValueError as error:
            raise SeriesError(k, str(error)) from None
    return out_x, out_P, prior_x, prior_P, pred_x, pred_P
