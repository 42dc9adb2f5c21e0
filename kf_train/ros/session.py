"""
What the estimator node does with its input, without rclpy: one code path, live or replayed.

An :class:`EstimatorSession` holds the node's streaming estimator, its counters, its
NIS window and its logging rules. The node (:mod:`kf_train.ros.estimator_node`) hands
it every measurement, control, reset and set-state request with the node clock, and
publishes what it returns; ``kf-train replay BAG`` hands it the bag's messages in
recorded order with the record time as the clock, and writes what it returns. So a
replay gives exactly what the live node publishes, rejections, out-of-sequence fusion,
corrected re-publishes after a late control, clock-jump and non-finite resets included.

Returned outputs (:class:`Outputs`): the estimate step to publish (estimate at
``step.stamp_ns`` with ``step.x``/``step.P``, prediction at
``step.prediction_stamp_ns``), or None; and the innovation record (stamp, update),
or None. The arrays may be the estimator's own: use them before the next call.

Time: ``now_ns`` (the node clock, or the record time) is the clock of the future-stamp
check and of the clock-jump reset (0: a simulated clock that has not started; no
check). ``monotonic_s`` (a callable, seconds) times the warning throttle and the
diagnostics' rates and ages: :func:`time.monotonic` live, the record time in a replay.
"""

import collections
import math
from typing import Callable, List, NamedTuple, Optional

from kf_train.estimator import NS_PER_S, Rejected, StreamEstimator
from kf_train.ros.diagnostics import (
    Activity, filter_status, FilterStatus, NodeCounts, with_noise_suggestion)
from kf_train.ros.estimator_params import changed_config, EstimatorConfig, NOISE_AND_GATE
from kf_train.ros.noise_advice import NoiseAdvisor
from kf_train.ros.track_input import TrackInput
import numpy as np

WARN_THROTTLE_S = 5.0
"""A rejection reason is logged at most once per this many seconds."""

Log = Callable[[str, str], None]
"""log(level, text), level 'info' or 'warning'."""


class Measurement(NamedTuple):
    """A position (and, for Odometry presets, velocity) measurement as the session takes it."""

    stamp_ns: int
    frame_id: str
    position_m: float
    variance_m2: float
    velocity_mps: float = math.nan
    velocity_variance_m2s2: float = math.nan


class Outputs(NamedTuple):
    """What one input makes the node publish."""

    step: Optional[object] = None
    """An EstimateStep to publish as estimate and prediction, or None."""
    innovation_stamp_ns: int = 0
    update: Optional[object] = None
    """The gate decision's update record (innovation, S, NIS) to publish, or None."""


NOTHING = Outputs()


def _quiet(level: str, text: str) -> None:
    """Log nothing."""


class EstimatorSession:
    """The estimator node's behaviour on its inputs (see the module doc)."""

    def __init__(self, config: EstimatorConfig, monotonic_s: Callable[[], float],
                 log: Log = _quiet):
        """Build the estimator of ``config``; ValueError if the settings are invalid."""
        self.config = config
        self.estimator = StreamEstimator(config.settings)
        self.preset = self.estimator.preset
        self.measures_velocity = self.preset.measurement_names == ('position', 'velocity')
        self.fuses_velocity = (self.estimator.fuses_velocity
                               and config.options.velocity_type != 'none')
        """Whether the node subscribes ``velocity`` (rail, velocity_type not none)."""
        self.track = (TrackInput(config.values, self.measures_velocity)
                      if config.options.measurement_type == 'navsatfix' else None)
        """The NavSatFix input (kf_train.ros.track_input), or None: poses."""
        self._monotonic_s = monotonic_s
        self._log = log
        self.received = self.fused = self.rejected = 0
        self.corrections = 0
        """Estimates republished because a late control changed them."""
        self.controls_received = self.controls_rejected = 0
        self.velocities_received = self.velocities_fused = self.velocities_rejected = 0
        self.set_state_refused = 0
        self.innovations = 0
        self.nis = collections.deque(maxlen=config.options.nis_window)
        self.timed_out = False
        self._warned = {}
        self._start_mono = self._tick_mono = monotonic_s()
        self._last_fused_mono = None
        self._received_at_tick = self._fused_at_tick = 0
        self._last_clock_ns = 0
        self.noise = self._noise_advisor()

    # -- configuration ------------------------------------------------------------------

    def apply_changes(self, changes: dict) -> EstimatorConfig:
        """Apply a validated runtime parameter change; return the old configuration."""
        old = self.config
        self.config = changed_config(old, changes)
        if self.config.settings != old.settings:
            self.estimator.reconfigure(self.config.settings)
        if self.config.options.nis_window != old.options.nis_window:
            self.nis = collections.deque(self.nis, maxlen=self.config.options.nis_window)
        if NOISE_AND_GATE & changes.keys():
            self.nis.clear()  # the old NIS values judged the old tuning
        if {'measurement_variance', 'measurement_velocity_variance'} & changes.keys():
            self.noise.invalidate()   # the suggestion is for the R the node uses
        if {'noise_suggestion_window', 'first_velocity_std_mps'} & changes.keys():
            self.noise = self._noise_advisor()
        return old

    def _noise_advisor(self) -> NoiseAdvisor:
        """Return an empty advisor for the suggested q (kf_train.ros.noise_advice)."""
        return NoiseAdvisor(self.preset, self.config.options.noise_suggestion_window,
                            self.config.settings.first_velocity_std_mps)

    # -- inputs -------------------------------------------------------------------------

    def on_measurement(self, measurement, now_ns: int) -> Outputs:
        """Fuse one measurement; return what to publish."""
        self.received += 1
        stamp_ns = measurement.stamp_ns
        now_ns = self.check_clock(now_ns)
        try:
            if self.measures_velocity:
                step = self.estimator.process(
                    stamp_ns, measurement.position_m, measurement.variance_m2,
                    frame_id=measurement.frame_id, now_ns=now_ns,
                    velocity_mps=measurement.velocity_mps,
                    velocity_variance_m2s2=measurement.velocity_variance_m2s2)
            else:  # a replay's hot path: no keyword dictionary built per message
                step = self.estimator.process(
                    stamp_ns, measurement.position_m, measurement.variance_m2,
                    frame_id=measurement.frame_id, now_ns=now_ns)
        except Rejected as rejection:
            self.rejected += 1
            self._warn_rejection(rejection.reason, str(rejection))
            outputs = NOTHING
            if rejection.update is not None:
                self.innovations += 1
                outputs = Outputs(None, stamp_ns, rejection.update)
            if rejection.reset is not None:
                self._after_reset(rejection.reset, str(rejection))
            return outputs
        if step.reset is not None:
            self._after_reset(step.reset, f'measurement at {stamp_ns} ns initialises it')
        if not self._publishable(step):
            return NOTHING
        self.fused += 1
        self._last_fused_mono = self._monotonic_s()
        if self.noise.active:
            self._add_to_noise_window(stamp_ns, measurement)
        if step.update is None:
            return Outputs(self._referenced(step))
        self.innovations += 1
        self.nis.append(step.update.nis)
        return Outputs(self._referenced(step), step.measurement_stamp_ns, step.update)

    def on_fix(self, fix, now_ns: int) -> List[Outputs]:
        """Project a NavSatFix (track_input.Fix) onto the track; fuse what it releases."""
        return [self.on_measurement(measurement, now_ns)
                for measurement in self.track.measurements(fix)]

    def _add_to_noise_window(self, stamp_ns: int, measurement) -> None:
        """Give the suggested-q window a fused measurement and its message's variances."""
        if self.measures_velocity:
            self.noise.add(stamp_ns, (measurement.position_m, measurement.velocity_mps),
                           (measurement.variance_m2, measurement.velocity_variance_m2s2))
        else:
            self.noise.add(stamp_ns, (measurement.position_m,), (measurement.variance_m2,))

    def _node_variances(self, message_variances) -> tuple:
        """Return the variances of the estimator's R for a message's (the one override rule)."""
        return tuple(self.estimator.measurement_noise(*message_variances).diagonal().tolist())

    def on_velocity(self, velocity, now_ns: int) -> Outputs:
        """
        Fuse one measured speed (``stamp_ns``, ``velocity_mps``, ``variance_m2s2``).

        The variance is the message's (``measurement_velocity_variance`` overrides it
        when > 0), or that parameter for a TwistStamped (``velocity_type`` twist). The
        estimate it corrects is published; its innovation is not (``innovation`` is the
        position's), nor does it enter the NIS window.
        """
        self.velocities_received += 1
        now_ns = self.check_clock(now_ns)
        variance = velocity.variance_m2s2
        if self.config.options.velocity_type == 'twist':
            variance = self.config.settings.measurement_velocity_variance
        try:
            step = self.estimator.process_velocity(velocity.stamp_ns, velocity.velocity_mps,
                                                   variance, now_ns=now_ns)
        except Rejected as rejection:
            self.velocities_rejected += 1
            self._warn_rejection('velocity.' + rejection.reason, str(rejection), 'velocity')
            return NOTHING
        if not self._publishable(step):
            return NOTHING
        self.velocities_fused += 1
        return Outputs(self._referenced(step))

    def on_control(self, control, now_ns: int) -> Outputs:
        """Take one control (``stamp_ns``, ``value``); the corrected estimate if it changed."""
        self.controls_received += 1
        now_ns = self.check_clock(now_ns)
        try:
            step = self.estimator.add_control(control.stamp_ns, [control.value], now_ns=now_ns)
        except Rejected as rejection:
            self.controls_rejected += 1
            self._warn_rejection('control.' + rejection.reason, str(rejection), 'control')
            return NOTHING
        self.noise.add_control((control.value,))
        if step is not None and self._publishable(step):
            self.corrections += 1
            return Outputs(self._referenced(step))
        return NOTHING

    def reset(self, reason: str = 'manual', detail: str = 'requested through ~/reset') -> None:
        """Forget the state (``~/reset``); the next measurement initialises the filter."""
        self.estimator.reset(reason)
        self._after_reset(reason, detail)

    def set_state(self, stamp_ns: int, frame_id: str, x, P, now_ns: int) -> bool:
        """Handle ``~/set_state`` (stamp 0: the newest fused stamp, or now); False if refused."""
        try:
            if frame_id and frame_id != self.config.options.frame_id:
                raise ValueError(f'frame_id {frame_id!r} is not '
                                 f'{self.config.options.frame_id!r}')
            stamp_ns = stamp_ns or self.estimator.last_stamp_ns or now_ns
            n = self.preset.dim_x  # the robot's state is the position alone
            self.estimator.set_state(stamp_ns, x[:n], [row[:n] for row in P[:n]])
        except ValueError as error:
            self.set_state_refused += 1
            self._log('warning', f'~/set_state refused: {error}')
            return False
        self._after_reset('set_state', f'x = {x} at {stamp_ns} ns')
        return True

    def check_clock(self, now_ns: int) -> int:
        """Return ``now_ns``; reset on a backwards jump of the clock (0: not started)."""
        if now_ns == 0:
            return 0  # a simulated clock that has not started yet
        last, self._last_clock_ns = self._last_clock_ns, now_ns
        if now_ns < last:
            jump = f'node clock jumped back {(last - now_ns) / NS_PER_S:.3f} s'
            if not self.config.options.reset_on_clock_jump:
                self._log('warning', f'{jump}; not resetting (reset_on_clock_jump false)')
            elif self.estimator.initialized:
                self.reset('clock_jump', jump)
            else:
                self._log('info', jump)
        return now_ns

    # -- diagnostics --------------------------------------------------------------------

    def diagnostics(self, now_ns: int) -> FilterStatus:
        """Return the ``/diagnostics`` status now; log once when measurements stop/resume."""
        self.check_clock(now_ns)
        now = self._monotonic_s()
        elapsed = max(now - self._tick_mono, 1e-9)
        since = self._last_fused_mono if self._last_fused_mono is not None else self._start_mono
        activity = Activity((self.received - self._received_at_tick) / elapsed,
                            (self.fused - self._fused_at_tick) / elapsed, now - since,
                            self._last_fused_mono is not None)
        self._tick_mono, self._received_at_tick, self._fused_at_tick = (
            now, self.received, self.fused)
        counts = NodeCounts(self.received, self.fused, self.rejected, self.set_state_refused,
                            self.controls_received, self.controls_rejected)
        status = filter_status(self.estimator, counts, activity,
                               self.config.options.timeout_s, self.nis)
        status = with_noise_suggestion(status, self.noise.suggestion(self._node_variances),
                                       self.config.settings.process_noise_density,
                                       self.noise.span_s)
        if self.track is not None:
            status = status._replace(values=list(status.values) + self.track.values())
        if status.timeout_warning is not None and not self.timed_out:
            self._log('warning', status.timeout_warning)
            self.timed_out = True
        elif status.timeout_warning is None and self.timed_out:
            self._log('info', 'measurements are being fused again')
            self.timed_out = False
        return status

    def newest_stamp_now_ns(self) -> Optional[int]:
        """Return the newest fused stamp plus the time since it was fused (None: none)."""
        if self._last_fused_mono is None or self.estimator.last_stamp_ns is None:
            return None
        age_s = max(self._monotonic_s() - self._last_fused_mono, 0.0)
        return self.estimator.last_stamp_ns + round(age_s * NS_PER_S)

    # -- helpers ------------------------------------------------------------------------

    def _publishable(self, step) -> bool:
        """Return True if the step is finite; else reset (nothing non-finite leaves)."""
        # One test for all four: 0·v is 0 for every finite v, NaN for NaN and ±inf.
        if not 0.0 * (sum(step.x.tolist()) + sum(step.P.ravel().tolist())
                      + sum(step.predicted_x.tolist())
                      + sum(step.predicted_P.ravel().tolist())) == 0.0 and not (
                np.isfinite(step.x).all() and np.isfinite(step.P).all()
                and np.isfinite(step.predicted_x).all()
                and np.isfinite(step.predicted_P).all()):
            # The core never produces this; if it ever did, nothing non-finite leaves.
            self.reset('non_finite', 'a non-finite state was not published')
            return False
        return True

    def _referenced(self, step):
        """Return the step with the covariances ``covariance_reference`` asks for."""
        if self.config.options.covariance_reference == 'absolute':
            return self.estimator.absolute(step)      # about the truth: + B on P_pp
        return step

    def _warn_rejection(self, reason: str, text: str, what: str = 'measurement') -> None:
        """Log a rejection, at most once per WARN_THROTTLE_S for each reason."""
        now = self._monotonic_s()
        last, suppressed = self._warned.get(reason, (-math.inf, 0))
        if now - last < WARN_THROTTLE_S:
            self._warned[reason] = (last, suppressed + 1)
            return
        more = f' ({suppressed} more since the last such warning)' if suppressed else ''
        self._log('warning', f'{what} rejected ({reason}): {text}{more}')
        self._warned[reason] = (now, 0)

    def _after_reset(self, reason: str, detail: str) -> None:
        """Log a reset the estimator went through and restart the NIS window."""
        self.nis.clear()
        self.noise.clear()
        text = f'filter reset ({reason}): {detail}'
        self._log('info' if reason in ('manual', 'set_state') else 'warning', text)
