"""
Maximum likelihood of the rail IMM's noises: a climb that cannot go backwards, from many starts.

The likelihood (:func:`kf_train.batch.rail_log_likelihoods`) evaluates many settings in
one pass over the data, so the fit works on batches (:mod:`kf_train.tune.climb`):

1. **starts**: the setting in use (the preset's, or the file given), any other start
   the caller names (the shipped defaults), and a grid of decades about the grid
   centre (the shipped defaults, so the grid does not depend on how the fit was
   started); one pass for all;
2. **climbs**: from the best of those, bounded Newton steps in log θ, each taken only
   if it raises ℓ (:func:`kf_train.tune.climb.climb`); then from any start that began
   above every end so far (rarely any);
3. **the answer**: the highest end point. It is never below the setting in use (the
   climb from it only goes up); when no climb beats it by ``MIN_GAIN`` the fit says
   so and keeps it (``improved`` False).

The intervals come from the Hessian at the maximum, in log-parameter space:
exp(log θ̂ ± z·se(log θ̂)); a process noise whose value 0 the data do not reject gets
[0, bound] (:func:`_boundary`); a noise the data cannot pin down gets, in words, why
(:func:`kf_train.tune.rail_identify.explain`).
"""

import math
import time
from typing import Callable, List, NamedTuple, Sequence, Tuple

from kf_train.batch import RailNoise
from kf_train.tune.climb import best_of, Climb, climb, derivatives, LN10, stencil
from kf_train.tune.noise_fit import boundary_threshold, normal_quantile
from kf_train.tune.rail_identify import explain
import numpy as np

START_DECADES = (-2.0, -1.0, 0.0, 1.0, 2.0)
MIN_GAIN = 1e-3
"""A fit that raises ℓ by less than this keeps the setting in use (nothing to gain)."""
MAX_LOG_SE = 10.0
"""se(log θ) above this (an interval of ±8 decades) is a singular curvature: not identified."""
SAME_START = 0.05
"""Starts closer than this in log θ (5 %) are climbed once."""


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
    reason: str = ''
    """Why the data cannot pin it down, in words ('' when they can)."""


class StartResult(NamedTuple):
    """One start and where its climb ended."""

    label: str
    start: RailNoise
    start_log_likelihood: float
    end: RailNoise
    log_likelihood: float
    stop: str


class RailFit(NamedTuple):
    """What :func:`fit_rail_noise` found."""

    setting: RailNoise
    estimates: Tuple[RailEstimate, ...]
    log_likelihood: float
    start_log_likelihood: float
    """ℓ of the setting in use (the first start)."""
    passes: int
    """Passes over the data (each evaluates a batch of settings)."""
    evaluations: int
    """Settings evaluated, over all passes."""
    seconds: float
    improved: bool
    """False: no start beat the setting in use by MIN_GAIN; ``setting`` is that setting."""
    stop: str
    """Why the winning climb stopped, in words."""
    starts: Tuple[StartResult, ...]


Likelihoods = Callable[[Sequence[RailNoise]], np.ndarray]
"""ℓ of each of a list of settings (one pass over the data)."""


def _setting(names: Sequence[str], vector, fixed: RailNoise) -> RailNoise:
    """Return ``fixed`` with the named fields set to exp(vector)."""
    return fixed._replace(**{n: float(math.exp(v)) for n, v in zip(names, vector)})


def _vector(names: Sequence[str], setting: RailNoise) -> np.ndarray:
    """Return log θ of the named fields (a field at 0 starts a decade below 1e-12)."""
    return np.array([math.log(max(getattr(setting, n), 1e-13)) for n in names])


def _objective(likelihoods: Likelihoods, names, fixed: RailNoise):
    """Return ℓ as a function of (K, n) log-vectors; a failing pass is −inf for all."""
    def objective(points: np.ndarray) -> np.ndarray:
        try:
            return np.asarray(likelihoods([_setting(names, p, fixed) for p in points]),
                              dtype=float)
        except (ValueError, ArithmeticError):
            return np.full(points.shape[0], -np.inf)
    return objective


def _grid(objective, names, centre: np.ndarray, starts: List[np.ndarray]):
    """Return (the grid of decades about ``centre`` plus ``starts``, ℓ of each): one pass."""
    process = [i for i, n in enumerate(names) if n != 'measurement_variance']
    # 5 values per noise (25 settings for two); 3 for three noises (27, not 125)
    decades = START_DECADES if len(process) <= 2 else START_DECADES[::2]
    grids = np.array(np.meshgrid(*[decades] * len(process), indexing='ij'))
    grids = grids.reshape(len(process), -1).T * LN10
    points = np.repeat(centre[None], grids.shape[0], axis=0)
    points[:, process] += grids
    points = np.concatenate([np.array(starts), points])
    ll = objective(points)
    return points, np.where(np.isfinite(ll), ll, -np.inf)


def _climbs(objective, points: np.ndarray, ll: np.ndarray, labels: List[str], low, high
            ) -> Tuple[List[Climb], List[str]]:
    """
    Climb from the best point of the batch, then from any start that began above every end.

    A start below an end already reached cannot improve the answer's guarantee (never
    below the setting in use), so it is not climbed: the answer then does not depend on
    how the fit was started, only on the grid, which is fixed.
    """
    order = [int(np.argmax(ll))] + [k for k in range(len(labels)) if k != int(np.argmax(ll))]
    climbs, names = [], []
    for k in order:
        if climbs and (ll[k] <= max(c.log_likelihood for c in climbs)
                       or any(np.max(np.abs(points[k] - c.start_vector)) < SAME_START
                              for c in climbs)):
            continue
        climbs.append(climb(objective, points[k], low, high, float(ll[k])))
        names.append(labels[k] if k < len(labels) else 'grid')
    return climbs, names


def fit_rail_noise(likelihoods: Likelihoods, names: Sequence[str], start: RailNoise,
                   fixed: RailNoise, rows: int, confidence: float = 0.95, *,
                   other_starts: Sequence[Tuple[str, RailNoise]] = (),
                   grid_centre: RailNoise = None, start_label: str = 'in use') -> RailFit:
    """
    Return the maximum-likelihood values of the ``names`` fields, with intervals.

    ``likelihoods`` evaluates a list of settings in one pass; ``start`` is the setting
    in use (the result is never below it), ``other_starts`` labelled further starts,
    ``grid_centre`` the centre of the grid of decades (default ``start``); ``fixed``
    gives the fields not estimated; ``rows`` is the number of measurements ℓ sums over.
    """
    began = time.perf_counter()
    names = list(names)
    objective = _objective(likelihoods, names, fixed)
    first = _vector(names, start)
    centre = first if grid_centre is None else _vector(names, grid_centre)
    # The box: 10 decades below and 6 above the grid's centre; ℓ is flat below what the
    # data can detect, and a climb stops there.
    low, high = centre - 10.0 * LN10, centre + 6.0 * LN10
    starts = [first] + [_vector(names, s) for _, s in other_starts]
    labels = [start_label] + [label for label, _ in other_starts]
    points, lls = _grid(objective, names, centre, starts)
    climbs, climbed = _climbs(objective, points, lls, labels, low, high)
    winner = climbs[best_of(climbs)]
    start_ll = float(lls[0])
    improved = winner.log_likelihood >= start_ll + MIN_GAIN
    vector = winner.vector if improved else first
    ll_hat = winner.log_likelihood if improved else start_ll
    values = objective(vector + stencil(len(names)))   # the intervals' full stencil
    H = -derivatives(np.where(np.isfinite(values), values, ll_hat - 1e30), len(names))[2]
    bounds, extra = _boundary(likelihoods, names, fixed, vector, ll_hat, confidence)
    estimates = explain(_estimates(names, vector, H, confidence, bounds), names, H)
    setting = _setting(names, vector, fixed)._replace(
        **{names[i]: 0.0 for i, (_, zero) in bounds.items() if zero})
    if not improved:
        setting = start
    results = tuple(StartResult(label, _setting(names, c.start_vector, fixed),
                                c.start_log_likelihood, _setting(names, c.vector, fixed),
                                c.log_likelihood, c.stop) for label, c in zip(climbed, climbs))
    return RailFit(setting, estimates, ll_hat, start_ll,
                   sum(c.passes for c in climbs) + 2 + 3 * bool(extra),
                   sum(c.evaluations for c in climbs) + points.shape[0] + values.shape[0]
                   + extra,
                   time.perf_counter() - began, improved, winner.stop, results)


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
        # se(log θ) beyond MAX_LOG_SE: a near-singular curvature, not an interval
        if not 0.0 < variance <= MAX_LOG_SE ** 2:
            out.append(RailEstimate(PARAMETERS[name], value, math.nan, math.nan, math.nan,
                                    False))
            continue
        sigma = math.sqrt(variance)                       # se(log θ)
        # exp(log θ̂ ± z·se(log θ̂)); se(θ) = θ·se(log θ) (delta method)
        out.append(RailEstimate(PARAMETERS[name], value, value * sigma,
                                math.exp(vector[i] - z * sigma), math.exp(vector[i] + z * sigma),
                                True))
    return tuple(out)
