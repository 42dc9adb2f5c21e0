"""
The filter family behind one interface: KF, EKF, UKF and particle filter.

``make_filter(preset, kind)`` returns a :class:`Filter` for kind ``'kf'``, ``'ekf'``,
``'ukf'``, ``'pf'`` or ``'bootstrap-pf'``, started at the preset's initial state. A
:class:`Filter` holds its state; every kind has the same interface, which the offline
series (:func:`kf_train.batch.series.run_filter_series`, the replay's ``--filter``)
uses. The streaming estimator keeps its states itself, as (x, P) pairs it can rewind
to, so it runs the pure models a :class:`GaussianFilter` wraps (the model contract,
:class:`~kf_train.filters.contract.StepModel`), not a :class:`Filter`. The interface:

* ``predict(dt_s, u=None)``: propagate over dt_s [s] (u required iff the preset has a
  control input);
* ``update(z, R=None) -> UpdateResult``: correct with measurement z (R defaults to
  the preset's); returns the innovation y, its covariance S, the NIS yᵀ S⁻¹ y and
  the gain;
* ``predict_ahead(dt_s, u=None) -> (x, P)``: a look-ahead that changes nothing;
* ``mean``, ``covariance`` (also ``x``, ``P``): copies of the current estimate;
* ``snapshot()`` / ``restore(snapshot)``: the whole state (for the particle filter
  the particles, weights and random generator too), so that an out-of-sequence
  measurement can rewind and replay exactly;
* ``reset(x0=None, P0=None)``: start again (from the preset's initial estimate by
  default); a reset particle filter also restarts its generator from its seed, so it
  behaves exactly like a new one;
* ``diagnostics()``: counters (UKF regularisations; PF effective sample size and
  resampling count).

A step that raises ValueError leaves the filter as it was.

What the kinds mean:

* ``kf``: the preset's exact linear path (:class:`~kf_train.filters.models.LinearModel`,
  Joseph-form update); linear presets only.
* ``ekf``: the preset's own model: the range-bearing EKF with its analytic Jacobian,
  and on a linear preset the same KF (an EKF of a linear model is the KF).
* ``ukf``: :class:`~kf_train.filters.ukf.UnscentedModel`, Merwe sigma points with
  ``alpha``, ``beta``, ``kappa``.
* ``pf``: :class:`~kf_train.filters.regularised_pf.RegularisedParticleFilter` (first
  update drawn from the measurement, progressive correction, regularisation with a
  Metropolis-Hastings move) with ``particles``, ``seed`` and ``resample_threshold``.
* ``bootstrap-pf``: the plain bootstrap filter,
  :class:`~kf_train.filters.particle.ParticleFilter`, with ``particles``, ``seed``,
  ``resample_threshold`` and ``roughening``; for teaching: it collapses where the
  likelihood is much narrower than the prior (range-bearing).
"""

from typing import Dict, NamedTuple, Optional, Tuple

from kf_train.filters.kalman import UpdateResult
from kf_train.filters.particle import (
    check_particles, check_seed, DEFAULT_RESAMPLE_THRESHOLD, ParticleFilter)
from kf_train.filters.regularised_pf import RegularisedParticleFilter
from kf_train.filters.ukf import DEFAULT_ALPHA, DEFAULT_BETA, DEFAULT_KAPPA, UnscentedModel
from kf_train.filters.validation import as_covariance, as_vector
import numpy as np

FILTER_KINDS = ('kf', 'ekf', 'ukf', 'pf', 'bootstrap-pf')
PARTICLE_KINDS = ('pf', 'bootstrap-pf')
DEFAULT_PARTICLES = 2000
"""Particles unless told otherwise: for 4 states ~1 ms (``bootstrap-pf``) or ~2-3 ms (``pf``)
per step on the 2-core test host."""


class FilterOptions(NamedTuple):
    """The tuning of the non-exact filters (each kind uses its own)."""

    alpha: float = DEFAULT_ALPHA
    """UKF sigma-point spread α > 0 (points at ±α√(n + κ)·σ)."""
    beta: float = DEFAULT_BETA
    """UKF prior-knowledge weight (2 is optimal for a Gaussian)."""
    kappa: float = DEFAULT_KAPPA
    """UKF secondary scaling."""
    particles: int = DEFAULT_PARTICLES
    """PF particle count."""
    seed: int = 0
    """PF random seed."""
    resample_threshold: float = DEFAULT_RESAMPLE_THRESHOLD
    """PF: resample when ESS < resample_threshold · particles."""
    roughening: float = 0.0
    """bootstrap-pf: roughening constant K after resampling (0: the plain filter)."""


class Filter:
    """The interface every kind implements; see the module docstring."""

    kind: str = ''

    def __init__(self, preset):
        """Keep the preset (names, initial estimate, dynamics)."""
        self.preset = preset

    @property
    def state_names(self) -> Tuple[str, ...]:
        """Return the state names."""
        return self.preset.state_names

    @property
    def dim_x(self) -> int:
        """Return the number of states."""
        return self.preset.dim_x

    @property
    def x(self) -> np.ndarray:
        """Return a copy of the mean (alias of ``mean``)."""
        return self.mean

    @property
    def P(self) -> np.ndarray:
        """Return a copy of the covariance (alias of ``covariance``)."""
        return self.covariance

    def _initial(self, x0, P0) -> Tuple[np.ndarray, np.ndarray]:
        """Return the checked (x0, P0), the preset's where not given."""
        n = self.dim_x
        x0 = as_vector('x0', self.preset.initial_state if x0 is None else x0, n)
        P0 = as_covariance('P0', self.preset.initial_covariance if P0 is None else P0, n)
        return x0, P0

    def __repr__(self) -> str:
        """Show the kind and preset."""
        return f'{type(self).__name__}({self.kind!r}, preset={self.preset.name!r})'


class GaussianFilter(Filter):
    """A filter whose state is (x, P): the KF, the EKF and the UKF."""

    def __init__(self, preset, kind: str, model):
        """Use ``model`` (pure ``predict(x, P, dt, u)`` and ``update(x, P, z, R)``)."""
        super().__init__(preset)
        self.kind = kind
        self.model = model
        self.reset()

    def reset(self, x0=None, P0=None) -> None:
        """Start from (x0, P0), the preset's initial estimate by default."""
        self._x, self._P = self._initial(x0, P0)
        self._regularisations_before = getattr(self.model, 'regularisations', 0)

    @property
    def mean(self) -> np.ndarray:
        """Return a copy of the mean."""
        return self._x.copy()

    @property
    def covariance(self) -> np.ndarray:
        """Return a copy of the covariance."""
        return self._P.copy()

    def predict(self, dt_s: float, u=None) -> None:
        """Propagate the estimate over dt_s."""
        self._x, self._P = self.model.predict(self._x, self._P, dt_s, u)

    def predict_ahead(self, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the estimate predicted over dt_s; the filter is unchanged."""
        return self.model.predict(self._x, self._P, dt_s, u)

    def update(self, z, R=None) -> UpdateResult:
        """Correct the estimate with z; return the innovation statistics."""
        self._x, self._P, result = self.model.update(self._x, self._P, z, R)
        return result

    def snapshot(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return read-only copies of (x, P)."""
        x, P = self._x.copy(), self._P.copy()
        x.flags.writeable = False
        P.flags.writeable = False
        return x, P

    def restore(self, snapshot) -> None:
        """Return to a snapshot (x, P)."""
        x, P = snapshot
        self._x = as_vector('x', x, self.dim_x).copy()
        self._P = as_covariance('P', P, self.dim_x).copy()

    def diagnostics(self) -> Dict[str, float]:
        """Return the UKF's regularisations since the last reset (empty for KF, EKF)."""
        count = getattr(self.model, 'regularisations', None)
        if count is None:
            return {}
        return {'regularisations': int(count - self._regularisations_before)}


class ParticlePresetFilter(Filter):
    """A particle filter (``pf`` or ``bootstrap-pf``) behind the common interface."""

    def __init__(self, preset, particles: int, seed: int, resample_threshold: float,
                 roughening: float = 0.0, kind: str = 'pf'):
        """Draw the initial particles from the preset's initial estimate."""
        super().__init__(preset)
        self.kind = kind
        args = (preset.model, preset.initial_state, preset.initial_covariance)
        if kind == 'pf':
            self.particle_filter = RegularisedParticleFilter(
                *args, n_particles=particles, seed=seed, resample_threshold=resample_threshold)
        else:
            self.particle_filter = ParticleFilter(
                *args, n_particles=particles, seed=seed, resample_threshold=resample_threshold,
                roughening=roughening)

    def reset(self, x0=None, P0=None, seed: Optional[int] = None) -> None:
        """Start from N(x0, P0), the generator restarted from ``seed`` (else the last)."""
        x0, P0 = self._initial(x0, P0)
        self.particle_filter.reset(x0, P0, seed)

    @property
    def seed(self) -> int:
        """Return the seed the generator restarts from on reset."""
        return self.particle_filter.seed

    @property
    def mean(self) -> np.ndarray:
        """Return the particles' weighted mean."""
        return self.particle_filter.mean

    @property
    def covariance(self) -> np.ndarray:
        """Return the particles' weighted covariance."""
        return self.particle_filter.covariance

    def predict(self, dt_s: float, u=None) -> None:
        """Move the particles over dt_s."""
        self.particle_filter.predict(dt_s, u)

    def predict_ahead(self, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the exact moments predicted over dt_s (no random draws)."""
        return self.particle_filter.predict_ahead(dt_s, u)

    def update(self, z, R=None) -> UpdateResult:
        """Weight (and maybe resample) the particles by z's likelihood."""
        return self.particle_filter.update(z, R)

    def snapshot(self):
        """Return the particles, log-weights and generator state."""
        return self.particle_filter.snapshot()

    def restore(self, snapshot) -> None:
        """Return to a snapshot."""
        self.particle_filter.restore(snapshot)

    def diagnostics(self) -> Dict[str, float]:
        """Return the effective sample size and the number of resamplings."""
        return {'ess': self.particle_filter.ess,
                'resample_count': self.particle_filter.resample_count,
                **getattr(self.particle_filter, 'counters', {})}


def check_kind(kind: str) -> str:
    """Return ``kind`` if it names a filter, else raise ValueError."""
    if kind not in FILTER_KINDS:
        raise ValueError(f"filter must be one of {', '.join(FILTER_KINDS)}, got {kind!r}")
    return kind


def gaussian_model(preset, kind: str, options: FilterOptions = FilterOptions()):
    """
    Return the pure model of a Gaussian kind (kf, ekf, ukf).

    It has ``predict(x, P, dt_s, u)`` and ``update(x, P, z, R)`` like the preset's
    own model, so code written for the preset's model runs any of them.
    """
    check_kind(kind)
    if kind == 'kf':
        if not preset.linear:
            raise ValueError(f'preset {preset.name!r} has a nonlinear measurement; '
                             "filter 'kf' needs a linear one (use ekf, ukf or pf)")
        return preset.model
    if kind == 'ekf':
        return preset.model
    if kind == 'ukf':
        return UnscentedModel.from_model(preset.model, alpha=options.alpha,
                                         beta=options.beta, kappa=options.kappa)
    raise ValueError(f'the particle filter has no (x, P) model; use make_filter(preset, '
                     f'{kind!r})')


def make_filter(preset, kind: str, options: Optional[FilterOptions] = None,
                **overrides) -> Filter:
    """
    Return a filter of the given kind for a preset, at its initial estimate.

    Tuning comes from ``options`` and keyword ``overrides`` (alpha, beta, kappa,
    particles, seed, resample_threshold, roughening); each is checked.
    """
    options = (options or FilterOptions())._replace(**overrides)
    check_kind(kind)
    if kind in PARTICLE_KINDS:
        return ParticlePresetFilter(preset, check_particles(options.particles),
                                    check_seed(options.seed), options.resample_threshold,
                                    options.roughening, kind)
    return GaussianFilter(preset, kind, gaussian_model(preset, kind, options))
