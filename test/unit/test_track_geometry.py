"""Track geometry files, projection of WGS 84 fixes against pyproj's geodesics, both ways."""

import json

from kf_train.io.track_fixes import (
    DIRECTION_FIXES, held_run_ends, held_run_m, TrackFixes)
from kf_train.io.track_geometry import load_track, TrackError, TrackGeometry
import numpy as np
import pytest

pyproj = pytest.importorskip('pyproj')   # the modules import it when a geometry is built

GEOD = pyproj.Geod(ellps='WGS84')
START = (4.48, 50.90)          # lon, lat: near Brussels airport (tp-lib's logs)
# The frame's scale error over these ±2 km is (2 km / 6371 km)² / 2 ~ 5e-8, a geodesic
# against its chord in the plane differs by far less than a millimetre: 5 mm is margin.
TOLERANCE_M = 5e-3


def geodesic_track(turn_deg_per_step: float, step_m: float = 100.0, steps: int = 30):
    """Return lon/lat (M, 2) of a line from START, azimuth 60° turning per step, and arcs."""
    lon, lat, azimuth = START[0], START[1], 60.0
    vertices, arcs = [(lon, lat)], [0.0]
    for _ in range(steps):
        lon, lat, back = GEOD.fwd(lon, lat, azimuth, step_m)
        vertices.append((lon, lat))
        arcs.append(arcs[-1] + step_m)
        azimuth = (back + 180.0 + turn_deg_per_step) % 360.0
    return np.array(vertices), np.array(arcs)


def offset_fixes(vertices: np.ndarray, arcs: np.ndarray, offsets_m: np.ndarray):
    """Return lat, lon, expected s, cross of fixes off each segment's geodesic midpoint."""
    lats, lons, s, cross = [], [], [], []
    for i, offset in zip(range(len(vertices) - 1), offsets_m):
        (lon1, lat1), (lon2, lat2) = vertices[i], vertices[i + 1]
        azimuth, _, length = GEOD.inv(lon1, lat1, lon2, lat2)
        lon_m, lat_m, back = GEOD.fwd(lon1, lat1, azimuth, length / 2.0)
        heading = back + 180.0
        # Left of travel is the heading minus 90° (azimuths turn clockwise).
        lon, lat, _ = GEOD.fwd(lon_m, lat_m, heading - 90.0 * np.sign(offset), abs(offset))
        lats.append(lat)
        lons.append(lon)
        s.append(arcs[i] + length / 2.0)
        cross.append(offset)
    return np.array(lats), np.array(lons), np.array(s), np.array(cross)


@pytest.mark.parametrize('turn_deg', [0.0, 2.0, -3.0])
@pytest.mark.parametrize('reverse', [False, True])
def test_projection_matches_geodesics(turn_deg, reverse):
    """Along-track s is the geodesic arc length, cross its offset (left +), either way drawn."""
    vertices, arcs = geodesic_track(turn_deg)
    rng = np.random.default_rng(7)
    offsets = rng.uniform(-8.0, 8.0, len(vertices) - 1)
    lat, lon, s, cross = offset_fixes(vertices, arcs, offsets)
    geometry = TrackGeometry(vertices, reversed_=reverse)
    assert geometry.length_m == pytest.approx(arcs[-1], abs=TOLERANCE_M)
    got_s, got_cross, tangent = geometry.project(lat, lon)
    if reverse:
        s, cross = arcs[-1] - s, -cross
    np.testing.assert_allclose(got_s, s, atol=TOLERANCE_M)
    np.testing.assert_allclose(got_cross, cross, atol=TOLERANCE_M)
    np.testing.assert_allclose(np.hypot(*tangent.T), 1.0)
    vertex_s, _, _ = geometry.project(vertices[:, 1], vertices[:, 0])
    expected = arcs[-1] - arcs if reverse else arcs
    np.testing.assert_allclose(vertex_s, expected, atol=TOLERANCE_M)


def write_geojson(path, geometry):
    """Write a GeoJSON document."""
    path.write_text(json.dumps(geometry))
    return path


@pytest.mark.parametrize('form', ['line', 'feature', 'collection', 'multi', 'csv'])
def test_files(tmp_path, form):
    """Every file form gives the same geometry."""
    vertices, arcs = geodesic_track(1.0, steps=6)
    coordinates = vertices.tolist()
    line = {'type': 'LineString', 'coordinates': coordinates}
    if form == 'csv':
        path = tmp_path / 'track.csv'
        path.write_text('name,lat,lon\n' + ''.join(f'v,{lat!r},{lon!r}\n'
                                                   for lon, lat in coordinates))
    else:
        document = {
            'line': line,
            'feature': {'type': 'Feature', 'properties': {}, 'geometry': line},
            'collection': {'type': 'FeatureCollection', 'features': [
                {'type': 'Feature', 'properties': {}, 'geometry': line},
                {'type': 'Feature', 'properties': {},
                 'geometry': {'type': 'Point', 'coordinates': coordinates[0]}}]},
            # The first part is drawn backwards, the second forwards: chained all the same.
            'multi': {'type': 'MultiLineString',
                      'coordinates': [coordinates[3::-1], coordinates[3:]]},
        }[form]
        path = write_geojson(tmp_path / 'track.geojson', document)
    geometry = load_track(path)
    np.testing.assert_allclose(geometry.arc_m, arcs, atol=TOLERANCE_M)


def test_bad_files(tmp_path):
    """A network, a header without lat/lon, a single vertex: each a TrackError."""
    line = {'type': 'LineString', 'coordinates': [[4.4, 50.9], [4.5, 50.9]]}
    feature = {'type': 'Feature', 'properties': {}, 'geometry': line}
    network = write_geojson(tmp_path / 'n.geojson',
                            {'type': 'FeatureCollection', 'features': [feature, feature]})
    headless = tmp_path / 'h.csv'
    headless.write_text('y,x\n50.9,4.4\n50.9,4.5\n')
    single = write_geojson(tmp_path / 's.geojson',
                           {'type': 'LineString', 'coordinates': [[4.4, 50.9]]})
    for path in (network, headless, single):
        with pytest.raises(TrackError):
            load_track(path)


def run(fixes: TrackFixes, lat, lon, covariance=None):
    """Feed fixes 0.4 s apart; return the released measurements."""
    out = []
    for i, (la, lo) in enumerate(zip(lat, lon)):
        out += fixes.add(0.4 * i, la, lo, covariance)
    return out


@pytest.mark.parametrize('reverse', [False, True])
def test_direction_auto(reverse):
    """A track drawn against the travel: x still grows; the held fixes come out in order."""
    vertices, arcs = geodesic_track(1.0)
    lat, lon, s, _ = offset_fixes(vertices, arcs, np.full(len(vertices) - 1, 2.0))
    geometry = TrackGeometry(vertices, reversed_=reverse)
    fixes = TrackFixes(geometry, variance_m2=3.0)
    out = run(fixes, lat, lon)
    assert fixes.counts.direction == ('reverse' if reverse else 'forward')
    assert len(out) == len(lat) == fixes.counts.fused
    x = np.array([f.x_m for f in out])
    assert np.all(np.diff(x) > 0.0)
    np.testing.assert_allclose(x, s if not reverse else geometry.length_m - arcs[-1] + s,
                               atol=TOLERANCE_M)
    assert all(f.cross_m == pytest.approx(2.0, abs=TOLERANCE_M) for f in out)
    assert [f.tag for f in out] == [0.4 * i for i in range(len(lat))]


def test_the_run_reads_only_its_ends():
    """The run is the medians' difference, and reads only the fixes held_run_ends names."""
    rng = np.random.default_rng(3)
    for count in range(1, 40):
        s_m = rng.normal(0.0, 10.0, count)
        k = min(DIRECTION_FIXES, max(1, count // 2))
        assert held_run_m(s_m) == float(np.median(s_m[-k:]) - np.median(s_m[:k]))
        unread = np.setdiff1d(np.arange(count), held_run_ends(count))
        assert unread.size == max(0, count - 2 * k)
        scrambled = s_m.copy()
        scrambled[unread] = rng.normal(0.0, 1e6, unread.size)
        assert held_run_m(scrambled) == held_run_m(s_m)


def test_direction_waits_for_a_run():
    """Standing fixes are held; one fix far along (an outlier) does not decide alone."""
    vertices, arcs = geodesic_track(0.0)
    lat, lon, _, _ = offset_fixes(vertices, arcs, np.zeros(len(vertices) - 1))
    fixes = TrackFixes(TrackGeometry(vertices), variance_m2=3.0)
    assert run(fixes, [lat[3]] * 8 + [lat[20]] + [lat[3]] * 3,
               [lon[3]] * 8 + [lon[20]] + [lon[3]] * 3) == []
    assert fixes.counts.direction == 'auto' and fixes.counts.pending == 12


def test_cross_track_gate():
    """A fix beyond cross_track_max_m + k σ is rejected and counted; inside, fused."""
    vertices, arcs = geodesic_track(0.0)
    bound_m = 10.0 + 3.0 * np.sqrt(3.0)                    # the defaults, σ² = 3 m²
    offsets = np.array([0.0, bound_m - 0.05, bound_m + 0.05, -(bound_m + 0.05), 200.0]
                       + [0.0] * 25)
    lat, lon, _, _ = offset_fixes(vertices, arcs, offsets)
    fixes = TrackFixes(TrackGeometry(vertices), variance_m2=3.0, direction='forward')
    out = run(fixes, lat, lon)
    assert fixes.counts.off_track == 3
    assert fixes.counts.fused == len(out) == len(lat) - 3
    # A fix with its own covariance: σ_cross from it (here 10 m across: the bound is 40 m).
    fixes.add(20.0, lat[4], lon[4], np.eye(2) * 100.0)
    assert fixes.counts.off_track == 4
    fixes.add(20.4, lat[2], lon[2], np.eye(2) * 100.0)
    assert fixes.counts.off_track == 4
    fixes.add(20.8, lat[5], lon[5], has_fix=False)
    assert fixes.counts.no_fix == 1 and fixes.counts.fixes == len(lat) + 3


def test_along_track_variance():
    """The variance along the track is the covariance's form along its bearing (60°)."""
    vertices, arcs = geodesic_track(0.0)
    lat, lon, _, _ = offset_fixes(vertices, arcs, np.zeros(len(vertices) - 1))
    fixes = TrackFixes(TrackGeometry(vertices), variance_m2=3.0, direction='forward')
    covariance = np.diag([4.0, 1.0])                       # east, north
    fix, = fixes.add(0.0, lat[14], lon[14], covariance)
    # sin²60° * 4 + cos²60° * 1; the bearing on the plane is the geodesic's to ~1e-3 rad.
    assert fix.variance_m2 == pytest.approx(3.25, abs=0.01)
    fix, = fixes.add(0.4, lat[14], lon[14])
    assert fix.variance_m2 == 3.0


def test_bad_options():
    """An unknown direction or a bound out of range is refused."""
    geometry = TrackGeometry(geodesic_track(0.0, steps=2)[0])
    with pytest.raises(ValueError):
        TrackFixes(geometry, 3.0, direction='backward')
    with pytest.raises(ValueError):
        TrackFixes(geometry, 3.0, cross_track_max_m=-1.0)
    with pytest.raises(ValueError):
        TrackFixes(geometry, 0.0)


def test_hostile_fixes():
    """Positions NaN or out of range are no fixes; the antipode is off the track; no raise."""
    vertices, arcs = geodesic_track(0.0)
    fixes = TrackFixes(TrackGeometry(vertices), variance_m2=3.0, direction='forward')
    for lat, lon in ((float('nan'), 4.5), (50.9, float('inf')), (91.0, 4.5), (50.9, -181.0)):
        assert fixes.add(0.0, lat, lon) == []
    assert fixes.counts.no_fix == 4
    assert fixes.add(0.0, -50.9, -175.5) == [] and fixes.counts.off_track == 1
    lat, lon, _, _ = offset_fixes(vertices, arcs, np.zeros(len(vertices) - 1))
    # A covariance with NaN: the variance goes on as NaN (the estimator refuses it).
    fix, = fixes.add(0.4, lat[3], lon[3], np.full((2, 2), np.nan))
    assert np.isnan(fix.variance_m2)
