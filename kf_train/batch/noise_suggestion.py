"""
The process noise the recent data suggest, for a running filter's diagnostics.

``/diagnostics`` flags a windowed mean NIS outside its χ² bounds ("noise too small"
or "too large"), which says that q or R is wrong but not which way to move q or how
far. :class:`RunningNoiseEstimate` keeps the latest measurements and, on request,
returns the maximum-likelihood q of that window with its confidence interval: the
likelihood of :mod:`kf_train.batch.noise_likelihood` (the node's own filter, started
on the window's first measurement as the node starts), with R fixed at the value the node
uses (the measurements carry it). Running maximum likelihood on a sliding window
tracks a q that changes (a train that starts braking hard) with a delay of about a
window.

It is pure (numpy only, no scipy, no ROS): the node calls :meth:`add` per fused
measurement and :meth:`suggest` at its diagnostics period. For the presets measuring
the position alone the likelihood runs for a whole grid of q at once
(:mod:`kf_train.batch.noise_grid`: a quarter-decade grid, then fine grids of spacing
1e-2 in log q around the minimum and the bound); otherwise the 1-D search is a grid
of decades of log q, refined by golden-section search. Both are written here because
the nodes must not import scipy. The interval is the Wald interval of log q from the
curvature (two more evaluations), or, when the window cannot tell q from 0, [0, the
likelihood-ratio bound] (½χ²₀ + ½χ²₁ at the boundary, as ``kf-train tune`` does).
"""

import collections
import math
from typing import NamedTuple, Optional, Sequence

from kf_train.batch import noise_grid
from kf_train.batch.noise_likelihood import make_segment, NoiseSetting, TuningProblem
from kf_train.filters import chi2_quantile, NS_PER_S
from kf_train.presets import is_constant_velocity, Preset
import numpy as np

_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
_DECADE = math.log(10.0)


class NoiseSuggestion(NamedTuple):
    """The q a window of measurements suggests."""

    process_noise_density: float
    """Maximum-likelihood q [m²/s³] of the window (0 when the window shows none)."""
    low: float
    high: float
    """Its confidence interval [m²/s³] (low 0 when q = 0 is not rejected)."""
    count: int
    """Innovations in the window's likelihood."""

    def advice(self, current_q: float) -> str:
        """Return which way and how far to move ``current_q``, for a diagnostics line."""
        q = self.process_noise_density
        if self.low <= current_q <= self.high:
            return (f'q = {current_q:.3g} is consistent with the last {self.count} '
                    f'measurements (suggested {q:.3g}, [{self.low:.3g}, {self.high:.3g}])')
        way = 'increase' if current_q < self.low else 'decrease'
        factor = f' about x{q / current_q:.3g}' if current_q > 0.0 and q > 0.0 else ''
        return (f'{way} q{factor}: suggested {q:.3g} m²/s³ [{self.low:.3g}, {self.high:.3g}] '
                f'from the last {self.count} measurements, now {current_q:.3g}')


def _golden_section(f, a: float, b: float, tolerance: float) -> float:
    """Return the minimiser of a unimodal f on [a, b] to ``tolerance``."""
    c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
    fc, fd = f(c), f(d)
    while b - a > tolerance:
        if fc <= fd:                       # the minimum is in [a, d]
            b, d, fd = d, c, fc
            c = b - _GOLDEN * (b - a)
            fc = f(c)
        else:                              # in [c, b]
            a, c, fc = c, d, fd
            d = a + _GOLDEN * (b - a)
            fd = f(d)
    return c if fc <= fd else d


def _bisect(f, a: float, b: float, tolerance: float) -> float:
    """Return x in [a, b] with f(x) = 0, for f(a) < 0 < f(b)."""
    while b - a > tolerance:
        middle = 0.5 * (a + b)
        if f(middle) < 0.0:
            a = middle
        else:
            b = middle
    return 0.5 * (a + b)


def _values(values) -> tuple:
    """Return a row's values as a tuple of numbers (a tuple of floats as it is)."""
    if type(values) is tuple and all(type(v) is float for v in values):
        return values                     # the node's rows: no array round trip
    return tuple(np.ravel(values))


class RunningNoiseEstimate:
    """The maximum-likelihood q of the latest ``window`` measurements of a stream."""

    def __init__(self, preset: Preset, *, window: int = 300, min_samples: int = 30,
                 first_velocity_std_mps: float = 100.0, confidence: float = 0.95):
        """Keep up to ``window`` measurements; suggest once ``min_samples`` are in."""
        if not is_constant_velocity(preset) or not preset.linear:
            raise ValueError(f'preset {preset.name!r} has no white-noise acceleration '
                             'density to suggest ([position, velocity] states needed)')
        for name, value, low in (('window', window, 4), ('min_samples', min_samples, 4)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f'{name} must be an integer >= {low}, got {value!r}')
        if min_samples > window:
            raise ValueError(f'min_samples ({min_samples}) must be <= window ({window})')
        if not 0.0 < confidence < 1.0:
            raise ValueError(f'confidence must be in (0, 1), got {confidence!r}')
        self.preset = preset
        self.min_samples = min_samples
        self.first_velocity_std_mps = float(first_velocity_std_mps)
        self.confidence = float(confidence)
        self._rows = collections.deque(maxlen=window)
        self._previous: Optional[float] = None   # log q of the last suggestion
        self.evaluations = 0
        """Likelihood evaluations so far (each one q's filter run over the window)."""
        self.batched = noise_grid.batched(preset)
        """Search q on grids, many q per filter run (:mod:`~kf_train.batch.noise_grid`);
        False: one q at a time (golden section and bisection), as for other presets."""
        # The grids' covariance passes, reused by later windows of the same times.
        self._gains = noise_grid.GainCache()
        # The likelihood-ratio threshold and the Wald z of the confidence.
        self._threshold = 0.5 * chi2_quantile(1.0 - 2.0 * (1.0 - self.confidence), 1)
        self._z = math.sqrt(chi2_quantile(self.confidence, 1))
        self._no_control = preset.dim_u == 0

    def __len__(self) -> int:
        """Return how many measurements the window holds."""
        return len(self._rows)

    def add(self, stamp_ns: int, z: Sequence[float], u: Optional[Sequence[float]] = None
            ) -> None:
        """
        Append a fused measurement (stamps increasing; an older one clears the window).

        ``u`` is the control of the interval ending at ``stamp_ns``, required exactly
        when the preset has a control input.
        """
        if (u is None) != self._no_control:
            raise ValueError(f'u must be given exactly when preset {self.preset.name!r} '
                             'has a control input')
        if self._rows and stamp_ns <= self._rows[-1][0]:
            self.clear()                     # a restarted stream: a new window
        self._rows.append((int(stamp_ns), _values(z), None if u is None else _values(u)))

    def clear(self) -> None:
        """Forget the window (after a reset of the filter)."""
        self._rows.clear()
        self._previous = None

    def _problem(self) -> TuningProblem:
        """Return the tuning problem of the window, times relative to its first stamp."""
        stamps = np.array([row[0] for row in self._rows], dtype=np.int64)
        t = (stamps - stamps[0]) / NS_PER_S        # exact: differences of integers
        z = np.array([row[1] for row in self._rows], dtype=float)
        u = (None if self.preset.dim_u == 0
             else np.array([row[2] for row in self._rows], dtype=float))
        segment = make_segment(self.preset, t, z, u)
        return TuningProblem(self.preset, [segment], initialization='first_measurement',
                             first_velocity_std_mps=self.first_velocity_std_mps)

    def suggest(self, measurement_variances: Sequence[float]) -> Optional[NoiseSuggestion]:
        """Return the window's q with its interval, or None before ``min_samples``."""
        if len(self._rows) < self.min_samples:
            return None
        problem = self._problem()
        variances = tuple(float(r) for r in np.ravel(measurement_variances))

        def nll(v: float) -> float:
            self.evaluations += 1
            return -problem.log_likelihood(NoiseSetting(math.exp(v), variances))
        t = problem.segments[0].t_s
        dt, span = float(np.median(np.diff(t))), float(t[-1] - t[0])
        R = variances[0]
        # q from far below what the window can detect (q·T³ ≪ R) to far above R/dt³
        low, high = math.log(R / span ** 3 * 1e-4), math.log(R / dt ** 3 * 1e4)
        if self.batched:
            found = self._grid_suggest(problem, R, low, high)
            if found is not None:
                return NoiseSuggestion(*found, problem.rows)
        grid = np.arange(low, high + _DECADE, _DECADE)
        if self._previous is not None:       # warm start: the decades around the last one
            near = grid[np.abs(grid - self._previous) <= 3.0 * _DECADE]
            grid = near if near.size >= 3 else grid
        values = [nll(v) for v in grid]
        best = int(np.argmin(values))
        if best in (0, len(grid) - 1) and grid.size < round((high - low) / _DECADE) + 1:
            grid = np.arange(low, high + _DECADE, _DECADE)    # an edge: search everything
            values = [nll(v) for v in grid]
            best = int(np.argmin(values))
        a, b = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
        v_hat = _golden_section(nll, a, b, 1e-2)   # q to 1 %: plenty for advice
        self._previous = v_hat
        return self._interval(nll, v_hat, low, high, problem.rows)

    def _grid_suggest(self, problem: TuningProblem, R: float, low: float, high: float):
        """Return (q, low, high) searched on grids of q at once, or None (see noise_grid)."""
        segment = problem.segments[0]
        likelihood = noise_grid.WindowLikelihood(
            self.preset, segment.t_s, segment.z[:, 0], segment.u, R,
            self.first_velocity_std_mps, self._gains)

        def nll(v: np.ndarray) -> np.ndarray:
            self.evaluations += v.size
            return -likelihood.log_likelihoods(np.exp(v))
        return noise_grid.grid_search(nll, low, high, self._threshold, self._z)

    def _interval(self, nll, v_hat: float, low: float, high: float,
                  count: int) -> NoiseSuggestion:
        """Return the suggestion at log q = v_hat with its confidence interval."""
        f_hat = nll(v_hat)
        threshold, z = self._threshold, self._z
        drop_at_zero = nll(low) - f_hat
        if drop_at_zero <= threshold:        # q = 0 not rejected: [0, LR bound]
            q = 0.0 if drop_at_zero <= 1e-3 else math.exp(v_hat)
            if nll(high) - f_hat <= threshold:
                return NoiseSuggestion(q, 0.0, math.inf, count)
            upper = _bisect(lambda v: nll(v) - f_hat - threshold, max(v_hat, low), high, 1e-2)
            return NoiseSuggestion(q, 0.0, math.exp(upper), count)
        h = 1e-2                               # curvature of −ℓ in log q (central difference)
        curvature = (nll(v_hat + h) - 2.0 * f_hat + nll(v_hat - h)) / h ** 2
        sigma = 1.0 / math.sqrt(curvature) if curvature > 0.0 else math.inf
        return NoiseSuggestion(math.exp(v_hat), math.exp(v_hat - z * sigma),
                               math.exp(v_hat + z * sigma), count)
