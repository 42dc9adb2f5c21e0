"""
Step adapters: every filter kind as a :class:`~kf_train.filters.contract.StepModel`.

The estimator keeps its states as (x, P) pairs and rewinds by going back to an older
pair, so it needs models without state of their own: pure ``predict``, ``update``,
``predict_update`` and ``predict_ahead`` (the contract). :func:`make_model` picks one:

* the preset's linear model with F(dt), Q(dt) and B(dt) cached per dt
  (:class:`_CachedModel`), plus a white-noise acceleration if one is set;
* the train's KF in closed form (:class:`_FastTrainModel`; equal to the generic path
  to rounding, ~4x cheaper);
* the UKF's unscented transform of either;
* a particle filter (``pf``: the regularised one; ``bootstrap-pf``) whose particles
  stay behind each mean it returns (:class:`_ParticleModel`);
* the rail preset's IMM, whose whole state stays behind each mean it returns
  (:class:`~kf_train.estimator.imm_model.IMMModel`).
"""

import math
from typing import Callable, Dict, Optional, Tuple, Union
import weakref

from kf_train.estimator.imm_model import IMMModel
from kf_train.filters import (
    closed_form, constant_velocity_model, LinearModel, PARTICLE_KINDS, ParticleFilter,
    PredictThenUpdate, RegularisedParticleFilter, StepModel, UnscentedModel, UpdateResult,
    white_noise_terms, WhiteNoiseAcceleration)
from kf_train.presets import Preset, RailPreset
import numpy as np

# Distinct dt values whose F, Q and B a preset model keeps computed.
_MODEL_CACHE_SIZE = 64


class _CachedModel(LinearModel):
    """A preset's linear model with F(dt), Q(dt) and B(dt) computed once per dt."""

    def __init__(self, model: LinearModel, extra_Q: Optional[Callable] = None):
        """Wrap ``model``; ``extra_Q(dt)``, if given, is added to its process noise."""
        base_Q = model.Q
        Q = base_Q if extra_Q is None else (lambda dt: base_Q(dt) + extra_Q(dt))
        super().__init__(self._cached(model.F), self._cached(Q), model.H, model.R,
                         B=None if model.B is None else self._cached(model.B),
                         state_names=model.state_names,
                         measurement_names=model.measurement_names,
                         control_names=model.control_names)

    @staticmethod
    def _cached(function: Callable) -> Callable:
        """Return ``function`` of dt remembering its latest _MODEL_CACHE_SIZE results."""
        cache: Dict[float, np.ndarray] = {}

        def cached(dt):
            key = float(dt)
            value = cache.get(key)
            if value is None:
                value = function(dt)
                value.setflags(write=False)  # shared between calls: never modified
                if len(cache) >= _MODEL_CACHE_SIZE:
                    cache.clear()
                cache[key] = value
            return value
        return cached


class _FastTrainModel(PredictThenUpdate):
    """
    Seed 000's train model with ``predict``/``update`` in closed form on plain floats.

    The same interface and results (to rounding) as the generic LinearModel with
    F(dt) = [[1, dt], [0, 1]], Q(dt) = q·[[dt³/3, dt²/2], [dt²/2, dt]], H = [1, 0],
    at a fraction of the cost: no numpy call but the arrays it returns, and no
    re-validation of the estimator's own, already checked, arrays. The arithmetic is
    :mod:`kf_train.filters.closed_form` (the Joseph form reduced for the optimal gain).
    Non-finite results and a zero S raise ValueError as the generic path does.
    """

    def __init__(self, model: LinearModel, q: float):
        """Mirror ``model`` (the generic train model with density q)."""
        self.base = model
        self.state_names = model.state_names
        self.measurement_names = model.measurement_names
        self.control_names = model.control_names
        self.dim_x, self.dim_z = 2, 1
        self.F, self.Q, self.B, self.H, self.R = model.F, model.Q, None, model.H, model.R
        self._q = float(q)
        self._noise = (None, 0.0, 0.0, 0.0)  # (dt, Q00, Q01, Q11) of the latest dt

    def _terms(self, dt_s) -> Tuple[float, float, float, float]:
        """Return (dt, Q00, Q01, Q11) for dt_s, checked and cached for a steady rate."""
        noise = self._noise
        if dt_s == noise[0]:
            return noise
        dt = float(dt_s)
        if not 0.0 <= dt < math.inf:
            raise ValueError(f'dt must be a finite number >= 0, got {dt_s!r}')
        try:
            noise = (dt,) + white_noise_terms(self._q, dt)
        except OverflowError:
            raise ValueError('prediction produced a non-finite state; inputs are too '
                             'large') from None
        self._noise = noise
        return noise

    def predict(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return (x⁻, P⁻) over dt_s: x⁻ = F x, P⁻ = F P Fᵀ + Q."""
        if u is not None:
            raise ValueError('u given to a model without control input')
        dt, q00, q01, q11 = self._terms(dt_s)
        x0, x1 = x.tolist()
        (p00, p01), (p10, p11) = P.tolist()
        p01 = 0.5 * (p01 + p10)  # the generic path symmetrises too
        x0, x1, p00, p01, p11 = closed_form.predict(
            x0, x1, p00, p01, p11, dt, q00, q01, q11)
        if not 0.0 * (x0 + x1 + p00 + p01 + p11) == 0.0:
            raise ValueError('prediction produced a non-finite state; inputs are too large')
        return np.array((x0, x1)), np.array(((p00, p01), (p01, p11)))

    # The look-ahead is the prediction (bound directly: one call less on the hot path).
    predict_ahead = predict

    def update(self, x, P, z, R=None) -> Tuple[np.ndarray, np.ndarray, UpdateResult]:
        """Return (x, P, UpdateResult) after position measurement z of variance R."""
        x0, x1 = x.tolist()
        (p00, p01), (p10, p11) = P.tolist()
        p01 = 0.5 * (p01 + p10)
        r = float((self.R if R is None else R)[0][0])
        try:
            (y0, y1, n00, n01, n11), result = closed_form.correct(
                x0, x1, p00, p01, p11, float(z[0]), r)
        except ZeroDivisionError:
            raise ValueError(f'innovation covariance S = H P Hᵀ + R is singular: '
                             f'[[{p00 + r}]]') from None
        nis = result.nis
        if not (0.0 * (y0 + y1 + n00 + n01 + n11) == 0.0 and 0.0 <= nis < math.inf):
            raise ValueError(f'update produced a non-finite state or an invalid NIS {nis}; '
                             f'S = [[{result.innovation_variance}]]')
        k0, k1 = result.gain
        return (np.array((y0, y1)), np.array(((n00, n01), (n01, n11))),
                UpdateResult(np.array((result.innovation,)),
                             np.array(((result.innovation_variance,),)), nis,
                             np.array(((k0,), (k1,)))))


class _ParticleModel(PredictThenUpdate):
    """
    A particle filter behind the pure model contract (predict_update: predict, update).

    The estimator keeps states as (x, P) and rewinds by going back to an older pair.
    Each mean this model returns stands for its particles: their snapshot (particles,
    log-weights, generator state) is kept in ``states`` under the mean's id until
    the mean is garbage-collected. A step restores the snapshot of the mean it is
    given, so rewinding and replaying repeats the same draws bit for bit. A mean that
    has no particles (an initialisation, set_state) is sampled as N(x, P) by a
    generator restarted from the seed: deterministic too.
    """

    def __init__(self, model: LinearModel, particles: int, seed: int,
                 resample_threshold: float, states: Dict[int, object],
                 filter_class=RegularisedParticleFilter):
        """Run ``model`` with ``particles`` particles; keep snapshots in ``states``."""
        self.base = model
        self.state_names = model.state_names
        self.measurement_names = model.measurement_names
        self.control_names = model.control_names
        self.dim_x, self.dim_z = model.dim_x, model.dim_z
        self.F, self.Q, self.B, self.H, self.R = model.F, model.Q, model.B, model.H, model.R
        self.seed = seed
        self.states = states
        n = model.dim_x
        self.filter = filter_class(model, np.zeros(n), np.zeros((n, n)),
                                   n_particles=particles, seed=seed,
                                   resample_threshold=resample_threshold)

    def _load(self, x: np.ndarray, P: np.ndarray) -> None:
        """Make the filter's particles those behind x (drawn from N(x, P) if none)."""
        snapshot = self.states.get(id(x))
        if snapshot is None or snapshot[0]() is not x:
            self.filter.reset(x, P, self.seed)
        else:
            self.filter.restore(snapshot[1])

    def _keep(self) -> Tuple[np.ndarray, np.ndarray]:
        """Return the filter's (mean, covariance), the mean remembering the particles."""
        x, P = self.filter.mean, self.filter.covariance
        key = id(x)
        # A weak reference tells the mean from a later array with the same id; the
        # snapshot goes when the mean is freed (nothing can rewind to it any more).
        self.states[key] = (weakref.ref(x), self.filter.snapshot())
        weakref.finalize(x, self.states.pop, key, None)
        return x, P

    def predict(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the particles' moments after moving them over dt_s."""
        self._load(x, P)
        self.filter.predict(dt_s, u)
        return self._keep()

    def predict_ahead(self, x, P, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the exact moments dt_s ahead of the particles behind x (no draws)."""
        self._load(x, P)
        return self.filter.predict_ahead(dt_s, u)

    def update(self, x, P, z, R=None):
        """Return (mean, covariance, UpdateResult) after weighting by z's likelihood."""
        self._load(x, P)
        result = self.filter.update(z, R)
        x, P = self._keep()
        return x, P, result


def make_model(settings, preset: Union[Preset, RailPreset],
               particle_states: Optional[Dict[int, object]] = None,
               fast: bool = True, jit: Optional[bool] = None) -> StepModel:
    """
    Return the filter's pure model: the preset's, plus white-noise acceleration q if set.

    ``settings`` are validated :class:`~kf_train.estimator.EstimatorSettings`. The rail
    preset is an :class:`IMMModel` (keeping its states in ``particle_states``). ``kf``
    and ``ekf`` (an EKF of a linear model is the KF) use the linear model itself,
    ``ukf`` its unscented transform, ``pf`` and ``bootstrap-pf`` a
    :class:`_ParticleModel` on it (keeping its particles in ``particle_states``). With
    ``fast``, the train's KF is :class:`_FastTrainModel`, its closed form, and the rail
    IMM compiled if ``jit`` (None: where KF_TRAIN_JIT=1 asks,
    :func:`~kf_train.filters.rail_model`); without, the numpy references.
    """
    if isinstance(preset, RailPreset):
        # The IMM of four Kalman filters (settings allow only kf/ekf for it); its
        # states are kept with the particle filters' (both keyed by a mean's id).
        # Compiled as ``jit`` says (kf_train.filters.rail_fast); ``fast`` False: numpy.
        return IMMModel(preset.model(jit if fast else False), preset.H, preset.R,
                        preset.state_names, states=particle_states)
    q = settings.process_noise_density
    if settings.preset == 'train':
        # Seed 000's model exactly as before presets: F(dt), Q(dt) = q·[...], H = [1, 0].
        model = constant_velocity_model(WhiteNoiseAcceleration(q))
        if fast and settings.filter in ('kf', 'ekf'):
            return _FastTrainModel(model, q)
    else:
        model = _CachedModel(preset.model, WhiteNoiseAcceleration(q) if q > 0.0 else None)
    if settings.filter == 'ukf':
        return UnscentedModel.from_model(model, alpha=settings.ukf_alpha,
                                         beta=settings.ukf_beta, kappa=settings.ukf_kappa)
    if settings.filter in PARTICLE_KINDS:
        return _ParticleModel(model, settings.pf_particles, settings.pf_seed,
                              settings.pf_resample_threshold,
                              {} if particle_states is None else particle_states,
                              RegularisedParticleFilter if settings.filter == 'pf'
                              else ParticleFilter)
    return model
