"""
The rail IMM's array arithmetic as loops, for numba to compile: one call per step.

The numpy reference (:mod:`kf_train.filters.imm_stack`, :mod:`kf_train.filters.rail_mixing`,
:meth:`kf_train.filters.rail_model.RailModel.transition`,
:func:`kf_train.filters.rail_model.hold_velocity` and ``bound_acceleration``) spends a step
in about 125 numpy calls on 4 x 6 x 6 stacks, each costing more than its arithmetic.
These functions do the same equations, in the same order, as plain loops over floats,
which numba compiles (:mod:`kf_train.filters.rail_fast`): a prediction, an update and a
combination are one call each. numba is optional: :mod:`kf_train.filters` loads this
module on first use only (its ``_LAZY``), and each kernel's uncompiled Python is its
``py_func``.
Compiled code is cached on disk (``cache=True``); ``error_model='numpy'`` keeps IEEE
division (as numpy's) instead of raising.
The entry rule is the reference's own gather tables (:class:`~kf_train.filters.rail_mixing.
EntryGather`), passed in. Results are the reference's to rounding (the tests hold them
to it); a status code reports what the reference raises for (``OK`` otherwise).
"""

import math

# numba freezes this global when it compiles, and its disk cache is keyed by this
# file: the tests hold the kernels to rail_model's bound_acceleration beyond the limit.
from kf_train.filters.rail_model import ACCELERATION_LIMIT_MPS2
import numba
import numpy as np

OK, NON_FINITE, SINGULAR, BAD_NIS, PREDICTION_NON_FINITE = 0, 1, 2, 3, 4
LOG_2PI = math.log(2.0 * math.pi)
_jit = numba.njit(cache=True, error_model='numpy')


@_jit
def _stop_probability(v: float, std: float, stop_speed_mps: float) -> float:
    """Return P(velocity <= stop_speed_mps) for N(v, std²) (rail_model.stop_probability)."""
    if std == 0.0:
        return 1.0 if v <= stop_speed_mps else 0.0
    return 0.5 * math.erfc(-((stop_speed_mps - v) / std) / math.sqrt(2.0))


@_jit
def _all_finite(values: np.ndarray) -> bool:
    """Return whether every entry of a flat array is finite."""
    for value in values:
        if not math.isfinite(value):
            return False
    return True


@_jit
def transition(means, covs, dt_s, rates, stopping, stop_rate_hz, stop_speed_mps):
    """Return Π(dt): first_jump_row of each rate row, -> stand scaled by P(slow)."""
    count = means.shape[0]
    matrix = np.zeros((count, count))
    row = np.empty(count)
    for i in range(count):
        for j in range(count):
            row[j] = rates[i, j]
        if stopping[i]:
            std = math.sqrt(max(covs[i, 1, 1], 0.0))
            row[0] = stop_rate_hz * _stop_probability(means[i, 1], std, stop_speed_mps)
        row[i] = 0.0
        leave = 0.0
        for j in range(count):
            leave += row[j]                                   # r_i
        stay = math.exp(-leave * dt_s)                        # Π_ii = e^(-r_i dt)
        for j in range(count):
            matrix[i, j] = (1.0 - stay) * (row[j] / leave) if leave > 0.0 else 0.0
        matrix[i, i] = stay
    return matrix


@_jit
def dynamics(dt_s, tau_s, stand_noise, capability_noise, stand_F, phi2_series, phi3_series,
             series_below, table, scale, powers, F, Q):
    """
    Write the regimes' F(dt) and Q(dt) (N, 6, 6), stand first: rail_dynamics' own, dt <= 1.5 τ.

    φ1 = 1 - e^-x, φ2 = x - φ1, φ3 = x²/2 - φ2 (x = dt/τ; Taylor series below
    ``series_below``), F's relaxation rows, Q's power series (RelaxationNoise.series).
    """
    x = dt_s / tau_s
    phi1 = -math.expm1(-x)
    phi2 = x - phi1
    phi3 = x * x / 2.0 - phi2
    if x < series_below:
        phi2, phi3 = 0.0, 0.0
        for k in range(phi2_series.shape[0]):
            power = x ** k
            phi2 += power * phi2_series[k]
            phi3 += power * phi3_series[k]
    F[:] = 0.0
    Q[:] = 0.0
    F[0] = stand_F
    Q[0, 0, 0] = stand_noise * dt_s                 # p's random walk at a stand
    tau2 = tau_s * tau_s
    rows = ((1.0, dt_s, tau2 * phi2, tau2 * phi3), (0.0, 1.0, tau_s * phi1, tau_s * phi2),
            (0.0, 0.0, 1.0 - phi1, phi1), (0.0, 0.0, 0.0, 1.0))
    x_powers = np.empty(powers.shape[0])
    for k in range(powers.shape[0]):
        x_powers[k] = x ** powers[k]
    for j in range(1, F.shape[0]):
        for a in range(4):
            for b in range(4):
                F[j, a, b] = rows[a][b]
                total = 0.0
                for k in range(powers.shape[0]):
                    total += table[4 * a + b, k] * x_powers[k]
                Q[j, a, b] = total * scale[4 * a + b]
        F[j, 4, 4] = F[j, 5, 5] = 1.0
    for j in range(F.shape[0]):
        Q[j, 4, 4] = Q[j, 5, 5] = capability_noise * dt_s   # A and B drift


@_jit
def predict(means, covs, probabilities, dt_s, F, Q, walk, rates, stopping, stop_rate_hz,
            stop_speed_mps, index_x, factor_x, index_P, factor_P, noise_P, out_x, out_P,
            out_probabilities):
    """
    Write the rail IMM's prediction over dt_s into out_x, out_P, out_probabilities.

    Π(dt) with the state's -> stand rates, the mixing of the components as they enter
    each regime (the gather tables), x⁻ = F x0, P⁻ = F P0 Fᵀ + Q, symmetrised, + the
    error walk ``walk`` = w dt on P_pp (RailModel.predict). Returns the status (arrays
    are written into arguments: returning them costs more than the step).
    """
    count, n = means.shape
    matrix = transition(means, covs, dt_s, rates, stopping, stop_rate_hz, stop_speed_mps)
    cbar = np.zeros(count)
    for j in range(count):
        for i in range(count):
            cbar[j] += probabilities[i] * matrix[i, j]        # c̄_j = Σ_i Π_ij μ_i
    weights = np.zeros((count, count))
    for j in range(count):
        if cbar[j] == 0.0:  # unreachable: the mode keeps its own estimate
            weights[j, j] = 1.0
        else:
            for i in range(count):
                weights[i, j] = matrix[i, j] * probabilities[i] / cbar[j]
    flat_x, flat_P = means.ravel(), covs.ravel()
    xs, Ps = np.empty((count, n)), np.empty((count, n * n))
    x0, P0 = np.empty(n), np.empty((n, n))
    for j in range(count):
        for i in range(count):                                # component i entering j
            for a in range(n):
                xs[i, a] = flat_x[index_x[j, i, a]] * factor_x[j, i, a]
            for ab in range(n * n):
                Ps[i, ab] = flat_P[index_P[j, i, ab]] * factor_P[j, i, ab] + noise_P[j, i, ab]
        for a in range(n):
            total = 0.0
            for i in range(count):
                total += weights[i, j] * xs[i, a]             # x0_j = Σ_i ω_ij x_ji
            x0[a] = total
        for a in range(n):
            for b in range(n):
                total = 0.0
                for i in range(count):
                    d_a, d_b = xs[i, a] - x0[a], xs[i, b] - x0[b]
                    total += weights[i, j] * (Ps[i, a * n + b] + d_a * d_b)
                P0[a, b] = total                              # Σ_i ω_ij (P_ji + d dᵀ)
        _propagate(x0, P0, F[j], Q[j], walk, out_x[j], out_P[j], True)
    total = 0.0
    for j in range(count):
        total += cbar[j]
    for j in range(count):
        out_probabilities[j] = cbar[j] / total
    return OK if _all_finite(out_x.ravel()) and _all_finite(out_P.ravel()) else NON_FINITE


@_jit
def _propagate(x, P, F, Q, walk, out_x, out_P, symmetrise):
    """Write x⁻ = F x and P⁻ = F P Fᵀ + Q (symmetrised if asked) + walk on P_pp."""
    n = x.shape[0]
    FP = np.empty((n, n))
    for a in range(n):
        total = 0.0
        for b in range(n):
            total += F[a, b] * x[b]
        out_x[a] = total
        for c in range(n):
            total = 0.0
            for b in range(n):
                total += F[a, b] * P[b, c]
            FP[a, c] = total
    for a in range(n):
        for c in range(n):
            total = 0.0
            for b in range(n):
                total += FP[a, b] * F[c, b]
            out_P[a, c] = total + Q[a, c]
    if symmetrise:
        _symmetrise(out_P)
    out_P[0, 0] += walk                              # the receiver's error walk, w dt


@_jit
def _symmetrise(P):
    """Replace P by (P + Pᵀ)/2 in place."""
    n = P.shape[0]
    for a in range(n):
        for b in range(a + 1, n):
            mean = (P[a, b] + P[b, a]) * 0.5
            P[a, b] = mean
            P[b, a] = mean


@_jit
def update(means, covs, probabilities, z, selected, R, out_x, out_P, out_posterior, out_gain):
    """
    Write the rail IMM's update by z of state ``selected`` (H = e_k), R the variance in use.

    Each mode's Joseph-form update (out_x, out_P), the posterior in the log domain
    (out_posterior), the moment-matched innovation of the prior mixture (returned:
    (y, S, NIS, status); its gain in out_gain), each mode's mean acceleration within
    its bound (bound_acceleration) and no mode's mean velocity below 0 (hold_velocity).
    """
    count, n = means.shape
    y_modes, s_modes = np.empty(count), np.empty(count)
    gains = np.empty((count, n))
    logs = np.empty(count)
    status = OK
    for j in range(count):
        y = z - means[j, selected]                            # y = z - H x⁻
        s = covs[j, selected, selected] + R                   # s = H P⁻ Hᵀ + R
        if s == 0.0:
            return 0.0, 0.0, 0.0, SINGULAR
        y_modes[j], s_modes[j] = y, s
        for a in range(n):
            gains[j, a] = covs[j, selected, a] / s            # K = P⁻ Hᵀ / s
            out_x[j, a] = gains[j, a] * y + means[j, a]       # x = x⁻ + K y
        _joseph(covs[j], gains[j], selected, R, out_P[j])
        nis = y * y / s
        if not math.isfinite(nis) or nis < 0.0:
            status = BAD_NIS
        logs[j] = -0.5 * (nis + math.log(s) + LOG_2PI) if status == OK else 0.0
    if not (_all_finite(out_x.ravel()) and _all_finite(out_P.ravel())):
        status = NON_FINITE
    if status != OK:
        return 0.0, 0.0, 0.0, status
    _posterior(probabilities, logs, out_posterior)
    y, S, nis = _mixture_innovation(probabilities, means, y_modes, s_modes, gains, out_gain)
    bound_acceleration(out_x, out_P)
    hold_velocity(out_x, out_P)
    return y, S, nis, status


@_jit
def predict_update(means, covs, probabilities, dt_s, F, Q, walk, rates, stopping,
                   stop_rate_hz, stop_speed_mps, index_x, factor_x, index_P, factor_P, noise_P,
                   z, selected, R, out_x, out_P, out_posterior, out_gain):
    """Do :func:`update` after :func:`predict`, in one call: returns (y, S, NIS, status)."""
    count, n = means.shape
    predicted_x, predicted_P = np.empty((count, n)), np.empty((count, n, n))
    predicted_probabilities = np.empty(count)
    if predict(means, covs, probabilities, dt_s, F, Q, walk, rates, stopping, stop_rate_hz,
               stop_speed_mps, index_x, factor_x, index_P, factor_P, noise_P, predicted_x,
               predicted_P, predicted_probabilities) != OK:
        return 0.0, 0.0, 0.0, PREDICTION_NON_FINITE
    return update(predicted_x, predicted_P, predicted_probabilities, z, selected, R, out_x,
                  out_P, out_posterior, out_gain)


@_jit
def step(means, covs, probabilities, dt_s, F, Q, walk, rates, stopping, stop_rate_hz,
         stop_speed_mps, index_x, factor_x, index_P, factor_P, noise_P, z, selected, R,
         ahead_F, ahead_Q, ahead_walk, tau_s, phi1, phi2, first, steps, with_ahead, out_x,
         out_P, out_posterior, out_gain, x, P, ahead_x, ahead_P):
    """
    Do a live step in one call: :func:`predict_update`, then :func:`combine` and :func:`ahead`.

    The estimate (x, P) and, if ``with_ahead``, the prediction ahead (ahead_x, ahead_P,
    over ahead_F, ahead_Q, ahead_walk and the StopFinder's tables) of the updated state,
    written by the very kernels a separate call runs (so their numbers are those to the
    bit).
    Returns (y, S, NIS, status, the prediction's status).
    """
    y, S, nis, status = predict_update(
        means, covs, probabilities, dt_s, F, Q, walk, rates, stopping, stop_rate_hz,
        stop_speed_mps, index_x, factor_x, index_P, factor_P, noise_P, z, selected, R, out_x,
        out_P, out_posterior, out_gain)
    if status != OK:
        return y, S, nis, status, OK
    combine(out_x, out_P, out_posterior, x, P)
    ahead_status = OK
    if with_ahead:
        ahead_status = ahead(out_x, out_P, out_posterior, ahead_F, ahead_Q, ahead_walk,
                             stopping, tau_s, phi1, phi2, first, steps, ahead_x, ahead_P)
    return y, S, nis, status, ahead_status


@_jit
def _joseph(P, K, k, R, out):
    """
    Write P = (I - K e_kᵀ) P⁻ (I - K e_kᵀ)ᵀ + K R Kᵀ, symmetrised, into ``out``.

    Row a of (I - K e_kᵀ) is e_aᵀ - K_a e_kᵀ: each product's entry is one or two terms
    (adding the other n - 2, exact zeros, leaves a sum as it was): the full sums to the bit.
    """
    n = P.shape[0]
    IP = np.empty((n, n))
    for a in range(n):
        for c in range(n):
            if a == k:
                IP[a, c] = (1.0 - K[a]) * P[k, c]
            else:
                IP[a, c] = P[a, c] + (-K[a]) * P[k, c]
    for a in range(n):
        for c in range(n):
            if c == k:
                total = IP[a, k] * (1.0 - K[c])
            else:
                total = IP[a, c] + IP[a, k] * (-K[c])
            out[a, c] = total + (K[a] * R) * K[c]
    _symmetrise(out)


@_jit
def _posterior(prior, logs, out):
    """Write μ_j ∝ c̄_j Λ_j, normalised in the log domain (imm_stack.posterior)."""
    count = prior.shape[0]
    weights = np.empty(count)
    top = -math.inf
    for j in range(count):
        weights[j] = math.log(prior[j]) + logs[j] if prior[j] > 0.0 else -math.inf
        top = max(top, weights[j])
    total = 0.0
    for j in range(count):
        weights[j] = math.exp(weights[j] - top)
        total += weights[j]
    for j in range(count):
        out[j] = weights[j] / total


@_jit
def _mixture_innovation(c, means, y_modes, s_modes, gains, gain):
    """Return (y, S, NIS) of the prior mixture, K in ``gain`` (imm_stack.mixture_innovation)."""
    count, n = means.shape
    y = 0.0
    for j in range(count):
        y += c[j] * y_modes[j]                                # y = z - Σ c̄_j ẑ_j
    S = 0.0
    for j in range(count):
        d = y_modes[j] - y
        S += c[j] * (s_modes[j] + d * d)                      # Σ c̄_j (s_j + d_j²)
    for a in range(n):
        x_bar = 0.0
        for j in range(count):
            x_bar += c[j] * means[j, a]
        total = 0.0
        for j in range(count):
            total += c[j] * s_modes[j] * gains[j, a] - \
                c[j] * (y_modes[j] - y) * (means[j, a] - x_bar)
        gain[a] = total / S                                   # K = P_xz / S
    return y, S, y * (y / S)


@_jit
def bound_acceleration(means, covs):
    """Project every mean acceleration beyond ±the limit onto it along its covariance."""
    count, n = means.shape
    for j in range(count):
        a = means[j, 2]
        limit = min(max(a, -ACCELERATION_LIMIT_MPS2), ACCELERATION_LIMIT_MPS2)
        if a != limit:
            variance = covs[j, 2, 2]
            shift = (a - limit) / variance if variance > 0.0 else 0.0
            for b in range(n):
                means[j, b] -= covs[j, b, 2] * shift          # x - P e Δa / P_aa
            means[j, 2] = limit


@_jit
def hold_velocity(means, covs):
    """Project every mean velocity below 0 onto v = 0 along its covariance, in place."""
    count, n = means.shape
    for j in range(count):
        v = means[j, 1]
        if v < 0.0:
            variance = covs[j, 1, 1]
            shift = v / variance if variance > 0.0 else 0.0
            for a in range(n):
                means[j, a] -= covs[j, a, 1] * shift          # x - P e v / P_vv
            means[j, 1] = 0.0


@_jit
def ahead(means, covs, probabilities, F, Q, walk, stopping, tau_s, phi1, phi2, first, steps, x,
          P):
    """
    Write the 2-s prediction's mixture (x, P): RailModel.predict_ahead; return the status.

    Each mode's x⁻ = F x, P⁻ = F P Fᵀ + Q (not symmetrised: the mixture is), a stopping
    regime's mean held where its path stops (:func:`_hold`, on the StopFinder's tables:
    φ1, φ2 at the horizon, the first grid's F and every step's), then the mixture.
    """
    count, n = means.shape
    out_x, out_P = np.empty((count, n)), np.empty((count, n, n))
    for j in range(count):
        _propagate(means[j], covs[j], F[j], Q[j], walk, out_x[j], out_P[j], False)
        if stopping[j]:
            _hold(means[j], out_x[j], tau_s, phi1, phi2, first, steps)
    return combine(out_x, out_P, probabilities, x, P)


@_jit
def _hold(start, predicted, tau_s, phi1, phi2, first, steps):
    """Hold ``predicted`` (in place) where the mean path from ``start`` stops (StopFinder.hold)."""
    p, v, a, command = start[0], start[1], start[2], start[3]
    if v >= 0.0 and v + tau_s * (phi1 * min(a, 0.0) + phi2 * min(command, 0.0)) > 0.0:
        return                                    # v(t) > 0 all along: it never stops
    state = np.array([p, max(v, 0.0), a, command])
    path = np.empty(4)
    grid = first
    for _ in range(2):
        found = -1
        for k in range(grid.shape[0]):
            for r in range(4):
                total = 0.0
                for c in range(4):
                    total += grid[k, r, c] * state[c]
                path[r] = total                       # the mean path at grid point k
            if path[1] <= 0.0:
                found = k
                break
        if found < 0:
            if v < 0.0:                               # started below 0: the clipped path
                for r in range(3):
                    predicted[r] = path[r]
            return
        stop_p = path[0]
        if found == 0:
            break                                     # standing with a <= 0 already
        grid = steps[found]
    predicted[0], predicted[1], predicted[2] = max(stop_p, p), 0.0, 0.0


@_jit
def combine(means, covs, probabilities, x, P):
    """Write the moment-matched mixture (x, P), P symmetrised; return the status."""
    count, n = means.shape
    x[:] = 0.0
    P[:] = 0.0
    for j in range(count):
        for a in range(n):
            x[a] += probabilities[j] * means[j, a]            # x = Σ μ_j x_j
    for j in range(count):
        for a in range(n):
            d_a = means[j, a] - x[a]
            for b in range(n):
                P[a, b] += probabilities[j] * (covs[j, a, b] + d_a * (means[j, b] - x[b]))
    _symmetrise(P)
    return OK if _all_finite(x) and _all_finite(P.ravel()) else NON_FINITE
