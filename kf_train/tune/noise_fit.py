"""
Maximum-likelihood noise with confidence intervals: q, R (and initial state) from data.

The likelihood is the estimator node's own (:class:`kf_train.batch.TuningProblem`), the
estimated quantities a :class:`kf_train.batch.NoiseParameterisation`. The optimiser is
scipy's (L-BFGS-B, Brent): scipy is the optional extra of ``kf-train tune`` (``pip
install kf_train[tune]``), imported only inside these functions and only in
:mod:`kf_train.tune`, never by the nodes.

The confidence intervals come from the curvature of ℓ at its maximum (the observed
information, inverted: the Wald interval in the optimiser's coordinates, mapped back by
exp for a log parameter; the standard error on the natural scale by the delta method,
se(θ) = θ·se(log θ)). A density the data cannot tell from 0 (a train that never
accelerates has q = 0) has no log-scale curvature: it is reported as compatible with 0
with a one-sided upper bound from the profile likelihood (the likelihood-ratio
statistic at a boundary is ½χ²₀ + ½χ²₁, so the 95 % bound is where 2Δℓ = χ²₁(0.90);
Self & Liang 1987), and the other parameters' intervals are conditional on it.

:func:`estimate_noise` asks of its problem and parameterisation only the interfaces
:class:`kf_train.batch.LikelihoodProblem` and :class:`kf_train.batch.Parameterisation`:
another model (a rail IMM model's regime noises) plugs in by providing them (its
likelihood would not be exact, an IMM approximating the mixture of its modes).
"""

import math
from typing import NamedTuple, Optional, Sequence, Tuple

from kf_train.batch import (
    LikelihoodProblem, NoiseSetting, Parameter, Parameterisation)
from kf_train.filters import chi2_quantile
import numpy as np


class Estimate(NamedTuple):
    """One estimated quantity with its confidence interval."""

    parameter: Parameter
    value: float
    std_error: float
    """Natural-scale standard error (delta method for log parameters); NaN if unknown."""
    low: float
    high: float
    """The interval at the requested confidence (natural scale)."""
    method: str
    """``wald`` (curvature, natural scale), ``wald-log`` (curvature of log θ, mapped by
    exp), ``profile`` (compatible with 0: [0, profile-likelihood bound]) or
    ``unidentified`` (no curvature: the data do not determine it)."""


class TuningResult(NamedTuple):
    """What :func:`estimate_noise` found."""

    setting: NoiseSetting
    """The maximum-likelihood setting."""
    estimates: Tuple[Estimate, ...]
    log_likelihood: float
    start_log_likelihood: float
    covariance: np.ndarray
    """Covariance of the optimiser vector (inverse observed information; NaN for a
    parameter at its boundary, the others' conditional on it)."""
    rows: int
    """Innovations in the likelihood."""
    evaluations: int
    """Likelihood evaluations, the optimiser's and the curvature's."""
    converged: bool
    message: str


def normal_quantile(confidence: float) -> float:
    """Return z with P(|N(0, 1)| <= z) = confidence (from χ²(1), no scipy.stats)."""
    return math.sqrt(chi2_quantile(confidence, 1))


class _Objective:
    """−ℓ per innovation of an optimiser vector, counting evaluations."""

    def __init__(self, problem, parameterisation):
        """Wrap a problem and its parameterisation."""
        self.problem, self.parameterisation = problem, parameterisation
        self.rows = problem.rows
        self.evaluations = 0

    def __call__(self, vector) -> float:
        """Return −ℓ/rows; a setting the filter cannot run counts as very unlikely."""
        self.evaluations += 1
        try:
            value = -self.problem.log_likelihood(self.parameterisation.setting(vector))
        except (ValueError, ArithmeticError):
            return 1e30
        return value / self.rows if math.isfinite(value) else 1e30

    def log_likelihood(self, vector) -> float:
        """Return ℓ of an optimiser vector."""
        return -self(vector) * self.rows


def _coarse_start(objective: _Objective, vector: np.ndarray, bounds) -> np.ndarray:
    """Improve the start coordinate by coordinate on a grid of decades (log parameters)."""
    best = objective(vector)
    vector = vector.copy()
    for i, parameter in enumerate(objective.parameterisation.parameters):
        if not parameter.log_scale:
            continue
        centre = vector[i]
        for decades in (-6.0, -3.0, -1.5, -0.5, 0.5, 1.5, 3.0):
            trial = vector.copy()
            trial[i] = min(max(centre + decades * math.log(10.0), bounds[i][0]), bounds[i][1])
            value = objective(trial)
            if value < best:
                best, vector = value, trial
    return vector


def _curvature(objective: _Objective, vector: np.ndarray) -> np.ndarray:
    """
    Return the Hessian of −ℓ at ``vector`` (the observed information), by central differences.

    Step h = 1e-3 (times max(1, |v_i|) for natural-scale parameters). In log
    coordinates the truncation error is O(h²) relative, ~1e-6; ℓ is computed to
    ~1e-13 relative (a few ulps per row), so the rounding error of a second difference,
    ~1e-13·|ℓ|/h², stays below 1e-6·|ℓ|, far under the curvature's own scale (≈ rows).
    (scipy.differentiate.hessian refines adaptively, but spends four times the 1 + 2n²
    likelihood evaluations these formulas need.)
    """
    n = len(vector)
    h = np.array([1e-3 if p.log_scale else 1e-3 * max(1.0, abs(v))
                  for p, v in zip(objective.parameterisation.parameters, vector)])

    def f(*steps):
        v = np.array(vector, dtype=float)
        for i, sign in steps:
            v[i] += sign * h[i]
        return objective(v) * objective.rows
    centre = f()
    H = np.empty((n, n))
    for i in range(n):
        H[i, i] = (f((i, 1)) - 2.0 * centre + f((i, -1))) / h[i] ** 2   # ∂²f/∂v_i²
        for j in range(i):
            H[i, j] = H[j, i] = (f((i, 1), (j, 1)) - f((i, 1), (j, -1)) - f((i, -1), (j, 1))
                                 + f((i, -1), (j, -1))) / (4.0 * h[i] * h[j])
    return H


def _profile_drop(objective: _Objective, vector, ll_hat: float, i: int, value: float,
                  bounds, scale, warm: Optional[list] = None) -> float:
    """
    Return ℓ̂ − max ℓ over the other parameters with parameter i held at ``value``.

    ``scale`` preconditions the inner search (1/√ of the curvature at the maximum);
    ``warm`` (a list holding the others' last optimum) starts it there and receives
    the new optimum: successive values of one profile are close.
    """
    from scipy import optimize
    others = [j for j in range(len(vector)) if j != i]
    start = np.asarray(vector, dtype=float)[others] if not warm else warm[0]

    def held(w):
        v = np.array(vector, dtype=float)
        v[others], v[i] = w, value
        return v
    if not others:
        return ll_hat - objective.log_likelihood(held([]))
    if len(others) == 1:
        (lo, hi), w0 = bounds[others[0]], float(start[0])
        result = optimize.minimize_scalar(
            lambda w: objective(held([min(max(w, lo), hi)])), method='brent',
            bracket=(w0, w0 + 0.05), options={'xtol': 1e-4})
        best = np.array([min(max(result.x, lo), hi)])
    else:
        s = np.asarray(scale, dtype=float)[others]
        lo = np.array([bounds[j][0] for j in others])
        hi = np.array([bounds[j][1] for j in others])
        result = optimize.minimize(lambda w: objective(held(start + s * w)),
                                   np.zeros(len(others)), method='L-BFGS-B', jac='3-point',
                                   bounds=list(zip((lo - start) / s, (hi - start) / s)))
        best = np.clip(start + s * result.x, lo, hi)
    if warm is not None:
        warm[:] = [best]
    return ll_hat - max(objective.log_likelihood(held(best)),
                        objective.log_likelihood(held(start)))


def boundary_threshold(confidence: float) -> float:
    """
    Return the drop of ℓ that rejects θ_i = 0 at 1 − ``confidence`` (one-sided).

    At the boundary θ_i → 0 the likelihood-ratio statistic 2(ℓ̂ − ℓ_p) is
    ½χ²₀ + ½χ²₁ (Self & Liang 1987): the test at level α, and the one-sided bound
    with confidence 1 − α, use χ²₁(1 − 2α).
    """
    return 0.5 * chi2_quantile(1.0 - 2.0 * (1.0 - confidence), 1)


def _profile_upper(objective, vector, ll_hat, i, bounds, scale, threshold) -> float:
    """
    Return θ_i > θ̂_i where the profile likelihood has dropped by ``threshold`` (or inf).

    The crossing with the others held at θ̂ comes first (ℓ with them held is below
    the profile), cheap to find; the profile's crossing is then bracketed by steps
    of e^0.5 up from there, and solved to 0.1 % (xtol in log θ).
    """
    from scipy import optimize
    low, high = max(vector[i], bounds[i][0]), bounds[i][1]

    def held(v):
        w = np.array(vector, dtype=float)
        w[i] = v
        return ll_hat - objective.log_likelihood(w) - threshold
    if held(high) <= 0.0:
        return math.inf
    warm = []

    def excess(v):
        return _profile_drop(objective, vector, ll_hat, i, v, bounds, scale, warm) - threshold
    a = optimize.brentq(held, low, high, xtol=1e-3) if held(low) < 0.0 else low
    b = a
    while excess(b) < 0.0:
        a, b = b, b + 0.5
        if b >= high:
            if excess(high) <= 0.0:
                return math.inf
            b = high
            break
    return math.exp(optimize.brentq(excess, a, b, xtol=1e-3)) if b > a else math.exp(b)


def _inverse_information(H: np.ndarray, keep: Sequence[int]) -> np.ndarray:
    """Return H restricted to ``keep``, inverted, in a full-size matrix (NaN elsewhere)."""
    covariance = np.full(H.shape, np.nan)
    if not keep:
        return covariance
    sub = H[np.ix_(keep, keep)]
    if np.all(np.isfinite(sub)) and np.linalg.eigvalsh(sub)[0] > 0.0:
        covariance[np.ix_(keep, keep)] = np.linalg.inv(sub)
    return covariance


def _estimates(objective, vector, H, ll_hat, bounds, confidence):
    """
    Return (estimates, covariance of the vector, parameters at 0).

    A log parameter whose value 0 the profile likelihood does not reject gets
    [0, profile bound]; it is then held at its boundary, and the others' covariance is
    the inverse of the information restricted to them. The rest get Wald intervals.
    """
    parameters = objective.parameterisation.parameters
    threshold = boundary_threshold(confidence)
    diagonal = np.diag(H) / objective.rows
    positive = diagonal > 0.0       # a flat direction (0) keeps the unit scale
    scale = np.ones_like(diagonal)
    scale[positive] = 1.0 / np.sqrt(diagonal[positive])
    # Only a density the node can run at 0 (q) has a boundary worth testing; R → 0
    # (noise-free measurements) never fits data that have noise.
    drops = {i: _profile_drop(objective, vector, ll_hat, i, bounds[i][0], bounds, scale)
             for i, p in enumerate(parameters) if p.log_scale and p.zero_allowed}
    boundary = [i for i, drop in drops.items() if drop <= threshold]
    covariance = _inverse_information(H, [i for i in range(len(parameters))
                                          if i not in boundary])
    z = normal_quantile(confidence)
    out, at_zero = [], []
    for i, parameter in enumerate(parameters):
        variance = covariance[i, i]
        sigma = math.sqrt(variance) if variance > 0.0 else math.nan
        if i in boundary:
            # ℓ no higher than at θ → 0 (to 1e-3): the maximum is at 0 itself
            zero = drops[i] <= 1e-3 and parameter.zero_allowed
            at_zero += [i] * zero
            out.append(Estimate(parameter, 0.0 if zero else math.exp(vector[i]), math.nan,
                                0.0, _profile_upper(objective, vector, ll_hat, i, bounds,
                                                    scale, threshold), 'profile'))
        elif sigma != sigma:
            value = math.exp(vector[i]) if parameter.log_scale else float(vector[i])
            out.append(Estimate(parameter, value, math.nan, math.nan, math.nan,
                                'unidentified'))
        elif parameter.log_scale:
            # se(θ) = θ·se(log θ) (delta method); the interval is exp(log θ ± z·se)
            value = math.exp(vector[i])
            with np.errstate(over='ignore'):   # a flat likelihood: an interval up to inf
                low, high = np.exp([vector[i] - z * sigma, vector[i] + z * sigma])
            out.append(Estimate(parameter, value, value * sigma, float(low), float(high),
                                'wald-log'))
        else:
            out.append(Estimate(parameter, float(vector[i]), sigma,
                                float(vector[i] - z * sigma), float(vector[i] + z * sigma),
                                'wald'))
    return tuple(out), covariance, at_zero


def _maximise(objective: _Objective, vector: np.ndarray, bounds):
    """
    Return (the maximiser of ℓ, scipy's result), by L-BFGS-B in preconditioned coordinates.

    Each coordinate is scaled by 1/√(∂²(−ℓ/rows)/∂v_i²) at the start (2n evaluations),
    so that a unit step changes ℓ alike in every direction: log variances and an initial
    position in metres differ in curvature by orders of magnitude otherwise.
    """
    from scipy import optimize
    h = np.array([1e-2 if p.log_scale else 1e-2 * max(1.0, abs(v))
                  for p, v in zip(objective.parameterisation.parameters, vector)])
    centre = objective(vector)
    scale = np.ones(len(vector))
    for i in range(len(vector)):
        step = np.zeros(len(vector))
        step[i] = h[i]
        d2 = (objective(vector + step) - 2.0 * centre + objective(vector - step)) / h[i] ** 2
        if d2 > 0.0 and math.isfinite(d2):
            scale[i] = 1.0 / math.sqrt(d2)
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    result = optimize.minimize(lambda w: objective(vector + scale * w), np.zeros(len(vector)),
                               method='L-BFGS-B', jac='3-point',
                               bounds=list(zip((lo - vector) / scale, (hi - vector) / scale)),
                               options={'ftol': 1e-12, 'gtol': 1e-8, 'maxiter': 1000})
    return np.clip(vector + scale * np.asarray(result.x, dtype=float), lo, hi), result


def estimate_noise(problem: 'LikelihoodProblem', parameterisation: 'Parameterisation', *,
                   confidence: float = 0.95, start=None) -> TuningResult:
    """
    Return the maximum-likelihood noise with confidence intervals.

    ``problem`` is a :class:`kf_train.batch.TuningProblem` and ``parameterisation`` a
    :class:`kf_train.batch.NoiseParameterisation`, or any pair with their interface
    (:class:`LikelihoodProblem`, :class:`Parameterisation`); ``start`` a setting.

    The optimiser is scipy's L-BFGS-B (bounded quasi-Newton, central-difference
    gradients) on −ℓ per innovation in the parameterisation's coordinates, from
    ``start`` (default: moment estimates refined on a grid of decades). Needs scipy.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f'confidence must be in (0, 1), got {confidence!r}')
    objective = _Objective(problem, parameterisation)
    bounds = parameterisation.bounds()
    first = parameterisation.vector(parameterisation.start() if start is None else start)
    first = np.clip(first, [b[0] for b in bounds], [b[1] for b in bounds])
    start_ll = objective.log_likelihood(first)
    vector = _coarse_start(objective, first, bounds) if start is None else first
    vector, result = _maximise(objective, vector, bounds)
    ll_hat = objective.log_likelihood(vector)
    H = _curvature(objective, vector)
    estimates, covariance, at_zero = _estimates(objective, vector, H, ll_hat, bounds,
                                                confidence)
    return TuningResult(parameterisation.setting(vector, at_zero), estimates, ll_hat, start_ll,
                        covariance, problem.rows, objective.evaluations,
                        bool(result.success), str(result.message))
