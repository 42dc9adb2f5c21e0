"""
The 2-state train filter in closed form, in plain Python floats.

The model is the one :mod:`kf_train.filters.models` builds for the train: state
[position m, velocity m/s], ``F(dt) = [[1, dt], [0, 1]]``, a position measurement
``H = [1, 0]`` with scalar variance R, and process noise Q(dt) from
:class:`~kf_train.filters.models.WhiteNoiseAcceleration`,
:class:`~kf_train.filters.models.PerStepNoise` or any callable dt -> 2x2 matrix.
The arithmetic is :mod:`kf_train.filters.closed_form` (predict, and the Joseph form
reduced for the optimal gain); :meth:`FastTrainFilter.step` and
:meth:`FastTrainFilter.run` transcribe it inline, so that a predict and update cost
about as much as the arithmetic itself: no numpy call, no temporary array, no call.

The results are those of :func:`kf_train.filters.kalman.predict` and
:func:`kf_train.filters.kalman.update` to rounding; the tests hold them to 1e-9, and
the inline copies to closed_form bit for bit. The checks are the generic path's too:
a bad input raises ``ValueError`` naming it, a step that would overflow raises, and
either leaves the filter exactly as it was.
"""

import math
from typing import NamedTuple, Optional, Tuple

from kf_train.filters.closed_form import (
    correct, FastUpdate, noise_terms_function, NoiseModel, predict)
from kf_train.filters.validation import as_covariance, as_duration, as_finite_array, as_vector
import numpy as np

_INF = float('inf')


def _number(name: str, value) -> float:
    """Return ``value`` as a finite float, or raise ValueError naming it."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a finite number, got {value!r}') from None
    if not -_INF < number < _INF:
        raise ValueError(f'{name} must be a finite number, got {number}')
    return number


class FastTrainFilter:
    """
    A Kalman filter for the constant-velocity train, state and covariance as floats.

    ``step(z, dt_s, R)`` is one predict over dt_s and one update with z: the hot path,
    one method call per measurement. ``predict`` and ``update`` are available apart.
    The statistics of the latest update are ``innovation``, ``innovation_variance``,
    ``nis`` and ``gain`` (all at once: ``last_update()``).
    """

    # One tuple (x0, x1, P00, P01, P11, y, S, NIS, K0, K1) rather than ten attributes:
    # loading and storing attributes is a large share of a step's cost in CPython.
    __slots__ = ('_s', '_R', '_c', '_noise', '_terms')

    def __init__(self, x0, P0, noise: NoiseModel = None, R: Optional[float] = None):
        """
        Start from mean ``x0`` (2,) and covariance ``P0`` (2, 2).

        ``noise`` gives Q(dt) (None: no process noise); ``R`` is the default
        measurement variance [m²] for updates that do not pass their own.
        """
        self._noise = noise
        self._terms = noise_terms_function(noise)
        # (dt, Q00, Q01, Q11, R): Q(dt) of the latest dt and the latest valid R passed
        # to step(), as a cache
        self._c = (math.nan, 0.0, 0.0, 0.0, math.nan)
        self.R = R
        self._s = (0.0,) * 5 + (math.nan,) * 5
        self.set_state(x0, P0)

    @property
    def R(self) -> Optional[float]:
        """Return the default measurement variance [m²], or None when there is none."""
        return None if math.isnan(self._R) else self._R

    @R.setter
    def R(self, value: Optional[float]) -> None:
        """Set the default measurement variance (finite, >= 0) or None for none."""
        if value is None:
            self._R = math.nan  # makes S NaN: step() then asks for an R
            return
        r = _number('R', value)
        if r < 0.0:
            raise ValueError(f'R must be a finite number >= 0, got {r}')
        self._R = r

    def set_state(self, x, P) -> None:
        """Replace the state with a validated mean (2,) and covariance (2, 2)."""
        x = as_vector('x', x, 2)
        P = as_covariance('P', P, 2)
        self._s = (float(x[0]), float(x[1]), float(P[0, 0]), float(P[0, 1]),
                   float(P[1, 1])) + self._s[5:]

    @property
    def state(self) -> Tuple[float, float, float, float, float]:
        """Return (position m, velocity m/s, P00, P01, P11) as floats."""
        return self._s[:5]

    @property
    def x(self) -> np.ndarray:
        """Return the state mean [position m, velocity m/s] as a new array."""
        return np.array(self._s[:2])

    @property
    def P(self) -> np.ndarray:
        """Return the state covariance as a new 2x2 array."""
        _, _, p00, p01, p11 = self._s[:5]
        return np.array([[p00, p01], [p01, p11]])

    @property
    def innovation(self) -> float:
        """Return y = z - x⁻[0] of the latest update [m] (NaN before any)."""
        return self._s[5]

    @property
    def innovation_variance(self) -> float:
        """Return S = P⁻[0, 0] + R of the latest update [m²]."""
        return self._s[6]

    @property
    def nis(self) -> float:
        """Return y² / S of the latest update."""
        return self._s[7]

    @property
    def gain(self) -> Tuple[float, float]:
        """Return the latest update's Kalman gain, as the pair K0, K1."""
        return self._s[8], self._s[9]

    def last_update(self) -> FastUpdate:
        """Return the statistics of the latest update."""
        y, s, nis, k0, k1 = self._s[5:]
        return FastUpdate(y, s, nis, (k0, k1))

    @classmethod
    def from_model(cls, model, x0, P0) -> 'FastTrainFilter':
        """
        Return a filter for a :class:`~kf_train.filters.models.LinearModel` of the train.

        The model must be the 1-D constant-velocity one (F(dt) = [[1, dt], [0, 1]],
        H = [[1, 0]], no control input), as ``constant_velocity_model`` builds it; its
        Q(dt) and R are used. Anything else raises ValueError: use kalman.py for it.
        """
        H = np.asarray(getattr(model, 'H', None), dtype=object)
        ok = (getattr(model, 'B', None) is None and H.shape == (1, 2)
              and H.tolist() == [[1.0, 0.0]])
        if ok:
            for dt in (0.0, 0.37, 12.5):
                ok = ok and np.array_equal(model.F(dt), [[1.0, dt], [0.0, 1.0]])
        if not ok:
            raise ValueError(f'model must be the constant-velocity train model with '
                             f'H = [[1, 0]] and no control input, got {model!r}')
        return cls(x0, P0, model.Q, float(np.asarray(model.R)[0, 0]))

    def copy(self) -> 'FastTrainFilter':
        """Return an independent filter with the same model, state and statistics."""
        other = FastTrainFilter(self.x, self.P, self._noise, self.R)
        other._s = self._s
        return other

    def _noise_for(self, dt: float) -> Tuple[float, float, float]:
        """Return Q(dt)'s entries for a float dt, computing them only when dt changes."""
        if not 0.0 <= dt < _INF:
            as_duration('dt', dt)  # raises with the usual message
        if dt != self._c[0]:
            try:
                terms = tuple(self._terms(dt))
            except OverflowError:  # float ** raises where * would give inf
                raise ValueError('prediction produced a non-finite state; inputs are too '
                                 'large') from None
            self._c = (dt,) + terms + self._c[4:]
        return self._c[1:4]

    def predict(self, dt_s: float) -> None:
        """Propagate the state over dt_s >= 0 seconds."""
        dt = dt_s if type(dt_s) is float else _number('dt', dt_s)
        q00, q01, q11 = self._noise_for(dt)
        x0, x1, p00, p01, p11 = predict(*self._s[:5], dt, q00, q01, q11)
        if not 0.0 * (x0 + p00 + p01 + p11) == 0.0:
            _overflow('prediction', x0, p00, p01, p11)
        self._s = (x0, x1, p00, p01, p11) + self._s[5:]

    def update(self, z: float, R: Optional[float] = None) -> FastUpdate:
        """Correct the state with position measurement z [m] of variance R [m²]."""
        z, R = self._measurement(z, R)
        prior = self._s[:5]
        try:
            posterior, result = correct(*prior, z, R)
        except ZeroDivisionError:
            _bad_innovation_variance(0.0, z, R, *prior)
        nis = result.nis
        if not 0.0 * sum(posterior) == 0.0 <= nis < _INF:
            _check_step(z, R, *prior, *posterior, nis, result.innovation_variance)
        self._s = posterior + (result.innovation, result.innovation_variance,
                               nis) + result.gain
        return result

    def _measurement(self, z, R) -> Tuple[float, float]:
        """Return (z, R) as floats, R defaulting to self.R; raise naming a bad one."""
        if type(z) is not float:
            z = _number('z', z)
        if R is None:
            return z, self._R
        if type(R) is not float:
            R = _number('R', R)
        if not 0.0 <= R < _INF:
            raise ValueError(f'R must be a finite number >= 0, got {R}')
        return z, R

    def step(self, z: float, dt_s: float, R: Optional[float] = None) -> float:
        """Predict over dt_s, then update with z (variance R, default self.R); return NIS."""
        # A dt equal to the latest one (a steady rate) needs neither a check nor a new
        # Q(dt), and an R equal to the latest one no check: the cached floats are used.
        # Anything else is converted to float and checked once.
        q_dt, q00, q01, q11, r = self._c
        try:
            if not dt_s == q_dt:
                q_dt = None
            if R is None:
                r = self._R
            elif not R == r:
                r = None
        except ValueError:  # an array compared: checked below
            q_dt = r = None
        if q_dt is None:
            dt = dt_s if type(dt_s) is float else _number('dt', dt_s)
            q00, q01, q11 = self._noise_for(dt)
        else:
            dt = q_dt
        if type(z) is not float:
            z = _number('z', z)
        if r is None:
            r = R if type(R) is float else _number('R', R)
            if not 0.0 <= r < _INF:
                raise ValueError(f'R must be a finite number >= 0, got {r}')
            self._c = self._c[:4] + (r,)
        R = r
        x0, x1, p00, p01, p11, _, _, _, _, _ = self._s
        # closed_form.predict and closed_form.correct, inline, operation for operation (a
        # test holds them bit for bit): calling them makes a step 2.7x as slow, 1.78
        # against 0.66 µs per measurement (make bench row 1's step() case, and the same
        # loop calling them, on its data; issue 22).
        # Predict: x⁻ = F x;  P⁻ = F P Fᵀ + Q with F = [[1, dt], [0, 1]]:
        #   P⁻00 = P00 + dt (P01 + (P01 + dt P11)) + Q00
        #   P⁻01 = P01 + dt P11 + Q01;  P⁻11 = P11 + Q11
        p01_dt = p01 + dt * p11
        x0 = x0 + dt * x1
        p00 = p00 + dt * (p01 + p01_dt) + q00
        p01 = p01_dt + q01
        p11 = p11 + q11
        s = p00 + R                         # S = H P⁻ Hᵀ + R
        y = z - x0                          # y = z - H x⁻
        try:
            k0 = p00 / s                    # K = P⁻ Hᵀ / S
            k1 = p01 / s
            a = R / s                       # = 1 - k0, without the cancellation
        except ZeroDivisionError:
            _bad_innovation_variance(s, z, R, x0, x1, p00, p01, p11)
        # The Joseph form P = (I - K H) P⁻ (I - K H)ᵀ + K R Kᵀ, for this optimal K
        # and H = [1, 0], entry by entry (a = 1 - k0 = R/S; the second forms use
        # P⁻01 - k1 P⁻00 = a P⁻01 and R k0 = a P⁻00):
        #   P00 = a² P⁻00 + R k0² = a P⁻00
        #   P01 = a (P⁻01 - k1 P⁻00) + R k0 k1 = a P⁻01
        #   P11 = (P⁻11 - k1 P⁻01) - k1 (P⁻01 - k1 P⁻00) + R k1² = P⁻11 - k1 P⁻01
        n11 = p11 - k1 * p01
        y0 = x0 + k0 * y                    # x = x⁻ + K y
        y1 = x1 + k1 * y
        nis = y * y / s                     # NIS = y² / S
        # One test for all: a NaN or ±inf anywhere (a non-finite z or prior included)
        # reaches y0, y1, P11 or the NIS and makes the sum NaN or ±inf (P00 = a P⁻00
        # and P01 = a P⁻01 with 0 <= a <= 1 are finite when those are), and S < 0 a
        # negative NIS; _check_step then says which input or step it was.
        if not 0.0 * (y0 + y1 + n11 + nis) == 0.0 <= nis:
            _check_step(z, R, x0, x1, p00, p01, p11, y0, y1, a * p00, a * p01, n11, nis, s)
        self._s = (y0, y1, a * p00, a * p01, n11, y, s, nis, k0, k1)
        return nis

    def run(self, z, dt_s, R=None) -> 'FastRun':
        """
        Filter a whole series: ``z`` (n,), ``dt_s`` and ``R`` scalars or (n,) arrays.

        Row i is ``step(z[i], dt_s[i], R[i])``, with the same arithmetic, in one loop
        without a call per row. Returns every row's posterior and statistics; the
        filter ends after the last row. A row that fails raises ValueError naming it
        and leaves the filter after the last good row.
        """
        z = as_vector('z', z)
        n = z.shape[0]
        dts = _series('dt_s', dt_s, n)
        if min(dts, default=0.0) < 0.0:
            raise ValueError(f'dt_s must be >= 0, got {min(dts)}')
        if R is None:
            if self.R is None:
                raise ValueError('R must be given: the filter has no default R')
            R = self._R
        rs = _series('R', R, n)
        if min(rs, default=0.0) < 0.0:
            raise ValueError(f'R must be >= 0, got {min(rs)}')
        flat, stopped = self._rows(z.tolist(), dts, rs)
        out = np.fromiter(flat, float, len(flat)).reshape(-1, 7)
        nis = out[:, 5] * out[:, 5] / out[:, 6]  # y² / S, as step() computes it
        good = np.isfinite(out).all(axis=1) & (nis >= 0.0) & (nis < _INF)
        last = out.shape[0] if good.all() else int(np.argmin(good))
        if last < n:
            # Leave the filter after the last good row; name the failing row's cause.
            if last > 0:
                self._commit_row(out[last - 1], float(nis[last - 1]))
            if last == out.shape[0] and stopped:
                raise ValueError(f'row {last}: {stopped}') from None
            try:
                self.step(z[last], dts[last], rs[last])
            except ValueError as error:
                raise ValueError(f'row {last}: {error}') from None
            raise AssertionError(f'row {last} failed in run() but not in step()')
        if n:
            self._commit_row(out[-1], float(nis[-1]))
        return FastRun(x=out[:, 0:2], P=_covariances(out[:, 2], out[:, 3], out[:, 4]),
                       innovation=out[:, 5], innovation_variance=out[:, 6], nis=nis)

    def _rows(self, zs: list, dts: list, rs: list):
        """
        Return (flat, stopped): (x0, x1, P00, P01, P11, y, S) of each row, in one list.

        ``stopped`` is False when every row ran, None when S = 0 stopped the loop (the
        row after the last one kept; step() names it) and the ValueError of Q(dt) when
        that stopped it. The filter itself is not changed.
        """
        x0, x1, p00, p01, p11 = self._s[:5]
        q_dt, q00, q01, q11, _ = self._c
        # One flat list of floats: a list of per-row tuples would keep the garbage
        # collector busy scanning them.
        flat = []
        extend = flat.extend
        try:
            for z_i, dt, r in zip(zs, dts, rs):
                if dt != q_dt:
                    q00, q01, q11 = self._noise_for(dt)
                    q_dt = dt
                # The arithmetic of step() (closed_form, inline), line for line. Calling
                # closed_form makes run() 1.8x as slow (2.0 against 1.11 µs a row), and
                # calling step() 1.4x (1.42 µs): make bench row 1's run() case, and the
                # loop calling them, on its data; issue 22.
                p01_dt = p01 + dt * p11
                x0 = x0 + dt * x1
                p00 = p00 + dt * (p01 + p01_dt) + q00
                p01 = p01_dt + q01
                p11 = p11 + q11
                s = p00 + r
                y = z_i - x0
                k0 = p00 / s
                k1 = p01 / s
                a = r / s
                p11 = p11 - k1 * p01
                p00 = a * p00
                p01 = a * p01
                x0 = x0 + k0 * y
                x1 = x1 + k1 * y
                extend((x0, x1, p00, p01, p11, y, s))
        except ZeroDivisionError:
            return flat, None
        except ValueError as error:
            return flat, error
        return flat, False

    def _commit_row(self, row: np.ndarray, nis: float) -> None:
        """Set the state and statistics from a row of run(): (x0, x1, P00, P01, P11, y, S)."""
        # (run() keeps no gains.)
        self._s = tuple(row.tolist()) + (nis, math.nan, math.nan)


class FastRun(NamedTuple):
    """The posteriors and statistics of :meth:`FastTrainFilter.run`, one row per step."""

    x: np.ndarray
    """(n, 2) posterior means."""
    P: np.ndarray
    """(n, 2, 2) posterior covariances."""
    innovation: np.ndarray
    """(n,) y = z - x⁻[0]."""
    innovation_variance: np.ndarray
    """(n,) S."""
    nis: np.ndarray
    """(n,) y² / S."""


def _overflow(step: str, *values: float) -> None:
    """Raise unless every value is finite (a quick sum test may overflow by itself)."""
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f'{step} produced a non-finite state; inputs are too large')


def _bad_innovation_variance(s: float, z: float, R: float, *prior: float) -> None:
    """Raise for S = 0 (or a missing R), naming the cause as the generic path would."""
    _check_inputs(z, R)
    _overflow('prediction', *prior)
    raise ValueError(f'innovation covariance S = H P Hᵀ + R is singular: [[{s}]]')


def _check_inputs(z: float, R: float) -> None:
    """Raise for a non-finite z or a missing R."""
    if math.isnan(R):
        raise ValueError('R must be given: the filter has no default R')
    if not -_INF < z < _INF:
        raise ValueError(f'z must be a finite number, got {z}')


def _check_step(z: float, R: float, x0: float, x1: float, p00: float, p01: float,
                p11: float, *posterior: float) -> None:
    """Raise for a step whose quick test failed, naming the cause; else return."""
    _check_inputs(z, R)
    _overflow('prediction', x0, x1, p00, p01, p11)
    *state, nis, s = posterior
    _overflow('update', *state)
    if not 0.0 <= nis < _INF:
        raise ValueError(f'update produced an invalid NIS {nis}; S = [[{s}]]')


def _series(name: str, value, n: int) -> list:
    """Return a scalar or (n,) series as a list of n Python floats."""
    array = as_finite_array(name, value)
    if array.ndim == 0:
        return [float(array)] * n
    return as_vector(name, array, n).tolist()


def _covariances(p00: np.ndarray, p01: np.ndarray, p11: np.ndarray) -> np.ndarray:
    """Return (n, 2, 2) symmetric matrices from their three distinct entries."""
    P = np.empty((p00.shape[0], 2, 2))
    P[:, 0, 0], P[:, 0, 1], P[:, 1, 0], P[:, 1, 1] = p00, p01, p01, p11
    return P
