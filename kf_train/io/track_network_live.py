"""
The path on a network chosen live, fix by fix: along-track x on the path taken so far.

:class:`NetworkFixes` is :class:`kf_train.io.track_fixes.TrackFixes` (the no-fix rule,
the cross-track gate, the along-track variance, the counts) on a
:class:`kf_train.io.track_network.TrackNetwork` instead of one line. Its model is the
network's (states: an element and the direction it is run in; :func:`emission`,
:meth:`TrackNetwork.transition`), run forward as the fixes come: per fix one Viterbi
step keeps, for each state, the score of the best chain of states ending in it.

* **x on a chain.** Each state carries the x at which its own best chain entered its
  element; passing on to a later state adds the elements run between
  (:meth:`TrackNetwork.entry_offsets_m`), staying keeps it. A fix's x on a state is
  that plus its distance along the element, in the state's direction. So every
  hypothesis has its own x, continuous along its chain: passing onto the next element
  continues from the chained length, and changing to another hypothesis moves x only
  by what the two chains' geometries differ (parallel tracks: centimetres).
* **The published state** (whose x is fused, whose element the cross-track gate
  measures against) follows its own lineage: the best state whose chain came from it.
  It changes to a better chain only when that one leads by more than one fix can give
  (``emission(0) - emission(MATCH_CAP_M)``), so a lone gross fix near another track
  cannot move it; it still feeds the model (capped), as offline. A fix beyond the
  published element's exit end is measured on the nearest element reachable from it
  within MAX_HOPS (the model passes on only once the evidence has paid SWITCH_COST).
* **The start.** x is 0 at the first fix's projection, on every state's element.
  Both directions of an element fit a fix alike, so the fixes are held (and counted
  as pending) until they have run ``direction_min_m`` along the best state's element
  (the medians of :func:`kf_train.io.track_fixes.held_run_m`); then on every element
  the held fixes ran that far along, the state run against them is dropped, and the
  held fixes are released on the best chain, traced back. From then on x grows with
  the travel, the direction being part of the state. A train that reverses is not
  followed (no state turns back).
* **Cost.** A fix is measured only on the segments near it
  (:meth:`TrackNetwork.segments_near`: every one within NEAR_M, the cap of
  :func:`emission`); an element with none of them scores the cap, as when measured,
  and a fix farther than the gate can reach from every element it could be measured
  on is rejected unmeasured. While the direction is open, only the held fixes the run
  reads are projected (:func:`kf_train.io.track_fixes.held_run_ends`). All of it
  gives the same numbers to the bit as measuring every fix on every segment.
"""

from typing import Any, List, NamedTuple, Optional, Tuple

from kf_train.io.track import (
    polyline_segments, polyline_tangents, project_onto_segments)
from kf_train.io.track_fixes import (
    CROSS_TRACK_MAX_M, CROSS_TRACK_SIGMAS, DIRECTION_MIN_M, ends_run_m, held_run_ends, TrackFix,
    TrackFixes)
from kf_train.io.track_network import emission, MATCH_CAP_M, NEAR_M, TrackNetwork
import numpy as np

_END_M = 1e-6
"""A fix projected this close to an element's exit end is at it (rounding of arc lengths)."""


class _Held(NamedTuple):
    """A fix held while the direction is open, with the model's state at its time."""

    tag: Any
    points_m: np.ndarray
    covariance_en_m2: Optional[np.ndarray]
    x0_m: np.ndarray
    back: np.ndarray


class NetworkFixes(TrackFixes):
    """Fixes in, along-track measurements on the path chosen live out (see the module)."""

    def __init__(self, network: TrackNetwork, variance_m2: float,
                 cross_track_max_m: float = CROSS_TRACK_MAX_M,
                 cross_track_sigmas: float = CROSS_TRACK_SIGMAS,
                 direction_min_m: float = DIRECTION_MIN_M) -> None:
        """Set the network, the default variance [m²] of a fix and the gates (as TrackFixes)."""
        super().__init__(network.frame, variance_m2, cross_track_max_m, cross_track_sigmas,
                         'auto', direction_min_m)
        self.network = network
        self._into = np.ascontiguousarray(network.transition().T)
        """[to, from]: a state's row holds its predecessors (argmax along a row: faster)."""
        hops = network.hops()
        self._offsets_m = network.entry_offsets_m(hops)
        self._ahead = [np.flatnonzero(np.isfinite(row) & (row > 0)) for row in hops]
        keep = [np.concatenate(([True], np.any(np.diff(line, axis=0) != 0.0, axis=1)))
                for line in network.lines_m]
        self._vertices_m = [line[k] for line, k in zip(network.lines_m, keep)]
        self._segments = [polyline_segments(v) for v in self._vertices_m]
        self._arc_m = [segments.arc for segments in self._segments]
        self._first_segment = np.cumsum([0] + [len(v) - 1 for v in self._vertices_m])
        # Per state: the segment ranges of its element and of those ahead (_surely_off).
        self._reach = [np.array([self._first_segment[[e, e + 1]] for e in
                                 np.concatenate(([s // 2], self._ahead[s] // 2))]).T
                       for s in range(2 * len(self._vertices_m))]
        swing = emission(np.array([[0.0, MATCH_CAP_M]]))[0]
        self.switch_margin = float(swing[0] - swing[2])
        """How far another chain must lead the published one to replace it (one fix's most)."""
        self._score: Optional[np.ndarray] = None
        self._x0_m = np.zeros(0)
        self._published: Optional[int] = None
        self._held: List[_Held] = []

    @property
    def element(self) -> Optional[Tuple[str, bool]]:
        """Return the published state: (element id, run reversed), or None before the start."""
        if self._published is None:
            return None
        return self.network.ids[self._published // 2], bool(self._published % 2)

    def _on_state(self, state: int, points_m: np.ndarray, near: Optional[np.ndarray] = None
                  ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (along, cross, tangent) of points on a state's element, in its direction."""
        e, reverse = divmod(state, 2)
        s_m, cross_m = self._project(e, points_m, near)
        tangent = polyline_tangents(self._vertices_m[e], self._arc_m[e], s_m)
        if reverse:
            return self._arc_m[e][-1] - s_m, -cross_m, -tangent
        return s_m, cross_m, tangent

    def _project(self, e: int, points_m: np.ndarray, near: Optional[np.ndarray]
                 ) -> Tuple[np.ndarray, np.ndarray]:
        """Return (s, cross) of points on element e, as drawn (near: segments_near, or None)."""
        if near is not None:
            # On the element's segments near the fix only, when the nearest is among them:
            # every one left out is farther than NEAR_M, so the same one wins (bit-equal).
            first = self._first_segment[e]
            lo, hi = np.searchsorted(near, (first, self._first_segment[e + 1]))
            if hi > lo:
                s_m, cross_m = project_onto_segments(points_m, self._segments[e],
                                                     near[lo:hi] - first)
                if abs(cross_m[0]) <= NEAR_M:
                    return s_m, cross_m
        return project_onto_segments(points_m, self._segments[e])

    def _locate(self, tag: Any, points_m: np.ndarray,
                covariance_en_m2: Optional[np.ndarray]) -> List[TrackFix]:
        """Take one fix's step of the model; release it (or the held ones) on the path."""
        near = self.network.segments_near(points_m)
        emissions = emission(self.network.distances_near_m(points_m, near))[0]
        states = np.arange(emissions.size)
        if self._score is None:
            self._score = emissions.copy()
            self._x0_m = -np.array([self._on_state(s, points_m)[0][0] for s in states])
            back = states
        else:
            total = self._score + self._into
            back = np.argmax(total, axis=1)
            score = total[states, back] + emissions
            self._score = score - score.max()
            self._x0_m = self._x0_m[back] + self._offsets_m[back, states]
        if not self.decided:
            return self._hold_held(_Held(tag, points_m, covariance_en_m2, self._x0_m, back))
        state = self._publish(back)
        fix = self._measure(tag, points_m, covariance_en_m2, state, float(self._x0_m[state]),
                            near)
        if fix is None:
            return []
        self.counts.fused += 1
        return [fix]

    def _measure(self, tag: Any, points_m: np.ndarray, covariance_en_m2: Optional[np.ndarray],
                 state: int, x0_m: float, near: Optional[np.ndarray] = None
                 ) -> Optional[TrackFix]:
        """Return the fix on a state's chain (x0_m: where it entered the element), gated."""
        if near is not None and self._surely_off(state, near, covariance_en_m2):
            self.counts.off_track += 1
            return None
        along_m, cross_m, tangent = self._on_state(state, points_m, near)
        if along_m[0] >= self._arc_m[state // 2][-1] - _END_M and self._ahead[state].size:
            # Past the element's exit end (the model has not passed on yet: entering
            # costs SWITCH_COST first): on the nearest element it reaches (MAX_HOPS).
            on = [self._on_state(s, points_m, near) for s in self._ahead[state]]
            nearest = int(np.argmin([abs(cross[0]) for _, cross, _ in on]))
            along_m, cross_m, tangent = on[nearest]
            x0_m += self._offsets_m[state, self._ahead[state][nearest]]
        return self._gated(tag, x0_m + float(along_m[0]), float(cross_m[0]), tangent[0],
                           covariance_en_m2)

    def _surely_off(self, state: int, near: np.ndarray,
                    covariance_en_m2: Optional[np.ndarray]) -> bool:
        """Return whether the gate would reject the fix: beyond NEAR_M of all it measures on."""
        # No segment of the state's element, nor of those _measure may pass on to, within
        # NEAR_M (+ the grid's margin), and the largest bound any tangent gives is within it.
        lo, hi = np.searchsorted(near, self._reach[state])
        if np.any(hi > lo):
            return False
        if covariance_en_m2 is None:
            variance_m2 = self.variance_m2
        else:       # uᵀCu <= the sum of |C|'s entries, for every unit u
            cov = np.asarray(covariance_en_m2, dtype=float).reshape(2, 2)     # as _gated
            variance_m2 = float(np.abs(cov).sum())
        return self.cross_track_bound_m(variance_m2) < NEAR_M

    def _publish(self, lineage: Optional[np.ndarray] = None) -> int:
        """Return the state to publish: the published one's best heir, unless beaten by more."""
        # lineage: each state's predecessor at this fix (the Viterbi step's back pointers);
        # None at the start, where no state has one: the best state is published.
        best = int(np.argmax(self._score))
        if self._published is not None and lineage is not None:
            heirs = np.flatnonzero(lineage == self._published)
            if heirs.size:
                heir = int(heirs[np.argmax(self._score[heirs])])
                if self._score[best] - self._score[heir] <= self.switch_margin:
                    best = heir
        self._published = best
        return best

    def _hold_held(self, held: _Held) -> List[TrackFix]:
        """Hold a fix until the direction is decided; then release the held ones on the path."""
        counts = self.counts
        self._enqueue(self._held, held)
        # Only the fixes the run reads are projected (a point's s does not depend on the
        # others projected with it): the held ones cost the same a fix however many.
        points_m = np.concatenate([self._held[k].points_m
                                   for k in held_run_ends(len(self._held))])
        best = int(np.argmax(self._score))
        if abs(self._run_m(best // 2, points_m)) < self.direction_min_m:
            return []
        for e in range(len(self._vertices_m)):
            run_m = self._run_m(e, points_m)
            if abs(run_m) >= self.direction_min_m:
                self._score[2 * e + (1 if run_m > 0.0 else 0)] = -np.inf
        state = self._publish(lineage=None)
        chain = []
        for h in reversed(self._held):
            chain.append(state)
            state = int(h.back[state])
        released = [self._measure(h.tag, h.points_m, h.covariance_en_m2, s, float(h.x0_m[s]))
                    for h, s in zip(self._held, reversed(chain))]
        released = [f for f in released if f is not None]
        self._held = []
        counts.direction, counts.pending = 'forward', 0
        counts.fused += len(released)
        return released

    def _run_m(self, e: int, ends_m: np.ndarray) -> float:
        """Return how far the held fixes ran along element e as drawn (ends_m: held_run_ends')."""
        return ends_run_m(project_onto_segments(ends_m, self._segments[e])[0])
