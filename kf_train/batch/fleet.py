"""
A fleet: N independent 2-state train filters stepped at once, as numpy arrays.

Every filter is the train model of :mod:`kf_train.filters.closed_form` (F(dt) =
[[1, dt], [0, 1]], H = [1, 0], Q(dt) from one shared noise model, its own R); filter i
of the fleet gives bit for bit what a :class:`~kf_train.filters.FastTrainFilter` fed
the same numbers would, and so the generic kalman.py path to rounding.

The state is kept as five component arrays (position, velocity, P00, P01, P11) of
length N rather than (N, 2) and (N, 2, 2): each equation is then one numpy call
on contiguous memory. A step works through the fleet in chunks of ``chunk_size``
filters so that its temporaries stay in the CPU cache, writes into a second set of
arrays, checks them, and only then swaps them in: a step that fails (a bad input or
an overflow in any filter) raises ValueError naming the input and the first filter
concerned, and leaves every filter as it was.
"""

import math
from typing import NamedTuple, Tuple

from kf_train.filters import (
    COVARIANCE_RTOL, noise_terms_function, NoiseModel, per_step_noise_terms, per_step_periods,
    per_step_weights, PerStepNoise, white_noise_terms_into, WhiteNoiseAcceleration)
import numpy as np

DEFAULT_CHUNK_SIZE = 32768
"""Filters per chunk: 7 temporaries of 256 KiB stay within a typical L2/L3 cache."""

_COMPONENTS = ('x0', 'x1', 'p00', 'p01', 'p11')
_STATISTICS = ('innovation', 'innovation_variance', 'nis')


class FleetState(NamedTuple):
    """Read-only views of a fleet's state, one entry per filter."""

    position: np.ndarray
    velocity: np.ndarray
    p00: np.ndarray
    p01: np.ndarray
    p11: np.ndarray


def _finite_array(name: str, value, n: int) -> np.ndarray:
    """Return ``value`` as a float64 array of shape (n,) or a 0-d scalar; check shape."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(f'{name} must be numeric: {error}') from None
    if array.ndim == 0:
        return array
    if array.shape != (n,):
        raise ValueError(f'{name} must be a scalar or have shape ({n},), got {array.shape}')
    return array


def _first_bad(name: str, array: np.ndarray, what: str, bad: np.ndarray) -> None:
    """Raise ValueError naming the first entry of ``array`` flagged in ``bad``."""
    if array.ndim == 0:
        raise ValueError(f'{name} must be {what}, got {float(array)}')
    where = np.unravel_index(int(np.argmax(bad)), array.shape)
    raise ValueError(f'{name} must be {what}, got {float(array[where])} for filter {where[0]}')


def _check_finite(name: str, array: np.ndarray) -> None:
    """Raise naming the first non-finite entry."""
    if not math.isfinite(float(np.add.reduce(array, axis=None))):
        bad = ~np.isfinite(array)
        if bad.any():
            _first_bad(name, array, 'finite', bad)


def _check_non_negative(name: str, array: np.ndarray) -> None:
    """Raise naming the first entry that is not finite and >= 0."""
    _check_finite(name, array)
    if array.size and float(np.minimum.reduce(array, axis=None)) < 0.0:
        _first_bad(name, array, '>= 0', array < 0.0)


class TrainFleet:
    """
    N independent constant-velocity train filters, stepped together.

    ``step(z, dt_s, R)`` predicts every filter over its dt_s and updates it with its
    z; z is (N,), dt_s and R are scalars shared by all or (N,) arrays. With ``index``
    (distinct filter numbers) only those filters take a step, with z, dt_s and R of
    that length; the others are left exactly as they are.

    ``state``, ``innovation``, ``innovation_variance`` and ``nis`` are read-only views
    of the fleet's arrays, without a copy: valid until the next step, which reuses
    their memory (copy what you keep). ``x``, ``P`` and ``filter_state`` are copies.
    """

    def __init__(self, x0, P0, noise: NoiseModel = None, R=None, *,
                 chunk_size: int = DEFAULT_CHUNK_SIZE):
        """
        Start N filters from means ``x0`` (N, 2) and covariances ``P0`` (N, 2, 2).

        ``P0`` may also be one (2, 2) matrix for all. ``noise`` is the process noise
        model shared by all filters (None: no process noise); ``R`` is the default
        measurement variance, a scalar or (N,), or None to require one per step.
        """
        x0 = np.array(x0, dtype=float)
        if x0.ndim != 2 or x0.shape[1] != 2:
            raise ValueError(f'x0 must have shape (N, 2), got {x0.shape}')
        n = x0.shape[0]
        _check_finite('x0', x0)
        P0 = np.array(P0, dtype=float)
        if P0.shape == (2, 2):
            P0 = np.broadcast_to(P0, (n, 2, 2))
        if P0.shape != (n, 2, 2):
            raise ValueError(f'P0 must have shape ({n}, 2, 2) or (2, 2), got {P0.shape}')
        _check_covariances('P0', P0)
        if int(chunk_size) < 1:
            raise ValueError(f'chunk_size must be >= 1, got {chunk_size}')
        self._n = n
        self._chunk = int(chunk_size)
        self._noise = noise
        self._terms = noise_terms_function(noise)
        self.R = R
        # Two sets of component and statistic arrays: a step reads one, writes the
        # other, and swaps them once the result is checked.
        self._sets = [
            {name: np.empty(n) for name in _COMPONENTS + _STATISTICS} for _ in range(2)]
        current = self._sets[0]
        current['x0'][:], current['x1'][:] = x0[:, 0], x0[:, 1]
        current['p00'][:], current['p01'][:], current['p11'][:] = (
            P0[:, 0, 0], P0[:, 0, 1], P0[:, 1, 1])
        for name in _STATISTICS:
            current[name].fill(math.nan)
        self._current = 0
        size = min(self._chunk, max(n, 1))
        self._scratch = [np.empty(size) for _ in range(8)]

    # -- read access ---------------------------------------------------------------

    def __len__(self) -> int:
        """Return the number of filters N."""
        return self._n

    @property
    def R(self):
        """Return the default measurement variance (a float, an (N,) array or None)."""
        return self._R

    @R.setter
    def R(self, value) -> None:
        """Set the default measurement variance: scalar or (N,), finite and >= 0, or None."""
        if value is None:
            self._R = None
            return
        array = _finite_array('R', value, self._n)
        _check_non_negative('R', array)
        self._R = float(array) if array.ndim == 0 else _read_only(array.copy())

    def _view(self, name: str) -> np.ndarray:
        """Return a read-only view of one current array."""
        return _read_only(self._sets[self._current][name].view())

    @property
    def state(self) -> FleetState:
        """Return read-only views of the five component arrays."""
        return FleetState(*(self._view(name) for name in _COMPONENTS))

    @property
    def x(self) -> np.ndarray:
        """Return the means as a new (N, 2) array [position m, velocity m/s]."""
        current = self._sets[self._current]
        return np.stack([current['x0'], current['x1']], axis=1)

    @property
    def P(self) -> np.ndarray:
        """Return the covariances as a new (N, 2, 2) array."""
        current = self._sets[self._current]
        P = np.empty((self._n, 2, 2))
        P[:, 0, 0], P[:, 1, 1] = current['p00'], current['p11']
        P[:, 0, 1] = P[:, 1, 0] = current['p01']
        return P

    @property
    def innovation(self) -> np.ndarray:
        """Return each filter's latest innovation y = z - x⁻[0] (read-only; NaN before)."""
        return self._view('innovation')

    @property
    def innovation_variance(self) -> np.ndarray:
        """Return each filter's latest S = P⁻00 + R (read-only)."""
        return self._view('innovation_variance')

    @property
    def nis(self) -> np.ndarray:
        """Return each filter's latest NIS y² / S (read-only)."""
        return self._view('nis')

    # -- stepping ------------------------------------------------------------------

    def step(self, z, dt_s, R=None, index=None) -> None:
        """
        Predict over dt_s and update with z, for all filters or those in ``index``.

        R defaults to the fleet's ``R``. On ValueError no filter has changed.
        """
        self._advance(z, dt_s, R, index, predict=True, update=True)

    def predict(self, dt_s, index=None) -> None:
        """Propagate all filters (or those in ``index``) over dt_s >= 0 seconds."""
        self._advance(None, dt_s, None, index, predict=True, update=False)

    def update(self, z, R=None, index=None) -> None:
        """Correct all filters (or those in ``index``) with z (variance R)."""
        self._advance(z, 0.0, R, index, predict=False, update=True)

    def _advance(self, z, dt_s, R, index, *, predict: bool, update: bool) -> None:
        """Check the inputs, run the kernel chunk by chunk, check, commit."""
        idx = None
        m = self._n
        if index is not None:
            idx = np.asarray(index)
            if idx.ndim != 1 or not (idx.size == 0 or np.issubdtype(idx.dtype, np.integer)):
                raise ValueError(f'index must be a 1-D array of filter numbers, got {index!r}')
            if idx.size and (idx.min() < 0 or idx.max() >= self._n):
                raise ValueError(f'index must be in [0, {self._n}), got '
                                 f'{int(idx.min())}..{int(idx.max())}')
            if np.unique(idx).size != idx.size:
                raise ValueError('index must not repeat a filter')
            m = idx.size
        dt = _finite_array('dt_s', dt_s, m)
        _check_non_negative('dt_s', dt)
        if update:
            if z is None:
                raise ValueError('z must be given')
            z = _finite_array('z', z, m)
            if z.ndim == 0:
                z = np.broadcast_to(z, (m,))
            _check_finite('z', z)
            if R is None:
                R = self._R
                if R is None:
                    raise ValueError('R must be given: the fleet has no default R')
                if idx is not None and not isinstance(R, float):
                    R = R[idx]
            R = _finite_array('R', R, m)
            _check_non_negative('R', R)
        q = self._noise_terms(dt) if predict else (0.0, 0.0, 0.0)
        chunk_terms = q if callable(q) else None

        source = self._sets[self._current]
        target = self._sets[1 - self._current]
        if idx is None:
            inputs = [source[name] for name in _COMPONENTS]
            outputs = [target[name] for name in _COMPONENTS + _STATISTICS]
            if not update:
                for name in _STATISTICS:  # a predict keeps the latest statistics
                    np.copyto(target[name], source[name])
        else:
            inputs = [source[name][idx] for name in _COMPONENTS]
            outputs = [np.empty(m) for _ in _COMPONENTS + _STATISTICS]
            if not update:
                for name, out in zip(_STATISTICS, outputs[5:]):
                    np.copyto(out, source[name][idx])
        with np.errstate(all='ignore'):  # overflow and S = 0 are found by _check below
            for start in range(0, m, self._chunk):
                part = slice(start, min(start + self._chunk, m))
                dt_part = _part(dt, part)
                if chunk_terms is not None:
                    q_part = chunk_terms(dt_part, self._scratch[5:8])
                else:
                    q_part = [_part(t, part) for t in q]
                _kernel([a[part] for a in inputs], _part(z, part), dt_part, _part(R, part),
                        q_part, [a[part] for a in outputs], self._scratch, predict, update)
        self._check(outputs, inputs, dt, idx, update)
        if idx is None:
            self._current = 1 - self._current
        else:
            for name, out in zip(_COMPONENTS + _STATISTICS, outputs):
                source[name][idx] = out

    def _noise_terms(self, dt: np.ndarray):
        """
        Return Q(dt)'s entries: floats for a scalar dt, else (n,) arrays or a function.

        For white-noise acceleration the function computes a chunk's entries into
        scratch arrays, where they stay in the cache: fn(dt chunk, 3 arrays) -> 3 arrays.
        """
        if dt.ndim == 0:
            try:
                return tuple(self._terms(float(dt)))
            except OverflowError:
                raise ValueError('prediction produced a non-finite state; inputs are too '
                                 'large') from None
        noise = self._noise
        if noise is None:
            return (0.0, 0.0, 0.0)
        if type(noise) is WhiteNoiseAcceleration:
            return _white_noise_chunk(float(noise.q))
        if type(noise) is PerStepNoise:
            return _per_step_noise_arrays(noise, dt)
        # Another callable: evaluated once per distinct dt.
        values, inverse = np.unique(dt, return_inverse=True)
        terms = np.array([self._terms(float(v)) for v in values]).reshape(-1, 3)
        return tuple(terms[inverse, k] for k in range(3))

    def _check(self, outputs, inputs, dt, idx, update: bool) -> None:
        """Raise ValueError for the first filter whose step overflowed or had S <= 0."""
        x0, x1, p00, p01, p11, _, s, nis = outputs
        watched = (x0, x1, p00, p01, p11, nis) if update else (x0, p00, p01, p11)
        total = sum(float(np.add.reduce(a, axis=None)) for a in watched)
        s_ok = not update or x0.size == 0 or float(np.minimum.reduce(s)) > 0.0
        if math.isfinite(total) and s_ok:
            return
        state = (x0, x1, p00, p01, p11)
        bad_state = np.zeros(x0.shape, dtype=bool)
        for a in state:
            bad_state |= ~np.isfinite(a)
        bad = bad_state.copy()
        if update:
            bad |= ~(s > 0.0) | ~np.isfinite(nis)
        if not bad.any():
            return  # the sum overflowed, not a value
        i = int(np.argmax(bad))
        number = f'filter {i if idx is None else int(idx[i])}'
        if not update or not _prior_finite(inputs, dt, i):
            raise ValueError(f'{number}: prediction produced a non-finite state; inputs are '
                             f'too large')
        if not s[i] > 0.0:
            raise ValueError(f'{number}: innovation covariance S = H P Hᵀ + R is singular: '
                             f'[[{float(s[i])}]]')
        if bad_state[i]:
            raise ValueError(f'{number}: update produced a non-finite state; inputs are too '
                             f'large')
        raise ValueError(f'{number}: update produced an invalid NIS {float(nis[i])}; '
                         f'S = [[{float(s[i])}]]')

    # -- one filter ----------------------------------------------------------------

    def filter_state(self, i: int) -> Tuple[float, float, float, float, float]:
        """Return filter i's (position, velocity, P00, P01, P11) as floats."""
        current = self._sets[self._current]
        return tuple(float(current[name][i]) for name in _COMPONENTS)


def _read_only(array: np.ndarray) -> np.ndarray:
    """Return ``array`` with writing disabled."""
    array.flags.writeable = False
    return array


def _part(value, part: slice):
    """Return a chunk of an (n,) array, or a scalar as it is."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        return value[part]
    return value


def _prior_finite(inputs, dt: np.ndarray, i: int) -> bool:
    """Return whether filter i's predicted state (before the update) is finite."""
    x0, x1, p00, p01, p11 = (float(a[i]) for a in inputs)
    dt = float(dt) if dt.ndim == 0 else float(dt[i])
    with np.errstate(all='ignore'):
        p01_dt = p01 + dt * p11
        prior = (x0 + dt * x1, p00 + dt * p01 + dt * p01_dt, p01_dt, p11)
    return all(math.isfinite(v) for v in prior)


def _white_noise_chunk(q: float):
    """Return fn(dt, scratch) -> (Q00, Q01, Q11): models.white_noise_terms_into for q."""
    return lambda dt, scratch: white_noise_terms_into(q, dt, scratch)


def _per_step_noise_arrays(noise: PerStepNoise, dt: np.ndarray) -> Tuple:
    """Return PerStepNoise's Q(dt) entries for an array of dt, as models.py computes them."""
    a, c, b = (float(noise.Q_step[0, 0]), float(noise.Q_step[0, 1]),
               float(noise.Q_step[1, 1]))
    T = float(noise.period_s)
    if float(np.max(per_step_periods(dt, T)[0], initial=0.0)) >= 2.0 ** 17:
        # (n-1)·n·(2n-1) would no longer be exact in a double: go one by one.
        terms = np.array([per_step_noise_terms(a, c, b, T, float(v)) for v in dt])
        return terms[:, 0], terms[:, 1], terms[:, 2]
    s0, s1, s2 = per_step_weights(dt, T)
    return a * s0 + 2.0 * c * s1 + b * s2, c * s0 + b * s1, b * s0


def _check_covariances(name: str, P: np.ndarray) -> None:
    """Raise unless every P[i] is finite, symmetric and positive semi-definite."""
    _check_finite(name, P)
    a, b, c, d = P[:, 0, 0], P[:, 0, 1], P[:, 1, 0], P[:, 1, 1]
    scale = np.maximum(1.0, np.max(np.abs(P.reshape(-1, 4)), axis=1))
    asymmetric = np.abs(b - c) > COVARIANCE_RTOL * scale
    if asymmetric.any():
        i = int(np.argmax(asymmetric))
        raise ValueError(f'{name} must be symmetric, got {P[i].tolist()} for filter {i}')
    m = 0.5 * (b + c)
    # Smallest eigenvalue of [[a, m], [m, d]], the test as_covariance makes.
    smallest = 0.5 * (a + d) - np.hypot(0.5 * (a - d), m)
    negative = smallest < -COVARIANCE_RTOL * scale
    if negative.any():
        i = int(np.argmax(negative))
        raise ValueError(
            f'{name} must be positive semi-definite, got {P[i].tolist()} for filter {i}')


def _kernel(prior, z, dt, R, q, out, scratch, predict: bool, update: bool) -> None:
    """
    Step one chunk: ``prior`` (x0, x1, P00, P01, P11) into ``out`` (the same and y, S, NIS).

    The arithmetic of :mod:`kf_train.filters.closed_form` (and FastTrainFilter.step),
    operation for operation, so that every filter's result is the scalar path's bit for
    bit; in place, chunk by chunk, because temporaries would leave the cache.
    """
    x0, x1, p00, p01, p11 = prior
    X0, X1, P00, P01, P11, Y, S, NIS = out
    n = X0.shape[0]
    t0, t1, t2, t3, t4 = (a[:n] for a in scratch[:5])
    mul, add, sub, div = np.multiply, np.add, np.subtract, np.divide
    q00, q01, q11 = q
    if predict:
        # x⁻ = F x;  P⁻ = F P Fᵀ + Q with F = [[1, dt], [0, 1]]
        mul(p11, dt, out=t0)
        add(p01, t0, out=t0)            # t0 = P01 + dt P11
        mul(x1, dt, out=t1)
        add(x0, t1, out=t1)             # t1 = x⁻0 = x0 + dt x1
        add(p01, t0, out=t2)
        mul(t2, dt, out=t2)
        add(p00, t2, out=t2)
        add(t2, q00, out=t2)            # t2 = P⁻00 = P00 + dt (P01 + t0) + Q00
        add(t0, q01, out=t0)            # t0 = P⁻01 = t0 + Q01
        add(p11, q11, out=t3)           # t3 = P⁻11 = P11 + Q11
    else:
        np.copyto(t1, x0)
        np.copyto(t2, p00)
        np.copyto(t0, p01)
        np.copyto(t3, p11)
    if not update:
        np.copyto(X0, t1)
        np.copyto(X1, x1)
        np.copyto(P00, t2)
        np.copyto(P01, t0)
        np.copyto(P11, t3)
        return
    add(t2, R, out=S)                   # S = P⁻00 + R
    sub(z, t1, out=Y)                   # y = z - x⁻0
    div(t2, S, out=P00)                 # (P00 holds K0 for now) K0 = P⁻00 / S
    mul(P00, Y, out=t4)
    add(t1, t4, out=X0)                 # x0 = x⁻0 + K0 y
    div(t0, S, out=P01)                 # (P01 holds K1 for now) K1 = P⁻01 / S
    mul(P01, Y, out=X1)
    add(x1, X1, out=X1)                 # x1 = x⁻1 + K1 y
    mul(P01, t0, out=P11)
    sub(t3, P11, out=P11)               # P11 = P⁻11 - K1 P⁻01
    div(R, S, out=t4)                   # a = 1 - K0 = R / S
    mul(t4, t2, out=P00)                # P00 = a P⁻00
    mul(t4, t0, out=P01)                # P01 = a P⁻01
    mul(Y, Y, out=NIS)
    div(NIS, S, out=NIS)                # NIS = y² / S
