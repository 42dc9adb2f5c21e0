"""
The rail IMM's log-likelihood for K noise settings over a whole segment, compiled.

:func:`kf_train.batch.rail_log_likelihoods` holds the numpy reference: the node's
likelihood (per-fix variances, the learned scale on R, the χ² gate) for K settings at
once, ~400-500 µs a row. This module runs the same recursion as loops for numba: the
settings in parallel (``prange``), each over the rows of a chunk (:data:`_CHUNK`). A
pass of 9 settings over 30,000 rows (jittered stamps, the scale learned, the gate on)
costs 0.74 s on the 2-core test machine (load ~1; 1 setting 0.19 s, 27 settings 2.5 s;
the numpy reference ~550 µs a row for one setting, 82 µs a row and setting for 9:
benchmarks/tune_rail_cost.py, 2026-11-28).

What is reused: F(dt) and Q(dt) are :mod:`kf_train.filters.rail_kernels`' ``dynamics``
(the series up to 1.5 τ), Π(dt) its ``transition``, the no-reversal rule and the
acceleration bound its ``hold_velocity`` and ``bound_acceleration``, the constants
:class:`~kf_train.filters.FastRailModel`'s and the entry rule's
(:class:`~kf_train.filters.rail_mixing.EntryGather`). The step itself is written for this
job, the same equations as rail_kernels' ``predict`` and ``update`` with their
zeros skipped: the entry changes only ℓ's row and column, every regime's F is
diag(G, I₂), H = e₀, and P is symmetric, so a step costs ~4 µs where the general
kernels cost ~13 µs (the tests hold the two engines to each other, and the numpy one to
the node).

Q is linear in the noises, so ``dynamics`` runs once per row with unit tables (q_a = 1,
q_ℓ = 0, then 0, 1) and each setting weighs them: Q = q_a Q_a + q_ℓ Q_ℓ + q_c dt (A, B)
+ stand_noise dt (a standing p). A dt beyond the series (> 1.5 τ: a gap, or a run of
gated fixes after which a setting predicts from its last fused fix) needs the
quadrature: the caller gives those unit matrices (``unit_matrices``); a setting that
meets a dt not yet held stops with :data:`NEED_MATRICES`, and
:func:`segment_likelihoods` adds it and resumes every setting where it stopped. numba is
optional: this module loads on first use (:mod:`kf_train.filters`' ``_LAZY``).
"""

import math
from typing import Callable, Tuple

from kf_train.filters.error_walk import NU_CLIP
from kf_train.filters.noise_adaptation import (
    CLIP_NIS, CLIPPED_NIS_MEAN, NoiseAdaptation, STEP_MAX)
from kf_train.filters.rail_dynamics import RelaxationNoise
from kf_train.filters.rail_fast import FastRailModel
from kf_train.filters.rail_kernels import (
    bound_acceleration, combine, dynamics, hold_velocity, LOG_2PI, NON_FINITE, OK, transition)
from kf_train.filters.rail_model import moved_past, RailModel, RailModelParameters
import numba
import numpy as np

NEED_MATRICES = 5
"""Status: the unit F, Q of a dt beyond the series are missing (the caller adds them)."""
_jit = numba.njit(cache=True, error_model='numpy')
_parallel = numba.njit(cache=True, error_model='numpy', parallel=True)
_CHUNK = 2048
"""Rows per parallel pass: the unit matrices of 2048 rows are 3.5 MB."""
UnitMatrices = Callable[[float], Tuple[np.ndarray, np.ndarray, np.ndarray]]
"""dt -> (F, Q per unit q_a, Q per unit q_ℓ), each (4, 6, 6): the quadrature's, for big dts."""


@_jit
def _learn(noise, y, S, r, window, prior, scale_min, scale_max):
    """Update ``noise`` [s, J, count] after a fused fix: NoiseAdaptation.learn."""
    if window <= 0.0 or not r > 0.0:
        return
    share = noise[0] * r / S                                  # a = s r / S
    nis = min(y * y / S, CLIP_NIS)
    score = 0.5 * share * (nis / CLIPPED_NIS_MEAN - 1.0)      # u = ½ a (y²/S - 1)
    information = noise[1] if noise[2] > 0.0 else 0.5 * prior
    information = information * (1.0 - 1.0 / window) + 0.5 * share * share
    step = min(max(score / information, -STEP_MAX), STEP_MAX)  # log s += u / J
    noise[0] = min(max(noise[0] * math.exp(step), scale_min), scale_max)
    noise[1] = information
    noise[2] = min(noise[2] + 1.0, window)


_moved_past = _jit(moved_past)


@_jit
def _moved_past_last(means, covs, probabilities, dt, R, threshold, x, P):
    """Return moved_past of the mixture at the last fused fix (x, P: scratch arrays)."""
    combine(means, covs, probabilities, x, P)                       # the node's (x, P)
    return _moved_past(x[1], P[1, 1], dt, P[0, 0] + R, threshold)


@_jit
def _matrices(dt, series_dt, tau_s, stand_F, phi2, phi3, below, table_a, table_l, scale,
              powers, big_dt, big_F, big_Qa, big_Ql, F, Qa, Ql):
    """Write the unit F, Q_a, Q_ℓ of dt (the series, or the caller's); False if missing."""
    if dt <= series_dt:
        dynamics(dt, tau_s, 0.0, 0.0, stand_F, phi2, phi3, below, table_a, scale, powers, F, Qa)
        dynamics(dt, tau_s, 0.0, 0.0, stand_F, phi2, phi3, below, table_l, scale, powers, F, Ql)
        return True
    for i in range(big_dt.shape[0] - 1, -1, -1):            # the newest first
        if big_dt[i] == dt:
            F[:] = big_F[i]
            Qa[:] = big_Qa[i]
            Ql[:] = big_Ql[i]
            return True
    return False


@_jit
def _learn_walk(noise, y, S, R, rate_hz, learning_rate, low, high):
    """Update ``noise`` [.., w, log(c/c₀), ν] after a fused fix weighed with R: ErrorWalk.learn."""
    if rate_hz <= 0.0:
        return
    nu = min(max(y / math.sqrt(S), -NU_CLIP), NU_CLIP)
    noise[3] = rate_hz * math.exp(noise[4]) * R                # the walk after it: c s r
    noise[4] = min(max(noise[4] + learning_rate * nu * noise[5], low), high)
    noise[5] = nu


@_jit
def _noise(Qa, Ql, q_a, q_l, q_c, stand_noise, walk, dt, Q):
    """
    Write Q = q_a Q_a + q_ℓ Q_ℓ + q_c dt on A, B (every regime), + stand_noise dt on p.

    ``walk`` the receiver's error walk w dt on every regime's p (RailModel.predict).
    """
    modes, n = Q.shape[0], Q.shape[1]
    for j in range(modes):
        for a in range(n):
            for b in range(n):
                Q[j, a, b] = q_a * Qa[j, a, b] + q_l * Ql[j, a, b]
        Q[j, 4, 4] += q_c * dt
        Q[j, 5, 5] += q_c * dt
        Q[j, 0, 0] += walk
    Q[0, 0, 0] += stand_noise * dt


@_jit
def _predict(means, covs, probabilities, dt_s, F, Q, rates, stopping, stop_rate_hz,
             stop_speed_mps, sources, factors, noises, ell, out_x, out_P, out_c, weights, xs,
             x0, P0, GP):
    """
    Write the prediction over dt_s (rail_kernels.predict's equations; c̄ normalised).

    Π(dt) is rail_kernels' ``transition``; the entry rule (EntryGather's sources,
    factors, noises) changes ℓ's row and column only, so the other entries are P_i's own
    (the gather's products by 1, exact); a component of weight 0 is skipped (it adds
    exactly 0), P0 is built on its upper triangle, and x⁻ = F x0, P⁻ = F P0 Fᵀ + Q use
    F's blocks (:func:`_propagate`).
    """
    count, n = means.shape
    matrix = transition(means, covs, dt_s, rates, stopping, stop_rate_hz, stop_speed_mps)
    total = 0.0
    for j in range(count):
        c = 0.0
        for i in range(count):
            c += probabilities[i] * matrix[i, j]                   # c̄_j = Σ_i Π_ij μ_i
        out_c[j] = c
        total += c
    for j in range(count):
        for i in range(count):
            # ω_ij = Π_ij μ_i / c̄_j; an unreachable regime keeps its own estimate
            weights[i] = (1.0 if i == j else 0.0) if out_c[j] == 0.0 else \
                matrix[i, j] * probabilities[i] / out_c[j]
        for a in range(n):
            x0[a] = 0.0
            for b in range(a, n):
                P0[a, b] = 0.0
        # Entering j ≠ i sets ℓ = c_j x[k_j] + w (k_j = ℓ, c_j = 0 without a source).
        source = sources[j] if sources[j] >= 0 else ell
        factor, entry_noise = factors[j], noises[j]
        for i in range(count):
            if weights[i] != 0.0:
                for a in range(n):
                    xs[i, a] = means[i, a]
                if i != j:
                    xs[i, ell] = means[i, source] * factor
                for a in range(n):
                    x0[a] += weights[i] * xs[i, a]                  # Σ_i ω_ij x_ji
        for i in range(count):
            w = weights[i]
            if w == 0.0:
                continue
            for a in range(n):
                d_a = xs[i, a] - x0[a]
                for b in range(a, n):
                    if i != j and (a == ell or b == ell):           # T_j P_i T_jᵀ + W_j
                        p = covs[i, source if a == ell else a, source if b == ell else b] * \
                            ((factor if a == ell else 1.0) * (factor if b == ell else 1.0)) + \
                            (entry_noise if a == b else 0.0)
                    else:
                        p = covs[i, a, b]
                    P0[a, b] += w * (p + d_a * (xs[i, b] - x0[b]))  # Σ_i ω_ij (P_ji + d dᵀ)
        for a in range(n):
            for b in range(a):
                P0[a, b] = P0[b, a]
        _propagate(x0, P0, F[j], Q[j], out_x[j], out_P[j], GP)
    for j in range(count):
        out_c[j] = out_c[j] / total


@_jit
def _propagate(x, P, F, Q, out_x, out_P, GP):
    """
    Write x⁻ = F x, P⁻ = F P Fᵀ + Q (symmetric) for F = diag(G, I₂), G its 4 x 4 block.

    Every regime's F has that form (A and B held; checked in :func:`_constants`), so
    G P₁₁ Gᵀ, G P₁₂ and P₂₂ cost about a third of the 6 x 6 product.
    """
    n, m = x.shape[0], 4
    for a in range(m):
        total = 0.0
        for b in range(m):
            total += F[a, b] * x[b]
        out_x[a] = total
        for c in range(n):
            total = 0.0
            for b in range(m):
                total += F[a, b] * P[b, c]
            GP[a, c] = total                                        # [G P₁₁, G P₁₂]
    for a in range(m, n):
        out_x[a] = x[a]
    for a in range(n):
        for c in range(a, n):
            if c < m:
                total = 0.0
                for b in range(m):
                    total += GP[a, b] * F[c, b]
                value = total + Q[a, c]                             # G P₁₁ Gᵀ
            elif a < m:
                value = GP[a, c] + Q[a, c]                          # G P₁₂
            else:
                value = P[a, c] + Q[a, c]                           # P₂₂
            out_P[a, c] = value
            out_P[c, a] = value


@_jit
def _update(means, covs, c, z, R, out_x, out_P, out_posterior, logs, h):
    """
    Write every regime's update by z of state h; return (y, S, log Σ_j c̄_j N(y_j; s_j)).

    rail_kernels.update's equations for H = e_h (0: a position, 1: a held position's
    speed of 0): y_j = z − x_jh, s_j = P_jhh + R,
    K = P_j[h] / s_j, the Joseph form (I − K e_hᵀ) P (I − K e_hᵀ)ᵀ + K R Kᵀ written out
    (its zero terms skipped), the posterior in the log domain, the mixture's (y, S), and
    the acceleration bound and no mean velocity below 0 (rail_kernels'
    ``bound_acceleration`` and ``hold_velocity``).
    """
    count, n = means.shape
    y = 0.0
    for j in range(count):
        y += c[j] * (z - means[j, h])                              # y = z − Σ c̄_j ẑ_j
    S = 0.0
    top = -math.inf
    for j in range(count):
        y_j = z - means[j, h]
        s = covs[j, h, h] + R
        d = y_j - y
        S += c[j] * (s + d * d)                                     # Σ c̄_j (s_j + d_j²)
        for a in range(n):
            out_x[j, a] = covs[j, h, a] / s * y_j + means[j, a]     # x = x⁻ + K y
        for a in range(n):
            k_a = covs[j, h, a] / s
            m_ah = covs[j, a, h] - k_a * covs[j, h, h]
            for b in range(a, n):
                k_b = covs[j, h, b] / s
                value = covs[j, a, b] - k_a * covs[j, h, b] - m_ah * k_b + (k_a * R) * k_b
                out_P[j, a, b] = value
                out_P[j, b, a] = value
        logs[j] = math.log(c[j]) - 0.5 * (y_j * y_j / s + math.log(s) + LOG_2PI) \
            if c[j] > 0.0 else -math.inf                            # log c̄_j N(y_j; s_j)
        top = max(top, logs[j])
    mass = 0.0
    for j in range(count):
        out_posterior[j] = math.exp(logs[j] - top)
        mass += out_posterior[j]
    for j in range(count):
        out_posterior[j] = out_posterior[j] / mass                  # μ_j ∝ c̄_j Λ_j
    bound_acceleration(out_x, out_P)
    hold_velocity(out_x, out_P)
    return y, S, top + math.log(mass)


@_jit
def _fuse_hold(k, t, row, px, pP, pc, variance, threshold, state, outputs, logs):
    """
    Fuse a held position as a speed of 0 (Fusion._hold) if that passes the gate.

    Return whether it did: then the state is the speed's update, ℓ has its term, y and
    S are NaN (no position innovation) and nothing is learned.
    """
    means, covs, probabilities, _, last_t, _ = state
    total, _, ys, Ss, _, _ = outputs
    modes, n = px.shape
    x, P, posterior = np.empty((modes, n)), np.empty((modes, n, n)), np.empty(modes)
    y, S, ll = _update(px, pP, pc, 0.0, variance, x, P, posterior, logs, 1)
    if not (math.isfinite(ll) and math.isfinite(S) and S > 0.0) or y * (y / S) > threshold:
        return False
    ys[k, row - 1], Ss[k, row - 1] = math.nan, math.nan
    total[k] += ll
    means[k] = x
    covs[k] = P
    probabilities[k] = posterior
    last_t[k] = t
    return True


@_jit
def _setting_rows(k, t, z, reported, stop, q_a, q_l, q_c, stand_noise, adaptation,
                  threshold, series_dt, dynamics_constants, predict_constants, big, units,
                  state, outputs, progress):
    """
    Run setting k from its next row up to ``stop``, in place.

    Where it stopped goes to ``progress`` (next_row, status, need_dt). A gated fix adds
    −½(γ + log S_gate + log 2π) and leaves the state as it was; a fused one adds
    log Σ_j c̄_j N(y_j; s_j) and teaches s and the error walk. ``adaptation``: the
    NoiseAdaptation's (window, prior, scale_min, scale_max), the ErrorWalk's (rate_hz,
    learning_rate, bounds of log(c/c₀)), the hold's (speed variance or 0, largest r).
    """
    tau_s, stand_F, phi2, phi3, below, table_a, table_l, scale, powers = dynamics_constants
    rates, stopping, stop_rate_hz, stop_speed_mps, sources, factors, noises, ell = \
        predict_constants
    big_dt, big_F, big_Qa, big_Ql = big
    F_rows, Qa_rows, Ql_rows, first = units
    means, covs, probabilities, noise, last_t, last_z = state
    total, gated_count, ys, Ss, gated, scales = outputs
    next_row, status, need_dt = progress
    modes, n = means.shape[1], means.shape[2]
    F_own, Qa_own, Ql_own, Q = np.empty((modes, n, n)), np.empty((modes, n, n)), \
        np.empty((modes, n, n)), np.empty((modes, n, n))
    px, pP, ux, uP = np.empty((modes, n)), np.empty((modes, n, n)), np.empty((modes, n)), \
        np.empty((modes, n, n))
    pc, posterior, logs = np.empty(modes), np.empty(modes), np.empty(modes)
    weights, xs, x0, P0, GP = np.empty(modes), np.empty((modes, n)), np.empty(n), \
        np.empty((n, n)), np.empty((n, n))
    row = next_row[k]
    while row < stop:
        dt = t[row] - last_t[k]
        F, Qa, Ql = F_rows[row - first], Qa_rows[row - first], Ql_rows[row - first]
        if dt != t[row] - t[row - 1]:              # after gated fixes: from the last fused
            if not _matrices(dt, series_dt, tau_s, stand_F, phi2, phi3, below, table_a,
                             table_l, scale, powers, big_dt, big_F, big_Qa, big_Ql, F_own,
                             Qa_own, Ql_own):
                need_dt[k] = dt
                status[k] = NEED_MATRICES
                break
            F, Qa, Ql = F_own, Qa_own, Ql_own
        _noise(Qa, Ql, q_a[k], q_l[k], q_c[k], stand_noise, noise[k, 3] * dt, dt, Q)
        _predict(means[k], covs[k], probabilities[k], dt, F, Q, rates, stopping, stop_rate_hz,
                 stop_speed_mps, sources, factors, noises, ell, px, pP, pc, weights, xs, x0,
                 P0, GP)
        r, s_now = reported[k, row], noise[k, 0]
        R = r if s_now == 1.0 else r * s_now                        # noise_in_use: s r
        y, S, ll = _update(px, pP, pc, z[row], R, ux, uP, posterior, logs, 0)
        if not (math.isfinite(ll) and math.isfinite(S) and S > 0.0):
            status[k] = NON_FINITE
            break
        gate_S = S + (1.0 - s_now) * r if s_now < 1.0 else S       # gated with the R given
        gate_nis = y * y / gate_S if s_now < 1.0 else y * (y / S)
        # A repeated epoch (the last fused position again) is judged on the R in use
        # and on the speed at the last fix (Fusion._reject_repeat), not fused, as gated.
        repeat = s_now < 1.0 and z[row] == last_z[k] and (
            y * (y / S) > threshold or _moved_past_last(
                means[k], covs[k], probabilities[k], dt, R, threshold, x0, P0))
        ys[k, row - 1], Ss[k, row - 1] = y, S
        if (adaptation[8] > 0.0 and s_now < 1.0 and z[row] == last_z[k] and not repeat
                and r <= adaptation[9] and _fuse_hold(k, t[row], row, px, pP, pc, adaptation[8],
                                                      threshold, state, outputs, logs)):
            pass                            # a held position: a speed of 0 (Fusion._hold)
        elif repeat or gate_nis > threshold:
            total[k] += -0.5 * (threshold + math.log(gate_S) + LOG_2PI)
            gated_count[k] += 1
            gated[k, row - 1] = True
        else:
            total[k] += ll
            means[k] = ux
            covs[k] = uP
            probabilities[k] = posterior
            _learn(noise[k], y, S, r, adaptation[0], adaptation[1], adaptation[2],
                   adaptation[3])
            _learn_walk(noise[k], y, S, R, adaptation[4], adaptation[5], adaptation[6],
                        adaptation[7])
            last_t[k] = t[row]
            last_z[k] = z[row]
        scales[k, row - 1] = noise[k, 0]
        row += 1
    next_row[k] = row


@_parallel
def settings_pass(t, z, reported, stop, q_a, q_l, q_c, stand_noise, adaptation, threshold,
                  series_dt, dynamics_constants, predict_constants, big, units, state,
                  outputs, progress):
    """Run every setting up to row ``stop``, in parallel: :func:`_setting_rows`."""
    for k in numba.prange(q_a.shape[0]):
        _setting_rows(k, t, z, reported, stop, q_a, q_l, q_c, stand_noise, adaptation,
                      threshold, series_dt, dynamics_constants, predict_constants, big,
                      units, state, outputs, progress)


@_jit
def settings_resume(t, z, reported, stop, q_a, q_l, q_c, stand_noise, adaptation, threshold,
                    series_dt, dynamics_constants, predict_constants, big, units, state,
                    outputs, progress):
    """
    Resume the settings after a missing dt (a row or a few), serially.

    Waking the threads of a parallel pass costs milliseconds on a loaded machine, and a
    run of gated fixes asks for a new dt at every row.
    """
    for k in range(q_a.shape[0]):
        _setting_rows(k, t, z, reported, stop, q_a, q_l, q_c, stand_noise, adaptation,
                      threshold, series_dt, dynamics_constants, predict_constants, big,
                      units, state, outputs, progress)


@_parallel
def unit_rows(t, first, stop, series_dt, dynamics_constants, big, F, Qa, Ql, found):
    """Write each row's unit F, Q_a, Q_ℓ (row − first) for its dt; ``found`` False if missing."""
    tau_s, stand_F, phi2, phi3, below, table_a, table_l, scale, powers = dynamics_constants
    big_dt, big_F, big_Qa, big_Ql = big
    for row in numba.prange(first, stop):
        i = row - first
        found[i] = _matrices(t[row] - t[row - 1], series_dt, tau_s, stand_F, phi2, phi3, below,
                             table_a, table_l, scale, powers, big_dt, big_F, big_Qa, big_Ql,
                             F[i], Qa[i], Ql[i])


def _constants(parameters: RailModelParameters):
    """Return (series dt, dynamics' unit constants, predict's constants): FastRailModel's."""
    model = FastRailModel(parameters)
    tau_s, _, _, stand_F, phi2, phi3, below, _, scale, powers = model._dynamics_constants
    tables = [RelaxationNoise(tau_s, q_a, q_l).series[0]
              for q_a, q_l in ((1.0, 0.0), (0.0, 1.0))]
    F = model.matrices(0.5)[0]
    if np.any(F[:, :4, 4:]) or np.any(F[:, 4:, :4]) or np.any(F[:, 4:, 4:] != np.eye(2)):
        raise ValueError('the compiled likelihood needs every F = diag(G, I2) (A, B held)')
    rule = model.entry_rule
    entry = (np.array([-1 if source is None else source for source in rule.sources]),
             np.array(rule.factors), np.array(rule.noises), rule.ell)
    return (model._series_dt_s, (tau_s, stand_F, phi2, phi3, below, *tables, scale, powers),
            model._constants[:4] + entry)


def segment_likelihoods(parameters: RailModelParameters, t_s: np.ndarray, z: np.ndarray,
                        reported: np.ndarray, noises: Tuple[np.ndarray, ...],
                        adaptation: NoiseAdaptation, threshold: float,
                        unit_matrices: UnitMatrices, state: tuple, outputs: tuple) -> None:
    """
    Run every setting over a whole segment, chunk by chunk, adding the big dts it asks for.

    ``reported`` (K, N) the variances given, ``noises`` (q_a, q_ℓ, q_c) each (K,),
    ``state`` (means, covs, probabilities, noise (K, 6): s, J, count, then the error
    walk's w, log(c/c₀), ν; last fused stamp and position (K,)) after the first fix,
    ``outputs`` (ℓ (K,), gated count (K,), y, S, gated,
    scale (K, N − 1)), in place.
    Raises ValueError for a non-finite state (a noise too large).
    """
    series_dt, dynamics_constants, predict_constants = _constants(parameters)
    count, N = reported.shape
    steps = np.diff(t_s)
    big = _BigDts(unit_matrices)
    big.add(steps[steps > series_dt])
    walk = parameters.error_walk()
    learning = np.array((float(adaptation.window), float(adaptation.prior),
                         adaptation.scale_min, adaptation.scale_max, walk.rate_hz,
                         walk.learning_rate) + (walk.bounds if walk.enabled else (0.0, 0.0))
                        + (parameters.hold_speed_std_mps ** 2, parameters.hold_max_variance_m2))
    progress = (np.ones(count, dtype=np.int64), np.zeros(count, dtype=np.int64),
                np.zeros(count))
    chunk = min(_CHUNK, N - 1)
    units = tuple(np.empty((chunk, 4, 6, 6)) for _ in range(3))
    found = np.empty(chunk, dtype=np.bool_)
    for first in range(1, N, chunk):
        stop = min(first + chunk, N)
        unit_rows(t_s, first, stop, series_dt, dynamics_constants, big.tables(), *units,
                  found)
        assert found[:stop - first].all()          # every row's big dt is in ``big``
        run = settings_pass
        while True:
            run(t_s, z, reported, stop, *noises, parameters.stand_noise, learning, threshold,
                series_dt, dynamics_constants, predict_constants, big.tables(),
                units + (first,), state, outputs, progress)
            next_row, status, need_dt = progress
            if np.any((status != OK) & (status != NEED_MATRICES)):
                k = int(np.nonzero((status != OK) & (status != NEED_MATRICES))[0][0])
                raise ValueError(f'the rail filter produced a non-finite state at row '
                                 f'{next_row[k]} (setting {k}); a noise is too large')
            if np.all(next_row >= stop):
                break
            big.add(need_dt[status == NEED_MATRICES])
            run = settings_resume
            status[:] = OK


class _BigDts:
    """The unit F, Q_a, Q_ℓ of the dts beyond the series (the caller's quadrature), grown."""

    def __init__(self, unit_matrices: UnitMatrices):
        """Start empty, room for 64 dts (doubled as needed)."""
        self.unit_matrices, self.count = unit_matrices, 0
        self.dt = np.empty(64)
        self.matrices = [np.empty((64, 4, 6, 6)) for _ in range(3)]

    def add(self, dts: np.ndarray) -> None:
        """Add the dts not held yet."""
        held = set(self.dt[:self.count].tolist())
        for dt in sorted(set(dts.tolist()) - held):
            if self.count == self.dt.shape[0]:
                self.dt = np.concatenate([self.dt, np.empty_like(self.dt)])
                self.matrices = [np.concatenate([m, np.empty_like(m)]) for m in self.matrices]
            self.dt[self.count] = dt
            for table, matrix in zip(self.matrices, self.unit_matrices(dt)):
                table[self.count] = matrix
            self.count += 1

    def tables(self) -> tuple:
        """Return (dts, F, Q_a, Q_ℓ) held, for the kernels."""
        return (self.dt[:self.count],) + tuple(m[:self.count] for m in self.matrices)


def warm_up() -> None:
    """Compile (first time) or load the kernel now: a short pass with a gated fix and a gap."""
    parameters = RailModelParameters()
    units = [RailModel(RailModelParameters(acceleration_noise=q_a, command_noise=q_l,
                                           capability_noise=0.0))
             for q_a, q_l in ((1.0, 0.0), (0.0, 1.0))]

    def unit_matrices(dt):
        F, Qa = units[0].matrices(dt)[:2]
        return F, Qa, units[1].matrices(dt)[1]
    t, z = np.array([0.0, 0.2, 0.4, 3.0]), np.array([0.0, 1.0, 500.0, 3.0])
    count, rows = 1, t.shape[0] - 1
    state = (np.tile(np.array([0.0, 0.0, 0.0, 0.0, 0.8, 0.9]), (count, 4, 1)),
             np.tile(parameters.initial_covariance(1.0), (count, 4, 1, 1)),
             np.full((count, 4), 0.25), np.array([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]]),
             np.zeros(count),
             np.zeros(count))
    outputs = (np.zeros(count), np.zeros(count, dtype=np.int64), np.zeros((count, rows)),
               np.zeros((count, rows)), np.zeros((count, rows), dtype=np.bool_),
               np.ones((count, rows)))
    segment_likelihoods(parameters, t, z, np.ones((count, t.shape[0])),
                        tuple(np.full(count, q) for q in (1e-4, 1e-4, 1e-6)),
                        parameters.adaptation(), 15.0, unit_matrices, state, outputs)
