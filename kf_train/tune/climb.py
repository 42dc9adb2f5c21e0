"""
A maximiser that cannot go backwards: bounded Newton steps in log space, many settings a pass.

The rail likelihood (:func:`kf_train.batch.rail_log_likelihoods`) evaluates K settings
in one pass over the data for little more than the cost of one, so every step of
:func:`climb` asks for two batches:

1. a finite-difference stencil about the current point (1 + 2n + n(n−1) settings,
   :func:`cheap_stencil`): ℓ, its gradient g and its Hessian H together;
2. candidate points along the Newton direction −H⁻¹g (H's eigenvalues made negative:
   a maximum's model) at steps 1, ½, ¼ and along the gradient, all within a trust
   radius of at most one decade (ln 10 in log θ); after a miss, along each axis too.

The best candidate is taken only if it raises ℓ; otherwise the radius shrinks fourfold.

A noise the data cannot tell from 0 has ℓ ≈ ℓ(0) + c·θ near 0: in log θ its gradient
and curvature are both c·θ, so each Newton step moves it down by one e-fold and wins a
share 1 − 1/e of what is left; crawling to the box's floor took 20 of a fit's 32
passes. So a candidate pass also tries, for every noise that ℓ pushes down, the Newton
step with that noise 2, 4 and 8 decades lower and at the floor (a ladder: an interior
maximum further down is met by a rung, not jumped over). A noise on the floor that ℓ
would push further down is held there (an active set): the Newton model, its gain and
the concavity test are those of the other noises.
Every accepted point is therefore better than the last, and the result is never below
the start, whatever the likelihood does (a gate that flips a fix, a flat ridge, a noisy
second difference): scipy's trust-region methods, used before, could return a point
worse than their start ("A bad approximation caused failure to predict improvement").

It stops, with a reason in words, when

* ``converged``: the Newton model predicts a further gain below ``GAIN_TOL`` in ℓ,
  at a point where ℓ curves down in every direction (or after a step below
  ``STEP_TOL`` in log θ): two starts that reach the same maximum then agree to
  ~√(2·GAIN_TOL/curvature) in log θ, 5e-4 relative for a curvature of 1 (an interval
  of ±2 decades) and 1.4e-5 for 1000: the printed 4 digits, but for the last of a
  barely identified noise;
* ``converged`` too when a step raised ℓ by less than ``GAIN_TOL``: creeping along a
  flat direction (a noise the data cannot tell from 0) wins nothing;
* ``no improving step``: no candidate raises ℓ even within ``STEP_TOL`` (a flat or
  kinked maximum);
* ``step limit``: ``MAX_STEPS`` steps.

Step h = 1e-2 in log θ for the stencil: its truncation error is O(h²) ≈ 1e-4 relative;
ℓ is computed to ~1e-14 relative (|ℓ| ~ 10⁴–10⁵: ~1e-9 absolute), so the rounding
error of a second difference, ~1e-9/h² = 1e-5, stays far below the curvature of any
noise the data identify (≥ 1: se(log θ) ≤ 1).
"""

import math
from typing import Callable, List, NamedTuple, Sequence

import numpy as np

STEP = 1e-2
"""The stencil's step in log θ."""
LN10 = math.log(10.0)
MAX_RADIUS = LN10
"""No step moves a noise by more than a decade."""
GAIN_TOL = 1e-7
"""Converged when the Newton model predicts less than this gain in ℓ ..."""
STEP_TOL = 1e-4
"""... and the last step was shorter than this in log θ (0.01 %)."""
MAX_STEPS = 60
NEWTON_FRACTIONS = (1.0, 0.5, 0.25)
GRADIENT_FRACTIONS = (1.0, 0.25)
LADDER_DECADES = (2.0, 4.0, 8.0)
"""The rungs below a noise that ℓ pushes down, in decades (then the floor itself)."""

Objective = Callable[[np.ndarray], np.ndarray]
"""ℓ at each row of a (K, n) array of log-parameter vectors (one pass); −inf if invalid."""


class Climb(NamedTuple):
    """Where :func:`climb` stopped."""

    vector: np.ndarray
    """log θ at the best point found."""
    log_likelihood: float
    start_log_likelihood: float
    gradient: np.ndarray
    """dℓ/d log θ at ``vector`` (from its stencil)."""
    hessian: np.ndarray
    """d²ℓ/d log θ² at ``vector`` (negative definite at a proper maximum)."""
    steps: int
    passes: int
    evaluations: int
    stop: str
    """Why it stopped, in words."""
    start_vector: np.ndarray
    start_hessian: np.ndarray
    """d²ℓ/d log θ² at the start (for a fit that keeps its start)."""


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


def cheap_stencil(n: int, h: float = STEP) -> np.ndarray:
    """Return the climb's stencil: the centre, ±h e_i, and ±(h, h) on every pair."""
    points = list(stencil(n, h)[:1 + 2 * n])
    for i in range(n):
        for j in range(i):
            for sign in (1.0, -1.0):
                p = np.zeros(n)
                p[i], p[j] = sign * h, sign * h
                points.append(p)
    return np.array(points)


def cheap_derivatives(values: np.ndarray, n: int, h: float = STEP):
    """
    Return (f, gradient, Hessian) from f on :func:`cheap_stencil`'s points, all O(h²).

    f(+h, +h) + f(−h, −h) = 2f + h²(H_ii + 2H_ij + H_jj) + O(h⁴), and the axis points
    give h²H_ii and h²H_jj: two corners per pair instead of four (13 settings for three
    noises, not 19), and an error small enough for Newton on a ridge of correlation
    0.98, where the one-corner O(h) formula made the climb creep.
    """
    f0, g, H = derivatives(np.concatenate([values[:1 + 2 * n],
                                           np.zeros(4 * (n * (n - 1) // 2))]), n, h)
    k = 1 + 2 * n
    for i in range(n):
        for j in range(i):
            axes = values[1 + 2 * i] + values[2 + 2 * i] + values[1 + 2 * j] + values[2 + 2 * j]
            H[i, j] = H[j, i] = (values[k] + values[k + 1] - axes + 2.0 * f0) / (2.0 * h * h)
            k += 2
    return f0, g, H


def newton_direction(g: np.ndarray, H: np.ndarray) -> np.ndarray:
    """
    Return the ascent step −H⁻¹g of ℓ's quadratic model, H made negative definite.

    H = V diag(λ) Vᵀ; each λ is replaced by −max(|λ|, 1e-8·max|λ|, 1e-12), so a saddle
    or a flat direction still yields an ascent direction (gᵀ step > 0).
    """
    if not np.all(np.isfinite(H)) or not np.all(np.isfinite(g)):
        return np.zeros_like(g)
    values, vectors = np.linalg.eigh(H)
    floor = max(1e-8 * float(np.max(np.abs(values))), 1e-12)
    curvature = np.maximum(np.abs(values), floor)                     # of −ℓ: positive
    return vectors @ ((vectors.T @ g) / curvature)                     # (−H̃)⁻¹ g


def _within(step: np.ndarray, radius: float) -> np.ndarray:
    """Return ``step`` shortened to the trust radius (Euclidean norm in log θ)."""
    norm = float(np.linalg.norm(step))
    return step if norm <= radius else step * (radius / norm)


def _candidates(g: np.ndarray, H: np.ndarray, radius: float, axes: bool) -> List[np.ndarray]:
    """Return the steps tried after a stencil: Newton's, the gradient's, each axis if asked."""
    n = g.shape[0]
    newton = _within(newton_direction(g, H), radius)
    steps = [newton * f for f in NEWTON_FRACTIONS]
    norm = float(np.linalg.norm(g))
    if norm > 0.0:
        steps += [g / norm * radius * f for f in GRADIENT_FRACTIONS]
    if axes:                                # a kinked or flat ℓ: try each axis alone
        for i in np.flatnonzero(g):             # not a held noise (g 0)
            axis = np.zeros(n)
            axis[i] = radius * 0.25 * (1.0 if g[i] >= 0.0 else -1.0)
            steps.append(axis)
    return steps


def _ladder(vector: np.ndarray, newton: np.ndarray, full: np.ndarray, low: np.ndarray
            ) -> List[np.ndarray]:
    """
    Return the Newton step with each noise headed for 0 set lower: LADDER_DECADES, the floor.

    Headed for 0: the full (unclipped) Newton step ``full`` moves it down by at least
    half an e-fold; near 0 it is one e-fold (the module docstring), near an interior
    maximum a short step.
    """
    steps = []
    for i in np.flatnonzero((full <= -0.5) & (vector > low)):
        for rung in [vector[i] - d * LN10 for d in LADDER_DECADES] + [low[i]]:
            if low[i] <= rung < vector[i] + newton[i]:
                step = newton.copy()
                step[i] = rung - vector[i]
                steps.append(step)
    return steps


def _held(vector: np.ndarray, g: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Return which noises sit on a box edge that ℓ pushes them past (one step wins < GAIN_TOL)."""
    flat = GAIN_TOL / STEP
    return (((vector <= low + STEP_TOL) & (g < flat))
            | ((vector >= high - STEP_TOL) & (g > -flat)))


def _free(g: np.ndarray, H: np.ndarray, held: np.ndarray):
    """Return (g, H) of the model restricted to the noises not held (held: g 0, H −I)."""
    g, H = np.where(held, 0.0, g), H.copy()
    H[held, :] = 0.0
    H[:, held] = 0.0
    H[held, held] = -1.0
    return g, H


def _concave(H: np.ndarray) -> bool:
    """Return whether H is negative definite (a proper maximum's curvature)."""
    return bool(np.all(np.isfinite(H)) and np.linalg.eigvalsh(H)[-1] < 0.0)


def climb(objective: Objective, start: np.ndarray, low: np.ndarray, high: np.ndarray,
          start_log_likelihood: float = None) -> Climb:
    """
    Return the maximum of ``objective`` found from ``start`` within the box [low, high].

    ``objective`` maps (K, n) log-parameter vectors to ℓ (K,) in one pass; an invalid
    value (non-finite) counts as −inf. See the module docstring for the steps and stops.
    """
    def clipped(v):
        return np.clip(v, low, high)

    def evaluate(points):
        values = np.asarray(objective(np.asarray(points, dtype=float)), dtype=float)
        return np.where(np.isfinite(values), values, -np.inf)
    offsets = cheap_stencil(start.shape[0])
    vector = clipped(np.asarray(start, dtype=float))
    passes = evaluations = steps = 0
    radius, last_step, last_gain = MAX_RADIUS, math.inf, math.inf
    ll0 = None if start_log_likelihood is None else float(start_log_likelihood)
    ll = ll0
    stop = f'step limit ({MAX_STEPS} steps)'
    g = H = start_H = None
    while True:
        values = evaluate(vector + offsets)         # −inf at a stencil point: its side is out
        passes, evaluations = passes + 1, evaluations + values.shape[0]
        ll = float(values[0]) if ll is None else ll
        ll0 = ll if ll0 is None else ll0
        values = np.where(np.isfinite(values), values, ll - 1e30)
        _, g, H = cheap_derivatives(values, len(vector))
        start_H = H if start_H is None else start_H
        if steps >= MAX_STEPS:
            break
        free_g, free_H = _free(g, H, _held(vector, g, low, high))
        full = newton_direction(free_g, free_H)           # the unclipped Newton step
        gain = 0.5 * float(free_g @ full)                 # the quadratic model's gain
        if gain < GAIN_TOL and (last_step < STEP_TOL or _concave(free_H)):
            stop = 'converged'
            break
        improved = False
        tries = 0
        while radius >= STEP_TOL and not improved:
            steps_tried = _candidates(free_g, free_H, radius, axes=tries > 0)
            steps_tried += _ladder(vector, steps_tried[0], full, low)
            points = np.array([clipped(vector + s) for s in steps_tried])
            tries += 1
            trial = evaluate(points)
            passes, evaluations = passes + 1, evaluations + trial.shape[0]
            best = int(np.argmax(trial))
            if trial[best] > ll:
                last_step = float(np.linalg.norm(points[best] - vector))
                last_gain = float(trial[best]) - ll
                vector, ll, improved = points[best], float(trial[best]), True
                # a full Newton step taken: trust more; a cut one: keep the radius
                radius = min(MAX_RADIUS, 2.0 * radius) if best == 0 else radius
            elif float(np.linalg.norm(full)) < STEP:
                break       # within the stencil's step ℓ's ripple (gate, stops) outweighs
            else:
                radius *= 0.25
        if not improved and float(np.linalg.norm(full)) < STEP:
            stop = (f'converged (the Newton step, {float(np.linalg.norm(full)):.1g} in log θ, '
                    f"is below the stencil's {STEP:g} and raises nothing)")
            break
        if not improved:
            stop = f'no improving step (none of {STEP_TOL:g} in log θ raises ℓ)'
            break
        steps += 1
        if last_gain < GAIN_TOL:        # creeping along a flat direction: nothing to win
            stop = f'converged (the last step raised ℓ by {last_gain:.1g})'
            break
        radius = max(radius, 4.0 * STEP_TOL)
    return Climb(vector, ll, ll0, g, H, steps, passes, evaluations, stop,
                 clipped(np.asarray(start, dtype=float)), start_H)


def best_of(climbs: Sequence[Climb]) -> int:
    """Return the index of the climb that ended highest (the first of equals)."""
    return int(np.argmax([c.log_likelihood for c in climbs]))
