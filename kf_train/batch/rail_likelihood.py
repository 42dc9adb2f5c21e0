"""
The rail IMM's log-likelihood of a measurement sequence, for many noise settings at once.

The rail preset (:class:`~kf_train.filters.RailModel`, docs/rail.md) is an IMM of four
regimes. Its prediction of the next measurement is a Gaussian mixture: after the
mixing and the mode-matched predictions, regime j predicts z_k ~ N(ẑ_j, s_j) with
probability c̄_j. The likelihood of the data given the model's noise θ is therefore

    ℓ(θ) = Σ_k log Σ_j c̄_kj N(y_kj; 0, s_kj),    y_kj = z_k − ẑ_kj,

summed over every measurement after the first (which initialises the filter, as the
node's ``first_measurement`` does). This is the standard IMM likelihood (Bar-Shalom,
Li & Kirubarajan 2001, §11.6.6): exact for the IMM's recursion, which itself
approximates the true 4ᵏ-component mixture by one Gaussian per regime after each
mixing; it is the likelihood of the filter the node runs, not of an exact switching
model.

Evaluating it once per setting with the node's own classes costs one IMM run
(~130 µs per measurement on the test machine, ~0.8 s for 6000 fixes); an optimiser
with numerical gradients and a curvature needs dozens of them. :func:`rail_log_likelihoods`
runs K settings at once instead: the same equations as
:class:`~kf_train.filters.RailModel` and :mod:`kf_train.filters.imm_stack` (mixing with
the regimes' entry transformation, the state-dependent brake → stand rate, x⁻ = F x,
P⁻ = F P Fᵀ + Q, the Joseph-form scalar update, |a| within its bound and no velocity
below 0 (:mod:`~kf_train.filters.rail_model`'s ``bound_acceleration`` and
``hold_velocity``), the posterior in the log domain),
with one more leading axis for the settings, so one pass costs little more than one
run. The tests hold it to the node's classes (RailModel.predict/update, and the
StreamEstimator) to 1e-9 relative on simulated runs.

Only noises that do not change the motion's transition F are varied here: the
acceleration noise q_a, the command noise q_ℓ, the capability noise and the
measurement variance R (:class:`RailNoise`); everything else is the preset's.

What the node runs on top of the IMM, each off by default (then R is the setting's,
fixed, as the fit of R itself needs):

* ``variances``: the variance r_k each message carries (a setting's
  ``measurement_variance`` overrides them, as the node's parameter does);
* ``adaptation``: R_k = s_k·r_k with s learned as the node learns it
  (:mod:`kf_train.filters.noise_adaptation`, from the fused fixes' mixture y and S;
  ``base.adaptation()`` is the preset's); the first fix starts with s = 1, R = r₀;
* ``gate_threshold``: the χ² gate on y²/S (y²/(S + (1 − s) r) when s < 1, as
  :meth:`~kf_train.filters.IMM.finish_update`'s ``gate_nis``). A gated fix is not
  fused: the state (and the scale) stay the last fused fix's, and the next fix is
  predicted from there, as in the node. It adds −½(γ + log S_gate + log 2π) to ℓ, the
  density of N(0, S_gate) at the gate's edge: a robust treatment, continuous in y at
  the gate, that charges an outlier a bounded amount whatever its size (as clutter in
  a PDA filter), so that a setting is not rewarded for gating out fixes it explains badly
  nor ruined by one 1-km fix. The last fused position repeated exactly is judged on the
  R in use (y²/S) instead, as the node judges a repeated epoch
  (``Fusion._reject_repeat``), and counted as gated when it fails.

A held position (the last fused one repeated exactly, a repeat let through, with a
variance given up to ``hold_max_variance_m2``) is fused as a speed of 0 ±
``hold_speed_std_mps`` when that passes the gate, as the node fuses it
(``Fusion._hold``): its ℓ term is the speed's, it teaches neither s nor the walk, and
its y and S are NaN.

Not modelled: the lock-out and re-acquisition after ``max_consecutive_outliers``
gated fixes in a row, measured speeds, out-of-sequence fixes (the tests stay clear of
them). ``engine`` 'numba' runs the same recursion compiled
(:mod:`kf_train.filters.rail_likelihood_kernel`, ~100x faster; the default ``auto``
where numba is installed), 'numpy' this module's reference.
"""

import dataclasses
import math
from typing import NamedTuple, Optional, Sequence

from kf_train import filters
from kf_train.batch.noise_likelihood import Segment
from kf_train.filters import (
    bound_acceleration, combine, first_jump_row, hold_velocity, LOG_2PI, MODE_NAMES,
    moved_past, NoiseAdaptation, NoiseScale, numba_available, position_walked, RailModel,
    RailModelParameters, RateTransition, stop_probability, STOPPING)
import numpy as np

STAND = MODE_NAMES.index('stand')
ENGINES = ('auto', 'numba', 'numpy')
"""How :func:`rail_log_likelihoods` runs: compiled (numba), the numpy reference, or numba
where it is installed (auto)."""
FIXED = NoiseScale()

RAIL_NOISE_FIELDS = ('acceleration_noise', 'command_noise', 'capability_noise')
"""The RailModelParameters a :class:`RailNoise` varies (they only change Q)."""


class RailNoise(NamedTuple):
    """One noise setting of the rail model (None: the preset's value)."""

    acceleration_noise: Optional[float] = None
    """q_a [m²/s⁵]."""
    command_noise: Optional[float] = None
    """q_ℓ [m²/s⁵]."""
    capability_noise: Optional[float] = None
    """Random walk of A and B [m²/s⁵]."""
    measurement_variance: Optional[float] = None
    """R [m²]; None: the preset's (its ``R``)."""

    def parameters(self, base: RailModelParameters) -> RailModelParameters:
        """Return ``base`` with this setting's noises (R as noise_std_m)."""
        fields = {name: getattr(self, name) for name in RAIL_NOISE_FIELDS
                  if getattr(self, name) is not None}
        if self.measurement_variance is not None:
            fields['noise_std_m'] = math.sqrt(self.measurement_variance)
        return dataclasses.replace(base, **fields)


class RailLikelihoods(NamedTuple):
    """What one pass over the data gives for K settings."""

    log_likelihood: np.ndarray
    """ℓ of each setting (K,)."""
    nis: np.ndarray
    """(K, rows): the mixture innovation's NIS y²/S at every measurement after the first.
    The per-fix fields (K, rows) are filled with ``innovations``, else (K, 0). A held
    position (fused as a speed of 0, not gated) has NaN for its NIS, y and S."""
    innovation: np.ndarray
    """(K, rows): the mixture innovation y = z − Σ c̄_j ẑ_j."""
    variance: np.ndarray
    """(K, rows): its variance S = Σ c̄_j (s_j + (ẑ_j − ẑ)²)."""
    gated_count: np.ndarray
    """(K,): how many fixes the χ² gate kept out, per setting."""
    gated: np.ndarray
    """(K, rows): whether each fix was gated out."""
    scale: np.ndarray
    """(K, rows): the learned scale s on R after each fix (1 without adaptation)."""


class _Unit(NamedTuple):
    """Per dt: F (4, 6, 6), Fᵀ, and Q per unit of each noise (4, 6, 6)."""

    F: np.ndarray
    F_transposed: np.ndarray
    acceleration: np.ndarray
    command: np.ndarray
    capability: np.ndarray
    stand: np.ndarray


class _UnitModels:
    """
    The regimes' F(dt) and their Q(dt) per unit of each noise, from the node's RailModel.

    Q is linear in the noises (RailModel's moving Q is RelaxationNoise(τ, q_a, q_ℓ)(dt)
    = q_a·Q(1, 0) + q_ℓ·Q(0, 1), plus capability_noise·dt on A and B; stand's is
    stand_noise·dt on p and capability_noise·dt on A and B), so the RailModel of each
    unit noise gives the unit matrices, and a setting's Q is their weighted sum.
    """

    def __init__(self, base: RailModelParameters):
        """Build one RailModel per unit noise (the others 0)."""
        zero = dataclasses.replace(base, acceleration_noise=0.0, command_noise=0.0,
                                   capability_noise=0.0, stand_noise=0.0)
        self.models = [RailModel(dataclasses.replace(zero, **{name: 1.0}))
                       for name in RAIL_NOISE_FIELDS + ('stand_noise',)]
        self.kept = {}

    def __call__(self, dt_s: float) -> _Unit:
        """Return the unit matrices for dt_s (kept per dt)."""
        unit = self.kept.get(dt_s)
        if unit is None:
            modes = self.models[0].modes
            F = np.array([mode.F(dt_s) for mode in modes])
            Qs = [np.array([mode.Q(dt_s) for mode in model.modes]) for model in self.models]
            unit = self.kept[dt_s] = _Unit(F, F.swapaxes(1, 2).copy(), *Qs)
        return unit


def _entry(model: RailModel):
    """
    Return (rows (4, 6), rows², W (4,)) of RailModel.entry for the four regimes.

    Entering regime j is x' = T_j x + w: T_j is the identity with ℓ's row replaced by
    ``rows[j]`` (A's for accelerate, −B's for brake, zeros otherwise) and w ~ N(0, W_j):
    the node's rule, :attr:`RailModel.entry_rule`, as rows.
    """
    rule = model.entry_rule
    rows = np.zeros((4, 6))
    for j, (source, factor) in enumerate(zip(rule.sources, rule.factors)):
        if source is not None:
            rows[j, source] = factor                          # ℓ = A + w, ℓ = −B + w
    return rows, rows * rows, np.array(rule.noises)


def _transition(base: np.ndarray, params: RailModelParameters, stop_rates: np.ndarray,
                dt_s: float, means: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """
    Return Π(dt) per setting (K, 4, 4): the fixed rates, → stand scaled by P(slow).

    As RailModel.transition: each row of STOPPING (a regime a slow train may stop
    from) has its stand rate stop_rate · P(v <= stop_speed) under that regime's
    estimate; the row is :func:`~kf_train.filters.first_jump_row`
    (Π_ii = e^(−r_i dt), Π_ij = (1 − e^(−r_i dt)) r_ij / r_i), per setting.
    """
    count = means.shape[0]
    matrix = np.repeat(base[None], count, axis=0)
    for regime in STOPPING:
        slow = stop_probability(means[:, regime, 1],
                                np.sqrt(np.maximum(covs[:, regime, 1, 1], 0.0)),
                                params.stop_speed_mps)
        rates = np.repeat(stop_rates[regime][None], count, axis=0)   # (K, 4), own 0
        rates[:, STAND] = params.stop_rate_hz * slow
        matrix[:, regime] = first_jump_row(rates, regime, dt_s)       # Π(dt)'s one formula
    return matrix


def _mix(matrix: np.ndarray, probabilities: np.ndarray, means: np.ndarray, covs: np.ndarray,
         entry):
    """
    Return (c̄ (K, 4), x0 (K, 4, 6), P0 (K, 4, 6, 6)): the IMM's mixing with the entry hook.

    c̄_j = Σ_i Π_ij μ_i, ω_ij = Π_ij μ_i / c̄_j (an unreachable regime, c̄_j = 0, keeps
    its own estimate); component i enters regime j as x' = T_j x + w (ℓ's entry, row and
    column change); x0_j = Σ_i ω_ij x_ji, P0_j = Σ_i ω_ij (P_ji + d dᵀ), d = x_ji − x0_j.
    """
    count, modes, n = means.shape
    rows, squares, noise = entry
    cbar = np.einsum('ki,kij->kj', probabilities, matrix)           # c̄_j = Σ_i Π_ij μ_i
    unreachable = cbar == 0.0
    blocked = unreachable.any()
    weights = matrix * probabilities[:, :, None] / (
        np.where(unreachable, 1.0, cbar) if blocked else cbar)[:, None]  # ω_ij = Π_ij μ_i / c̄_j
    if blocked:
        for k, j in zip(*np.nonzero(unreachable)):
            weights[k, :, j] = 0.0
            weights[k, j, j] = 1.0
    columns = weights.swapaxes(1, 2)                                 # [k, j, i] = ω_ij
    eye = np.arange(modes)
    xs = np.repeat(means[:, None], modes, axis=1)                    # [k, j, i] = x_i
    xs[:, :, :, 3] = np.einsum('jn,kin->kji', rows, means)          # ℓ_ji = T_j's row · x_i
    xs[:, eye, eye, 3] = means[:, :, 3]                              # staying: itself
    x0 = np.matmul(columns[:, :, None, :], xs)[:, :, 0, :]           # Σ_i ω_ij x_ji
    ell = np.einsum('jn,kinm->kjim', rows, covs)                     # row ℓ of T_j P_i
    diagonal = covs[:, :, np.arange(n), np.arange(n)]                # (K, i, n)
    ell[:, :, :, 3] = np.einsum('jn,kin->kji', squares, diagonal) + noise[None, :, None]
    ell[:, eye, eye, :] = covs[:, :, 3, :]
    spread = np.matmul(columns, covs.reshape(count, modes, n * n)).reshape(count, modes, n, n)
    row = np.matmul(columns[:, :, None, :], ell)[:, :, 0, :]         # Σ_i ω_ij (row ℓ)
    spread[:, :, 3, :] = row
    spread[:, :, :, 3] = row
    d = xs - x0[:, :, None, :]                                       # d_ji = x_ji − x0_j
    P0 = spread + np.matmul((columns[..., None] * d).swapaxes(2, 3), d)
    return cbar, x0, (P0 + P0.swapaxes(-1, -2)) * 0.5


def _update(means: np.ndarray, covs: np.ndarray, z: float, R: np.ndarray,
            identity: np.ndarray, h: int = 0):
    """
    Return (x, P, y (K, 4), s (K, 4)): every regime corrected by a scalar z of state h.

    H = e_h (0: the position, 1: the speed): y = z − x_h, s = P_hh + R, K = P[:, h] / s,
    x = x + K y and the Joseph form P = (I − K H) P (I − K H)ᵀ + K R Kᵀ, symmetrised,
    as imm_stack.update does.
    """
    y = z - means[:, :, h]                                           # y = z − H x⁻
    s = covs[:, :, h, h] + R[:, None]                                # s = H P⁻ Hᵀ + R
    gain = covs[:, :, :, h] / s[:, :, None]                          # K = P⁻ Hᵀ / s
    x = means + gain * y[:, :, None]                                 # x = x⁻ + K y
    I_KH = identity.copy()
    I_KH[:, :, :, h] -= gain                                         # I − K H
    P = np.matmul(np.matmul(I_KH, covs), I_KH.swapaxes(-1, -2)) + \
        (gain * R[:, None, None])[..., None] * gain[:, :, None, :]   # + K R Kᵀ
    return x, (P + P.swapaxes(-1, -2)) * 0.5, y, s


def _noise_of(settings: Sequence[RailNoise], base: RailModelParameters):
    """Return (q_a, q_ℓ, q_c, R override or NaN) per setting, each (K,)."""
    def column(name, default):
        return np.array([default if getattr(s, name) is None else float(getattr(s, name))
                         for s in settings])
    return (column('acceleration_noise', base.acceleration_noise),
            column('command_noise', base.command_noise),
            column('capability_noise', base.capability_noise),
            column('measurement_variance', math.nan))


class _Model:
    """The preset's constant parts, per dt, and the settings' noises, for the numpy pass."""

    def __init__(self, base: RailModelParameters, noise):
        """Keep the entry rule, rates, unit matrices and the noises q_a, q_ℓ, q_c (K,)."""
        self.base = base
        self.walk = base.error_walk()                # the receiver's error walk: the node's
        self.entry, self.rates = _entry(RailModel(base)), RateTransition(base.rates())
        self.stop_rates = base.rates()
        self.units, self.bases = _UnitModels(base), {}
        self.weights = tuple(q[:, None, None, None] for q in noise[:3])

    def predict(self, dt: float, chosen, means: np.ndarray, covs: np.ndarray,
                probabilities: np.ndarray):
        """Return (c̄, x⁻, P⁻) of the settings ``chosen`` (an index or slice) over dt."""
        unit, base = self.units(dt), self.base
        if dt not in self.bases:
            self.bases[dt] = self.rates.matrix(dt)
        matrix = _transition(self.bases[dt], base, self.stop_rates, dt, means, covs)
        cbar, mixed_x, mixed_P = _mix(matrix, probabilities, means, covs, self.entry)
        cbar = cbar / cbar.sum(axis=1, keepdims=True)                # as IMM.predict
        q_a, q_l, q_c = (w[chosen] for w in self.weights)
        Q = q_a * unit.acceleration + q_l * unit.command + q_c * unit.capability + \
            base.stand_noise * unit.stand
        means = np.matmul(unit.F, mixed_x[..., None])[..., 0]        # x⁻ = F x
        covs = np.matmul(np.matmul(unit.F, mixed_P), unit.F_transposed) + Q  # F P Fᵀ + Q
        return cbar, means, (covs + covs.swapaxes(-1, -2)) * 0.5


def _first(base: RailModelParameters, z0: float, r0: np.ndarray):
    """Return (means, covs, probabilities) after first_measurement: z₀ with variance r₀."""
    count = r0.shape[0]
    x0 = np.array([z0, 0.0, 0.0, 0.0, base.accelerate_mps2, base.brake_mps2])
    means = np.tile(x0, (count, 4, 1))
    covs = np.tile(base.initial_covariance(1.0), (count, 4, 1, 1))
    covs[:, :, 0, 0] = r0[:, None]
    return means, covs, np.full((count, 4), 0.25)


def _predict_all(model: _Model, dts: np.ndarray, means, covs, probabilities):
    """Return (c̄, x⁻, P⁻) of every setting, each over its own dt (the time since its last fix)."""
    if np.all(dts == dts[0]):
        return model.predict(float(dts[0]), slice(None), means, covs, probabilities)
    cbar, predicted_x, predicted_P = (np.empty_like(a) for a in (probabilities, means, covs))
    for dt in np.unique(dts).tolist():
        chosen = np.nonzero(dts == dt)[0]
        cbar[chosen], predicted_x[chosen], predicted_P[chosen] = model.predict(
            dt, chosen, means[chosen], covs[chosen], probabilities[chosen])
    return cbar, predicted_x, predicted_P


def _mixture_log_likelihood(cbar: np.ndarray, y: np.ndarray, s: np.ndarray):
    """Return (log Σ_j c̄_j N(y_j; s_j) (K,), posterior μ (K, 4)), in the log domain."""
    logs = np.log(cbar) - 0.5 * (y * y / s + np.log(s) + LOG_2PI)     # log c̄_j N(y_j; s_j)
    top = logs.max(axis=1, keepdims=True)
    w = np.exp(logs - top)
    mass = w.sum(axis=1)
    return top[:, 0] + np.log(mass), w / mass[:, None]                # μ_j ∝ c̄_j Λ_j


def _mixture_moments(cbar: np.ndarray, y: np.ndarray, s: np.ndarray):
    """Return the mixture's innovation (ȳ (K,), S (K,)), as IMM.update moment-matches it."""
    ybar = np.einsum('kj,kj->k', cbar, y)                            # y = z − Σ c̄_j ẑ_j
    d = y - ybar[:, None]
    return ybar, np.einsum('kj,kj->k', cbar, s + d * d)              # Σ c̄_j (s_j + d_j²)


def _segment_pass(segment: Segment, model: _Model, reported: np.ndarray,
                  adaptation: Optional[NoiseAdaptation], threshold: float):
    """Return _SegmentResult of one segment (see rail_log_likelihoods), the numpy reference."""
    count, N = reported.shape
    t, z = segment.t_s, segment.z[:, 0]
    rows = max(N - 1, 0)
    result = _SegmentResult.empty(count, rows)
    if rows == 0:
        return result
    means, covs, probabilities = _first(model.base, float(z[0]), reported[:, 0])
    identity = np.tile(np.eye(6), (count, 4, 1, 1))
    noises = [FIXED] * count
    scale, walk = np.ones(count), np.zeros(count)
    last_t, last_z = np.full(count, t[0]), np.full(count, z[0])
    for k in range(rows):
        r = reported[:, k + 1]
        dts = t[k + 1] - last_t
        cbar, predicted_x, predicted_P = _predict_all(model, dts, means, covs, probabilities)
        predicted_P = position_walked(predicted_P, dts[:, None], walk[:, None])  # RailModel's
        R = np.where(scale == 1.0, r, r * scale)                     # noise_in_use: s r
        x, P, y, s = _update(predicted_x, predicted_P, float(z[k + 1]), R, identity)
        x = hold_velocity(bound_acceleration(x, P), P)                # |a| bound, no reversal
        ll, posterior = _mixture_log_likelihood(cbar, y, s)
        ybar, S = _mixture_moments(cbar, y, s)
        # The gate's variance: with s < 1 the R given (IMM.finish_update's gate_nis).
        gate_S = np.where(scale < 1.0, S + (1.0 - scale) * r, S)
        gate_nis = np.where(scale < 1.0, ybar * ybar / gate_S, ybar * (ybar / S))
        # A repeated epoch: the last fused position again, judged on the R in use and
        # on the speed at the last fix (Fusion._reject_repeat), not fused, counted as
        # gated.
        repeat = _repeats(float(z[k + 1]), last_z, t[k + 1] - last_t, scale, R,
                          ybar * (ybar / S), threshold, (means, covs, probabilities))
        fused = ~(gate_nis > threshold) & ~repeat
        # A held position (a repeat let through, a variance given up to the bound): a
        # speed of 0 when that passes the gate (Fusion._hold), teaching nothing.
        held = _holds(model.base, scale, repeat, float(z[k + 1]), last_z, r)
        if held.any():
            *hold, hold_nis = _hold_update(model.base, cbar, predicted_x, predicted_P,
                                           identity)
            held &= ~(hold_nis > threshold)
            x, P, posterior, ll = (
                np.where(held.reshape((-1,) + (1,) * (position.ndim - 1)), speed, position)
                for position, speed in zip((x, P, posterior, ll), hold))
            ybar, S = (np.where(held, np.nan, a) for a in (ybar, S))   # no position's
            fused |= held
        result.add(k, ll, fused, threshold, gate_S, ybar, S)
        means = np.where(fused[:, None, None], x, means)
        covs = np.where(fused[:, None, None, None], P, covs)
        probabilities = np.where(fused[:, None], posterior, probabilities)
        last_t = np.where(fused, t[k + 1], last_t)
        last_z = np.where(fused, z[k + 1], last_z)
        for i in np.nonzero(fused & ~held)[0].tolist():  # the node's own rules, fix by fix
            noise = noises[i]
            if adaptation is not None:
                noise = adaptation.learn(noise, float(ybar[i]), float(S[i]), float(r[i]))
            noises[i] = model.walk.learn(noise, float(ybar[i]), float(S[i]), float(R[i]))
            scale[i], walk[i] = noises[i].scale, noises[i].walk_m2_per_s
        result.scale[:, k] = scale
    if not (np.all(np.isfinite(means)) and np.all(np.isfinite(covs))):
        raise ValueError('the rail filter produced a non-finite state; a noise is too large')
    return result


def _holds(base: RailModelParameters, scale: np.ndarray, repeat: np.ndarray, z: float,
           last_z: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Return which settings may take z as a held position: a repeat let through (Fusion)."""
    if base.hold_speed_std_mps == 0.0:
        return np.zeros(last_z.shape, dtype=bool)
    return (scale < 1.0) & (z == last_z) & ~repeat & (r <= base.hold_max_variance_m2)


def _hold_update(base: RailModelParameters, cbar: np.ndarray, predicted_x: np.ndarray,
                 predicted_P: np.ndarray, identity: np.ndarray) -> tuple:
    """Return (x, P, μ, ℓ term, NIS) of every setting after a speed of 0 (a hold)."""
    R = np.full(cbar.shape[0], base.hold_speed_std_mps ** 2)
    x, P, y, s = _update(predicted_x, predicted_P, 0.0, R, identity, h=1)
    x = hold_velocity(bound_acceleration(x, P), P)                   # as RailModel._held
    ll, posterior = _mixture_log_likelihood(cbar, y, s)
    ybar, S = _mixture_moments(cbar, y, s)
    return x, P, posterior, ll, ybar * (ybar / S)


def _repeats(z: float, last_z: np.ndarray, dt_s: np.ndarray, scale: np.ndarray,
             R: np.ndarray, moved_nis: np.ndarray, threshold: float, state) -> np.ndarray:
    """Return which settings reject z as a repeated epoch (Fusion._reject_repeat)."""
    repeat = (scale < 1.0) & (z == last_z)
    for i in np.nonzero(repeat & ~(moved_nis > threshold))[0].tolist():
        x, P = combine(*(part[i] for part in state))   # the state at the last fused fix
        repeat[i] = moved_past(float(x[1]), float(P[1, 1]), float(dt_s[i]),
                               float(P[0, 0]) + float(R[i]), threshold)
    return repeat


class _SegmentResult(NamedTuple):
    """One segment's figures per setting (K): ℓ, gated count; per fix (K, rows): the rest."""

    total: np.ndarray
    gated_count: np.ndarray
    y: np.ndarray
    S: np.ndarray
    gated: np.ndarray
    scale: np.ndarray

    @classmethod
    def empty(cls, count: int, rows: int) -> '_SegmentResult':
        """Return zeros (the scales ones) for ``count`` settings and ``rows`` fixes."""
        return cls(np.zeros(count), np.zeros(count, dtype=np.int64), np.zeros((count, rows)),
                   np.zeros((count, rows)), np.zeros((count, rows), dtype=bool),
                   np.ones((count, rows)))

    def add(self, k: int, ll: np.ndarray, fused: np.ndarray, threshold: float,
            gate_S: np.ndarray, y: np.ndarray, S: np.ndarray) -> None:
        """Add fix k: ℓ's term (a gated fix: the density at the gate's edge), y, S, gated."""
        edge = -0.5 * (threshold + np.log(gate_S) + LOG_2PI)        # N(√γ; 0, S_gate)
        self.total[:] += np.where(fused, ll, edge)
        self.gated_count[:] += ~fused
        self.gated[:, k] = ~fused
        self.y[:, k], self.S[:, k] = y, S


def _compiled_pass(segment: Segment, model: _Model, reported: np.ndarray, noise,
                   adaptation: Optional[NoiseAdaptation], threshold: float) -> _SegmentResult:
    """Return _SegmentResult of one segment by the compiled kernel (the numpy pass's equal)."""
    count, N = reported.shape
    result = _SegmentResult.empty(count, max(N - 1, 0))
    if N < 2:
        return result
    state = _first(model.base, float(segment.z[0, 0]), reported[:, 0]) + (
        np.tile(np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]), (count, 1)),
        np.full(count, segment.t_s[0]),
        np.full(count, float(segment.z[0, 0])))

    def unit_matrices(dt_s: float):
        unit = model.units(dt_s)
        return unit.F, unit.acceleration, unit.command
    filters.rail_likelihood_kernel.segment_likelihoods(
        model.base, segment.t_s, segment.z[:, 0].copy(), reported, noise[:3],
        adaptation or NoiseAdaptation(window=0), threshold, unit_matrices, state, tuple(result))
    return result


def _reported(noise, variances: Optional[np.ndarray], preset_variance: float,
              rows: int) -> np.ndarray:
    """Return r (K, N): the setting's R where set, else the rows' variances (or the preset's)."""
    override = noise[3]
    given = np.full(rows, preset_variance) if variances is None else \
        np.asarray(variances, dtype=float)
    if given.shape != (rows,):
        raise ValueError(f'variances must hold one (N,) array per segment, got {given.shape} '
                         f'for {rows} rows')
    reported = np.where(np.isnan(override)[:, None], given[None, :], override[:, None])
    if not (np.all(np.isfinite(reported)) and np.all(reported > 0.0)):
        raise ValueError('the measurement variances must be finite numbers > 0')
    return reported


def _engine(engine: str) -> str:
    """Return 'numba' or 'numpy' for ``engine`` ('auto': numba where it is installed)."""
    if engine not in ENGINES:
        raise ValueError(f'engine must be one of {ENGINES}, got {engine!r}')
    if engine == 'auto':
        return 'numba' if numba_available() else 'numpy'
    if engine == 'numba' and not numba_available():
        raise ValueError("engine 'numba' needs numba (the jit extra: pip install "
                         "'kf_train[jit]')")
    return engine


def rail_log_likelihoods(base: RailModelParameters, segments: Sequence[Segment],
                         settings: Sequence[RailNoise], preset_variance: float = None,
                         innovations: bool = False, *,
                         variances: Optional[Sequence[np.ndarray]] = None,
                         adaptation: Optional[NoiseAdaptation] = None,
                         gate_threshold: float = math.inf,
                         engine: str = 'auto') -> RailLikelihoods:
    """
    Return ℓ (and optionally the mixture innovations) of each setting, in one pass.

    ``base``: the preset's RailModelParameters; ``segments``: one per object (each
    started by its first measurement, as the node's first_measurement); ``settings``:
    K :class:`RailNoise` (a None field keeps ``base``'s value). R given per fix: the
    setting's measurement_variance when set (the node's override), else ``variances``
    (one (N,) array per segment: the messages'), else ``preset_variance`` (default
    base.noise_std_m²). ``adaptation`` (e.g. ``base.adaptation()``): the node's learned
    scale on R; ``gate_threshold``: its χ² gate (see the module docstring); ``engine``:
    'numba', 'numpy' or 'auto' (numba where installed). Raises ValueError for a negative
    noise or an R <= 0.
    """
    if not settings:
        raise ValueError('settings must hold at least one RailNoise')
    compiled = _engine(engine) == 'numba'
    variance = base.noise_std_m ** 2 if preset_variance is None else float(preset_variance)
    noise = _noise_of(settings, base)
    for name, values in zip(RAIL_NOISE_FIELDS + ('measurement_variance',), noise):
        values = values[~np.isnan(values)] if name == 'measurement_variance' else values
        if not np.all(np.isfinite(values)) or np.any(values < 0.0):
            raise ValueError(f'{name} must be finite numbers >= 0, got {values.tolist()}')
    if variances is not None and len(variances) != len(segments):
        raise ValueError(f'variances must hold one array per segment ({len(segments)}), got '
                         f'{len(variances)}')
    threshold = float(gate_threshold)
    if not threshold > 0.0:
        raise ValueError(f'gate_threshold must be > 0, got {gate_threshold!r}')
    adaptation = adaptation if adaptation is not None and adaptation.enabled else None
    model, results = _Model(base, noise), []
    for i, segment in enumerate(segments):
        if segment.z.ndim != 2 or segment.z.shape[1] != 1:
            raise ValueError(f'rail segments measure the position alone: z must be (N, 1), '
                             f'got {segment.z.shape}')
        reported = _reported(noise, None if variances is None else variances[i], variance,
                             segment.t_s.shape[0])
        if compiled:
            results.append(_compiled_pass(segment, model, reported, noise, adaptation,
                                          threshold))
            continue
        with np.errstate(divide='ignore'):     # log c̄_j = −inf for an unreachable regime
            results.append(_segment_pass(segment, model, reported, adaptation, threshold))
    results = results or [_SegmentResult.empty(len(settings), 0)]
    y, S = (np.concatenate([getattr(r, name) for r in results], axis=1) for name in 'yS')
    nis = np.divide(y * y, S, out=np.zeros_like(y), where=S > 0.0)
    nis[np.isnan(S)] = np.nan                  # a held position: no position innovation
    gated = np.concatenate([r.gated for r in results], axis=1)
    scale = np.concatenate([r.scale for r in results], axis=1)
    if not innovations:
        y, S, nis, gated, scale = (a[:, :0] for a in (y, S, nis, gated, scale))
    return RailLikelihoods(sum(r.total for r in results), nis, y, S,
                           sum(r.gated_count for r in results), gated, scale)
