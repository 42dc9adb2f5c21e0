"""
Points onto a track: along-track position s and signed cross-track distance d.

A track is a polyline of vertices in a metric plane (x east, y north, metres, any
local frame). :func:`project_onto_polyline` drops each point perpendicularly onto the
nearest piece of the polyline: s is the arc length from the first vertex to the foot
point, d the distance from the foot point to the point, positive to the left of the
direction of travel along the vertices. A window [s_min, s_max] per point restricts
the search to that stretch of arc length: a track that runs past the same place
twice (a reversal, a loop) is then resolved by where the point is expected to be,
not by the nearest copy. Pure numpy; no map matching (which track a train took is the
caller's business).
"""

from typing import NamedTuple, Tuple, Union

import numpy as np

ArrayOrFloat = Union[np.ndarray, float, None]

_PAIRS_PER_CHUNK = 1 << 19
"""Point-segment pairs per vectorised chunk: bounds the work arrays to ~50 MB."""


def polyline_arc_lengths_m(vertices_m: np.ndarray) -> np.ndarray:
    """Return the arc length from the first vertex to each vertex (M,) [m]."""
    vertices = np.asarray(vertices_m, dtype=float)
    steps = np.hypot(*np.diff(vertices, axis=0).T)
    return np.concatenate(([0.0], np.cumsum(steps)))


def polyline_tangents(vertices_m: np.ndarray, arc_m: np.ndarray, s_m) -> np.ndarray:
    """Return the (N, 2) unit direction of a polyline (distinct vertices) at arc lengths s_m."""
    segment = np.clip(np.searchsorted(arc_m, np.atleast_1d(s_m), side='right') - 1,
                      0, arc_m.size - 2)
    step = vertices_m[segment + 1] - vertices_m[segment]
    return step / np.hypot(step[:, 0], step[:, 1])[:, None]


def _window(bound: ArrayOrFloat, count: int, fill: float) -> np.ndarray:
    """Return a per-point bound (count,) from None, a scalar or an array."""
    if bound is None:
        return np.full(count, fill)
    return np.broadcast_to(np.asarray(bound, dtype=float), (count,))


class Segments(NamedTuple):
    """A polyline's segments (its distinct vertices), as project_onto_polyline takes them."""

    start: np.ndarray
    """(M, 2) first vertex of each segment [m]."""
    step: np.ndarray
    """(M, 2) from its first vertex to its last [m]."""
    length: np.ndarray
    """(M,) [m]."""
    unit: np.ndarray
    """(M, 2) step / length."""
    arc: np.ndarray
    """(M + 1,) arc length at each vertex [m]."""


def polyline_segments(vertices_m: np.ndarray) -> Segments:
    """Return the segments of a polyline (M, 2), repeated vertices dropped."""
    vertices = np.asarray(vertices_m, dtype=float)
    if vertices.ndim != 2 or vertices.shape[1] != 2:
        raise ValueError(f'vertices must be (M, 2), got {vertices.shape}')
    keep = np.concatenate(([True], np.any(np.diff(vertices, axis=0) != 0.0, axis=1)))
    vertices = vertices[keep]                    # repeated vertices make empty segments
    if vertices.shape[0] < 2:
        raise ValueError('the polyline needs two distinct vertices')
    arc = polyline_arc_lengths_m(vertices)
    step, length = np.diff(vertices, axis=0), np.diff(arc)
    return Segments(vertices[:-1], step, length, step / length[:, None], arc)


def _windows(segments: Segments, lo: np.ndarray, hi: np.ndarray, index=slice(None)
             ) -> Tuple[np.ndarray, np.ndarray]:
    """Return the windows [lo, hi] of arc length in each segment's own coordinate (n, m)."""
    arc_start = segments.arc[:-1][index]
    return (np.maximum(lo[:, None] - arc_start[None, :], 0.0),
            np.minimum(hi[:, None] - arc_start[None, :], segments.length[index][None, :]))


def project_onto_polyline(points_m: np.ndarray, vertices_m: np.ndarray,
                          s_min_m: ArrayOrFloat = None, s_max_m: ArrayOrFloat = None
                          ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return (s_m, cross_m) (N,) of points (N, 2) on the polyline vertices (M, 2).

    Each point goes to its nearest foot point on the polyline within arc lengths
    [s_min_m, s_max_m] (scalars or (N,), default the whole line); the foot point may
    be an end of that stretch. cross_m is the distance to the foot point, signed
    positive left of the polyline's direction (the side of the segment it falls on).
    """
    points = np.asarray(points_m, dtype=float).reshape(-1, 2)
    segments = polyline_segments(vertices_m)
    count = points.shape[0]
    lo = _window(s_min_m, count, 0.0)
    hi = _window(s_max_m, count, segments.arc[-1])
    s_out, cross_out = np.empty(count), np.empty(count)
    chunk = max(1, _PAIRS_PER_CHUNK // segments.length.size)
    for first in range(0, count, chunk):
        part = slice(first, first + chunk)
        s_out[part], cross_out[part] = _project_chunk(
            points[part], segments, *_windows(segments, lo[part], hi[part]))
    return s_out, cross_out


def project_onto_segments(points_m: np.ndarray, segments: Segments, index=slice(None)
                          ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return (s_m, cross_m) of points (N, 2) on a polyline's segments (index: some, rising).

    Bit-equal to project_onto_polyline (no window) wherever each point's nearest
    segment is among them and the left-out ones are all farther: the same arithmetic
    per segment, and the same first-of-equals choice, on fewer segments.
    """
    points = np.asarray(points_m, dtype=float).reshape(-1, 2)
    whole = np.array([0.0]), np.array([segments.arc[-1]])     # the same for every point
    return _project_chunk(points, segments, *_windows(segments, *whole, index), index)


def _project_chunk(points: np.ndarray, segments: Segments, seg_lo: np.ndarray,
                   seg_hi: np.ndarray, index=slice(None)) -> Tuple[np.ndarray, np.ndarray]:
    """Return (s, cross) of a chunk of points on segments[index], windows (n or 1, m) given."""
    start, unit = segments.start[index], segments.unit[index]
    rel = points[:, None, :] - start[None, :, :]                  # point - segment start
    along = (rel * segments.step[index]).sum(axis=2) / segments.length[index]
    # The window, in each segment's own coordinate (an empty window: the segment is out).
    inside = seg_lo <= seg_hi
    along = np.clip(along, seg_lo, np.maximum(seg_lo, seg_hi))
    foot = start[None, :, :] + along[..., None] * unit[None, :, :]
    distance = np.hypot(*(points[:, None, :] - foot).transpose(2, 0, 1))
    distance = np.where(inside, distance, np.inf)
    best = np.argmin(distance, axis=1)
    rows = np.arange(points.shape[0])
    if not np.all(np.isfinite(distance[rows, best])):
        raise ValueError('a point has an empty window: s_min_m > s_max_m or off the line')
    cross = unit[best, 0] * rel[rows, best, 1] - unit[best, 1] * rel[rows, best, 0]
    side = np.where(cross >= 0.0, 1.0, -1.0)                        # left of travel: +
    return segments.arc[:-1][index][best] + along[rows, best], side * distance[rows, best]
