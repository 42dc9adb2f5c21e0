"""
The estimator's state machine on checked inputs: fuse, rewind, replay, reset.

:class:`Fusion` keeps the newest state (x, P at the last fused stamp), the history
for out-of-sequence fusion (:mod:`~kf_train.estimator.history`), the controls
(:mod:`~kf_train.estimator.controls`) and the counts. Its inputs have passed the
contract (:mod:`~kf_train.estimator.contract`): integer stamps, finite measurements
as (z, R) arrays, read-only control vectors. It applies the policy: the χ² gate, the
lock-out after consecutive rejections, the stream restart after consecutive stale
stamps. Every rejection is counted and raised as :class:`Rejected`, with the state
exactly as before unless the rejection itself reset the filter.
"""

from typing import List, Optional, Tuple

from kf_train.estimator.contract import (
    Counters, EstimateStep, NUMERICAL_ERRORS, Rejected)
from kf_train.estimator.controls import Controls, propagate, prune_controls
from kf_train.estimator.history import (
    Entry, History, initial_state, is_speed, replay, replay_control, rewind_point)
from kf_train.estimator.reacquire import consistent_group, fit_line, jump_covariance
from kf_train.estimator.receiver_rules import held_standstill, repeated_epoch
from kf_train.estimator.settings import Configuration
from kf_train.filters import NS_PER_S, UpdateResult
import numpy as np


class _Reacquire(Exception):
    """A lock-out that keeps the track: raised by the gate, caught by the in-order fusion."""


class _Held(Exception):
    """A held position fused as a standstill: raised with (x, P, predicted, z, R)."""


class Fusion:
    """The fused state of one stream, and the ways a measurement or control changes it."""

    def __init__(self, config: Configuration, dim_u: int):
        """Start uninitialised with ``config``; controls of ``dim_u`` components (0: none)."""
        self.x: Optional[np.ndarray] = None
        self.P: Optional[np.ndarray] = None
        self.last_stamp_ns: Optional[int] = None
        self.history = History()
        self.consecutive_outliers = 0
        self.stale_streak = 0
        self.locked_out = False
        # The fixes rejected in a row (stamp, z, R), and after a lock-out the group the
        # next measurement re-initialises with (kf_train.estimator.reacquire).
        self.rejected: List[Tuple[int, np.ndarray, np.ndarray]] = []
        self.regroup: List[Tuple[int, np.ndarray, np.ndarray]] = []
        self.counters = Counters()
        self.last_z: Optional[np.ndarray] = None
        """The newest fused position (read-only): its exact repeat may be a repeated epoch."""
        self.last_variance_m2 = 0.0
        """The variance given with the newest fused position (R[0, 0]; 0 before one)."""
        self.newest_is_velocity = False
        """Whether the newest fused step is a speed (a position of its stamp goes before it)."""
        self.configure(config)
        self.controls: Optional[Controls] = Controls(dim_u) if dim_u else None

    def configure(self, config: Configuration) -> None:
        """Use ``config`` from now on (the state is kept; history_s 0 drops the history)."""
        self.config = config
        self.history.window_ns = config.history_ns
        if config.history_ns == 0:
            self.history.clear()

    def reset(self, reason: str) -> None:
        """Forget the state; the next measurement initialises the filter again."""
        self.x = self.P = self.last_z = None
        self.last_variance_m2 = 0.0
        self.newest_is_velocity = False
        self.last_stamp_ns = None
        self.history.clear()
        self.consecutive_outliers = 0
        self.stale_streak = 0
        self.locked_out = reason == 'outlier_lockout'
        self.regroup = self.rejected if self.locked_out else []
        self.rejected = []
        if reason in ('clock_jump', 'stream_restart') and self.controls is not None:
            self.controls.clear()  # stamped on the old time line
        self.counters.resets[reason] += 1

    def set_state(self, stamp_ns: int, x: np.ndarray, P: np.ndarray) -> None:
        """Replace the state with checked (x, P) at ``stamp_ns`` (a ``set_state`` reset)."""
        self.reset('set_state')
        self.x, self.P, self.last_stamp_ns = x, P, stamp_ns
        self.history.append(Entry(stamp_ns, None, None, self.config.model, x, P, 'set'))

    def measure(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Fuse a checked measurement: initialise, in order, out of sequence, or stale."""
        newest = self.last_stamp_ns
        if self.x is None:
            return self._initialise(stamp_ns, z, R)
        if stamp_ns > newest:
            return self._fuse_in_order(stamp_ns, z, R)
        if stamp_ns == newest and self.newest_is_velocity:
            # The speed of this stamp came first: the position goes before it.
            if self.history:
                return self._fuse_out_of_sequence(stamp_ns, z, R)
            return self._fuse_in_order(stamp_ns, z, R)  # no history: after it, dt = 0
        if stamp_ns == newest:
            self._reject('duplicate_stamp', f'measurement stamp {stamp_ns} ns is not newer than '
                         f'the last fused one, {newest} ns (a duplicate)')
        if newest - stamp_ns < self.history.window_ns:
            return self._fuse_out_of_sequence(stamp_ns, z, R)
        return self._stale(stamp_ns, z, R)

    def measure_velocity(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """
        Fuse a checked speed measurement: in order, out of sequence, or reject it.

        A speed never initialises the filter (``no_state``), is gated on its own NIS,
        and at a position's stamp is fused after it (dt = 0). Its rejections are
        counted apart and never count toward the positions' lock-out or restart.
        """
        if self.x is None:
            self._reject_velocity('no_state', 'a speed needs a state: no position has been '
                                  'fused since start or reset')
        newest = self.last_stamp_ns
        if stamp_ns > newest or (stamp_ns == newest and not self.newest_is_velocity):
            x, P, result, predicted = self._gated_velocity(
                self.x, self.P, newest, stamp_ns, z, R)
            self.x, self.P, self.last_stamp_ns = x, P, stamp_ns
            self.newest_is_velocity = True
            self.history.commit(Entry(stamp_ns, z, R, self.config.velocity_model, x, P,
                                      'update', True))
            self.counters.velocities_fused += 1
            return self._step(stamp_ns, x, P, result, predicted, stamp_ns)
        if stamp_ns == newest:
            self._reject_velocity('duplicate_stamp', f'velocity stamp {stamp_ns} ns is not '
                                  f'newer than the last fused speed, {newest} ns')
        if not self.history or newest - stamp_ns >= self.history.window_ns:
            self._reject_velocity('stale_stamp', (
                f'velocity stamp {stamp_ns} ns is {(newest - stamp_ns) / NS_PER_S:.6f} s '
                f'older than the newest fused one, beyond history_s = '
                f'{self.config.settings.history_s}'))
        return self._velocity_out_of_sequence(stamp_ns, z, R)

    def _reject_velocity(self, reason: str, message: str,
                         update: Optional[UpdateResult] = None) -> None:
        """Count a speed's rejection and raise it (nothing else changes)."""
        self.counters.velocity_rejections[reason] += 1
        raise Rejected(reason, message, None, update)

    def _gated_velocity(self, x0, P0, t_a: int, t_b: int, z: np.ndarray, R: np.ndarray):
        """Return (x, P, result, prediction ahead) after a speed, or reject it."""
        try:
            x, P, result = self.config.velocity_model.predict_update(
                x0, P0, (t_b - t_a) / NS_PER_S, z, R)
        except NUMERICAL_ERRORS as error:
            self._reject_velocity('numerical', f'velocity update failed: {error}')
        if result.nis > self.config.gate_threshold:
            self._reject_velocity('outlier', (
                f'velocity NIS {result.nis:.6g} exceeds the gate '
                f'{self.config.gate_threshold:.6g}; innovation {result.innovation[0]:.6g} '
                'm/s'), result)
        try:
            predicted = self._predict_ahead(x, P)
        except NUMERICAL_ERRORS as error:
            self._reject_velocity('numerical', f'prediction failed: {error}')
        return x, P, result, predicted

    def _velocity_out_of_sequence(self, stamp_ns: int, z: np.ndarray,
                                  R: np.ndarray) -> EstimateStep:
        """Rewind to the last state before a speed's stamp, fuse it, replay the later ones."""
        entries = self.history.entries()
        try:
            i = rewind_point(entries, stamp_ns, self.last_stamp_ns, velocity=True)
        except Rejected as rejection:
            self.counters.velocity_rejections[rejection.reason] += 1
            raise
        anchor = entries[i - 1]
        x, P, result, _ = self._gated_velocity(anchor.x, anchor.P, anchor.stamp_ns, stamp_ns,
                                               z, R)
        rebuilt = entries[:i] + [Entry(stamp_ns, z, R, self.config.velocity_model, x, P,
                                       'update', True)]
        try:
            rebuilt, x, P, _ = replay(rebuilt, entries[i:], None, self.controls)
            predicted = self._predict_ahead(x, P)
        except NUMERICAL_ERRORS as error:
            self._reject_velocity('numerical', f'replay failed: {error}')
        self.history.replace(rebuilt)
        self.x, self.P = x, P
        self.newest_is_velocity = is_speed(rebuilt[-1])
        self.counters.velocities_fused += 1
        self.counters.velocities_out_of_sequence += 1
        return self._step(self.last_stamp_ns, x, P, result, predicted, stamp_ns,
                          replayed=len(entries) - i)

    def control(self, stamp_ns: int, u: np.ndarray) -> Optional[EstimateStep]:
        """Take a checked control; return the corrected estimate if fused ones changed."""
        newest = self.last_stamp_ns
        if self.x is None or (not self.history and stamp_ns > newest):
            self.controls.put(stamp_ns, u)
            return self._accept_control()
        if not self.history:
            self._reject_control('stale_stamp', (
                f'control stamp {stamp_ns} ns is not newer than the last fused measurement, '
                f'{newest} ns, and no state is kept to replay from (history_s = 0)'))
        return self._late_control(stamp_ns, u)

    def _reject(self, reason: str, message: str, reset: Optional[str] = None,
                update: Optional[UpdateResult] = None) -> None:
        """Count a rejection and raise it."""
        self.counters.rejections[reason] += 1
        raise Rejected(reason, message, reset, update)

    def _reject_control(self, reason: str, message: str) -> None:
        """Count a control rejection and raise it."""
        self.counters.control_rejections[reason] += 1
        raise Rejected(reason, message)

    def _reject_update(self, reason: str, message: str,
                       update: Optional[UpdateResult] = None, fix: Optional[tuple] = None,
                       in_order: bool = False) -> None:
        """
        Reject an outlier, a repeated epoch or a numerical failure; enough in a row lock out.

        ``fix`` (stamp, z, R) is the rejected measurement. The lock-out needs the last
        ``max_consecutive_outliers`` rejected fixes to be one consistent group
        (:func:`~kf_train.estimator.reacquire.consistent_group`): scattered gross
        fixes are rejected and the track coasts on. A group of outliers, the last one
        in order, re-acquires the track (``lockout`` reacquire: raises _Reacquire for
        :meth:`_fuse_in_order`); otherwise the track is reset and restarts from the group.
        """
        self.consecutive_outliers += 1
        needed = self.config.settings.max_consecutive_outliers
        if fix is not None:
            self.rejected = (self.rejected + [fix])[-needed:]
        reset = None
        if self.consecutive_outliers >= needed and self._group_agrees():
            if (in_order and reason in ('outlier', 'repeated') and len(self.rejected) >= 2
                    and self.controls is None and self.config.settings.lockout == 'reacquire'):
                raise _Reacquire()
            reset = 'outlier_lockout'
            message += (f'; {self.consecutive_outliers} consecutive rejections that agree '
                        'with each other: filter reset, the next measurement initialises '
                        'it with them')
            self.reset(reset)
        self._reject(reason, message, reset, update)

    def _group_agrees(self) -> bool:
        """Return whether the fixes rejected in a row agree with each other (or are few)."""
        group = self.rejected
        return consistent_group([stamp for stamp, _, _ in group],
                                [float(z[0]) for _, z, _ in group],
                                [float(R[0, 0]) for _, _, R in group],
                                self.config.settings.gate_probability)

    def _reacquire(self) -> EstimateStep:
        """
        Keep the track through a lock-out: widen it by the group's jump, fuse the group.

        The rejected fixes (the last one is this measurement) agree on a line; the track
        at the last fused stamp is widened by the jump between its prediction and that
        line (:func:`~kf_train.estimator.reacquire.jump_covariance`), then each fix is
        fused in order, never gated. A speed input fused while the group was rejected
        has moved the track past the group's first fixes: those shape the line, and the
        fixes from the track's stamp on are fused. Nothing rewinds past the widening (it
        is kept as a 'reinit' entry). Should that fail numerically, the track is reset.
        """
        group = sorted(self.rejected, key=lambda fix: fix[0])
        anchor_ns, model = self.last_stamp_ns, self.config.model
        stamps = [stamp for stamp, _, _ in group]
        try:
            line = fit_line(stamps, [float(z[0]) for _, z, _ in group],
                            [float(R[0, 0]) for _, _, R in group])
            predicted_x, _ = model.predict_ahead(self.x, self.P,
                                                 (stamps[-1] - anchor_ns) / NS_PER_S)
            jump = jump_covariance(model.state_names, predicted_x, line)
            if jump is None or not np.all(np.isfinite(jump)):
                raise FloatingPointError('no finite jump between the track and the group')
            widened = x, P = model.widen(self.x, self.P, jump)
            fused = []
            if group[-1][0] < anchor_ns:
                raise ValueError('the group is older than the track (speeds fused since)')
            for stamp_ns, z, R in (fix for fix in group if fix[0] >= anchor_ns):
                x, P, result = model.predict_update(x, P, (stamp_ns - anchor_ns) / NS_PER_S,
                                                    z, R)
                fused.append((stamp_ns, z, R, x, P, result))
                anchor_ns = stamp_ns
            predicted = self._predict_ahead(x, P)
        except NUMERICAL_ERRORS as error:
            self.reset('outlier_lockout')
            self._reject('numerical', f're-acquisition failed ({error}): filter reset, the '
                         'next measurement initialises it with the rejected fixes',
                         'outlier_lockout')
        self.history.clear()
        self.history.commit(Entry(self.last_stamp_ns, None, None, model, *widened, 'reinit'))
        for stamp_ns, z, R, x, P, result in fused:
            self._commit(stamp_ns, x, P, 'update', z, R)
        # The group's earlier fixes stay counted as rejected; this one is fused.
        self.counters.fused -= len(fused) - 1
        self.counters.reacquisitions += 1
        return self._step(stamp_ns, x, P, result, predicted, stamp_ns)

    def _late_control(self, stamp_ns: int, u: np.ndarray) -> Optional[EstimateStep]:
        """Keep a control for fused intervals: rewind to before it and replay."""
        try:
            outcome = replay_control(self.config, self.controls, self.history.entries(),
                                     self.locked_out, stamp_ns, u, self._predict_ahead)
        except Rejected as rejection:
            self.counters.control_rejections[rejection.reason] += 1
            raise
        if outcome.entries is None:
            if outcome.prune:
                return self._accept_control()
            self.counters.controls_accepted += 1
            return None
        self.history.replace(outcome.entries)
        self.x, self.P = outcome.x, outcome.P
        self.counters.controls_late += 1
        self._accept_control()
        newest = self.last_stamp_ns
        return EstimateStep(stamp_ns=newest, x=outcome.x.copy(), P=outcome.P.copy(),
                            update=None, prediction_stamp_ns=newest + self.config.horizon_ns,
                            predicted_x=outcome.predicted[0],
                            predicted_P=outcome.predicted[1], replayed=outcome.replayed,
                            control_stamp_ns=stamp_ns)

    def _accept_control(self) -> None:
        """Count an accepted control; forget controls no longer needed. Return None."""
        self.counters.controls_accepted += 1
        self._prune_controls()

    def _prune_controls(self) -> None:
        """Forget controls no replay or prediction can need any more."""
        prune_controls(self.controls, self.history, self.last_stamp_ns,
                       self.config.nominal_ns)

    def _stale(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Reject a stale measurement, or restart from it after enough in a row."""
        self.stale_streak += 1
        if self.stale_streak >= self.config.settings.restart_after_stale:
            self.reset('stream_restart')
            return self._initialise(stamp_ns, z, R)._replace(reset='stream_restart')
        newest = self.last_stamp_ns
        self._reject('stale_stamp', (
            f'measurement stamp {stamp_ns} ns is not newer than the last fused one, '
            f'{newest} ns, and {(newest - stamp_ns) / NS_PER_S:.6f} s older: beyond '
            f'history_s = {self.config.settings.history_s}'))

    def _init_state(self, stamp_ns: int, z: np.ndarray, R: np.ndarray, model):
        """Return (x, P, update result or None, u, exact) of the filter initialised by z."""
        return initial_state(self.config, self.controls, self.locked_out, stamp_ns, z, R,
                             model)

    def _initialise(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Start the filter from this measurement (never gated), or from its group."""
        group = [fix for fix in self.regroup if fix[0] < stamp_ns]
        self.regroup = []
        if group:
            try:
                return self._initialise_group(group + [(stamp_ns, z, R)])
            except Rejected:
                self.history.clear()  # the group failed numerically: start from this one
                self.x = self.P = self.last_stamp_ns = None
                self.locked_out = True
        try:
            x, P, result, u, exact = self._init_state(stamp_ns, z, R, self.config.model)
            predicted = self._predict_ahead(x, P, u)
        except NUMERICAL_ERRORS as error:
            self._reject('numerical', f'initialisation failed: {error}')
        self.history.clear()
        # After a lock-out the state starts from the measurement: no rewinding past it.
        self._commit(stamp_ns, x, P, 'reinit' if self.locked_out else 'init', z, R)
        self.counters.provisional += result is not None and not exact
        self.locked_out = False
        return self._step(stamp_ns, x, P, result, predicted, stamp_ns)

    def _initialise_group(self, group: List[tuple]) -> EstimateStep:
        """Re-initialise from the fixes of a lock-out and this one: the first, then the rest."""
        first, *rest = group
        step = self._initialise(*first)
        model = self.config.model
        for stamp_ns, z, R in rest:  # never gated: they agreed with each other
            try:
                x, P, result = model.predict_update(
                    self.x, self.P, (stamp_ns - self.last_stamp_ns) / NS_PER_S, z, R)
                predicted = self._predict_ahead(x, P)
            except NUMERICAL_ERRORS as error:
                self._reject('numerical', f're-initialisation failed: {error}')
            self._commit(stamp_ns, x, P, 'update', z, R)
            step = self._step(stamp_ns, x, P, result, predicted, stamp_ns)
        self.counters.fused -= len(rest)  # the group's own fixes were counted as rejected
        return step

    def _fuse_in_order(self, stamp_ns: int, z: np.ndarray, R: np.ndarray) -> EstimateStep:
        """Predict from the newest state to the stamp, gate, update, commit."""
        try:
            x, P, result, predicted, exact = self._gated_update(
                self.x, self.P, self.last_stamp_ns, stamp_ns, z, R, in_order=True)
        except _Reacquire:
            return self._reacquire()
        except _Held as held:
            return self._commit_hold(stamp_ns, *held.args)
        self._commit(stamp_ns, x, P, 'update', z, R)
        self.counters.provisional += not exact
        return self._step(stamp_ns, x, P, result, predicted, stamp_ns)

    def _hold(self, x0: np.ndarray, P0: np.ndarray, dt_s: float, R: np.ndarray) -> None:
        """Raise _Held if the repeat is a held position (receiver_rules.held_standstill)."""
        held = held_standstill(self.config, x0, P0, dt_s, R)
        if held is not None:
            try:
                predicted = self._predict_ahead(held[0], held[1])
            except NUMERICAL_ERRORS:
                return
            raise _Held(held[0], held[1], predicted, held[2], held[3])

    def _commit_hold(self, stamp_ns: int, x, P, predicted, z, R) -> EstimateStep:
        """
        Make the state after a hold the newest, kept as a speed entry; count it.

        Its step has no update: no position was measured anew, so no innovation is
        published or enters the NIS window (a speed's is not the position's).
        """
        self.x, self.P, self.last_stamp_ns = x, P, stamp_ns
        self.newest_is_velocity = False   # it stands for this stamp's position
        self.history.commit(Entry(stamp_ns, z, R, self.config.velocity_model, x, P,
                                  'hold', True))
        self._after_fusion()
        self.counters.holds += 1        # last_z stays the held position, for the next
        return self._step(stamp_ns, x, P, None, predicted, stamp_ns)

    def _gated_update(self, x0, P0, t_a: int, t_b: int, z: np.ndarray, R: np.ndarray,
                      in_order: bool = False):
        """Return (x, P, result, prediction ahead, exact) or reject as outlier/numerical."""
        model = self.config.model
        try:
            if self.controls is None:
                # Every model's one call (StepModel.predict_update): the rail IMM's
                # fused step, predict then update for the others.
                x, P, result = model.predict_update(x0, P0, (t_b - t_a) / NS_PER_S, z, R)
                u, exact = None, True
            else:  # the prediction split at the control stamps (controls.propagate)
                x, P, u, exact = propagate(self.controls, model, x0, P0, t_a, t_b)
                x, P, result = model.update(x, P, z, R)
        except NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'update failed: {error}', fix=(t_b, z, R))
        threshold = self.config.gate_threshold
        # One float comparison first: np.array_equal costs ~3 µs, on every fix.
        if in_order and result.gate_nis is not None and self.last_z is not None and \
                z[0] == self.last_z[0]:
            self._reject_repeat(x0, P0, (t_b - t_a) / NS_PER_S, t_b, z, R, result)
            if np.array_equal(z, self.last_z):
                self._hold(x0, P0, (t_b - t_a) / NS_PER_S, R)
        nis = result.nis if result.gate_nis is None else result.gate_nis
        if nis > threshold:
            self._reject_update('outlier', (
                f'NIS {nis:.6g} exceeds the gate {threshold:.6g} '
                f'(gate_probability {self.config.settings.gate_probability}); innovation '
                f'{np.array2string(result.innovation, precision=6)}'), result, (t_b, z, R),
                in_order)
        try:
            predicted = self._predict_ahead(x, P, u)
        except NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'prediction failed: {error}')
        return x, P, result, predicted, exact

    def _reject_repeat(self, x0: np.ndarray, P0: np.ndarray, dt_s: float, stamp_ns: int,
                       z: np.ndarray, R: np.ndarray, result: UpdateResult) -> None:
        """Reject an exact repeat of the newest position as a repeated epoch (receiver_rules)."""
        if not np.array_equal(z, self.last_z):
            return
        why = repeated_epoch(self.config, x0, P0, dt_s, R, result)
        if why is not None:
            self._reject_update('repeated', (
                f'the last fused position again, {np.array2string(z, precision=6)}, though '
                f'the track moved {np.array2string(-result.innovation, precision=6)} from '
                f'it ({why}): a repeated epoch'), result, (stamp_ns, z, R), in_order=True)

    def _fuse_newest_position(self, stamp_ns: int, z: np.ndarray, R: np.ndarray,
                              entries: list, i: int) -> EstimateStep:
        """
        Fuse a position late only behind speeds: in order from entries[i - 1], then those.

        A receiver's driver may publish an epoch's velocity before its fix, or a fix may
        come late behind the next epoch's speed. It is still the newest position, so the
        rules of an in-order fix apply to it (the repeated epoch, the held position, the
        lock-out's re-acquisition, the newest position kept); the speeds after it are
        then fused again, in the order :func:`~kf_train.estimator.history.rewind_point`
        gives (at one stamp the position first).
        """
        anchor = entries[i - 1]
        try:
            x, P, result, _, exact = self._gated_update(
                anchor.x, anchor.P, anchor.stamp_ns, stamp_ns, z, R, in_order=True)
            entry = Entry(stamp_ns, z, R, self.config.model, x, P, 'update')
        except _Reacquire:
            return self._reacquire()
        except _Held as held:
            x, P, _, held_z, held_R = held.args
            entry, result, exact = Entry(stamp_ns, held_z, held_R, self.config.velocity_model,
                                         x, P, 'hold', True), None, True
        x, P, predicted = self._replayed(entries, i, entry, None)
        if result is None:
            self.counters.holds += 1    # last_z stays the held position, as in order
        else:
            self.last_z, self.last_variance_m2 = z, float(R[0, 0])
        self.counters.provisional += not exact
        return self._step(self.last_stamp_ns, x, P, result, predicted, stamp_ns,
                          replayed=len(entries) - i)

    def _fuse_out_of_sequence(self, stamp_ns: int, z: np.ndarray,
                              R: np.ndarray) -> EstimateStep:
        """Rewind to the last state before stamp_ns, fuse, replay the later ones."""
        entries = self.history.entries()
        try:
            i = rewind_point(entries, stamp_ns, self.last_stamp_ns)
        except Rejected as rejection:
            self.counters.rejections[rejection.reason] += 1
            raise
        if i > 0 and all(is_speed(entry) for entry in entries[i:]):
            return self._fuse_newest_position(stamp_ns, z, R, entries, i)
        if i == 0:
            # Older than the initialising measurement: in order, this one would have
            # initialised the filter and the old first one been an update.
            try:
                x, P, result, u, exact = self._init_state(stamp_ns, z, R, self.config.model)
            except NUMERICAL_ERRORS as error:
                self._reject('numerical', f'initialisation failed: {error}')
            kind = 'init'
        else:
            anchor = entries[i - 1]
            x, P, result, _, exact = self._gated_update(
                anchor.x, anchor.P, anchor.stamp_ns, stamp_ns, z, R)
            u = None
            kind = 'update'
        # entries[i:] is never empty here: the newest fused stamp is later.
        x, P, predicted = self._replayed(
            entries, i, Entry(stamp_ns, z, R, self.config.model, x, P, kind), u)
        self.counters.provisional += result is not None and not exact
        return self._step(self.last_stamp_ns, x, P, result, predicted, stamp_ns,
                          replayed=len(entries) - i)

    def _replayed(self, entries: list, i: int, entry: Entry, u) -> tuple:
        """Put ``entry`` at entries[i], replay the later ones, keep it all; (x, P, ahead)."""
        try:
            rebuilt, x, P, u = replay(entries[:i] + [entry], entries[i:], u, self.controls)
            predicted = self._predict_ahead(x, P, u)
        except NUMERICAL_ERRORS as error:
            self._reject_update('numerical', f'replay failed: {error}')
        self.history.replace(rebuilt)
        self.x, self.P = x, P
        self._after_fusion()
        self.counters.out_of_sequence += 1
        return x, P, predicted

    def _predict_ahead(self, x: np.ndarray, P: np.ndarray, u=None
                       ) -> Tuple[np.ndarray, np.ndarray]:
        """Return the state horizon_s after (x, P), holding the control u."""
        predict = self.config.predict_ahead
        if self.controls is None:
            return predict(x, P, self.config.horizon_s)
        return predict(x, P, self.config.horizon_s, u)

    def _commit(self, stamp_ns: int, x: np.ndarray, P: np.ndarray, kind: str,
                z: np.ndarray, R: np.ndarray) -> None:
        """Make (x, P) at stamp_ns the newest state and keep it for replay."""
        self.x, self.P, self.last_stamp_ns, self.last_z = x, P, stamp_ns, z
        self.last_variance_m2 = float(R[0, 0])
        self.newest_is_velocity = False
        self.history.commit(Entry(stamp_ns, z, R, self.config.model, x, P, kind))
        self._after_fusion()
        if self.controls is not None:
            self._prune_controls()

    def _after_fusion(self) -> None:
        """Count a fused measurement; it ends any run of outliers or stale stamps."""
        self.counters.fused += 1
        self.consecutive_outliers = 0
        self.stale_streak = 0
        self.rejected = []

    def _step(self, stamp_ns: int, x: np.ndarray, P: np.ndarray,
              result: Optional[UpdateResult], predicted, measurement_stamp_ns: int,
              replayed: int = 0) -> EstimateStep:
        """Return the public EstimateStep (copies of the kept arrays)."""
        return EstimateStep(stamp_ns=stamp_ns, x=x.copy(), P=P.copy(), update=result,
                            prediction_stamp_ns=stamp_ns + self.config.horizon_ns,
                            predicted_x=predicted[0], predicted_P=predicted[1],
                            measurement_stamp_ns=measurement_stamp_ns, replayed=replayed)
