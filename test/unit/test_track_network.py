"""Map matching on a small synthetic network with a switch: the path the fixes ran."""

from kf_train.io.track_network import emission, MATCH_CAP_M, NEAR_M, TrackNetwork
import numpy as np
import pytest

pyproj = pytest.importorskip('pyproj')

GEOD = pyproj.Geod(ellps='WGS84')
SWITCH = (4.48, 50.90)                     # lon, lat of the switch


def line(start, azimuth_deg, length_m, step_m=50.0):
    """Return lon/lat vertices of a geodesic from start."""
    points = [start]
    for _ in range(int(length_m / step_m)):
        points.append(GEOD.fwd(*points[-1], azimuth_deg, step_m)[:2])
    return [list(p) for p in points]


def network(with_relations: bool) -> dict:
    """Return A (west of the switch, to it), B (straight on east), C (diverging 8°)."""
    west = GEOD.fwd(*SWITCH, 270.0, 1000.0)[:2]
    elements = {'A': line(west, 90.0, 1000.0), 'B': line(SWITCH, 90.0, 1000.0),
                'C': line(SWITCH, 98.0, 1000.0)[::-1]}          # C drawn towards the switch
    elements['A'][-1] = list(SWITCH)
    features = [{'type': 'Feature', 'properties': {'id': name},
                 'geometry': {'type': 'LineString', 'coordinates': coordinates}}
                for name, coordinates in elements.items()]
    if with_relations:
        for other, position in (('B', 0), ('C', 1)):
            features.append({'type': 'Feature', 'geometry': {'type': 'Point',
                                                             'coordinates': list(SWITCH)},
                             'properties': {'type': 'netrelation', 'netelementA': 'A',
                                            'positionOnA': 1, 'netelementB': other,
                                            'positionOnB': position,
                                            'navigability': 'both'}})
    return {'type': 'FeatureCollection', 'features': features}


def run_fixes(branch_azimuth_deg: float, reverse: bool, gross: bool = True):
    """Return lat, lon of a train from 800 m west of the switch to 800 m along a branch."""
    rng = np.random.default_rng(5)
    points = []
    for along in np.arange(-800.0, 800.0, 8.0):
        start, azimuth = (SWITCH, branch_azimuth_deg) if along >= 0 else (SWITCH, 270.0)
        lon, lat, _ = GEOD.fwd(*start, azimuth, abs(along))
        lon, lat, _ = GEOD.fwd(lon, lat, rng.uniform(0, 360), abs(rng.normal(0.0, 1.5)))
        points.append((lat, lon))
    if gross:                                   # two 200-m jumps towards the other branch
        for k in (150, 151):
            other = 90.0 if branch_azimuth_deg != 90.0 else 98.0
            points[k] = tuple(GEOD.fwd(*SWITCH, other, 400.0)[1::-1])
    points = np.array(points[::-1] if reverse else points)
    return points[:, 0], points[:, 1]


@pytest.mark.parametrize('with_relations', [True, False])
@pytest.mark.parametrize('branch, azimuth', [('B', 90.0), ('C', 98.0)])
@pytest.mark.parametrize('reverse', [False, True])
def test_the_path_through_the_switch(with_relations, branch, azimuth, reverse):
    """The branch taken is found, either way of travel, relations or geometry alone."""
    net = TrackNetwork(network(with_relations))
    path = net.match(*run_fixes(azimuth, reverse))
    # C is drawn towards the switch: run away from it, it is run reversed.
    forward = [('A', False), (branch, branch == 'C')]
    assert path == ([(name, not rev) for name, rev in forward[::-1]] if reverse else forward)
    chained = net.path_lonlat(path)
    assert chained.shape[1] == 2 and len(chained) > 30


def test_no_turn_back_at_a_switch():
    """B and C are not joined to each other: a train cannot pass from one to the other."""
    net = TrackNetwork(network(False))
    b, c = net.ids.index('B'), net.ids.index('C')
    assert (c, 1) not in net.joins[(b, 0)] and (b, 0) not in net.joins[(c, 1)]


def test_distances_near_a_point_as_distances():
    """Within NEAR_M the grid's distances are distances_m's to the bit; beyond, both cap."""
    net = TrackNetwork(network(False))
    rng = np.random.default_rng(9)
    vertices = np.concatenate(net.lines_m)
    points = vertices[rng.integers(0, len(vertices), 1000)] + rng.uniform(-90, 90, (1000, 2))
    full = net.distances_m(points)
    for k, point in enumerate(points):
        near = net.distances_near_m(point[None], net.segments_near(point[None]))
        within = full[k] <= NEAR_M
        assert np.array_equal(near[0, within], full[k, within])
        assert np.all(near[0, ~within] >= MATCH_CAP_M)
        assert np.array_equal(emission(near), emission(full[k:k + 1]))
    assert 0.2 < np.mean(full <= NEAR_M) < 0.8          # both sides of the reach are tried
