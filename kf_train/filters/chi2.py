"""
The χ² distribution without scipy: CDF, survival function and quantile.

The nodes gate measurements and judge filter consistency with χ² quantiles, and
must not import scipy (a heavy import, and not a ROS dependency). The regularised
incomplete gamma function is evaluated by its power series below ``a + 1`` and by
its continued fraction above (Numerical Recipes §6.2), each to full double
precision; the quantile inverts whichever tail is smaller, so that probabilities
near 1 (a 0.9999 gate) keep their precision. Agreement with scipy is tested to 1e-9.
"""

import math
from typing import Tuple

_EPS = 1e-16
_TINY = 1e-300
_MAX_ITERATIONS = 100_000


def _check_dof(dof: float) -> float:
    """Return dof as a float, or raise if it is not a finite number > 0."""
    try:
        value = float(dof)
    except (TypeError, ValueError):
        raise ValueError(f'dof must be a number, got {dof!r}') from None
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f'dof must be a finite number > 0, got {dof!r}')
    return value


def _log_prefactor(a: float, x: float) -> float:
    """Return log(x^a e^-x / Γ(a)), common to both expansions."""
    return a * math.log(x) - x - math.lgamma(a)


def _lower_series(a: float, x: float) -> float:
    """Return P(a, x) by its series; converges fast for x < a + 1."""
    # P(a, x) = x^a e^-x / Γ(a) · Σ_n x^n / (a (a+1) … (a+n))
    term = 1.0 / a
    total = term
    denominator = a
    for _ in range(_MAX_ITERATIONS):
        denominator += 1.0
        term *= x / denominator
        total += term
        if abs(term) < abs(total) * _EPS:
            break
    return total * math.exp(_log_prefactor(a, x))


def _upper_fraction(a: float, x: float) -> float:
    """Return Q(a, x) by its continued fraction (modified Lentz); for x >= a + 1."""
    # Q(a, x) = x^a e^-x / Γ(a) · 1/(x+1-a- 1·(1-a)/(x+3-a- 2·(2-a)/(x+5-a- …)))
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, _MAX_ITERATIONS):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        if abs(d) < _TINY:
            d = _TINY
        c = b + an / c
        if abs(c) < _TINY:
            c = _TINY
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return math.exp(_log_prefactor(a, x)) * h


def _tails(x: float, dof: float) -> Tuple[float, float]:
    """Return (CDF, survival) of χ²(dof) at x, the smaller one computed directly."""
    if x <= 0.0:
        return 0.0, 1.0
    if math.isinf(x):
        return 1.0, 0.0
    a, half_x = 0.5 * dof, 0.5 * x  # χ²(k) CDF = P(k/2, x/2)
    if half_x < a + 1.0:
        lower = _lower_series(a, half_x)
        return lower, 1.0 - lower
    upper = _upper_fraction(a, half_x)
    return 1.0 - upper, upper


def chi2_cdf(x: float, dof: float) -> float:
    """Return P(X <= x) for X ~ χ²(dof)."""
    return _tails(float(x), _check_dof(dof))[0]


def chi2_sf(x: float, dof: float) -> float:
    """Return P(X > x) for X ~ χ²(dof), accurate also far in the upper tail."""
    return _tails(float(x), _check_dof(dof))[1]


def _log_pdf(x: float, dof: float) -> float:
    """Return log of the χ²(dof) density at x > 0."""
    a = 0.5 * dof
    # f(x) = x^(a-1) e^(-x/2) / (2^a Γ(a))
    return (a - 1.0) * math.log(x) - 0.5 * x - a * math.log(2.0) - math.lgamma(a)


def _normal_quantile_approx(p: float) -> float:
    """Return a rough standard normal quantile (|error| < 5e-4), a starting point only."""
    # Abramowitz & Stegun 26.2.23.
    q = p if p < 0.5 else 1.0 - p
    t = math.sqrt(-2.0 * math.log(q))
    z = t - ((0.010328 * t + 0.802853) * t + 2.515517) / (
        ((0.001308 * t + 0.189269) * t + 1.432788) * t + 1.0)
    return -z if p < 0.5 else z


def chi2_quantile(p: float, dof: float) -> float:
    """Return x with P(X <= x) = p for X ~ χ²(dof); p = 1 gives inf."""
    dof = _check_dof(dof)
    try:
        p = float(p)
    except (TypeError, ValueError):
        raise ValueError(f'p must be a probability, got {p!r}') from None
    if not 0.0 <= p <= 1.0:
        raise ValueError(f'p must be in [0, 1], got {p!r}')
    if p == 0.0:
        return 0.0
    if p == 1.0:
        return math.inf
    # Solve in the smaller tail: residual(x) increases with x and is 0 at the answer.
    lower_tail = p <= 0.5
    target = p if lower_tail else 1.0 - p

    def residual(x: float) -> float:
        cdf, sf = _tails(x, dof)
        return cdf - target if lower_tail else target - sf

    # Wilson-Hilferty start: x ≈ k (1 - 2/(9k) + z sqrt(2/(9k)))³.
    z = _normal_quantile_approx(p)
    c = 2.0 / (9.0 * dof)
    x = dof * max(1.0 - c + z * math.sqrt(c), 0.1) ** 3
    low, high = 0.0, math.inf
    for _ in range(1000):
        r = residual(x)
        if r == 0.0:
            return x
        if r < 0.0:
            low = x
        else:
            high = x
        # Newton step x - r / f(x); fall back to bisection (or doubling) outside the bracket.
        step = r / math.exp(_log_pdf(x, dof))
        candidate = x - step
        if not low < candidate < high:
            candidate = 2.0 * low + 1.0 if math.isinf(high) else 0.5 * (low + high)
        if abs(candidate - x) <= 4.0 * _EPS * x or (
                not math.isinf(high) and high - low <= 4.0 * _EPS * high):
            return candidate
        x = candidate
    return x


def chi2_mean_bounds(count: int, dof: float, confidence: float = 0.99) -> Tuple[float, float]:
    """
    Return the two-sided ``confidence`` interval of the mean of ``count`` χ²(dof) samples.

    The sum of ``count`` independent χ²(dof) variables is χ²(count·dof), so the mean's
    bounds are that distribution's (1 ∓ confidence)/2 quantiles divided by count.
    """
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise ValueError(f'count must be a positive integer, got {count!r}')
    dof = _check_dof(dof)
    if not 0.0 < confidence < 1.0:
        raise ValueError(f'confidence must be in (0, 1), got {confidence!r}')
    tail = 0.5 * (1.0 - confidence)
    total_dof = count * dof
    return (chi2_quantile(tail, total_dof) / count,
            chi2_quantile(1.0 - tail, total_dof) / count)
