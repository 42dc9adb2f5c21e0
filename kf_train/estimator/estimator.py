"""
The live estimator as a pure state machine: stamped measurements and controls in, estimates out.

It runs the rail preset (``preset``: ``rail``, the default: a train in four regimes,
stand/accelerate/cruise/brake, as an IMM; docs/rail.md) and any 1-D preset of
:mod:`kf_train.presets.loader` on a stream (``train``, ``car``, ``car-exact``,
``robot``, ``robot-exact``, ``cv-position``, ``cv-position-velocity``, or the path of a
preset YAML file of the same shape; see :func:`check_live_preset`). The defaults are
for real data: rail, the χ² gate on (0.9999), first_measurement;
:data:`~kf_train.estimator.settings.SEED_SWITCH` (preset train, prior, no gate)
reproduces seed 000. The preset
brings the model, the initial state and covariance, the nominal period and the
horizon; a setting that is not None overrides the preset's value.

The rail preset's IMM (:class:`~kf_train.estimator.imm_model.IMMModel`) keeps its
whole state (per-regime means, covariances, probabilities) behind every (x, P) it
returns, as the particle filter keeps its particles: x and P are the mixture's
moments, rewinds and replays repeat the IMM's steps bit for bit, the χ² gate judges
the mixture's innovation, and the prediction ``horizon_s`` ahead is the mixture of
each regime's own prediction (a train never reverses in it).
:meth:`StreamEstimator.mode_probabilities` gives the regime probabilities. An (x, P)
the IMM did not produce (``set_state``, an initialisation) starts every regime at
(x, P) with equal probabilities.

The filter (``filter``, fixed for the estimator's life like the preset) is ``kf``
(default), ``ekf`` (the KF on these linear presets), ``ukf``, ``pf`` (the regularised
particle filter) or ``bootstrap-pf`` (the plain bootstrap filter): each is a pure
``predict(x, P, dt, u)``/``update(x, P, z, R)`` model, so the input contract, the χ²
gate (on the filter's own NIS), the out-of-sequence replay, controls and resets work
alike for all. The particle filter keeps the particles behind every kept mean, so a
rewind restores them and the generator, and a replay repeats its draws bit for bit.
The train's KF runs in closed form (:mod:`kf_train.estimator.adapters`; equal to the
generic path to rounding, ~4x cheaper).

Time is kept in integer nanoseconds (as ROS stamps are), so that dt between two
stamps is exact: a float of epoch seconds has only ~0.2 µs resolution, which alone
would move the estimate by more than 1e-9.

Initialisation:

* ``prior`` (the seeds' mode): the initial state and covariance hold one nominal
  period before the first measurement's stamp; every measurement, the first
  included, is then a predict and an update.
* ``first_measurement`` (default): the first measurement sets the states it measures
  with its own variance; the other states (the velocity, unless measured) come from
  the initial state with a standard deviation of ``first_velocity_std_mps``, so the
  filter converges within a few samples even when it joins a train that is far down
  the track. (With Q = 0 the seed's prior would lock the filter onto its wrong
  initial velocity.) The rail preset takes the other states' variances from its
  initial covariance instead (its priors: velocity 20 m/s, acceleration 1 m/s², the
  capabilities A and B), all regimes equally likely.

Controls (presets with a control input: ``car``, acceleration [m/s²]; ``robot``,
velocity [m/s]), fed by :meth:`StreamEstimator.add_control`:

* A control stamped t_k is the input applied over the interval (t_{k-1}, t_k] that
  *ends* at t_k (the seeds' convention: docs/presets.md). The latest value received
  for a stamp is kept.
* A prediction from t_a to t_b is split at every control stamp inside (t_a, t_b):
  each piece uses the control of the interval it lies in. The last piece uses the
  control stamped t_b; if that has not arrived, the control of the interval that
  contains t_b (the first later stamp), else the latest earlier one (zero-order
  hold), else zero. Such a fusion is counted as ``provisional``.
* A control that arrives after a measurement that needed it (the topics are not
  ordered against each other) is applied by rewinding to the last state before it
  and replaying the later measurements, as an out-of-sequence measurement is; the
  result is what in-order arrival would have given, whatever the order. This works
  within ``history_s`` (0 turns it off); a control too old for that is rejected as
  ``stale_stamp``. So the estimate never waits for a control, and is exact once the
  control is in.
* The prediction ``horizon_s`` ahead holds the control of the newest interval.
* Controls are kept while a replay or the next prediction may need them: from the
  oldest state kept for replay on (all of them before the first measurement), at
  most MAX_CONTROLS (the oldest go first).

Input contract: :meth:`StreamEstimator.process` raises :class:`Rejected` (a
``ValueError``) with a ``reason`` from :data:`REJECTION_REASONS` for a measurement it
will not fuse, and the filter state (x, P, last stamp, history) is then exactly as
before, unless the rejection itself triggered a reset (``Rejected.reset``). The
checks, cheapest first:

* ``wrong_frame``: ``expected_frame_id`` is set and the measurement's frame differs;
* ``non_finite``: NaN or Inf in a measured value or the message's variance;
* ``bad_variance``: a variance in use (the override, else the message's) <= 0;
* ``zero_stamp``: a stamp <= 0 (an unset header);
* ``future_stamp``: more than ``max_future_s`` after ``now_ns``, when that is given;
* ``duplicate_stamp``: a stamp already fused;
* ``stale_stamp``: older than the newest fused one by ``history_s`` or more;
* ``outlier``: the NIS exceeds the χ² gate (``gate_probability``);
* ``numerical``: the update could not be computed in floating point.

:meth:`StreamEstimator.add_control` rejects likewise, counted apart by
:data:`CONTROL_REJECTION_REASONS`.

Time handling:

* A measurement older than the newest fused one but by less than ``history_s`` is
  fused out of sequence: the filter rewinds to the state after the last measurement
  before it, fuses it, and replays the later measurements (each with the R and model
  it was first fused with, and the controls known now). The result equals in-order
  processing to rounding. Replayed measurements are not gated again. A measurement
  older than the first one since (re)initialisation re-initialises from it and
  replays everything, as in-order processing would have.
* ``restart_after_stale`` consecutive stale measurements mean the stream restarted
  (a bag loop, a restarted sensor): the filter resets and initialises from the last
  of them.
* A repeated epoch, the newest fused position again while the track has moved beyond
  the gate on the R in use, is rejected (``repeated``) where R is learned below the R
  given (the gate then uses the R given, under which a repeat 6 m behind a 31 m/s
  train passes and is weighed with σ of a few cm).
* ``max_consecutive_outliers`` consecutive gate (repeated, numerical) rejections that
  agree with each other are a lock-out (:mod:`~kf_train.estimator.reacquire`). By default
  (``lockout`` reacquire) the track is kept: widened by the jump between it and the
  group's line, the group fused into it, never gated, the last fix's step returned
  (``stats().reacquisitions``). With ``lockout`` reset, or when the lock-out came from
  numerical failures, an out-of-sequence fix or with controls, the filter resets; the
  next measurement initialises it with the group, from the measurements as in
  ``first_measurement`` mode even in ``prior`` mode (the prior is what the data
  contradicted). Either way the filter cannot stay locked out. Other resets
  re-initialise in the configured mode. A clock jump
  or a stream restart also forgets the controls (their stamps belong to the old
  time line).

Measured speeds (the rail preset: :meth:`StreamEstimator.process_velocity`, a GNSS
Doppler along the track) are a second input with the same contract and gate (on the
speed's own NIS), fused by the IMM's velocity update (H = e_1; the learned scale on R
is the position's and stays out of it) and kept in the same history, so out-of-sequence
speeds and positions rewind and replay exactly. At one stamp the position goes first
(dt = 0 to the speed), whichever arrived first. A speed never initialises the filter,
and its rejections (:data:`~kf_train.estimator.contract.VELOCITY_REJECTION_REASONS`)
are counted apart and never count toward the lock-out or a stream restart.

Every rejection and reset is counted by reason (:meth:`StreamEstimator.stats`).

The parts live beside this module: the settings (:mod:`~kf_train.estimator.settings`),
the contract and the counters (:mod:`~kf_train.estimator.contract`), which presets
run live (:mod:`~kf_train.estimator.live_presets`), the step adapters
(:mod:`~kf_train.estimator.adapters`), the controls buffer
(:mod:`~kf_train.estimator.controls`) and the history and replay
(:mod:`~kf_train.estimator.history`), and the state machine on checked inputs
(:mod:`~kf_train.estimator.fusion`). This module is the public API and the input
contract in front of them.
"""


from typing import Optional, Tuple

from kf_train.estimator.contract import (
    check_control, check_measurement, check_stamp, check_velocity, EstimateStep, EstimatorStats,
    measurement_noise, override_variance, Rejected, RESET_REASONS)
from kf_train.estimator.fusion import Fusion
from kf_train.estimator.history import History
from kf_train.estimator.settings import Configuration, configure, EstimatorSettings
from kf_train.filters import as_covariance, as_vector, NS_PER_S
import numpy as np


class StreamEstimator:
    """Fuses stamped measurements (and controls): the rail preset by default."""

    fast_path = True
    """Run the train's KF in closed form and the rail IMM compiled as ``jit`` says (see
    :mod:`~kf_train.estimator.adapters`); False: the generic numpy references."""

    def __init__(self, settings: EstimatorSettings = EstimatorSettings(), *,
                 jit: Optional[bool] = None):
        """
        Validate ``settings``; the filter starts uninitialised.

        ``jit``: run the rail IMM compiled (True: numba must be installed) or numpy
        (False); None (the node's, the replay's): as the KF_TRAIN_JIT variable says
        (:func:`~kf_train.filters.rail_model`). Fixed for the estimator's life.
        """
        self.settings: Optional[EstimatorSettings] = None
        self._jit = jit
        # The particle filter's particles behind each kept mean (see adapters._ParticleModel).
        self._particle_states = {}
        self._fusion: Optional[Fusion] = None
        self._apply(settings.validated())

    def _apply(self, settings: EstimatorSettings) -> None:
        """Install validated settings and everything derived from them."""
        config: Configuration = configure(settings, self.settings, self._particle_states,
                                          self.fast_path, self._jit)
        # Everything is checked: install it.
        self._config = config
        self.settings, self.preset, self.model = settings, config.preset, config.model
        self.initial_state = config.initial_state
        self.nominal_period_s, self.horizon_s = config.nominal_period_s, config.horizon_s
        if self._fusion is None:
            self._fusion = Fusion(config, self.preset.dim_u)
        else:
            self._fusion.configure(config)

    # -- what it knows -----------------------------------------------------------

    @property
    def initialized(self) -> bool:
        """Return whether a measurement has been fused since start or reset."""
        return self._fusion.x is not None

    @property
    def last_stamp_ns(self) -> Optional[int]:
        """Return the stamp of the newest fused measurement, or None."""
        return self._fusion.last_stamp_ns

    @property
    def state(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """Return a copy of (x, P), or None before the first measurement."""
        if self._fusion.x is None:
            return None
        return self._fusion.x.copy(), self._fusion.P.copy()

    def mode_probabilities(self) -> Optional[Tuple[Tuple[str, ...], np.ndarray]]:
        """
        Return (mode names, probabilities) of the current state, or None.

        For the rail preset (an IMM): its regimes (stand, accelerate, cruise, brake)
        and their probabilities after the newest fused measurement (a new array,
        summing to 1). None for the other presets, and before the first measurement.
        """
        fusion = self._fusion
        if fusion.x is None:
            return None
        probabilities = self.model.mode_probabilities(fusion.x, fusion.P)
        return None if probabilities is None else (self.model.mode_names, probabilities)

    def noise_scale(self) -> Optional[float]:
        """
        Return the learned scale s on the measurement noise (R = s · the variance given).

        For the rail preset, which learns it from its innovations (``noise_window``,
        :mod:`kf_train.filters.noise_adaptation`); None for the other presets, and
        before the first measurement.
        """
        fusion = self._fusion
        return None if fusion.x is None else self.model.noise_scale(fusion.x, fusion.P)

    def error_walk_rate_hz(self) -> Optional[float]:
        """
        Return c, the learned rate of the measured position's error walk [1/s].

        For the rail preset (``error_walk_rate_hz``, :mod:`kf_train.filters.error_walk`);
        None for the other presets, and before the first measurement.
        """
        fusion = self._fusion
        return None if fusion.x is None else self.model.error_walk_rate_hz(fusion.x, fusion.P)

    def receiver_error_variance_m2(self) -> float:
        """
        Return B, the variance of the receiver's slow error that no fix reveals [m²].

        The rail preset's ``absolute_error_scale`` times the variance given with the
        newest fused position (0 for the other presets, whose fixes' errors are white,
        and before the first). The filter's P describes the track in the fixes' own
        frame, which a receiver's slow error moves with it: P is the band against later
        fixes, P + B (position entry) the band about the truth (:meth:`absolute`).
        """
        return self._config.absolute_error_scale * self._fusion.last_variance_m2

    def absolute_covariance(self, P: np.ndarray) -> np.ndarray:
        """Return a copy of a covariance of this estimator's state with B on P_pp."""
        P = np.array(P, dtype=float)
        P[0, 0] += self.receiver_error_variance_m2()
        return P

    def absolute(self, step: EstimateStep) -> EstimateStep:
        """Return ``step`` with B (:meth:`receiver_error_variance_m2`) on both P_pp."""
        if self.receiver_error_variance_m2() == 0.0:
            return step
        return step._replace(P=self.absolute_covariance(step.P),
                             predicted_P=self.absolute_covariance(step.predicted_P))

    def predict_to(self, stamp_ns: int) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return (x, P) predicted from the newest state to ``stamp_ns``; nothing changes.

        ``stamp_ns`` must not be before the newest fused stamp. It is the model's own
        look-ahead (the published prediction's: the rail IMM's mixture, the particle
        filter's exact moments), holding the newest interval's control. Raises
        ValueError before the first measurement.
        """
        fusion = self._fusion
        stamp_ns = check_stamp(stamp_ns)
        if fusion.x is None:
            raise ValueError('no state yet: nothing has been fused since start or reset')
        if stamp_ns < fusion.last_stamp_ns:
            raise ValueError(f'stamp_ns {stamp_ns} is before the newest fused stamp '
                             f'{fusion.last_stamp_ns}')
        dt_s = (stamp_ns - fusion.last_stamp_ns) / NS_PER_S
        predict = self._config.predict_ahead
        if fusion.controls is None:
            x, P = predict(fusion.x, fusion.P, dt_s)
        else:
            u = fusion.controls.for_interval_ending(fusion.last_stamp_ns)[0]
            x, P = predict(fusion.x, fusion.P, dt_s, u)
        return x.copy(), P.copy()

    @property
    def gate_threshold(self) -> float:
        """Return the NIS above which a measurement is an outlier (inf: no gate)."""
        return self._config.gate_threshold

    @property
    def has_control(self) -> bool:
        """Return whether the preset has a control input (see add_control)."""
        return self._fusion.controls is not None

    @property
    def _history(self) -> History:
        """Return the states kept for out-of-sequence replay (for the tests' snapshots)."""
        return self._fusion.history

    def stats(self) -> EstimatorStats:
        """Return what the estimator has done since construction (a snapshot)."""
        fusion = self._fusion
        return fusion.counters.snapshot(
            len(fusion.history), 0 if fusion.controls is None else len(fusion.controls))

    def measurement_noise(self, variance_m2: float,
                          velocity_variance_m2s2: Optional[float] = None) -> np.ndarray:
        """Return the R (m, m) a message's variances are fused with (the overrides applied)."""
        return measurement_noise(self.settings, variance_m2, velocity_variance_m2s2)

    def measurement_variance(self, message_variance_m2: float) -> float:
        """Return R of the position: the override when set, else the message's variance."""
        return override_variance(self.settings.measurement_variance, message_variance_m2)

    def variance_in_use(self, message_variance_m2: float) -> float:
        """Return the R a position of this variance is weighed with now (the scale learned)."""
        scale = self.noise_scale()
        return self.measurement_variance(message_variance_m2) * (1.0 if scale is None else scale)

    def velocity_variance(self, message_variance_m2s2: float) -> float:
        """Return R of a measured velocity: the override when set, else the message's."""
        return override_variance(self.settings.measurement_velocity_variance,
                                 message_variance_m2s2)

    # -- what changes it -----------------------------------------------------------

    def reconfigure(self, settings: EstimatorSettings) -> None:
        """
        Use new settings from the next measurement on; the current state is kept.

        Initial state, covariance and initialisation mode matter again only at the
        next (re)initialisation. Measurements already fused keep the model and R they
        were fused with when they are replayed. The preset cannot change.
        """
        self._apply(settings.validated())

    def reset(self, reason: str = 'manual') -> None:
        """Forget the state; the next measurement initialises the filter again."""
        if reason not in RESET_REASONS:
            raise ValueError(f'reason must be one of {RESET_REASONS}, got {reason!r}')
        self._fusion.reset(reason)

    def set_state(self, stamp_ns: int, x, P) -> None:
        """
        Replace the state with (x, P) valid at ``stamp_ns``; on ValueError nothing changes.

        Counted as a ``set_state`` reset: the history is dropped, and measurements
        older than ``stamp_ns`` are then stale.
        """
        if (not isinstance(stamp_ns, (int, np.integer)) or isinstance(stamp_ns, bool)
                or stamp_ns <= 0):
            raise ValueError(f'stamp_ns must be a positive integer, got {stamp_ns!r}')
        x = as_vector('x', x, self.model.dim_x)
        P = as_covariance('P', P, self.model.dim_x)
        self._fusion.set_state(int(stamp_ns), x, P)

    def process(self, stamp_ns: int, position_m: float, variance_m2: float, *,
                frame_id: Optional[str] = None, now_ns: Optional[int] = None,
                velocity_mps: Optional[float] = None,
                velocity_variance_m2s2: Optional[float] = None) -> EstimateStep:
        """
        Fuse one measurement; on ValueError the estimator state is unchanged.

        ``frame_id`` is checked against ``expected_frame_id`` when both are given;
        ``now_ns`` (the receiver's clock; None or 0 when unknown) bounds future stamps.
        ``velocity_mps`` and its variance are required exactly when the preset
        measures the velocity. Raises :class:`Rejected` for a measurement that breaks
        the input contract, a plain ValueError for a stamp that is not an integer or
        a velocity given to (or missing for) the wrong preset.
        """
        stamp_ns = check_stamp(stamp_ns)
        try:
            z, R = check_measurement(
                self.settings, self.model, self.preset.name, self._config.max_future_ns,
                stamp_ns, position_m, variance_m2, frame_id, now_ns, velocity_mps,
                velocity_variance_m2s2)
        except Rejected as rejection:
            self._fusion.counters.rejections[rejection.reason] += 1
            raise
        return self._fusion.measure(stamp_ns, z, R)

    @property
    def fuses_velocity(self) -> bool:
        """Return whether the preset fuses a separate speed (process_velocity: rail)."""
        return self._config.velocity_model is not None

    def process_velocity(self, stamp_ns: int, velocity_mps: float, variance_m2s2: float, *,
                         now_ns: Optional[int] = None) -> EstimateStep:
        """
        Fuse one measured speed along the track [m/s] (a Doppler); on ValueError nothing changes.

        The rail preset only (:attr:`fuses_velocity`; a plain ValueError for the others):
        its IMM is corrected by the speed (H = e_1, R = ``variance_m2s2`` [m²/s²], or
        ``measurement_velocity_variance`` when set; the learned scale on R is the
        position's and is not applied). The input contract is :meth:`process`'s:
        :class:`Rejected` with a reason from
        :data:`~kf_train.estimator.contract.VELOCITY_REJECTION_REASONS` (counted in
        ``stats().velocity_rejections``, never toward the positions' lock-out or
        restart), the χ² gate on the speed's own NIS, out-of-sequence fusion within
        ``history_s``. A speed stamped like a position is fused after it (dt = 0),
        whichever came first; a speed before the first position is ``no_state``.
        """
        if self._config.velocity_model is None:
            raise ValueError(f'preset {self.preset.name!r} does not fuse a separate speed '
                             'measurement (the rail preset does)')
        stamp_ns = check_stamp(stamp_ns)
        try:
            z, R = check_velocity(self.settings, self._config.max_future_ns, stamp_ns,
                                  velocity_mps, variance_m2s2, now_ns)
        except Rejected as rejection:
            self._fusion.counters.velocity_rejections[rejection.reason] += 1
            raise
        return self._fusion.measure_velocity(stamp_ns, z, R)

    def add_control(self, stamp_ns: int, u, *, now_ns: Optional[int] = None
                    ) -> Optional[EstimateStep]:
        """
        Take the control applied over the interval that ends at ``stamp_ns``.

        Returns the corrected estimate when the control changed fused estimates (it
        came after a measurement that needed it; see the module docs), else None. On
        :class:`Rejected` (``CONTROL_REJECTION_REASONS``) nothing changes; a plain
        ValueError for a preset without control input, a stamp that is not an integer
        or a control of the wrong size.
        """
        if self._fusion.controls is None:
            raise ValueError(f'preset {self.preset.name!r} has no control input')
        stamp_ns = check_stamp(stamp_ns)
        try:
            u = check_control(self.preset, self._config.max_future_ns,
                              self.settings.max_future_s, stamp_ns, u, now_ns)
        except Rejected as rejection:
            self._fusion.counters.control_rejections[rejection.reason] += 1
            raise
        return self._fusion.control(stamp_ns, u)
