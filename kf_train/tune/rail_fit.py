"""
Maximum likelihood of the rail IMM's noises: scipy's trust-region Newton on log-noises.

The likelihood (:func:`kf_train.batch.rail_likelihood.rail_log_likelihoods`) evaluates
many settings in one pass over the data for little more than the cost of one, so each
optimiser step asks for a whole finite-difference stencil at once: the centre, ±h on
every axis and the four corners of every pair (1 + 2n² points, 9 for two noises, 19
for three), which gives ℓ, its gradient and its Hessian (the observed information)
together. scipy's ``trust-exact`` (a trust-region Newton method) uses all three, so
it converges in a handful of passes; a start grid of decades (one pass) keeps it
away from a far-off start. The intervals come from the Hessian at the maximum, in
log-parameter space: exp(log θ̂ ± z·se(log θ̂)), as ``kf-train tune`` does for q.

Step h = 1e-2 in log θ: the stencil's truncation error is O(h²) ≈ 1e-4 relative; ℓ
is computed to ~1e-14 relative (|ℓ| ~ 10⁴ for 6000 fixes: ~1e-10 absolute), so the
rounding error of a second difference, ~1e-10/h² = 1e-6, stays far below the
curvatures (≥ 1 for any identified noise: se(log θ) ≤ 1).
"""

import math
import time
from typing import Callable, List, NamedTuple, Sequence, Tuple

from kf_train.batch import RailNoise
from kf_train.tune.noise_fit import boundary_threshold, normal_quantile
import numpy as np

STEP = 1e-2
START_DECADES = (-2.0, -1.0, 0.0, 1.0, 2.0)


class RailParameter(NamedTuple):
    """One estimated noise of the rail model."""

    name: str
    """The RailNoise field (and the preset's parameter, or measurement_variance)."""
    symbol: str
    unit: str


PARAMETERS = {
    'acceleration_noise': RailParameter('acceleration_noise', 'q_a', 'm²/s⁵'),
    'command_noise': RailParameter('command_noise', 'q_l', 'm²/s⁵'),
    'capability_noise': RailParameter('capability_noise', 'q_c', 'm²/s⁵'),
    'measurement_variance': RailParameter('measurement_variance', 'R', 'm²'),
}


class RailEstimate(NamedTuple):
    """One estimate with its interval (natural scale)."""

    parameter: RailParameter
    value: float
    std_error: float
    low: float
    high: float
    identified: bool


class RailFit(NamedTuple):
    """What :func:`fit_rail_noise` found."""

    setting: RailNoise
    estimates: Tuple[RailEstimate, ...]
    log_likelihood: float
    start_log_likelihood: float
    passes: int
    """Passes over the data (each evaluates a whole stencil of settings)."""
    evaluations: int
    """Settings evaluated, over all passes."""
    seconds: float
    converged: bool
    message: str


Likelihoods = Callable[[Sequence[RailNoise]], np.ndarray]
"""ℓ of each of a list of settings (one pass over the data)."""


def _setting(names: Sequence[str], vector, fixed: RailNoise) -> RailNoise:
    """Return ``fixed`` with the named fields set to exp(vector)."""
    return fixed._replace(**{n: float(math.exp(v)) for n, v in zip(names, vector)})


def stencil(n: int, h: float = STEP) -> np.ndarray:
    """Return the offsets of the centre, ±h e_i and (±h, ±h) on every pair: (1 + 2n², n)."""
    points = [np.zeros(n)]
    for i in range(n):
        for sign in (1.0, -1.0):
            p = np.zeros(n)
            p[i] = sign * h
            points.append(p)
    for i in range(n):
        for j in range(i):
            for si in (1.0, -1.0):
                for sj in (1.0, -1.0):
                    p = np.zeros(n)
                    p[i], p[j] = si * h, sj * h
                    points.append(p)
    return np.array(points)


def derivatives(values: np.ndarray, n: int, h: float = STEP):
    """Return (f, gradient, Hessian) from f on :func:`stencil`'s points (central differences)."""
    f0 = values[0]
    g, H = np.zeros(n), np.zeros((n, n))
    for i in range(n):
        plus, minus = values[1 + 2 * i], values[2 + 2 * i]
        g[i] = (plus - minus) / (2.0 * h)                             # ∂f/∂v_i
        H[i, i] = (plus - 2.0 * f0 + minus) / h ** 2                  # ∂²f/∂v_i²
    k = 1 + 2 * n
    for i in range(n):
        for j in range(i):
            pp, pm, mp, mm = values[k:k + 4]
            H[i, j] = H[j, i] = (pp - pm - mp + mm) / (4.0 * h * h)   # ∂²f/∂v_i∂v_j
            k += 4
    return f0, g, H


class _Stencils:
    """−ℓ/rows, its gradient and Hessian at a vector, one pass per new vector."""

    def __init__(self, likelihoods: Likelihoods, names, fixed: RailNoise, rows: int):
        """Wrap the pass; ``rows`` scales ℓ to per-measurement values."""
        self.likelihoods, self.names, self.fixed, self.rows = likelihoods, names, fixed, rows
        self.offsets = stencil(len(names))
        self.kept = None
        self.passes = self.evaluations = 0

    def at(self, vector):
        """Return (f, g, H) of −ℓ/rows at ``vector`` (cached for the last vector)."""
        vector = np.asarray(vector, dtype=float)
        if self.kept is not None and np.array_equal(self.kept[0], vector):
            return self.kept[1]
        points = vector + self.offsets
        try:
            ll = self.likelihoods([_setting(self.names, p, self.fixed) for p in points])
            values = np.where(np.isfinite(ll), -ll / self.rows, 1e30)
        except (ValueError, ArithmeticError):
            values = np.full(points.shape[0], 1e30)
        self.passes += 1
        self.evaluations += points.shape[0]
        result = derivatives(values, len(self.names))
        self.kept = (vector.copy(), result)
        return result


def _start(likelihoods: Likelihoods, names, fixed: RailNoise, vector: np.ndarray):
    """Return (the best of a grid of decades around ``vector``, its size, ℓ at ``vector``)."""
    process = [i for i, n in enumerate(names) if n != 'measurement_variance']
    # 5 values per noise (25 settings for two); 3 for three noises (27, not 125)
    decades = START_DECADES if len(process) <= 2 else START_DECADES[::2]
    grids = np.array(np.meshgrid(*[decades] * len(process), indexing='ij'))
    grids = grids.reshape(len(process), -1).T * math.log(10.0)
    points = np.repeat(vector[None], grids.shape[0], axis=0)
    points[:, process] += grids
    ll = likelihoods([_setting(names, p, fixed) for p in points])
    ll = np.where(np.isfinite(ll), ll, -np.inf)
    at_start = float(ll[int(np.flatnonzero(np.all(grids == 0.0, axis=1))[0])])
    return points[int(np.argmax(ll))], points.shape[0], at_start


def fit_rail_noise(likelihoods: Likelihoods, names: Sequence[str], start: RailNoise,
                   fixed: RailNoise, rows: int, confidence: float = 0.95) -> RailFit:
    """
    Return the maximum-likelihood values of the ``names`` fields, with intervals.

    ``likelihoods`` evaluates a list of settings in one pass; ``start`` gives the
    starting values of the estimated fields, ``fixed`` the others; ``rows`` is the
    number of measurements ℓ sums over. A process noise whose value 0 the data do not
    reject (ℓ drops by less than the boundary threshold when it is set to 0) gets the
    interval [0, bound] (:func:`_boundary`). Needs scipy.
    """
    from scipy import optimize
    began = time.perf_counter()
    names = list(names)
    vector = np.array([math.log(getattr(start, n)) for n in names])
    # The box: 10 decades below and 6 above the start; the likelihood is flat below
    # what the data can detect, and the optimiser stops there (gradient ~ 0).
    low, high = vector - 10.0 * math.log(10.0), vector + 6.0 * math.log(10.0)
    stencils = _Stencils(likelihoods, names, fixed, rows)
    vector, grid_points, start_ll = _start(likelihoods, names, fixed, vector)

    def clipped(v):
        return np.clip(v, low, high)
    result = optimize.minimize(lambda v: stencils.at(clipped(v))[0], vector,
                               method='trust-exact', jac=lambda v: stencils.at(clipped(v))[1],
                               hess=lambda v: stencils.at(clipped(v))[2],
                               options={'gtol': 1e-7, 'maxiter': 40})
    vector = clipped(np.asarray(result.x, dtype=float))
    f, _, H = stencils.at(vector)
    ll_hat = -f * rows
    bounds, extra = _boundary(likelihoods, names, fixed, vector, ll_hat, confidence)
    estimates = _estimates(names, vector, H * rows, confidence, bounds)
    setting = _setting(names, vector, fixed)._replace(
        **{names[i]: 0.0 for i, (_, zero) in bounds.items() if zero})
    return RailFit(setting, estimates, ll_hat, start_ll, stencils.passes + 1 + 3 * bool(extra),
                   stencils.evaluations + grid_points + extra, time.perf_counter() - began,
                   bool(result.success), str(result.message))


LN10 = math.log(10.0)
COARSE = np.arange(0.0, 17.0) * LN10
"""Offsets in log θ of the first scan for an upper bound: whole decades above θ̂."""
FINE = np.linspace(0.1, 1.0, 10) * LN10
"""Offsets within the decade where the first scan crossed: tenths of a decade."""


def _crossing(excess: np.ndarray, offsets: np.ndarray, first: float, at_first: float):
    """Return the offset where ``excess`` (increasing) crosses 0, linear in log θ; None if not."""
    past = np.flatnonzero(excess > 0.0)
    if past.size == 0:
        return None
    k = int(past[0])
    a, ea = (offsets[k - 1], excess[k - 1]) if k else (first, at_first)
    return a + (offsets[k] - a) * (-ea) / (excess[k] - ea)


def _boundary(likelihoods: Likelihoods, names, fixed: RailNoise, vector, ll_hat: float,
              confidence: float):
    """
    Return ({i: (upper bound, at zero)} for the noises compatible with 0, evaluations).

    At the boundary θ_i = 0 the likelihood-ratio statistic is ½χ²₀ + ½χ²₁ (Self &
    Liang 1987), so θ_i = 0 is not rejected when 2(ℓ̂ − ℓ(θ_i = 0)) <= χ²₁(1 − 2α),
    and the one-sided bound is where ℓ has dropped by that much. The others are held
    at their estimates (a conditional bound: one pass for all, where a profile would
    re-optimise them at every point). Found in two passes: whole decades above θ̂,
    then tenths of the decade that crossed, interpolated linearly in log θ (to ~1 % of
    θ). "At zero": ℓ(θ_i = 0) is within 1e-3 of ℓ̂.
    """
    threshold = boundary_threshold(confidence)
    process = [i for i, n in enumerate(names) if n != 'measurement_variance']
    base = _setting(names, vector, fixed)
    zeros = likelihoods([base._replace(**{names[i]: 0.0}) for i in process])
    drops = {i: ll_hat - float(ll) for i, ll in zip(process, zeros)}
    compatible = [i for i in process if drops[i] <= threshold]
    if not compatible:
        return {}, len(process)

    def scan(offsets_of):
        settings = [base._replace(**{names[i]: float(math.exp(vector[i] + o))})
                    for i in compatible for o in offsets_of(i)]
        lls = np.asarray(likelihoods(settings)).reshape(len(compatible), -1)
        return {i: ll_hat - row - threshold for i, row in zip(compatible, lls)}, len(settings)
    coarse, count = scan(lambda i: COARSE)
    decade = {}
    for i in compatible:
        past = np.flatnonzero(coarse[i] > 0.0)
        decade[i] = None if past.size == 0 else int(past[0])
    fine, more = scan(lambda i: COARSE[max((decade[i] or 1) - 1, 0)] + FINE)
    out = {}
    for i in compatible:
        if decade[i] is None:
            upper = math.inf
        elif decade[i] == 0:
            upper = math.exp(vector[i])                     # already past at θ̂ itself
        else:
            low = COARSE[decade[i] - 1]
            offset = _crossing(fine[i], low + FINE, low, coarse[i][decade[i] - 1])
            upper = math.exp(vector[i] + (COARSE[decade[i]] if offset is None else offset))
        out[i] = (upper, drops[i] <= 1e-3)
    return out, len(process) + count + more


def _estimates(names: List[str], vector: np.ndarray, H: np.ndarray, confidence: float,
               bounds: dict):
    """
    Return the intervals: [0, bound] at the boundary, else Wald in log space.

    The covariance is the inverse of the observed information H (of −ℓ) restricted
    to the noises not at the boundary (theirs conditional on those).
    """
    z = normal_quantile(confidence)
    inner = [i for i in range(len(names)) if i not in bounds]
    covariance = np.full(H.shape, np.nan)
    sub = H[np.ix_(inner, inner)]
    if inner and np.all(np.isfinite(sub)) and np.linalg.eigvalsh(sub)[0] > 0.0:
        covariance[np.ix_(inner, inner)] = np.linalg.inv(sub)
    out = []
    for i, name in enumerate(names):
        value = math.exp(vector[i])
        if i in bounds:
            upper, zero = bounds[i]
            out.append(RailEstimate(PARAMETERS[name], 0.0 if zero else value, math.nan,
                                    0.0, upper, True))
            continue
        variance = covariance[i, i]
        if not variance > 0.0:
            out.append(RailEstimate(PARAMETERS[name], value, math.nan, math.nan, math.nan,
                                    False))
            continue
        sigma = math.sqrt(variance)                       # se(log θ)
        # exp(log θ̂ ± z·se(log θ̂)); se(θ) = θ·se(log θ) (delta method)
        out.append(RailEstimate(PARAMETERS[name], value, value * sigma,
                                math.exp(vector[i] - z * sigma), math.exp(vector[i] + z * sigma),
                                True))
    return tuple(out)
