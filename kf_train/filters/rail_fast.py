"""
The rail IMM compiled: :class:`FastRailModel`, the same model in one call per step.

:class:`~kf_train.filters.rail_model.RailModel` is the readable reference: its step
costs about 125 numpy calls on 4 x 6 x 6 stacks, and numpy's overhead per call, not the
arithmetic, is what it costs (docs/performance.md). :class:`FastRailModel` is a
RailModel whose public IMM methods (``predict``, ``update``, ``update_component``,
``predict_ahead``, ``estimate``) run the arithmetic as numba-compiled loops
(:mod:`kf_train.filters.rail_kernels`): the same equations, the Joseph form, the
state's -> stand rates, the entry rule's own gather tables, the held velocities. All
that is not array arithmetic is the reference's own code, called as it is: F(dt) and
Q(dt) (:meth:`RailModel.matrices`), the learned measurement noise and the gate's NIS
(:meth:`~kf_train.filters.imm.IMM.finish_update`), the no-reversal hold
(:meth:`RailModel.hold_paths`), the checks of inputs. The tests hold it to the reference
to rounding (relative 1e-9) on random regimes, dts, rewinds and speed updates.
A live step is one compiled call: :meth:`FastRailModel.predict_update` also combines
the new state and predicts it as far ahead as the last :meth:`~FastRailModel.predict_ahead`
asked (the estimator's horizon), by the kernels those methods run, and hands both out
once to the next :meth:`~FastRailModel.estimate` and ``predict_ahead`` of that state.

numba is the optional ``jit`` extra, and the compiled model is opt-in:
:func:`rail_model` gives it when numba is installed and the environment variable
:data:`JIT_VARIABLE` is ``1``, the reference otherwise (importing numba and loading the
kernels costs a process ~0.9 s of start-up and ~125 MiB: docs/performance.md); either
way live and replayed runs of one process take one path, so they stay equal to the bit.
A caller may choose for itself (``jit``: ``kf-train tune``'s held-out scoring runs it
whenever numba is installed, :mod:`kf_train.tune.validation`).
The first use compiles the kernels (seconds) and caches them on disk (numba's
``cache=True``, beside the module or in numba's cache folder); a later process loads them
(docs/performance.md). :meth:`FastRailModel.warm_up` does both at once (``make
jit-cache``, before the tests: a node's first fix should not compile).
"""

import importlib
import importlib.util
import os
from typing import Dict, Optional, Tuple

from kf_train.filters import imm_stack
from kf_train.filters.imm import _measurement, _noise_row, _read_only, IMMState, noise_in_use
from kf_train.filters.kalman import UpdateResult
from kf_train.filters.rail_dynamics import (
    _PHI2_SERIES, _PHI3_SERIES, _SERIES_BELOW, RelaxationNoise, STAND_TRANSITION)
from kf_train.filters.rail_model import RailModel, RailModelParameters, STOPPING
import numpy as np

JIT_VARIABLE = 'KF_TRAIN_JIT'
"""Set to ``1`` to run the compiled model where numba is installed (opt-in)."""
_KEPT = 64

_ERRORS = {1: '{} produced a non-finite state; inputs are too large',
           2: 'innovation covariance S = H P Hᵀ + R is singular in {}',
           3: '{} produced an invalid NIS',
           4: 'prediction produced a non-finite state; inputs are too large'}


def numba_available() -> bool:
    """Return whether numba is installed (the ``jit`` extra)."""
    return importlib.util.find_spec('numba') is not None


def jit_enabled() -> bool:
    """Return whether :func:`rail_model` compiles: KF_TRAIN_JIT=1 and numba installed."""
    return os.environ.get(JIT_VARIABLE, '').strip() == '1' and numba_available()


def rail_model(parameters: RailModelParameters = RailModelParameters(),
               jit: Optional[bool] = None) -> RailModel:
    """Return the rail IMM: compiled if ``jit`` (default: :func:`jit_enabled`), else numpy."""
    if jit if jit is not None else jit_enabled():
        return FastRailModel(parameters)
    return RailModel(parameters)


def _raise(status: int, step: str) -> None:
    """Raise the ValueError a kernel's status code stands for (0: none)."""
    if status:
        raise ValueError(_ERRORS[status].format(step))


class FastRailModel(RailModel):
    """The rail IMM with its array arithmetic compiled; see the module docstring."""

    def __init__(self, parameters: RailModelParameters = RailModelParameters()):
        """Build the regimes from ``parameters`` and load (or compile) the kernels."""
        super().__init__(parameters)
        self.kernels = importlib.import_module('kf_train.filters.rail_kernels')
        stack = self._stack
        if stack is None or stack.selected is None or np.any(stack.R != stack.R[0]):
            raise ValueError('the compiled rail model needs regimes measuring one state '
                             'with one R')
        rates = parameters.rates()                    # the rates' diagonal is 0
        stopping = np.array([regime in STOPPING for regime in range(self.mode_count)])
        gather = self.entry_rule
        self._constants = (rates, stopping, parameters.stop_rate_hz,
                           parameters.stop_speed_mps, gather.index_x, gather.factor_x,
                           gather.index_P, gather.factor_P, gather.noise_P)
        table, scale, powers, span = RelaxationNoise(
            parameters.response_time_s, parameters.acceleration_noise,
            parameters.command_noise).series
        self._series_dt_s = span * parameters.response_time_s
        self._dynamics_constants = (
            parameters.response_time_s, parameters.stand_noise, parameters.capability_noise,
            STAND_TRANSITION, _PHI2_SERIES, _PHI3_SERIES, _SERIES_BELOW, table, scale, powers)
        self._kept: Dict[float, Tuple[np.ndarray, np.ndarray]] = {}
        # What the last predict_update computed beyond its state (see predict_update):
        # (state, x, P) and (state, horizon, status, x, P), each handed out once.
        self._step_estimate: Optional[tuple] = None
        self._step_ahead: Optional[tuple] = None
        self._ahead_s: Optional[float] = None
        """The horizon of the last predict_ahead: the one a step computes ahead for."""
        # Typed as StopFinder.tables' grids (numba compiles one version): strided, read-only.
        no_grid = np.zeros((1, 4, 8))[:, :, ::2], np.zeros((1, 1, 4, 4))
        for array in no_grid:
            array.flags.writeable = False
        self._no_ahead = (0.0, 0.0) + no_grid

    def dynamics(self, dt_s: float) -> Tuple[np.ndarray, np.ndarray]:
        """
        Return the regimes' stacked F(dt_s), Q(dt_s): :meth:`matrices`', compiled up to 1.5 τ.

        A sensor with jittered stamps brings a new dt at every step: there, the numpy
        build of F and Q would cost more than the step. Kept for the last 64 dt values.
        """
        kept = self._kept.get(dt_s)
        if kept is None:
            if dt_s > self._series_dt_s:
                kept = self.matrices(dt_s)[:2]         # the quadrature's: the reference's
            else:
                count, n = self.mode_count, self._stack.dim_x
                kept = np.empty((count, n, n)), np.empty((count, n, n))
                self.kernels.dynamics(dt_s, *self._dynamics_constants, *kept)
                for array in kept:
                    array.flags.writeable = False
            if len(self._kept) >= _KEPT:
                self._kept.pop(next(iter(self._kept)))
            self._kept[dt_s] = kept
        return kept

    def predict(self, state: IMMState, dt_s: float, u=None) -> IMMState:
        """Return the state predicted over dt_s (IMM.predict, compiled)."""
        if u is not None:
            return super().predict(state, dt_s, u)
        dt_s = imm_stack.duration(dt_s)
        F, Q = self.dynamics(dt_s)
        walk = state.noise.walk_m2_per_s * dt_s                     # RailModel.predict's
        means, covs, probabilities = self._arrays()
        _raise(self.kernels.predict(state.means, state.covariances, state.probabilities, dt_s,
                                    F, Q, walk, *self._constants, means, covs, probabilities),
               'prediction')
        return IMMState(_read_only(means), _read_only(covs), _read_only(probabilities),
                        state.noise)

    def predict_update(self, state: IMMState, dt_s: float, z, R=None,
                       index: Optional[int] = None) -> Tuple[IMMState, UpdateResult]:
        """
        Return the update (of state ``index``) after the prediction: one compiled call.

        The same call (``rail_kernels.step``) combines the new state (for
        :meth:`estimate`) and predicts it as far ahead as the last :meth:`predict_ahead`
        asked: a live step's three calls in one. Both are kept for the new state and
        handed out once, by the kernels a separate call runs (the same numbers).
        """
        dt_s = imm_stack.duration(dt_s)
        z, reported, selected, learn = self._measurement(z, R, index)
        reported_m2 = float(reported[0])
        in_use_m2 = noise_in_use(reported_m2, state.noise, learn)
        F, Q = self.dynamics(dt_s)
        horizon_s, ahead_walk = self._ahead_s, 0.0
        if horizon_s is None:
            (ahead_F, ahead_Q), tables = (F, Q), self._no_ahead
        else:
            (ahead_F, ahead_Q), tables = self.dynamics(horizon_s), self.stop_finder.tables(
                horizon_s)
            # Ahead of the new state: the walk after this fix (ErrorWalk.walk_after,
            # known before the update); a speed leaves the last position fix's.
            ahead_walk = horizon_s * (self.error_walk.walk_after(state.noise, in_use_m2)
                                      if learn else state.noise.walk_m2_per_s)
        means, covs, posterior = self._arrays()
        n = self._stack.dim_x
        gain, x, P, ahead_x, ahead_P = (np.empty(n), np.empty(n), np.empty((n, n)),
                                        np.empty(n), np.empty((n, n)))
        y, S, nis, status, ahead_status = self.kernels.step(
            state.means, state.covariances, state.probabilities, dt_s, F, Q,
            state.noise.walk_m2_per_s * dt_s, *self._constants, z, selected, in_use_m2,
            ahead_F, ahead_Q, ahead_walk, self.stop_finder.tau_s, *tables, horizon_s is not None,
            means, covs, posterior, gain, x, P, ahead_x, ahead_P)
        _raise(status, 'update')
        updated, result = self.finish_update(state, means, covs, posterior,
                                             (y, S, nis, gain), reported_m2, learn)
        self._step_estimate = updated, x, P
        self._step_ahead = None if horizon_s is None else (
            updated, horizon_s, ahead_status, ahead_x, ahead_P)
        return updated, result

    def update(self, state: IMMState, z, R=None) -> Tuple[IMMState, UpdateResult]:
        """Return the state corrected by a position z, velocities held (compiled)."""
        return self._corrected(state, *self._measurement(z, R, None))

    def update_component(self, state: IMMState, z, R, index: int
                         ) -> Tuple[IMMState, UpdateResult]:
        """Return the state corrected by a measurement of state ``index`` (compiled)."""
        return self._corrected(state, *self._measurement(z, R, index))

    def _measurement(self, z, R, index: Optional[int]) -> Tuple[float, np.ndarray, int, bool]:
        """Return (z, R given, the state measured, whether R is learned), as IMM checks."""
        stack = self._stack
        if index is None:
            return _measurement(z), stack.R if R is None else _noise_row(R), stack.selected, True
        n = stack.dim_x
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < n:
            raise ValueError(f'index must be a state index in [0, {n - 1}], got {index!r}')
        if R is None:
            raise ValueError('R must be given when H is not the modes own measurement')
        return _measurement(z), _noise_row(R), index, False

    def _corrected(self, state: IMMState, z: float, reported: np.ndarray, index: int,
                   learn: bool) -> Tuple[IMMState, UpdateResult]:
        """Return the compiled update by z of state ``index`` (learn: the position's R)."""
        means, covs, posterior = self._arrays()
        gain = np.empty(self._stack.dim_x)
        y, S, nis, status = self.kernels.update(
            state.means, state.covariances, state.probabilities, z, index,
            float(noise_in_use(reported, state.noise, learn)[0]), means, covs, posterior, gain)
        _raise(status, 'update')
        return self.finish_update(state, means, covs, posterior, (y, S, nis, gain),
                                  float(reported[0]), learn)

    def estimate(self, state: IMMState) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) of a state (compiled; a step's own if it made it)."""
        kept = self._step_estimate
        if kept is not None and kept[0] is state:
            self._step_estimate = None
            return kept[1], kept[2]
        n = self._stack.dim_x
        x, P = np.empty(n), np.empty((n, n))
        self.kernels.combine(state.means, state.covariances, state.probabilities, x, P)
        return x, P

    def predict_ahead(self, state: IMMState, dt_s: float, u=None
                      ) -> Tuple[np.ndarray, np.ndarray]:
        """Return the combined (x, P) dt_s ahead, no regime going backwards (compiled)."""
        dt_s = imm_stack.duration(dt_s)
        if u is not None:
            raise ValueError('u given to a model without control input')
        self._ahead_s = dt_s
        kept = self._step_ahead
        if kept is not None and kept[0] is state and kept[1] == dt_s:
            self._step_ahead = None
            _raise(kept[2], 'prediction')
            return kept[3], kept[4]
        F, Q = self.dynamics(dt_s)
        stops = self.stop_finder
        n = self._stack.dim_x
        x, P = np.empty(n), np.empty((n, n))
        _raise(self.kernels.ahead(state.means, state.covariances, state.probabilities, F, Q,
                                  state.noise.walk_m2_per_s * dt_s, self._constants[1],
                                  stops.tau_s, *stops.tables(dt_s), x, P),
               'prediction')
        return x, P

    def warm_up(self) -> None:
        """Call every kernel once, so that numba compiles (first time) or loads them now."""
        state = self.first_estimate(0.0, 1.0)
        for dt_s in (0.1, 2.0):
            state = self.predict(state, dt_s)
            state = self.update(state, 0.5)[0]
            state = self.predict_update(state, dt_s, 0.5, None)[0]
            state = self.predict_update(state, dt_s, 0.1, [[0.01]], 1)[0]
            state = self.update_component(state, 0.1, [[0.01]], 1)[0]
            self.estimate(state)
            self.predict_ahead(state, dt_s)

    def _arrays(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return new (N, n), (N, n, n) and (N,) arrays for a kernel to write."""
        count, n = self.mode_count, self._stack.dim_x
        return np.empty((count, n)), np.empty((count, n, n)), np.empty(count)
