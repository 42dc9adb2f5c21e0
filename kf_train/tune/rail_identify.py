"""
Identifiability in plain words: why the data cannot pin a noise down, from ℓ's curvature.

The fit's intervals come from the observed information H (the Hessian of −ℓ in
log θ). Where an interval is missing, open or very wide, :func:`explain` says why:

* **flat**: H_ii (ℓ's curvature along log θ_i) is so small that ℓ changes by less
  than ``FLAT_DROP`` over a decade either side: nothing in the data excites that
  noise (a command noise on a log without acceleration changes, an R the node learns
  online anyway);
* **traded off**: H_ii is large but H is singular (or nearly: correlation of the
  estimates beyond ``TRADE_OFF``) with another noise: the data fix a combination of
  the two, not each;
* **not a maximum**: ℓ curves up along it (the climb stopped where H is not negative
  definite): a ridge or a kink, often a gate flipping fixes in and out;
* **compatible with 0**: the data do not reject θ_i = 0 (the bound is one-sided);
* **wide**: identified, but the interval spans more than ``WIDE_DECADES`` decades.
"""

import math
from typing import List, Sequence, Tuple

import numpy as np

FLAT_DROP = 0.5
"""ℓ units: less than this over a decade either side is "the data cannot tell"."""
TRADE_OFF = 0.95
"""|correlation| of two estimates beyond which they are reported as traded off."""
WIDE_DECADES = 2.0
LN10 = math.log(10.0)


def _correlation(H: np.ndarray, i: int, j: int) -> float:
    """Return the correlation of the estimates i and j from the 2×2 block of H⁻¹."""
    a, b, d = H[i, i], H[i, j], H[j, j]
    if not (a > 0.0 and d > 0.0):
        return math.nan
    return float(-b / math.sqrt(a * d))          # (H⁻¹)_ij / √((H⁻¹)_ii (H⁻¹)_jj)


def _partner(H: np.ndarray, i: int, symbols: Sequence[str]) -> Tuple[str, float]:
    """Return (the symbol, correlation) of the noise most correlated with i ('', nan if none)."""
    best, value = '', math.nan
    for j in range(H.shape[0]):
        if j == i:
            continue
        r = _correlation(H, i, j)
        if math.isfinite(r) and not abs(r) <= abs(value if math.isfinite(value) else 0.0):
            best, value = symbols[j], r
    return best, value


def reason(i: int, estimate, H: np.ndarray, symbols: Sequence[str]) -> str:
    """Return why estimate i is not pinned down, in words ('' when it is)."""
    curvature = H[i, i]
    drop = 0.5 * curvature * LN10 ** 2               # ℓ's drop over one decade, quadratic
    partner, r = _partner(H, i, symbols)
    if estimate.identified and estimate.low == 0.0:
        return 'the data cannot tell it from 0 (one-sided bound)'
    if not math.isfinite(curvature):
        return 'the likelihood failed near it'
    if not estimate.identified:
        if abs(drop) < FLAT_DROP:
            return (f'the data cannot tell: ℓ changes by {abs(drop):.2g} over a decade either '
                    'side (nothing in the data excites it)')
        if curvature < 0.0:
            return 'the data cannot tell: ℓ is not at a maximum along it (a ridge or a kink)'
        if partner and abs(r) > TRADE_OFF:
            return (f'the data cannot tell it from {partner}: only their combination is '
                    f'identified (correlation {r:.2f})')
        return 'the data cannot tell: the curvature is singular with the other noises'
    decades = math.log10(estimate.high / estimate.low) if estimate.low > 0.0 else math.inf
    if partner and abs(r) > TRADE_OFF:
        return f'trades off against {partner} (correlation {r:.2f})'
    if decades > WIDE_DECADES:
        return f'barely identified: the interval spans {decades:.1f} decades'
    return ''


def explain(estimates: Sequence, names: Sequence[str], H: np.ndarray) -> Tuple:
    """Return ``estimates`` with their ``reason`` filled in (H: the Hessian of −ℓ in log θ)."""
    symbols: List[str] = [e.parameter.symbol for e in estimates]
    return tuple(e._replace(reason=reason(i, e, H, symbols)) for i, e in enumerate(estimates))
