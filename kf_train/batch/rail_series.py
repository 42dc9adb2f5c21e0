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

No χ² gate offline (as for every preset in ``replay``), and no RTS smoother: an IMM
is a mixture, not one linear-Gaussian model. Rows before an object's first measurement (empty
cells, ``updated`` 0) carry the preset's prior unchanged, position 0 included: there
is no estimate yet, and those rows say nothing about where the train is.
"""

from typing import Dict, Optional, Tuple

from kf_train.filters import (
    as_covariance, as_duration, as_vector, IMMFilter, UpdateResult)
from kf_train.presets import RailPreset
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
        self.imm = preset.model()
        self.R = preset.R
        self._prior: Tuple[np.ndarray, np.ndarray] = (preset.initial_state,
                                                      preset.initial_covariance)
        self._running: Optional[IMMFilter] = None

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

    def predict(self, dt_s: float, u=None) -> None:
        """Propagate over dt_s (nothing to propagate before the first measurement)."""
        if u is not None:
            raise ValueError(f'preset {self.preset.name!r} has no control input')
        dt_s = as_duration('dt_s', dt_s)
        if self._running is not None:
            self._running.predict(dt_s)

    def update(self, z, R=None) -> Optional[UpdateResult]:
        """Correct with position z; the first one starts the filter (returns None then)."""
        z = as_vector('z', z, 1)
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
        return self._running.update(z, R)

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
        return {f'p_{name}': float(p)
                for name, p in zip(self.mode_names, self.mode_probabilities)}
