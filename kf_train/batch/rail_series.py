"""
The rail preset offline: its IMM as a filter of the family, started by the first measurement.

``kf-train replay --preset rail`` (and ``compare``, ``plot``) run the rail preset's IMM
(:class:`~kf_train.filters.RailModel`, docs/rail.md) row by row through the same
loop as ``--filter`` (:func:`kf_train.batch.series.filter_rows`, streamed or in
memory). :class:`RailSeriesFilter` has the interface that loop uses (predict,
update, predict_ahead, mean, covariance, reset, snapshot, restore) and starts as the
streaming estimator's default does (``initialization: first_measurement``): the
first row's position sets the position with variance R, the other states keep the
preset's initial state and covariance (its priors), every regime equally likely;
predictions before that row change nothing. So a replay of a CSV gives the
estimates :class:`~kf_train.estimator.StreamEstimator` (preset rail, no gate)
gives for the same stamps, bit for bit. (The seeds' "initial estimate at t0" would
pin a train at position 0 ± 1 m; a train's first fix is anywhere on the line.)

With measured speeds (``z_velocity`` and its variance ``var_z_velocity`` in the input:
the preset :meth:`~kf_train.presets.RailPreset.with_speed`), a row's speed corrects the
IMM after its position (a prediction over dt = 0, then
:meth:`~kf_train.filters.RailModel.update_velocity`: R as given, the learned scale
untouched), as the streaming estimator's ``process_velocity`` does for the same
stamp; either cell may be empty (a fix without a speed, a speed without a fix), and a
speed before the first position is skipped (no state to correct yet).

No χ² gate offline (as for every preset in ``replay``), and no RTS smoother: an IMM
is a mixture, not one linear-Gaussian model. Rows before an object's first measurement (empty
cells, ``updated`` 0) carry the preset's prior unchanged, position 0 included: there
is no estimate yet, and those rows say nothing about where the train is.
"""

import math
from typing import Dict, Optional, Tuple

from kf_train.filters import (
    as_covariance, as_duration, as_vector, IMMFilter, regime_columns, UpdateResult)
from kf_train.presets import RailPreset, SPEED_VARIANCE_COLUMN
import numpy as np


class RailSeriesFilter:
    """
    The rail IMM holding its state, started by its first update; see the module docs.

    The running state is an :class:`~kf_train.filters.IMMFilter` (the one holder of a
    running IMM state), made at the first measurement; before it, the preset's prior.
    """

    kind = 'imm'

    def __init__(self, preset: RailPreset):
        """Build the preset's IMM; the filter waits for its first measurement."""
        self.preset = preset
        self.partial_rows = preset.speed
        """Rows may have empty (NaN) cells, each skipped here (the speed preset's)."""
        self.imm = preset.model()
        self.R = preset.R
        self._prior: Tuple[np.ndarray, np.ndarray] = (preset.initial_state,
                                                      preset.initial_covariance)
        self._running: Optional[IMMFilter] = None
        self.position_nis = math.nan
        """The NIS of the last update's position (NaN: it fused none, or started the filter)."""

    @property
    def mode_names(self) -> Tuple[str, ...]:
        """Return the regimes: stand, accelerate, cruise, brake."""
        return self.imm.mode_names

    @property
    def mode_probabilities(self) -> np.ndarray:
        """Return the regime probabilities (equal before the first measurement)."""
        if self._running is None:
            return np.full(self.imm.mode_count, 1.0 / self.imm.mode_count)
        return self._running.mode_probabilities

    @property
    def mean(self) -> np.ndarray:
        """Return the mixture's x (the prior's before the first measurement)."""
        if self._running is None:
            return self._prior[0].copy()
        return self._running.mean

    @property
    def covariance(self) -> np.ndarray:
        """Return the mixture's P (the prior's before the first measurement)."""
        if self._running is None:
            return self._prior[1].copy()
        return self._running.covariance

    def reset(self, x0=None, P0=None) -> None:
        """Wait for a first measurement again, with priors (x0, P0) (the preset's)."""
        n = self.preset.dim_x
        x0 = as_vector('x0', self.preset.initial_state if x0 is None else x0, n).copy()
        P0 = as_covariance('P0', self.preset.initial_covariance if P0 is None else P0, n)
        self._prior = (x0, P0.copy())
        self._running = None
        self.position_nis = math.nan

    def predict(self, dt_s: float, u=None) -> None:
        """Propagate over dt_s (nothing to propagate before the first measurement)."""
        if u is not None:
            raise ValueError(f'preset {self.preset.name!r} has no control input')
        dt_s = as_duration('dt_s', dt_s)
        if self._running is not None:
            self._running.predict(dt_s)

    def update(self, z, R=None) -> Optional[UpdateResult]:
        """
        Correct with position z; the first one starts the filter (returns None then).

        With speeds z is (position, speed, its variance), NaN where a cell was empty:
        the position first, then the speed (the speed's result is returned).
        """
        self.position_nis = math.nan
        if not self.preset.speed:
            return self._update_position(as_vector('z', z, 1), R)
        position, speed, variance = np.asarray(z, dtype=float).reshape(3).tolist()
        result = None
        if not math.isnan(position):
            result = self._update_position(np.array([position]), R)
        if not math.isnan(speed) and self._running is not None:
            if not variance > 0.0 or math.isinf(variance):
                raise ValueError(f'a speed needs a finite variance > 0 (column '
                                 f'{SPEED_VARIANCE_COLUMN}), got {variance}')
            # After a prediction over dt = 0, as the streaming estimator fuses a speed
            # stamped like its position (it brings the stand regime to v = 0 right
            # after the first position; later it changes nothing).
            self._running.predict(0.0)
            state, result = self.imm.update_velocity(self._running.state, speed, variance)
            self._running.restore(state)
        return result

    def _update_position(self, z: np.ndarray, R) -> Optional[UpdateResult]:
        """Correct with a checked position z (1,); the first one starts the filter."""
        R = self.R if R is None else as_covariance('R', R, 1)
        if self._running is None:
            # first_measurement: position from z with variance R, the rest the priors'.
            x, P = self._prior[0].copy(), self._prior[1].copy()
            x[0] = z[0]
            P[0, :] = 0.0
            P[:, 0] = 0.0
            P[0, 0] = R[0, 0]
            self._running = IMMFilter(self.imm, x, P)
            return None
        result = self._running.update(z, R)
        self.position_nis = result.nis
        return result

    def predict_ahead(self, dt_s: float, u=None) -> Tuple[np.ndarray, np.ndarray]:
        """Return the mixture dt_s ahead (no regime reverses); the filter is unchanged."""
        if u is not None:
            raise ValueError(f'preset {self.preset.name!r} has no control input')
        if self._running is not None:
            return self._running.predict_ahead(dt_s)
        return self.imm.predict_ahead(self.imm.initial_state(*self._prior), dt_s)

    def snapshot(self) -> tuple:
        """Return the whole state (immutable parts: keeping it is enough)."""
        return (self._prior, None if self._running is None else self._running.snapshot())

    def restore(self, snapshot: tuple) -> None:
        """Return to a snapshot of this filter."""
        self._prior, state = snapshot
        if state is None:
            self._running = None
        else:
            if self._running is None:
                self._running = IMMFilter(self.imm, state.means[0], state.covariances[0])
            self._running.restore(state)

    def copy(self) -> 'RailSeriesFilter':
        """Return an independent filter in the same state."""
        other = object.__new__(RailSeriesFilter)
        other.__dict__.update(self.__dict__)
        if self._running is not None:
            other._running = self._running.copy()
        return other

    def diagnostics(self) -> Dict[str, float]:
        """Return the regime probabilities by name (p_stand, ...)."""
        return {column: float(p)
                for column, p in zip(regime_columns(self.mode_names), self.mode_probabilities)}
