"""
The rail regimes' dynamics for any dt: transition F(dt) and process noise Q(dt), once.

The regimes' state is [p, v, a, ℓ, A, B] (:mod:`kf_train.filters.rail_model`): a moving
regime's F and Q are the relaxation's below on [p, v, a, ℓ], with A and B held under a
random walk (:func:`moving_transition`, :func:`moving_noise`); the stand regime holds
p (plus its own random walk) and A, B, and sets v = a = ℓ = 0 (:data:`STAND_TRANSITION`,
:func:`stand_noise`).

A moving train follows ṗ = v, v̇ = a, ȧ = (ℓ - a)/τ, ℓ̇ = 0, with white noise q_a on ȧ
and q_ℓ on ℓ̇ (:mod:`kf_train.filters.rail_model`). F(dt) has a closed form in
φ1 = 1 - e^-x, φ2 = x - φ1, φ3 = x²/2 - φ2 (x = dt/τ); Q(dt) is the integral
∫₀^dt F(s) diag(0, 0, q_a, q_ℓ) F(s)ᵀ ds.

Both are asked for at every new dt, and a real sensor's stamps jitter, so a stream
can bring a new dt at every step: they are computed in a handful of numpy calls. For
dt <= 1.5 τ, Q(dt) is a power series in dt whose coefficients are built once per
(τ, q_a, q_ℓ) (:class:`RelaxationNoise`); beyond, Gauss-Legendre quadrature
(:func:`relaxation_noise`), which is also the series' reference in the tests.
"""

import math
from typing import Tuple

import numpy as np

# Below this x = dt/τ the φ functions use their Taylor series (no cancellation).
_SERIES_BELOW = 0.1
# Powers x^0 ... x^11 and the series coefficients Σ (-1)^k x^k / k!: φ2 from k = 2,
# φ3 from k = 3 (10 terms: error < x¹²/12! < 1e-21 for x < 0.1).
_PHI_POWERS = np.arange(12)
_PHI2_SERIES = np.array([0.0, 0.0] + [(-1.0) ** k / math.factorial(k) for k in range(2, 12)])
_PHI3_SERIES = -_PHI2_SERIES
_PHI3_SERIES[2] = 0.0
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(8)
# Q(dt) by its power series up to dt = _NOISE_SERIES_SPAN · τ, with _NOISE_TERMS terms
# of each φ: the first neglected term of a product is below (2x)^35 / 35! < 1e-23 at
# x = 1.5, and the alternating sums lose at most a factor e^(2x) = 20 to cancellation,
# so the series is within ~1e-14 of ‖Q‖ (tested against the quadrature).
_NOISE_SERIES_SPAN = 1.5
_NOISE_TERMS = 34


def _phi(x) -> Tuple:
    """
    Return φ1 = 1 - e^-x, φ2 = x - φ1 and φ3 = x²/2 - φ2 for x >= 0 (a float or an array).

    φ2 ≈ x²/2 and φ3 ≈ x³/6 for small x, where the differences cancel; there the
    Taylor series Σ (-1)^k x^k / k! (k >= 2, resp. k >= 3) is used instead. A float
    (one dt, a new one at every step when stamps jitter) is computed as floats.
    """
    scalar = type(x) is float
    if not scalar:
        x = np.asarray(x, dtype=float)
    phi1 = -math.expm1(-x) if scalar else -np.expm1(-x)
    phi2 = x - phi1
    phi3 = x * x / 2.0 - phi2
    if scalar:
        return (phi1,) + (_series(x) if x < _SERIES_BELOW else (phi2, phi3))
    small = x < _SERIES_BELOW
    if np.any(small):
        phi2 = np.where(small, 0.0, phi2)
        phi3 = np.where(small, 0.0, phi3)
        phi2[small], phi3[small] = _series(x[small])
    return phi1, phi2, phi3


def _series(x) -> Tuple:
    """Return the Taylor series of φ2 and φ3 at x (a float or an array), as x is."""
    powers = np.power.outer(x, _PHI_POWERS)                # x^0 ... x^11 (last axis)
    phi2, phi3 = powers.dot(_PHI2_SERIES), powers.dot(_PHI3_SERIES)
    return (float(phi2), float(phi3)) if type(x) is float else (phi2, phi3)


def relaxation_transition(dt_s, tau_s: float) -> np.ndarray:
    """
    Return F(dt) of ṗ = v, v̇ = a, ȧ = (ℓ - a)/τ, ℓ̇ = 0 for each dt: shape (k, 4, 4).

    With x = dt/τ: a(dt) = e^-x a + φ1 ℓ, v(dt) = v + τ φ1 a + τ φ2 ℓ,
    p(dt) = p + dt v + τ² φ2 a + τ² φ3 ℓ (exact solution of the linear ODE).
    """
    dt = np.atleast_1d(np.asarray(dt_s, dtype=float))
    rows = relaxation_rows(dt, tau_s, *_phi(dt / tau_s), np.ones_like(dt), np.zeros_like(dt))
    return np.moveaxis(np.array(rows), 2, 0)


def relaxation_rows(dt, tau_s: float, phi1, phi2, phi3, one, zero) -> tuple:
    """Return F(dt)'s 4x4 entries as rows of floats or arrays (one, zero: of their kind)."""
    tau2 = tau_s * tau_s
    return ((one, dt, tau2 * phi2, tau2 * phi3),
            (zero, one, tau_s * phi1, tau_s * phi2),
            (zero, zero, 1.0 - phi1, phi1),
            (zero, zero, zero, one))


def relaxation_noise(dt_s: float, tau_s: float, q_a: float, q_l: float) -> np.ndarray:
    """
    Return Q(dt) = ∫₀^dt F(s) diag(0, 0, q_a, q_ℓ) F(s)ᵀ ds by quadrature.

    Gauss-Legendre, 8 nodes on panels no wider than τ/2: the integrand is a
    polynomial of degree <= 4 times e^(-ks/τ), k <= 2, which 8 nodes integrate to
    rounding on such a panel.
    """
    panels = max(1, int(math.ceil(dt_s / (0.5 * tau_s))))
    edges = np.linspace(0.0, dt_s, panels + 1)
    half = 0.5 * np.diff(edges)
    s = ((edges[:-1] + half)[:, None] + half[:, None] * _GL_NODES).ravel()
    w = (half[:, None] * _GL_WEIGHTS).ravel()
    F = relaxation_transition(s, tau_s)
    col_a, col_l = F[:, :, 2], F[:, :, 3]              # how noise on a and on ℓ spreads
    Q = q_a * np.einsum('k,ka,kb->ab', w, col_a, col_a) + \
        q_l * np.einsum('k,ka,kb->ab', w, col_l, col_l)
    return 0.5 * (Q + Q.T)


class RelaxationNoise:
    """
    Q(dt) of :func:`relaxation_noise` for one (τ, q_a, q_ℓ), cheap for dt <= 1.5 τ.

    With x = s/τ, the columns of F(s) that carry the noise are [τ²φ2, τφ1, e^-x, 0]
    for a and [τ²φ3, τφ2, φ1, 1] for ℓ: power series in x (each φ's is e^-x's, shifted)
    times τ^p_a, p = (2, 1, 0, 0) for both. So is each product of two of them (a
    convolution of coefficients), and its integral over s = τx from 0 to dt (each
    coefficient divided by its new power, times τ). Q_ab is then τ^(1 + p_a + p_b)
    times one product of a fixed table with [X, X², ...], X = dt/τ <= 1.5: a few
    numpy calls instead of a quadrature, and no power of τ or dt that could overflow.
    Entries (a, b) and (b, a) share one row: Q is exactly symmetric.
    """

    def __init__(self, tau_s: float, q_a: float, q_l: float):
        """Build the coefficient table for ``tau_s`` [s], ``q_a`` and ``q_l`` [m²/s⁵]."""
        self.tau_s, self.q_a, self.q_l = float(tau_s), float(q_a), float(q_l)
        k = np.arange(_NOISE_TERMS + 1)
        decay = np.array([(-1.0) ** i / math.factorial(i) for i in k])   # e^-x
        phi1 = -decay
        phi1[0] = 0.0                                         # 1 - e^-x
        phi2 = -phi1
        phi2[1] += 1.0                                        # x - φ1
        phi3 = -phi2
        phi3[2] += 0.5                                        # x²/2 - φ2
        one, zero = np.zeros(k.size), np.zeros(k.size)
        one[0] = 1.0
        columns = ((self.q_a, (phi2, phi1, decay, zero)), (self.q_l, (phi3, phi2, phi1, one)))
        table = np.zeros((16, k.size))
        for q, column in columns:
            for a in range(4):
                for b in range(a, 4):
                    product = np.convolve(column[a], column[b])[:k.size]
                    table[4 * a + b] += q * product / (k + 1.0)   # ∫₀^X x^k = X^(k+1)/(k+1)
        for a in range(4):
            for b in range(a):
                table[4 * a + b] = table[4 * b + a]
        powers_of_tau = np.array([2.0, 1.0, 0.0, 0.0])
        self._scale = (self.tau_s ** (1.0 + powers_of_tau[:, None] + powers_of_tau[None, :])
                       ).reshape(16)                          # τ^(1 + p_a + p_b)
        self._table = table
        self._powers = k + 1.0

    @property
    def series(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Return (table (16, k), τ^(1 + p_a + p_b) (16,), powers (k,), largest dt/τ)."""
        return self._table, self._scale, self._powers, _NOISE_SERIES_SPAN

    def __call__(self, dt_s: float) -> np.ndarray:
        """Return the 4x4 Q(dt_s) (a new array)."""
        x = dt_s / self.tau_s
        if x > _NOISE_SERIES_SPAN:
            return relaxation_noise(dt_s, self.tau_s, self.q_a, self.q_l)
        Q = self._table.dot(x ** self._powers)
        Q *= self._scale
        return Q.reshape(4, 4)


DIM_X = 6
"""The regimes' states: p, v, a, ℓ, A, B."""
STAND_TRANSITION = np.diag([1.0, 0.0, 0.0, 0.0, 1.0, 1.0])
"""F of the stand regime, for every dt: p, A and B held, v = a = ℓ = 0."""
STAND_TRANSITION.flags.writeable = False


def stand_noise(dt_s: float, position_noise: float, capability_noise: float) -> np.ndarray:
    """Return the 6x6 Q(dt) of the stand regime: p's random walk, and A, B's drift."""
    return np.diag([position_noise * dt_s, 0.0, 0.0, 0.0,
                    capability_noise * dt_s, capability_noise * dt_s])


def moving_transition(dt_s: float, tau_s: float) -> np.ndarray:
    """Return the 6x6 F(dt) of a moving regime: the relaxation, A and B held."""
    F = np.eye(DIM_X)
    F[:4, :4] = relaxation_rows(dt_s, tau_s, *_phi(dt_s / tau_s), 1.0, 0.0)
    return F


def moving_noise(dt_s: float, relaxation: RelaxationNoise, capability_noise: float
                 ) -> np.ndarray:
    """Return the 6x6 Q(dt) of a moving regime: the relaxation's, and A, B's drift."""
    Q = np.zeros((DIM_X, DIM_X))
    Q[:4, :4] = relaxation(dt_s)
    Q[4, 4] = Q[5, 5] = capability_noise * dt_s
    return Q
