"""
What a noise estimate estimates: settings of the filter's noise as one optimiser vector.

:class:`NoiseParameterisation` maps a :class:`~kf_train.batch.noise_likelihood.NoiseSetting`
(q, the measurement variances, optionally the initial state) to the vector an optimiser
moves, and back. Variances and the density are its logarithms (positive, and the
likelihood is closer to quadratic in them); the initial state is on its natural scale.
It also gives the optimiser a start (moment estimates of the data) and a box.

The estimator (``kf_train.tune.noise_fit.estimate_noise``, which needs scipy) asks only
for the interfaces :class:`LikelihoodProblem` and :class:`Parameterisation`: other
models (the regime noises of a rail IMM model) plug in by providing them.
"""

import math
from typing import List, NamedTuple, Optional, Protocol, Sequence, Tuple, Union

from kf_train.batch.noise_likelihood import (
    NoiseSetting, STATE_UNITS, TuningProblem, VARIANCE_PARAMETERS)
from kf_train.presets import is_constant_velocity
import numpy as np

VARIANCE_UNITS = {'position': 'm²', 'velocity': 'm²/s²'}


class LikelihoodProblem(Protocol):
    """What ``estimate_noise`` needs of a problem (:class:`TuningProblem` has it)."""

    rows: int
    """How many terms ℓ sums (it optimises ℓ per term)."""

    def log_likelihood(self, setting) -> float:
        """Return ℓ of a setting; ValueError or ArithmeticError for an impossible one."""


class Parameterisation(Protocol):
    """
    What ``estimate_noise`` needs of a parameterisation: settings as vectors.

    :class:`NoiseParameterisation` is the one for q, R and the initial state; a rail
    model's regime noises would be another (one log entry per regime's density).
    """

    parameters: Tuple['Parameter', ...]

    def setting(self, vector, at_zero: Sequence[int] = ()):
        """Return the setting of a vector, the ``at_zero`` log entries at 0."""

    def vector(self, setting) -> np.ndarray:
        """Return the vector of a setting."""

    def bounds(self) -> List[Tuple[float, float]]:
        """Return the box of the vector's entries."""

    def start(self):
        """Return a starting setting."""


class Parameter(NamedTuple):
    """One estimated quantity."""

    name: str
    """The node parameter it sets (``process_noise_density``, ``measurement_variance``,
    ``measurement_velocity_variance``), else a descriptive name."""
    symbol: str
    """Short name for tables: q, R, R[velocity], x0[position]."""
    unit: str
    log_scale: bool
    """Estimated as its logarithm (a variance or density > 0)."""
    zero_allowed: bool = False
    """Whether the node can run with it at 0 (q can; R = 0 means "the message's R")."""


class NoiseParameterisation:
    """
    Which parts of a :class:`NoiseSetting` are estimated, as one optimiser vector.

    The vector is [log q] (when ``process_noise`` and the preset is constant
    velocity), [log R_i for each estimated measurement], [x0 (natural scale) when
    ``initial_state``]; everything else comes from ``fixed``.
    """

    def __init__(self, problem: TuningProblem, *, process_noise: bool = True,
                 measurement_noise: Union[bool, Sequence[str]] = True,
                 initial_state: bool = False, fixed: NoiseSetting = NoiseSetting()):
        """Choose the estimated quantities; raise ValueError for an impossible choice."""
        preset = problem.preset
        self.problem, self.fixed = problem, fixed
        if process_noise and not is_constant_velocity(preset):
            raise ValueError(f'q cannot be estimated for preset {preset.name!r}: white-noise '
                             'acceleration needs [position, velocity] states')
        names = preset.measurement_names
        chosen = names if measurement_noise is True else (
            () if measurement_noise is False else tuple(measurement_noise))
        for name in chosen:
            if name not in names:
                raise ValueError(f'{name!r} is not a measurement of preset {preset.name!r}')
        self.process_noise = bool(process_noise)
        self.measured = tuple(names.index(name) for name in chosen)
        self.initial_state = bool(initial_state)
        if initial_state and problem.initialization != 'prior':
            raise ValueError('the initial state can be estimated only with the prior '
                             'initialization (first_measurement takes it from the data)')
        if initial_state and len(problem.segments) != 1:
            raise ValueError('the initial state can be estimated for one object only, got '
                             f'{len(problem.segments)}')
        params = [Parameter('process_noise_density', 'q', 'm²/s³', True, True)] * process_noise
        for i in self.measured:
            name = names[i]
            params.append(Parameter(VARIANCE_PARAMETERS.get(name, f'variance_{name}'),
                                    'R' if i == 0 and len(names) == 1 else f'R[{name}]',
                                    VARIANCE_UNITS.get(name, f'({name})²'), True))
        if initial_state:
            params += [Parameter(f'initial_{s}', f'x0[{s}]', STATE_UNITS.get(s, ''), False)
                       for s in preset.state_names]
        self.parameters = tuple(params)
        if not self.parameters:
            raise ValueError('nothing to estimate: choose q, R or the initial state')
        self._scales = None

    def _base_variances(self) -> np.ndarray:
        """Return the variances of the fixed setting (the preset's where unset)."""
        fixed = self.fixed.measurement_variances
        return np.array(np.diag(self.problem.preset.model.R) if fixed is None else fixed,
                        dtype=float)

    def setting(self, vector, at_zero: Sequence[int] = ()) -> NoiseSetting:
        """Return the setting a vector stands for; ``at_zero``: entries (q) set to 0."""
        v = np.asarray(vector, dtype=float)
        k = 0
        q = self.fixed.process_noise_density
        if self.process_noise:
            q, k = (0.0 if 0 in at_zero else math.exp(v[0])), 1
        variances = self.fixed.measurement_variances
        if self.measured:
            r = self._base_variances()
            for i in self.measured:
                r[i] = math.exp(v[k])
                k += 1
            variances = tuple(float(x) for x in r)
        x0 = self.fixed.initial_state
        if self.initial_state:
            x0 = tuple(float(x) for x in v[k:])
        return NoiseSetting(float(q), variances, x0)

    def vector(self, setting: NoiseSetting) -> np.ndarray:
        """Return the optimiser vector of a setting (its estimated parts)."""
        out = [math.log(setting.process_noise_density)] if self.process_noise else []
        r = (self._base_variances() if setting.measurement_variances is None
             else setting.measurement_variances)
        out += [math.log(r[i]) for i in self.measured]
        if self.initial_state:
            out += list(self.problem.preset.initial_state if setting.initial_state is None
                        else setting.initial_state)
        return np.array(out, dtype=float)

    def scales(self) -> Tuple[float, np.ndarray, float, float]:
        """
        Return (q_start, R_start (m,), median dt, time span) from moments of the data.

        For a constant-velocity truth under white-noise acceleration measured with
        variance R, the second differences d_k = z_{k+1} − 2 z_k + z_{k−1} at a
        steady dt are MA(1) with γ₀ = 6R + ⅔ q dt³ and γ₁ = −4R + ⅙ q dt³, hence
        R = (γ₀ − 4γ₁)/22 and q = 3(γ₀ − 6R)/(2 dt³): a start for the optimiser (and
        its bounds), not an estimate (controls and irregular dt bias it).
        """
        if self._scales is not None:
            return self._scales
        m = self.problem.preset.dim_z
        g0, g1, count, dts, span = np.zeros(m), np.zeros(m), 0, [], 0.0
        for s in self.problem.segments:
            if len(s.t_s) > 1:
                dts.append(np.diff(s.t_s))
                span = max(span, float(s.t_s[-1] - s.t_s[0]))
            if len(s.t_s) < 4:
                continue
            d = np.diff(s.z, n=2, axis=0)
            g0 += np.sum(d * d, axis=0)
            g1 += np.sum(d[1:] * d[:-1], axis=0)
            count += d.shape[0]
        dt = float(np.median(np.concatenate(dts))) if dts else self.problem.preset.nominal_period_s
        span = max(span, dt)
        if count == 0 or not np.all(g0 > 0.0):
            raise ValueError('the measurements do not vary (or there are fewer than 4 rows '
                             'per object): nothing to estimate the noise from')
        g0, g1 = g0 / count, g1 / (count - 1 if count > 1 else 1)
        R = np.maximum((g0 - 4.0 * g1) / 22.0, g0 / 600.0)
        q = max(3.0 * (g0[0] - 6.0 * R[0]) / (2.0 * dt ** 3), 1e-3 * R[0] / dt ** 3)
        self._scales = (q, R, dt, span)
        return self._scales

    def start(self) -> NoiseSetting:
        """Return the optimiser's start: moment estimates where estimated, else fixed."""
        q, R, _, _ = self.scales()
        variances = self._base_variances()
        for i in self.measured:
            variances[i] = R[i]
        return NoiseSetting(q if self.process_noise else self.fixed.process_noise_density,
                            tuple(float(r) for r in variances), self._initial_state_start())

    def _initial_state_start(self) -> Optional[Tuple[float, ...]]:
        """
        Return a start for an estimated initial state: a line through the first rows.

        For a constant-velocity preset measuring the position, the least-squares line
        through the first (up to 20) rows, evaluated at the prior's time; else the
        fixed (or the preset's) initial state.
        """
        problem = self.problem
        if not self.initial_state or not is_constant_velocity(problem.preset):
            return self.fixed.initial_state
        names = problem.preset.measurement_names
        segment = problem.segments[0]
        if 'position' not in names or len(segment.t_s) < 2:
            return self.fixed.initial_state
        t, z = segment.t_s[:20], segment.z[:20, names.index('position')]
        t0 = problem.start_time(segment)
        slope, intercept = np.polyfit(t - t0, z, 1)    # z ≈ x0 + v0·(t − t0)
        return (float(intercept), float(slope))

    def bounds(self) -> List[Tuple[float, float]]:
        """
        Return the optimiser's box: wide enough never to bind on an identified value.

        q from (R/T³)·1e-6, far below what a span T of data can detect (q T³ ≪ R), to
        (R/dt³)·1e6; R from 1e-8 to 1e4 times its moment estimate.
        """
        q, R, dt, span = self.scales()
        R0 = float(R[0])
        out = ([(math.log(R0 / span ** 3 * 1e-6), math.log(R0 / dt ** 3 * 1e6))]
               if self.process_noise else [])
        out += [(math.log(R[i] * 1e-8), math.log(R[i] * 1e4)) for i in self.measured]
        out += [(-math.inf, math.inf)] * (self.problem.preset.dim_x * self.initial_state)
        return out
