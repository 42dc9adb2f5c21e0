"""
Where a regime's mean path stops: the rail model's no-reversal prediction.

A moving regime's mean follows ṗ = v, v̇ = a, ȧ = (ℓ - a)/τ, ℓ̇ = 0 (its transition
F(t), :func:`kf_train.filters.rail_dynamics.relaxation_transition`). A train does not
reverse, so a prediction whose mean velocity reaches 0 within the horizon is held where
it stopped. The first root is bracketed on a 41-point grid over the horizon, then on a
41-point grid within the bracketing step (to horizon/1600), as the rail model always
did. The grids' transitions depend only on the horizon, so they are computed once per
horizon (and bracketing step) and kept: finding a stop costs two small matrix-vector
products instead of two evaluations of F on a grid.
"""

from typing import Callable, Dict, Tuple

import numpy as np

_GRID_POINTS = 41
# Horizons remembered (a live node asks for one); each keeps up to 41 grids.
_HORIZONS_KEPT = 4


class StopFinder:
    """The no-reversal hold of a mean path, for one response time τ."""

    def __init__(self, tau_s: float, transition: Callable[[np.ndarray, float], np.ndarray],
                 phi: Callable[[np.ndarray], Tuple[np.ndarray, np.ndarray, np.ndarray]]):
        """Keep τ, ``transition(t, τ) -> F(t) (k, 4, 4)`` and ``phi(x) -> (φ1, φ2, φ3)``."""
        self.tau_s = float(tau_s)
        self._transition = transition
        self._phi = phi
        self._grids: Dict[float, dict] = {}
        self._bounds: Dict[float, Tuple[float, float]] = {}
        self._tables: Dict[float, tuple] = {}

    def _grid(self, horizon_s: float, step: int) -> Tuple[np.ndarray, np.ndarray]:
        """Return (t, F(t)) of the first grid (step -1) or of its step-th step's grid."""
        grids = self._grids.get(horizon_s)
        if grids is None:
            if len(self._grids) >= _HORIZONS_KEPT:
                self._grids.pop(next(iter(self._grids)))
            grids = self._grids[horizon_s] = {}
        grid = grids.get(step)
        if grid is None:
            if step < 0:
                t = np.linspace(0.0, horizon_s, _GRID_POINTS)
            else:
                first = self._grid(horizon_s, -1)[0]
                t = np.linspace(first[step - 1], first[step], _GRID_POINTS)
            F = self._transition(t, self.tau_s)
            t.flags.writeable = F.flags.writeable = False
            grid = grids[step] = (t, F)
        return grid

    def _horizon_phi(self, horizon_s: float) -> Tuple[float, float]:
        """Return φ1(T/τ) and φ2(T/τ) for horizon T, remembered."""
        bound = self._bounds.get(horizon_s)
        if bound is None:
            phi1, phi2, _ = self._phi(np.array([horizon_s / self.tau_s]))
            bound = (float(phi1[0]), float(phi2[0]))
            if len(self._bounds) >= _HORIZONS_KEPT:
                self._bounds.pop(next(iter(self._bounds)))
            self._bounds[horizon_s] = bound
        return bound

    def tables(self, horizon_s: float) -> Tuple[float, float, np.ndarray, np.ndarray]:
        """
        Return (φ1(T/τ), φ2(T/τ), the first grid's F (41, 4, 4), every step's (41, 41, 4, 4)).

        What :meth:`hold` reads, all at once, for a compiled transcription of it
        (:mod:`kf_train.filters.rail_kernels`); the step grids' entry 0 is unused.
        """
        kept = self._tables.get(horizon_s)
        if kept is None:
            phi1, phi2 = self._horizon_phi(horizon_s)
            first = self._grid(horizon_s, -1)[1]
            steps = np.zeros((_GRID_POINTS,) + first.shape)
            for step in range(1, _GRID_POINTS):
                steps[step] = self._grid(horizon_s, step)[1]
            steps.flags.writeable = False
            if len(self._tables) >= _HORIZONS_KEPT:
                self._tables.pop(next(iter(self._tables)))
            kept = self._tables[horizon_s] = (phi1, phi2, first, steps)
        return kept

    def may_stop(self, start, horizon_s: float) -> bool:
        """
        Return False when the mean path from ``start`` surely never stops within horizon_s.

        ``start`` as for :meth:`hold`. The quick bound of :meth:`hold` alone, on plain
        floats: when it is False, :meth:`hold` returns its ``predicted`` unchanged.
        """
        _, v, a, command = start[:4]
        if v < 0.0:
            return True
        phi1, phi2 = self._horizon_phi(horizon_s)
        return not v + self.tau_s * (phi1 * min(a, 0.0) + phi2 * min(command, 0.0)) > 0.0

    def hold(self, start, predicted: np.ndarray, horizon_s: float) -> np.ndarray:
        """
        Return the predicted mean with the train held where its mean velocity reaches 0.

        The mean path from ``start`` (velocity clipped at 0) is v(t) = v + τφ1 a + τφ2 ℓ.
        If it reaches 0 within horizon_s, the first root is bracketed on a 40-step grid,
        then on a 40-step grid within that step (to horizon_s/1600), and the train
        stands from then on (v = a = 0) at the position it reached. ``start`` is the
        regime's current mean (an array, or its first four entries as a list of floats);
        ``predicted`` itself is returned when the path never stops.
        """
        p, v, a, command = start[:4] if type(start) is list else start[:4].tolist()
        if v >= 0.0:
            # φ1, φ2 grow with t, so v(t) >= v + τ φ1(T/τ) min(a, 0) + τ φ2(T/τ) min(ℓ, 0):
            # if that is positive the mean path never stops and the prediction stands.
            phi1, phi2 = self._horizon_phi(horizon_s)
            if v + self.tau_s * (phi1 * min(a, 0.0) + phi2 * min(command, 0.0)) > 0.0:
                return predicted
        state = np.array([p, max(v, 0.0), a, command])
        step = -1
        for _ in range(2):
            _, F = self._grid(horizon_s, step)
            path = np.matmul(F, state)                               # (41, 4) mean path
            below = np.flatnonzero(path[:, 1] <= 0.0)
            if below.size == 0:
                if v >= 0.0:
                    return predicted
                held = predicted.copy()  # started below 0: follow the clipped path
                held[:3] = path[-1, :3]
                return held
            first = int(below[0])
            stop = path[first]
            if first == 0:
                break  # standing with a <= 0 already: it stays where it is
            step = first
        held = predicted.copy()
        held[0], held[1], held[2] = max(float(stop[0]), p), 0.0, 0.0
        return held
