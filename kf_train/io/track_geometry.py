"""
A track's geometry from a file, in a local metric frame, and WGS 84 fixes on it.

:func:`load_track` reads a GeoJSON LineString (bare, a Feature, or a FeatureCollection
holding one; a MultiLineString whose parts chain end to end is joined) or a CSV with a
``lat,lon`` header (an OpenStreetMap export of a line, saved as CSV, works). Any other
column is ignored.

:class:`TrackGeometry` puts the vertices in a transverse Mercator frame centred on the
track (x east, y north, metres, scale 1 on its central meridian) and projects fixes
onto the polyline (:func:`kf_train.io.track.project_onto_polyline`): the along-track
position s from the first vertex and the signed cross-track distance, left of the
direction of the vertices positive. Why transverse Mercator about the track's own
centre: it is conformal (the along-track direction of a fix's covariance is the
track's bearing on the plane) and its scale error is (d / R)² / 2 at d from the
central meridian, 1.2e-6 at 10 km, 1.2e-4 at 100 km: centimetres per kilometre of
track; a UTM zone would add 4e-4 everywhere. The projection is pyproj's (PROJ: the
reference implementation of these maps, well kept, wheels for every supported
Python; the extra ``[track]``); it is imported when a geometry is built.
"""

import csv
import json
from pathlib import Path
from typing import Optional, Sequence, Tuple

from kf_train.io.track import (
    polyline_arc_lengths_m, polyline_tangents, project_onto_polyline)
import numpy as np

CHAIN_TOLERANCE_M = 1.0
"""Two parts of a MultiLineString chain when their ends are this close (metres)."""

_METRES_PER_DEGREE = 111_000.0   # only to compare part ends, never to measure the track


class TrackError(ValueError):
    """A track file that cannot be read as one line."""


def _line_from_geojson(document: dict) -> np.ndarray:
    """Return the (M, 2) lon/lat vertices of the one line a GeoJSON document holds."""
    kind = document.get('type')
    if kind == 'FeatureCollection':
        lines = [f for f in document.get('features') or []
                 if (f.get('geometry') or {}).get('type') in ('LineString', 'MultiLineString')]
        if len(lines) != 1:
            raise TrackError(f'a FeatureCollection must hold one LineString, '
                             f'found {len(lines)} (a network is not a track)')
        return _line_from_geojson(lines[0])
    if kind == 'Feature':
        return _line_from_geojson(document.get('geometry') or {})
    if kind == 'LineString':
        return np.asarray(document.get('coordinates'), dtype=float)[:, :2]
    if kind == 'MultiLineString':
        return _chain_parts([np.asarray(p, dtype=float)[:, :2]
                             for p in document.get('coordinates') or []])
    raise TrackError(f'GeoJSON {kind!r} is not a LineString')


def _chain_parts(parts: Sequence[np.ndarray]) -> np.ndarray:
    """Join the parts of a MultiLineString, in order, each turned to start at the last end."""
    if not parts:
        raise TrackError('an empty MultiLineString')
    line = parts[0]
    tolerance_deg = CHAIN_TOLERANCE_M / _METRES_PER_DEGREE

    def meets(point: np.ndarray, part: np.ndarray) -> bool:
        return min(np.abs(part[[0, -1]] - point).max(axis=1)) <= tolerance_deg

    if len(parts) > 1 and not meets(line[-1], parts[1]) and meets(line[0], parts[1]):
        line = line[::-1]                        # the first part drawn from its far end
    for number, part in enumerate(parts[1:], start=1):
        if np.abs(part[-1] - line[-1]).max() <= tolerance_deg:
            part = part[::-1]
        if np.abs(part[0] - line[-1]).max() > tolerance_deg:
            raise TrackError(f'MultiLineString part {number} does not join the previous')
        line = np.concatenate((line, part[1:]))
    return line


def _line_from_csv(path: Path) -> np.ndarray:
    """Return the (M, 2) lon/lat vertices of a CSV with lat and lon columns."""
    with open(path, newline='', encoding='utf-8-sig') as stream:
        reader = csv.DictReader(stream)
        names = {name.strip().lower(): name for name in reader.fieldnames or ()}
        if 'lat' not in names or 'lon' not in names:
            raise TrackError(f'{path}: a track CSV needs a lat,lon header, got '
                             f'{reader.fieldnames}')
        try:
            rows = [(float(row[names['lon']]), float(row[names['lat']])) for row in reader]
        except (TypeError, ValueError) as error:
            raise TrackError(f'{path}: line {reader.line_num}: {error}') from None
    return np.asarray(rows, dtype=float).reshape(-1, 2)


def read_track_lonlat(path) -> np.ndarray:
    """Return the (M, 2) WGS 84 longitude, latitude [deg] vertices of a track file."""
    path = Path(path)
    if path.suffix.lower() == '.csv':
        lonlat = _line_from_csv(path)
    else:
        try:
            document = json.loads(path.read_text(encoding='utf-8'))
        except json.JSONDecodeError as error:
            raise TrackError(f'{path}: not GeoJSON ({error})') from None
        lonlat = _line_from_geojson(document)
    if lonlat.ndim != 2 or lonlat.shape[0] < 2 or not np.all(np.isfinite(lonlat)):
        raise TrackError(f'{path}: a track needs two or more finite vertices')
    if np.any(np.abs(lonlat[:, 1]) > 90.0) or np.any(np.abs(lonlat[:, 0]) > 180.0):
        raise TrackError(f'{path}: a vertex out of latitude/longitude range')
    return lonlat


class TrackGeometry:
    """A track's polyline in a local transverse Mercator frame; fixes projected onto it."""

    def __init__(self, lonlat_deg: np.ndarray, reversed_: bool = False) -> None:
        """Build the frame about the vertices' (M, 2) lon/lat [deg]; reversed_: s from the end."""
        from pyproj import Transformer   # the extra [track]; only a geometry needs it
        lonlat = np.asarray(lonlat_deg, dtype=float)
        if reversed_:
            lonlat = lonlat[::-1]
        lon0, lat0 = ((lonlat.min(axis=0) + lonlat.max(axis=0)) / 2.0).tolist()
        self.lonlat_deg = lonlat
        self.origin_deg = (float(lat0), float(lon0))
        self._transformer = Transformer.from_crs(
            'EPSG:4326', f'+proj=tmerc +lat_0={lat0!r} +lon_0={lon0!r} +k=1 +x_0=0 +y_0=0 '
            '+ellps=WGS84 +units=m +no_defs', always_xy=True)
        self.vertices_m = self.to_local(lonlat[:, 1], lonlat[:, 0])
        keep = np.concatenate(([True], np.any(np.diff(self.vertices_m, axis=0) != 0.0,
                                              axis=1)))
        self.vertices_m = self.vertices_m[keep]
        if self.vertices_m.shape[0] < 2:
            raise TrackError('a track needs two distinct vertices')
        self.arc_m = polyline_arc_lengths_m(self.vertices_m)
        self.length_m = float(self.arc_m[-1])

    @classmethod
    def from_file(cls, path, reversed_: bool = False) -> 'TrackGeometry':
        """Load a track file (see the module)."""
        return cls(read_track_lonlat(path), reversed_)

    def flipped(self) -> 'TrackGeometry':
        """Return the same track with s from its other end (cross-track sign flipped)."""
        return TrackGeometry(self.lonlat_deg, reversed_=True)

    def to_local(self, lat_deg, lon_deg) -> np.ndarray:
        """Return (N, 2) east, north [m] in the track's frame of WGS 84 positions."""
        east, north = self._transformer.transform(np.asarray(lon_deg, dtype=float),
                                                  np.asarray(lat_deg, dtype=float))
        return np.column_stack((np.ravel(east), np.ravel(north)))

    def project(self, lat_deg, lon_deg, s_min_m=None, s_max_m=None
                ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (s_m, cross_m, tangent (N, 2)) of fixes: position on the track, its bearing."""
        return self.project_local(self.to_local(lat_deg, lon_deg), s_min_m, s_max_m)

    def project_local(self, points_m: np.ndarray, s_min_m=None, s_max_m=None
                      ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (s_m, cross_m, tangent) of (N, 2) finite points in the track's frame."""
        s_m, cross_m = project_onto_polyline(points_m, self.vertices_m, s_min_m, s_max_m)
        return s_m, cross_m, self.tangent(s_m)

    def tangent(self, s_m) -> np.ndarray:
        """Return the (N, 2) unit direction (east, north) of the track at arc lengths s_m."""
        return polyline_tangents(self.vertices_m, self.arc_m, s_m)


def load_track(path, reversed_: Optional[bool] = False) -> TrackGeometry:
    """Return the geometry of a track file, s from its first vertex (or its last: reversed_)."""
    return TrackGeometry.from_file(path, bool(reversed_))
