"""
The rail IMM's log-likelihood for K noise settings over a whole segment, compiled: one call.

:func:`kf_train.batch.rail_log_likelihoods` is the numpy reference: the node's likelihood
(the learned scale on R, the χ² gate) for K settings at once, ~400-500 µs a row. This
module runs the same recursion as plain loops for numba (rows outside, settings inside),
each step the node's own compiled kernels (:mod:`kf_train.filters.rail_kernels`:
``dynamics``, ``predict``, ``update``, with :class:`~kf_train.filters.FastRailModel`'s
constants), so that a pass of 9 settings over 30,000 rows takes well under a second.

Q is linear in the noises, so ``dynamics`` runs once per row with unit tables (q_a = 1,
q_ℓ = 0, then 0, 1) and each setting weighs them: Q = q_a Q_a + q_ℓ Q_ℓ + q_c dt (A, B)
+ stand_noise dt (a standing p). A dt beyond the series (> 1.5 τ: a gap, or a run of
gated fixes) needs the quadrature: its unit matrices come from the caller (``big_*``);
one it does not hold stops the kernel with :data:`NEED_MATRICES` at (row, setting), and
:func:`segment_likelihoods` computes it and resumes there. numba is optional: this
module loads on first use (:mod:`kf_train.filters`' ``_LAZY``).
"""

import math
from typing import Callable, Tuple

from kf_train.filters.noise_adaptation import NoiseAdaptation
from kf_train.filters.rail_dynamics import RelaxationNoise
from kf_train.filters.rail_fast import FastRailModel
from kf_train.filters.rail_kernels import (
    dynamics, LOG_2PI, OK, predict, PREDICTION_NON_FINITE, update)
from kf_train.filters.rail_model import RailModel, RailModelParameters
import numba
import numpy as np

NEED_MATRICES = 5
"""Status: the unit F, Q of a dt beyond the series are missing (the caller adds them)."""
_jit = numba.njit(cache=True, error_model='numpy')
UnitMatrices = Callable[[float], Tuple[np.ndarray, np.ndarray, np.ndarray]]
"""dt -> (F, Q per unit q_a, Q per unit q_ℓ), each (4, 6, 6): the quadrature's, for big dts."""


@_jit
def _learn(noise, y, S, r, window, prior, scale_min, scale_max):
    """Update ``noise`` [s, excess, reported, count] after a fused fix: NoiseAdaptation.learn."""
    if window <= 0.0 or not r > 0.0:
        return
    h = S - noise[0] * r                                      # H P Hᵀ
    excess = y * y - h                                        # y² - h: estimates s r
    if noise[3] == 0.0:
        mean_excess, mean_reported, weight = r, r, prior      # the prior s = 1
    else:
        mean_excess, mean_reported = noise[1], noise[2]
        weight = min(noise[3] + prior, window)
    w = 1.0 / (weight + 1.0)
    mean_excess += w * (excess - mean_excess)
    mean_reported += w * (r - mean_reported)
    noise[0] = min(max(mean_excess / mean_reported, scale_min), scale_max)
    noise[1], noise[2] = mean_excess, mean_reported
    noise[3] = min(noise[3] + 1.0, window)


@_jit
def _matrices(dt, series_dt, tau_s, stand_F, phi2, phi3, below, table_a, table_l, scale,
              powers, big_dt, big_F, big_Qa, big_Ql, F, Qa, Ql):
    """Write the unit F, Q_a, Q_ℓ of dt (the series, or the caller's); False if missing."""
    if dt <= series_dt:
        dynamics(dt, tau_s, 0.0, 0.0, stand_F, phi2, phi3, below, table_a, scale, powers, F, Qa)
        dynamics(dt, tau_s, 0.0, 0.0, stand_F, phi2, phi3, below, table_l, scale, powers, F, Ql)
        return True
    for i in range(big_dt.shape[0]):
        if big_dt[i] == dt:
            F[:] = big_F[i]
            Qa[:] = big_Qa[i]
            Ql[:] = big_Ql[i]
            return True
    return False


@_jit
def _noise(Qa, Ql, q_a, q_l, q_c, stand_noise, dt, Q):
    """Write Q = q_a Q_a + q_ℓ Q_ℓ + q_c dt on A, B (every regime) + stand_noise dt on p (stand)."""
    modes, n = Q.shape[0], Q.shape[1]
    for j in range(modes):
        for a in range(n):
            for b in range(n):
                Q[j, a, b] = q_a * Qa[j, a, b] + q_l * Ql[j, a, b]
        Q[j, 4, 4] += q_c * dt
        Q[j, 5, 5] += q_c * dt
    Q[0, 0, 0] += stand_noise * dt


@_jit
def _mixture_log_likelihood(x, P, c, z, R):
    """Return log Σ_j c̄_j N(z − x_j0; P_j00 + R), in the log domain (the likelihood's term)."""
    count = c.shape[0]
    logs = np.empty(count)
    top = -math.inf
    for j in range(count):
        y, s = z - x[j, 0], P[j, 0, 0] + R
        logs[j] = math.log(c[j]) - 0.5 * (y * y / s + math.log(s) + LOG_2PI) \
            if c[j] > 0.0 else -math.inf
        top = max(top, logs[j])
    mass = 0.0
    for j in range(count):
        mass += math.exp(logs[j] - top)
    return top + math.log(mass)


@_jit
def segment_pass(t, z, reported, first_row, first_setting, q_a, q_l, q_c, stand_noise,
                 adaptation, threshold, series_dt, tau_s, stand_F, phi2, phi3, below, table_a,
                 table_l, scale, powers, rates, stopping, stop_rate_hz, stop_speed_mps,
                 index_x, factor_x, index_P, factor_P, noise_P, big_dt, big_F, big_Qa, big_Ql,
                 means, covs, probabilities, noise, last_t, total, gated_count, ys, Ss,
                 gated, scales):
    """
    Run K settings over rows first_row… of a segment; return (status, row, setting, dt).

    State per setting (updated in place): means (K, 4, 6), covs, probabilities (K, 4),
    the learned scale's [s, excess, reported, count] (K, 4), the last fused stamp; ℓ and
    the gated count are added to; y, S, gated, the scale after each fix written (K, rows).
    A gated fix adds −½(γ + log S_gate + log 2π) and leaves the state as it was.
    """
    count, modes, n = means.shape
    F_row, Qa_row, Ql_row = np.empty((modes, n, n)), np.empty((modes, n, n)), \
        np.empty((modes, n, n))
    F_own, Qa_own, Ql_own = np.empty_like(F_row), np.empty_like(F_row), np.empty_like(F_row)
    Q, px, pP, ux, uP = np.empty_like(F_row), np.empty((modes, n)), \
        np.empty((modes, n, n)), np.empty((modes, n)), np.empty((modes, n, n))
    pc, posterior, gain = np.empty(modes), np.empty(modes), np.empty(n)
    window, prior, scale_min, scale_max = adaptation[0], adaptation[1], adaptation[2], \
        adaptation[3]
    row_dt = -1.0
    for row in range(first_row, t.shape[0]):
        dt_row = t[row] - t[row - 1]
        if dt_row != row_dt:
            if not _matrices(dt_row, series_dt, tau_s, stand_F, phi2, phi3, below, table_a,
                             table_l, scale, powers, big_dt, big_F, big_Qa, big_Ql, F_row,
                             Qa_row, Ql_row):
                return NEED_MATRICES, row, 0, dt_row
            row_dt = dt_row
        for k in range(first_setting if row == first_row else 0, count):
            dt = t[row] - last_t[k]
            F, Qa, Ql = F_row, Qa_row, Ql_row
            if dt != dt_row:                       # after gated fixes: from the last fused
                if not _matrices(dt, series_dt, tau_s, stand_F, phi2, phi3, below, table_a,
                                 table_l, scale, powers, big_dt, big_F, big_Qa, big_Ql,
                                 F_own, Qa_own, Ql_own):
                    return NEED_MATRICES, row, k, dt
                F, Qa, Ql = F_own, Qa_own, Ql_own
            _noise(Qa, Ql, q_a[k], q_l[k], q_c[k], stand_noise, dt, Q)
            if predict(means[k], covs[k], probabilities[k], dt, F, Q, rates, stopping,
                       stop_rate_hz, stop_speed_mps, index_x, factor_x, index_P, factor_P,
                       noise_P, px, pP, pc) != OK:
                return PREDICTION_NON_FINITE, row, k, dt
            r, s_now = reported[k, row], noise[k, 0]
            R = r if s_now == 1.0 else r * s_now                    # noise_in_use: s r
            ll = _mixture_log_likelihood(px, pP, pc, z[row], R)
            y, S, nis, status = update(px, pP, pc, z[row], 0, R, ux, uP, posterior, gain)
            if status != OK:
                return status, row, k, dt
            gate_S = S + (1.0 - s_now) * r if s_now < 1.0 else S   # gated with the R given
            gate_nis = y * y / gate_S if s_now < 1.0 else nis
            ys[k, row - 1], Ss[k, row - 1] = y, S
            if gate_nis > threshold:
                total[k] += -0.5 * (threshold + math.log(gate_S) + LOG_2PI)
                gated_count[k] += 1
                gated[k, row - 1] = True
            else:
                total[k] += ll
                means[k] = ux
                covs[k] = uP
                probabilities[k] = posterior
                _learn(noise[k], y, S, r, window, prior, scale_min, scale_max)
                last_t[k] = t[row]
            scales[k, row - 1] = noise[k, 0]
    return OK, t.shape[0], 0, 0.0


def _constants(parameters: RailModelParameters):
    """Return (series dt, dynamics' unit constants, predict's constants): FastRailModel's."""
    model = FastRailModel(parameters)
    tau_s, _, _, stand_F, phi2, phi3, below, _, scale, powers = model._dynamics_constants
    tables = [RelaxationNoise(tau_s, q_a, q_l).series[0] for q_a, q_l in ((1.0, 0.0),
                                                                           (0.0, 1.0))]
    return (model._series_dt_s, (tau_s, stand_F, phi2, phi3, below, *tables, scale, powers),
            model._constants)


def segment_likelihoods(parameters: RailModelParameters, t_s: np.ndarray, z: np.ndarray,
                        reported: np.ndarray, noises: Tuple[np.ndarray, ...],
                        adaptation: NoiseAdaptation, threshold: float,
                        unit_matrices: UnitMatrices, state: tuple, outputs: tuple) -> None:
    """
    Run :func:`segment_pass` over a whole segment, adding the big dts' matrices it asks for.

    ``reported`` (K, N) the variances given, ``noises`` (q_a, q_ℓ, q_c) each (K,),
    ``state`` (means, covs, probabilities, noise (K, 4), last stamp (K,)) after the first
    fix, ``outputs`` (ℓ (K,), gated count (K,), y, S, gated, scale (K, N − 1)), in place.
    Raises ValueError for a non-finite state (a noise too large).
    """
    series_dt, dynamics_constants, predict_constants = _constants(parameters)
    steps = np.diff(t_s)
    big = sorted(set(steps[steps > series_dt].tolist()))
    tables = [np.empty((0, 4, 6, 6)) for _ in range(3)]
    if big:
        tables = [np.array(m) for m in zip(*(unit_matrices(dt) for dt in big))]
    big_dt = np.array(big, dtype=float)
    learning = (float(adaptation.window), float(adaptation.prior), adaptation.scale_min,
                adaptation.scale_max)
    row, setting = 1, 0
    while True:
        status, row, setting, dt = segment_pass(
            t_s, z, reported, row, setting, *noises, parameters.stand_noise, np.array(learning),
            threshold, series_dt, *dynamics_constants, *predict_constants, big_dt, *tables,
            *state, *outputs)
        if status != NEED_MATRICES:
            break
        big_dt = np.append(big_dt, dt)
        tables = [np.concatenate([table, matrix[None]])
                  for table, matrix in zip(tables, unit_matrices(dt))]
    if status != OK:
        raise ValueError(f'the rail filter produced a non-finite state at row {row} (setting '
                         f'{setting}); a noise is too large')


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
             np.full((count, 4), 0.25), np.array([[1.0, 0.0, 0.0, 0.0]]), np.zeros(count))
    outputs = (np.zeros(count), np.zeros(count, dtype=np.int64), np.zeros((count, rows)),
               np.zeros((count, rows)), np.zeros((count, rows), dtype=np.bool_),
               np.ones((count, rows)))
    segment_likelihoods(parameters, t, z, np.ones((count, t.shape[0])),
                        tuple(np.full(count, q) for q in (1e-4, 1e-4, 1e-6)),
                        parameters.adaptation(), 15.0, unit_matrices, state, outputs)
