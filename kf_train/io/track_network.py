"""
A railway network (many LineStrings joined at switches) and the path fixes took on it.

:class:`TrackNetwork` reads a GeoJSON FeatureCollection of LineStrings (the network's
elements; ``properties.id`` names them, else their index). Two elements are joined
where tp-lib's ``netrelation`` Points say so (``netelementA``/``netelementB``,
``positionOnA``/``positionOnB`` 0 or 1, ``navigability`` not ``none``); without such
Points, where an end of one lies within JOIN_TOLERANCE_M of an end of the other and the
two leave that point in directions more than 90° apart (a train runs through a switch,
it does not turn back on it).

:meth:`TrackNetwork.match` chooses the path of a series of fixes offline, as map
matching does (a hidden Markov model decoded by Viterbi, as tp-lib's path calculation
and DLR's railpos do): the hidden state is an element and the direction it is run in;
a fix's likelihood falls with its distance to the element (Gaussian of MATCH_SIGMA_M,
flat beyond MATCH_CAP_M so that a gross fix cannot pull the path away); the state may
stay, or pass to an element joined at its far end (up to MAX_HOPS elements on between
two fixes, SWITCH_COST per element entered). The result is the chain of elements in
travel order, which :meth:`TrackNetwork.path_lonlat` turns into one line for
:class:`kf_train.io.track_geometry.TrackGeometry`. The same model, run forward fix by
fix as the fixes come, is :mod:`kf_train.io.track_network_live`: :meth:`distances_m`,
:func:`emission` and :meth:`TrackNetwork.transition` are the one home of both.
"""

import json
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

from kf_train.io.track import polyline_arc_lengths_m
from kf_train.io.track_geometry import TrackError, TrackGeometry
import numpy as np

JOIN_TOLERANCE_M = 1.0
MATCH_SIGMA_M = 10.0
MATCH_CAP_M = 40.0
SWITCH_COST = 5.0
MAX_HOPS = 3
NEAR_M = MATCH_CAP_M
"""TrackNetwork.segments_near finds every segment within this of a point (the cap: beyond
it every distance scores alike)."""
_NEAR_MARGIN_M = 1.0
"""Reach of the grid beyond NEAR_M: far more than any rounding of a distance."""
_CELL_M = 40.0
"""Side of a cell of the grid of segments [m]: a fix's candidates lie within ~80 m of it."""
_PAIRS_PER_CHUNK = 1 << 19
"""Point-segment pairs per vectorised chunk of distances_m: bounds its arrays to ~20 MB."""


def is_network_file(path) -> bool:
    """Return whether a file is a GeoJSON FeatureCollection of more than one LineString."""
    try:
        document = json.loads(Path(path).read_text(encoding='utf-8'))
    except (OSError, ValueError):
        return False
    if not isinstance(document, dict) or document.get('type') != 'FeatureCollection':
        return False
    return sum((f.get('geometry') or {}).get('type') == 'LineString'
               for f in document.get('features') or [] if isinstance(f, dict)) > 1


def emission(distance_m: np.ndarray) -> np.ndarray:
    """Return the log-likelihood of fixes (N, E) at distance_m from the elements, per state."""
    score = -0.5 * (np.minimum(distance_m, MATCH_CAP_M) / MATCH_SIGMA_M) ** 2
    return np.repeat(score, 2, axis=-1)                     # both directions alike


def _elements(document: dict) -> Tuple[List[str], List[np.ndarray], List[dict]]:
    """Return the ids, lon/lat vertices of the LineStrings and the netrelation properties."""
    ids, lines, relations = [], [], []
    for index, feature in enumerate(document.get('features') or []):
        geometry, properties = feature.get('geometry') or {}, feature.get('properties') or {}
        if geometry.get('type') == 'LineString':
            ids.append(str(properties.get('id', index)))
            lines.append(np.asarray(geometry['coordinates'], dtype=float)[:, :2])
        elif properties.get('type') == 'netrelation':
            relations.append(properties)
    if not lines:
        raise TrackError('a network needs LineStrings')
    return ids, lines, relations


class TrackNetwork:
    """Elements, their joins, and the path a series of fixes ran (see the module)."""

    def __init__(self, document: dict) -> None:
        """Build the network of a GeoJSON FeatureCollection (pyproj: the extra [track])."""
        self.ids, self.lonlat, relations = _elements(document)
        frame = TrackGeometry(np.concatenate(self.lonlat))      # one frame for all
        self.frame = frame
        self.lines_m = [frame.to_local(line[:, 1], line[:, 0]) for line in self.lonlat]
        self.lengths_m = np.array([polyline_arc_lengths_m(line)[-1] for line in self.lines_m])
        # Every element's segments in one table (repeated vertices dropped), for distances_m.
        distinct = [line[np.concatenate(([True], np.any(np.diff(line, axis=0) != 0.0, axis=1)))]
                    for line in self.lines_m]
        self._first_segment = np.cumsum([0] + [len(v) - 1 for v in distinct[:-1]])
        self._segment_start = np.concatenate([v[:-1] for v in distinct])
        step = np.concatenate([np.diff(v, axis=0) for v in distinct])
        self._segment_length = np.hypot(step[:, 0], step[:, 1])
        self._segment_unit = step / self._segment_length[:, None]
        self._segment_element = np.repeat(np.arange(len(distinct)),
                                          [len(v) - 1 for v in distinct])
        self._grid = self._build_grid()
        count = len(self.ids)
        # joins[(element, end)] = [(element, end), ...]: ends 0 (first vertex) or 1.
        self.joins: Dict[Tuple[int, int], List[Tuple[int, int]]] = {
            (e, end): [] for e in range(count) for end in (0, 1)}
        if relations:
            index = {name: e for e, name in enumerate(self.ids)}
            for r in relations:
                a, b = index.get(str(r.get('netelementA'))), index.get(str(r.get('netelementB')))
                if a is None or b is None or r.get('navigability') == 'none':
                    continue
                ends = (int(r.get('positionOnA', 1)), int(r.get('positionOnB', 0)))
                self.joins[(a, ends[0])].append((b, ends[1]))
                self.joins[(b, ends[1])].append((a, ends[0]))
        else:
            self._join_by_geometry()

    @classmethod
    def from_file(cls, path) -> 'TrackNetwork':
        """Read a network GeoJSON file."""
        return cls(json.loads(Path(path).read_text(encoding='utf-8')))

    def _end(self, e: int, end: int) -> Tuple[np.ndarray, np.ndarray]:
        """Return an element end's point and the unit direction leaving it into the element."""
        line = self.lines_m[e] if end == 0 else self.lines_m[e][::-1]
        step = line[1] - line[0]
        return line[0], step / max(np.hypot(*step), 1e-12)

    def _join_by_geometry(self) -> None:
        """Join ends that meet, where the elements leave the point in opposite directions."""
        ends = [(e, end) for e in range(len(self.ids)) for end in (0, 1)]
        for i, first in enumerate(ends):
            point, out = self._end(*first)
            for second in ends[i + 1:]:
                if second[0] == first[0]:
                    continue
                other, other_out = self._end(*second)
                if np.hypot(*(point - other)) <= JOIN_TOLERANCE_M and out @ other_out < 0.0:
                    self.joins[first].append(second)
                    self.joins[second].append(first)

    def successors(self, state: int) -> List[int]:
        """Return the states one element on: state = 2 element + direction (1: reversed)."""
        e, direction = divmod(state, 2)
        exit_end = 1 - direction                   # run forwards: leaves by its end 1
        return [2 * f + (1 if entry_end == 1 else 0) for f, entry_end in self.joins[(e, exit_end)]]

    def hops(self) -> np.ndarray:
        """Return the fewest elements entered from each state to each (inf: beyond MAX_HOPS)."""
        count = 2 * len(self.ids)
        hops = np.full((count, count), np.inf)
        np.fill_diagonal(hops, 0.0)
        for start in range(count):
            frontier = [start]
            for hop in range(1, MAX_HOPS + 1):
                frontier = [s for f in frontier for s in self.successors(f)
                            if hops[start, s] == np.inf]
                for s in frontier:
                    hops[start, s] = hop
        return hops

    def distances_m(self, points_m: np.ndarray) -> np.ndarray:
        """Return the (N, E) distance of points (N, 2) in the network's frame to each element."""
        points = np.asarray(points_m, dtype=float).reshape(-1, 2)
        out = np.empty((points.shape[0], len(self.ids)))
        chunk = max(1, _PAIRS_PER_CHUNK // self._segment_start.shape[0])
        for first in range(0, points.shape[0], chunk):
            out[first:first + chunk] = np.minimum.reduceat(
                self._segment_distances(points[first:first + chunk, None, :]),
                self._first_segment, axis=1)
        return out

    def _segment_distances(self, part: np.ndarray, index=slice(None)) -> np.ndarray:
        """Return the distance (n, m) of points (n, 1, 2) to their feet on segments[index]."""
        start, unit = self._segment_start[index], self._segment_unit[index]
        along = np.clip(((part - start) * unit).sum(axis=2), 0.0, self._segment_length[index])
        gap = part - (start + along[..., None] * unit)             # to the foot on each
        return np.hypot(gap[..., 0], gap[..., 1])

    def segments_near(self, point_m: np.ndarray) -> np.ndarray:
        """Return the rising indices of segments that may lie within NEAR_M of a point (1, 2)."""
        cell = np.floor(np.asarray(point_m, dtype=float).reshape(2) / _CELL_M)
        return self._grid.get((int(cell[0]), int(cell[1])), np.zeros(0, dtype=np.intp))

    def _build_grid(self) -> Dict[Tuple[int, int], np.ndarray]:
        """Return {cell: rising indices of the segments whose box, widened, overlaps it}."""
        start = self._segment_start
        end = start + self._segment_unit * self._segment_length[:, None]
        reach_m = NEAR_M + _NEAR_MARGIN_M
        low = np.floor((np.minimum(start, end) - reach_m) / _CELL_M).astype(np.intp)
        high = np.floor((np.maximum(start, end) + reach_m) / _CELL_M).astype(np.intp)
        size = high - low + 1
        count = size[:, 0] * size[:, 1]
        segment = np.repeat(np.arange(start.shape[0]), count)
        k = np.arange(segment.size) - np.repeat(np.cumsum(count) - count, count)
        ix = low[segment, 0] + k % size[segment, 0]
        iy = low[segment, 1] + k // size[segment, 0]
        order = np.lexsort((segment, iy, ix))
        ix, iy, segment = ix[order], iy[order], segment[order]
        cuts = np.flatnonzero((np.diff(ix) != 0) | (np.diff(iy) != 0)) + 1
        return {(int(ix[a]), int(iy[a])): segment[a:b]
                for a, b in zip(np.concatenate(([0], cuts)), np.concatenate((cuts, [ix.size])))}

    def distances_near_m(self, point_m: np.ndarray, near: np.ndarray) -> np.ndarray:
        """Return distances_m of one point (1, 2), but inf for elements provably beyond NEAR_M."""
        # near: segments_near(point_m). Within NEAR_M the same arithmetic on fewer segments
        # (the element's nearest one is among them): bit-equal; beyond it both are
        # >= MATCH_CAP_M, which emission caps.
        out = np.full((1, len(self.ids)), np.inf)
        if near.size:
            part = np.asarray(point_m, dtype=float).reshape(1, 1, 2)
            element = self._segment_element[near]
            first = np.flatnonzero(np.concatenate(([True], element[1:] != element[:-1])))
            out[0, element[first]] = np.minimum.reduceat(
                self._segment_distances(part, near), first, axis=1)[0]
        return out

    def transition(self) -> np.ndarray:
        """Return the (S, S) log-probability of passing from state to state between two fixes."""
        return -SWITCH_COST * self.hops()                       # -inf beyond reach

    def entry_offsets_m(self, hops: np.ndarray) -> np.ndarray:
        """Return (S, S): the run from entering a state to entering one reachable from it [m]."""
        offsets = np.zeros(hops.shape)
        for start, goal in zip(*np.nonzero(np.isfinite(hops) & (hops > 0))):
            way = [int(start)] + self._between(int(start), int(goal))
            offsets[start, goal] = self.lengths_m[np.array(way) // 2].sum()
        return offsets

    def match(self, lat_deg: Sequence[float], lon_deg: Sequence[float]) -> List[Tuple[str, bool]]:
        """Return the path of the fixes: (element id, run reversed) in travel order."""
        points = self.frame.to_local(lat_deg, lon_deg)
        emissions = emission(self.distances_m(points))
        transition = self.transition()
        score = emissions[0].copy()
        back = np.zeros(emissions.shape, dtype=np.int32)
        for k in range(1, len(points)):
            total = score[:, None] + transition
            back[k] = np.argmax(total, axis=0)
            score = total[back[k], np.arange(total.shape[1])] + emissions[k]
        states = [int(np.argmax(score))]
        for k in range(len(points) - 1, 0, -1):
            states.append(int(back[k, states[-1]]))
        return self._chain(states[::-1])

    def _chain(self, states: List[int]) -> List[Tuple[str, bool]]:
        """Return the elements of a state sequence, the skipped ones between filled in."""
        path = [states[0]]
        for state in states[1:]:
            if state != path[-1]:
                path += self._between(path[-1], state) + [state]
        return [(self.ids[s // 2], bool(s % 2)) for s in path]

    def _between(self, start: int, goal: int) -> List[int]:
        """Return the states entered on the fewest-elements way from start to goal, exclusive."""
        previous = {start: None}
        frontier = [start]
        while frontier and goal not in previous:
            following = []
            for f in frontier:
                for s in self.successors(f):
                    if s not in previous:
                        previous[s] = f
                        following.append(s)
            frontier = following
        way, state = [], previous.get(goal)
        while state is not None and state != start:
            way.append(state)
            state = previous[state]
        return way[::-1]

    def path_lonlat(self, path: Sequence[Tuple[str, bool]]) -> np.ndarray:
        """Return the (M, 2) lon/lat line of a path: its elements chained in travel order."""
        index = {name: e for e, name in enumerate(self.ids)}
        parts = [self.lonlat[index[name]][::-1] if reverse else self.lonlat[index[name]]
                 for name, reverse in path]
        return np.concatenate([parts[0]] + [part[1:] for part in parts[1:]])
