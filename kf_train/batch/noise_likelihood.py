"""
The exact log-likelihood of a noise setting: the innovations of the node's own filter.

A linear filter's innovations y_k = z_k − H x⁻_k are, when its model is right,
independent Gaussians with the covariances S_k = H P⁻_k Hᵀ + R it computes, so the
exact log-likelihood of the data given the noise θ (prediction-error decomposition,
Schweppe 1965; Harvey 1989, §3.4) is

    ℓ(θ) = −½ Σ_k [m log 2π + log det S_k(θ) + y_k(θ)ᵀ S_k(θ)⁻¹ y_k(θ)].

It is evaluated with the replay's own vectorised filter
(:func:`kf_train.batch.run_linear_series`: the covariance and gain sequence of a
linear preset does not depend on the data, the mean is an affine recursion), on the
preset the estimator node runs with a :class:`NoiseSetting`: the preset's process
noise plus white-noise acceleration of density q (the node's
``process_noise_density``), R in place of the preset's (``measurement_variance``),
and the node's initialisation (the first measurement sets the measured states, the
velocity starts wide; or the prior). So the likelihood is the node's, not an
approximation of it; the tests hold its innovations to the streaming estimator's and
its value to pykalman's.

The data come as :class:`Segment` s, one per object (an ``id`` of a replay CSV): the
objects share the noise, and ℓ sums over them.
"""

import copy
import dataclasses
from dataclasses import dataclass
import math
from typing import List, NamedTuple, Optional, Sequence, Tuple

from kf_train.batch.linear import run_linear_series
from kf_train.batch.series import SeriesResult, time_steps_s
from kf_train.filters import as_finite_array, as_vector, LOG_2PI
from kf_train.presets import INITIALIZATIONS, is_constant_velocity, measured_states, Preset
import numpy as np

# Node parameter of each measured quantity's variance (others have none).
VARIANCE_PARAMETERS = {'position': 'measurement_variance',
                       'velocity': 'measurement_velocity_variance'}
"""How a tuned filter starts: as the estimator node's ``initialization``."""
STATE_UNITS = {'position': 'm', 'velocity': 'm/s'}


class Segment(NamedTuple):
    """One object's series, as a replay reads it, and its truth where known."""

    t_s: np.ndarray
    """Times (N,) [s], increasing."""
    z: np.ndarray
    """Measurements (N, m)."""
    u: Optional[np.ndarray] = None
    """Controls (N, p) of the interval ending at each row, or None."""
    truth: Optional[np.ndarray] = None
    """True states (N, n), NaN where unknown; None without truth."""


def make_segment(preset: Preset, t_s, z, u=None, truth=None) -> Segment:
    """Return a checked :class:`Segment` for ``preset``; ValueError names the input."""
    t = as_finite_array('t_s', t_s)
    if t.ndim != 1:
        raise ValueError(f't_s must be a vector, got shape {t.shape}')
    if t.size:
        time_steps_s(t, t[0])  # increasing by at least 1 ns
    N, m, p, n = t.shape[0], preset.dim_z, preset.dim_u, preset.dim_x
    z = as_finite_array('z', z)
    z = z[:, None] if z.ndim == 1 and m == 1 else z
    if z.shape != (N, m):
        raise ValueError(f'z must have shape ({N}, {m}), got {z.shape}')
    if p:
        if u is None:
            raise ValueError(f'u is required by preset {preset.name!r}')
        u = as_finite_array('u', u)
        u = u[:, None] if u.ndim == 1 and p == 1 else u
        if u.shape != (N, p):
            raise ValueError(f'u must have shape ({N}, {p}), got {u.shape}')
    elif u is not None:
        raise ValueError(f'preset {preset.name!r} has no control input, but u was given')
    if truth is not None:
        truth = np.array(truth, dtype=float)
        truth = truth[:, None] if truth.ndim == 1 and n == 1 else truth
        if truth.shape != (N, n) or np.any(np.isinf(truth)):
            raise ValueError(f'truth must have shape ({N}, {n}), finite or NaN, got '
                             f'{truth.shape}')
    return Segment(t, z, u, truth)


@dataclass(frozen=True)
class NoiseSetting:
    """The noise a filter runs with, in the estimator node's terms."""

    process_noise_density: float = 0.0
    """q [m²/s³], white-noise acceleration added to the preset's own process noise."""
    measurement_variances: Optional[Tuple[float, ...]] = None
    """R's diagonal, one variance per measurement; None: the preset's R."""
    initial_state: Optional[Tuple[float, ...]] = None
    """The initial state; None: the preset's."""


def noisy_preset(preset: Preset, process_noise_density: float = 0.0,
                 measurement_variances: Optional[Sequence[float]] = None) -> Preset:
    """
    Return ``preset`` with white-noise acceleration q added and R's diagonal replaced.

    Q(dt) becomes the preset's Q(dt) + q·[[dt³/3, dt²/2], [dt²/2, dt]] (a continuous
    density diag(0, q), integrated exactly by the preset's dynamics), as the node adds
    ``process_noise_density``; R becomes diag(measurement_variances), as the node's
    ``measurement_variance`` overrides the message's.
    """
    q = float(process_noise_density)
    if not q >= 0.0 or not math.isfinite(q):
        raise ValueError(f'process_noise_density must be a finite number >= 0, got {q}')
    # Shallow copies with the noise replaced (the values checked here): rebuilding
    # and re-validating the dynamics and the model costs more than a short filter run.
    dyn, model = copy.copy(preset.dynamics), copy.copy(preset.model)
    if q > 0.0:
        if not is_constant_velocity(preset):
            raise ValueError(f'process_noise_density must be 0 for preset {preset.name!r}: '
                             'a white-noise acceleration needs [position, velocity] states')
        continuous = np.zeros((2, 2)) if dyn.continuous is None else dyn.continuous.copy()
        continuous[1, 1] += q        # ∫ F(s) diag(0, q) F(s)ᵀ ds = q·[[dt³/3, dt²/2], ...]
        dyn.continuous = continuous
    if measurement_variances is not None:
        r = as_vector('measurement_variances', measurement_variances, preset.dim_z)
        if not np.all(r > 0.0):
            raise ValueError(f'measurement variances must be > 0, got {r.tolist()}')
        model.R = np.diag(r)
    model.F, model.Q = dyn.F, dyn.Q
    if preset.dim_u:
        model.B = dyn.control
    return dataclasses.replace(preset, dynamics=dyn, model=model)


class Innovations(NamedTuple):
    """Every innovation of a run and its covariance, segments one after another."""

    y: np.ndarray
    """Innovations z − H x⁻ (K, m)."""
    S: np.ndarray
    """Their covariances H P⁻ Hᵀ + R (K, m, m)."""

    def nis(self) -> np.ndarray:
        """Return the normalised innovation squared yᵀ S⁻¹ y of every row (K,)."""
        if self.y.shape[1] == 1:
            return self.y[:, 0] ** 2 / self.S[:, 0, 0]
        return np.einsum('ki,ki->k', self.y, np.linalg.solve(self.S, self.y[:, :, None])[..., 0])

    def log_likelihood(self) -> float:
        """Return −½ Σ (m log 2π + log det S + yᵀ S⁻¹ y)."""
        K, m = self.y.shape
        if m == 1:
            log_det = np.log(self.S[:, 0, 0])
        else:
            sign, log_det = np.linalg.slogdet(self.S)
            if np.any(sign <= 0.0):
                return -math.inf
        return float(-0.5 * (K * m * LOG_2PI + np.sum(log_det) + np.sum(self.nis())))


class TuningProblem:
    """
    The data and the filter whose noise is estimated: the node's filter on each segment.

    ``initialization`` is the node's: ``first_measurement`` (the first row of each
    segment sets the measured states with its variance, the others come from the
    initial state with σ = ``first_velocity_std_mps``; the likelihood is that of the
    later rows given the first) or ``prior`` (the initial state and covariance, the
    preset's or ``initial_covariance``, hold ``prior_lead_s`` before each segment's
    first row, the preset's nominal period by default as in the node, or at
    ``prior_t0_s`` for every segment as in a replay).
    """

    def __init__(self, preset: Preset, segments: Sequence[Segment], *,
                 initialization: str = 'first_measurement',
                 first_velocity_std_mps: float = 100.0,
                 prior_lead_s: Optional[float] = None, prior_t0_s: Optional[float] = None,
                 initial_covariance=None):
        """Check the preset and data; raise ValueError naming what cannot be tuned."""
        if not preset.linear:
            raise ValueError(f'preset {preset.name!r} has a nonlinear measurement model: '
                             'tuning needs a linear preset')
        if initialization not in INITIALIZATIONS:
            raise ValueError(f'initialization must be one of {INITIALIZATIONS}, '
                             f'got {initialization!r}')
        self.selector = measured_states(preset)
        if initialization == 'first_measurement' and self.selector is None:
            raise ValueError(f'initialization must be prior for preset {preset.name!r}: '
                             'first_measurement needs measurements that are states')
        if not first_velocity_std_mps > 0.0 or not math.isfinite(first_velocity_std_mps):
            raise ValueError('first_velocity_std_mps must be a finite number > 0, got '
                             f'{first_velocity_std_mps!r}')
        self.preset = preset
        self.segments = list(segments)
        self.initialization = initialization
        self.first_velocity_std_mps = float(first_velocity_std_mps)
        self.prior_lead_s = float(preset.nominal_period_s if prior_lead_s is None
                                  else prior_lead_s)
        if not self.prior_lead_s >= 0.0:
            raise ValueError(f'prior_lead_s must be >= 0, got {prior_lead_s!r}')
        self.prior_t0_s = None if prior_t0_s is None else float(prior_t0_s)
        if self.prior_t0_s is not None and any(
                len(s.t_s) and s.t_s[0] < self.prior_t0_s for s in self.segments):
            raise ValueError(f'prior_t0_s = {prior_t0_s!r} is after the first time of a '
                             'segment')
        self.initial_covariance = (preset.initial_covariance if initial_covariance is None
                                   else np.array(initial_covariance, dtype=float))
        skip = 1 if initialization == 'first_measurement' else 0
        self.rows = sum(max(len(s.t_s) - skip, 0) for s in self.segments)
        """How many innovations the likelihood sums over."""
        if self.rows == 0:
            raise ValueError('no innovations to estimate from: the data need at least '
                             f'{skip + 1} rows per object')

    def preset_for(self, setting: NoiseSetting) -> Preset:
        """Return the preset the node runs with ``setting``."""
        return noisy_preset(self.preset, setting.process_noise_density,
                            setting.measurement_variances)

    def start_time(self, segment: Segment) -> float:
        """Return when the initial estimate holds, for a segment (its first row or earlier)."""
        if self.initialization == 'first_measurement':
            return float(segment.t_s[0])
        return float(segment.t_s[0] - self.prior_lead_s if self.prior_t0_s is None
                     else self.prior_t0_s)

    def _start(self, preset: Preset, setting: NoiseSetting, segment: Segment):
        """Return (t0, x0, P0, first row filtered) of a segment, as the node starts."""
        x0 = np.array(preset.initial_state if setting.initial_state is None
                      else setting.initial_state, dtype=float)
        if self.initialization == 'prior':
            return self.start_time(segment), x0, self.initial_covariance, 0
        R = preset.model.R
        variances = np.full(preset.dim_x, self.first_velocity_std_mps ** 2)
        P0 = np.zeros((preset.dim_x, preset.dim_x))
        for i, j in enumerate(self.selector):
            x0[j] = segment.z[0, i]                   # measured states from z₀ ...
            variances[j] = R[i, i]                    # ... with its variance
            for k, m in enumerate(self.selector):
                P0[j, m] = R[i, k]
        P0[np.diag_indices_from(P0)] = variances
        return self.start_time(segment), x0, P0, 1

    def run(self, setting: NoiseSetting, horizon_s: float = 0.0
            ) -> List[Optional[Tuple[SeriesResult, int]]]:
        """Return per segment (its filtered rows, the first row index), None if none."""
        return self._run(self.preset_for(setting), setting, horizon_s)

    def _run(self, preset: Preset, setting: NoiseSetting, horizon_s: float):
        """Run the segments with ``preset`` (the setting's noise already in it)."""
        out = []
        for segment in self.segments:
            t0, x0, P0, first = self._start(preset, setting, segment)
            if len(segment.t_s) <= first:
                out.append(None)
                continue
            u = None if segment.u is None else segment.u[first:]
            out.append((run_linear_series(preset, segment.t_s[first:], segment.z[first:], u,
                                          t0_s=t0, horizon_s=horizon_s, x0=x0, P0=P0),
                        first))
        return out

    def innovations(self, setting: NoiseSetting) -> Innovations:
        """Return the innovations of every filtered row and their covariances."""
        preset = self.preset_for(setting)
        H, R = preset.model.H, preset.model.R
        ys, Ss = [], []
        for segment, run in zip(self.segments, self._run(preset, setting, 0.0)):
            if run is None:
                continue
            result, first = run
            ys.append(segment.z[first:] - result.x_prior @ H.T)          # y = z − H x⁻
            Ss.append(np.einsum('ij,kjl,ml->kim', H, result.P_prior, H) + R)  # H P⁻ Hᵀ + R
        return Innovations(np.concatenate(ys), np.concatenate(Ss))

    def log_likelihood(self, setting: NoiseSetting) -> float:
        """Return the exact log-likelihood of the data under ``setting``."""
        return self.innovations(setting).log_likelihood()
