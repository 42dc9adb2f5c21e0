"""The path chosen live on a network with a switch and a parallel pair: x as offline's."""

from kf_train.io import NetworkFixes, TrackGeometry, TrackNetwork
import numpy as np
import pytest

pyproj = pytest.importorskip('pyproj')

GEOD = pyproj.Geod(ellps='WGS84')
SWITCH = (4.48, 50.90)                     # lon, lat of the switch A | B, C
NOISE_M = 1.5                              # the fixes' horizontal noise (Rayleigh-ish)
STEP_M = 8.0                               # travel between two fixes
GROSS_M = 200.0


def line(start, azimuth_deg, length_m, step_m=50.0):
    """Return lon/lat vertices of a geodesic from start."""
    points = [tuple(start)]
    for _ in range(int(round(length_m / step_m))):
        points.append(GEOD.fwd(*points[-1], azimuth_deg, step_m)[:2])
    return [list(p) for p in points]


def elements() -> dict:
    """Return A to the switch; B straight on, C diverging 8°; after B, P and Q 4 m apart."""
    west = GEOD.fwd(*SWITCH, 270.0, 1000.0)[:2]
    a, b, c = line(west, 90.0, 1000.0), line(SWITCH, 90.0, 1000.0), line(SWITCH, 98.0, 1000.0)
    a[-1] = list(SWITCH)
    lead = GEOD.fwd(*b[-1], 90.0 + np.degrees(np.arctan2(4.0, 100.0)), np.hypot(4.0, 100.0))
    q = [b[-1]] + line(lead[:2], 90.0, 500.0)
    return {'A': a, 'B': b, 'C': c[::-1], 'P': line(b[-1], 90.0, 600.0), 'Q': q}


def network(drawn_reversed: bool = False) -> dict:
    """Return the network as GeoJSON, joined by geometry (every element flipped: reversed)."""
    return {'type': 'FeatureCollection', 'features': [
        {'type': 'Feature', 'properties': {'id': name},
         'geometry': {'type': 'LineString',
                      'coordinates': coordinates[::-1] if drawn_reversed else coordinates}}
        for name, coordinates in elements().items()]}


def walk(route, step_m: float):
    """Return (lon, lat, azimuth) every step_m along a lon/lat polyline."""
    out, carry = [], 0.0
    for start, end in zip(route[:-1], route[1:]):
        azimuth, _, length = GEOD.inv(*start, *end)
        along = carry
        while along < length:
            out.append(GEOD.fwd(*start, azimuth, along)[:2] + (azimuth,))
            along += step_m
        carry = along - length
    return out


def fixes(names, reverse: bool, gross=(), seed: int = 7):
    """Return lat, lon of a noisy run along the elements named, in travel order."""
    parts = [elements()[n][::-1] if n == 'C' else elements()[n] for n in names]
    route = parts[0] + [p for part in parts[1:] for p in part[1:]]
    route = route[::-1] if reverse else route
    rng = np.random.default_rng(seed)
    points = []
    for lon, lat, _ in walk(route, STEP_M):
        lon, lat, _ = GEOD.fwd(lon, lat, rng.uniform(0, 360), abs(rng.normal(0.0, NOISE_M)))
        points.append((lat, lon))
    points = np.array(points)
    for k, (lon, lat) in gross:
        points[k] = (lat, lon)
    return points[:, 0], points[:, 1]


def run_live(net: TrackNetwork, lat, lon):
    """Return the fixes released (index as tag) and the published element after each fix."""
    live = NetworkFixes(net, NOISE_M ** 2)
    released, published = [], []
    for k, (a, b) in enumerate(zip(lat.tolist(), lon.tolist())):
        released += live.add(k, a, b)
        published.append(live.element)
    return live, released, published


def offline_x(net: TrackNetwork, lat, lon, path, released) -> np.ndarray:
    """Return the released fixes' x on the offline path, from the first fix's projection."""
    s_m, _, _ = TrackGeometry(net.path_lonlat(path)).project(lat, lon)
    return s_m[[f.tag for f in released]] - s_m[0]


@pytest.mark.parametrize('drawn_reversed', [False, True])
@pytest.mark.parametrize('reverse', [False, True])
def test_the_diverging_branch_and_gross_fixes(drawn_reversed, reverse):
    """Past the switch onto C: the live path ends on C, x is the offline path's, gross out."""
    net = TrackNetwork(network(drawn_reversed))
    lat, lon = fixes('AC', reverse)

    def fix_at(past_m: float) -> int:
        """Return the fix this far past the switch (on C; negative: on A)."""
        return int(round((1000.0 + (past_m if not reverse else -past_m)) / STEP_M))

    # 200 m gross fixes, each alone: sideways (one on A, three on C), and onto B (the
    # other branch) from three on C (at 96 m, C leads B by less than one fix gives).
    gross = []
    for past_m in (-560.0, 328.0, 408.0, 488.0):
        k = fix_at(past_m)
        azimuth = GEOD.inv(lon[k - 1], lat[k - 1], lon[k], lat[k])[0]
        gross.append((k, GEOD.fwd(lon[k], lat[k], azimuth + 90.0, GROSS_M)[:2]))
    for past_m in (96.0, 448.0, 600.0):
        gross.append((fix_at(past_m), GEOD.fwd(*SWITCH, 90.0, past_m + 185.0)[:2]))
    lat, lon = fixes('AC', reverse, gross)
    path = net.match(lat, lon)
    names = [name for name, _ in path]
    assert names == (['A', 'C'] if not reverse else ['C', 'A'])
    live, released, published = run_live(net, lat, lon)
    assert published[-1] is not None and published[-1][0] == names[-1]
    # The published elements are the path's, each once: the gross fixes move nothing.
    runs = [p[0] for k, p in enumerate(published) if p and (k == 0 or p != published[k - 1])]
    assert runs == names
    assert live.counts.off_track == len(gross)
    assert sorted(set(range(lat.size)) - {f.tag for f in released}) == sorted(
        k for k, _ in gross)
    x = np.array([f.x_m for f in released])
    # x is the offline path's to the noise's share of the geometry: the fixes measured
    # on B before the model passes on to C (within ~40 m of the switch) differ by
    # a (1 - cos 8°) < 0.4 m; elsewhere x is the same projection (frames: < 1 mm).
    assert np.abs(x - offline_x(net, lat, lon, path, released)).max() < 0.4
    assert np.all(np.diff(x) > 0.0)                   # x grows with the travel


@pytest.mark.parametrize('drawn_reversed', [False, True])
@pytest.mark.parametrize('reverse', [False, True])
def test_the_parallel_pair_keeps_x_continuous(drawn_reversed, reverse):
    """A, B, then P of the pair 4 m apart: x continuous, the offline path's, either track."""
    net = TrackNetwork(network(drawn_reversed))
    lat, lon = fixes('ABP', reverse)
    path = net.match(lat, lon)
    live, released, published = run_live(net, lat, lon)
    assert live.counts.off_track == 0 and len(released) == lat.size
    assert published[-1][0] in ('P', 'Q') if not reverse else published[-1][0] == 'A'
    x = np.array([f.x_m for f in released])
    # On P or Q alike: a fix's x on the two differs by Q's lead (√(100² + 4²) − 100 =
    # 0.08 m) and its 2.3° angle (≤ 4 m · sin 2.3° = 0.16 m): < 0.4 m with the switch's.
    assert np.abs(x - offline_x(net, lat, lon, path, released)).max() < 0.4
    step = np.diff(x)
    # No step beyond the travel and the noise: 8 m ± 2 · 3 σ of the along-track noise.
    assert np.all(np.abs(step - STEP_M) < 6 * NOISE_M)


@pytest.mark.parametrize('with_covariance', [False, True])
@pytest.mark.parametrize('reverse', [False, True])
def test_the_segments_near_a_fix_change_nothing(monkeypatch, with_covariance, reverse):
    """On the segments near each fix only (the grid), every output is all segments' to the bit."""
    lat, lon = fixes('ABP', reverse)
    gross = []                 # sideways: 25 m (within the grid's reach) and 200 m (beyond)
    for k, off_m in ((40, 25.0), (90, GROSS_M), (150, GROSS_M), (200, 25.0), (230, GROSS_M)):
        azimuth = GEOD.inv(lon[k - 1], lat[k - 1], lon[k], lat[k])[0]
        gross.append((k, GEOD.fwd(lon[k], lat[k], azimuth + 90.0, off_m)[:2]))
    lat, lon = fixes('ABP', reverse, gross)
    wide = {150, 230}          # σ 80 m: a bound beyond the reach, so the fix is measured

    def run(net: TrackNetwork):
        """Return what a run published: the fixes released, the elements, the counts."""
        live = NetworkFixes(net, NOISE_M ** 2)
        released, published = [], []
        for k, (a, b) in enumerate(zip(lat.tolist(), lon.tolist())):
            covariance = None
            if with_covariance:
                covariance = np.diag([6400.0, 6400.0]) if k in wide else np.array(
                    [[4.0, 1.0], [1.0, 9.0]])
            released += live.add(k, a, b, covariance)
            published.append(live.element)
        return released, published, live.counts

    fast = run(TrackNetwork(network()))
    every = TrackNetwork(network())
    all_segments = np.arange(sum(len(line) - 1 for line in every.lines_m))
    monkeypatch.setattr(every, 'segments_near', lambda point_m: all_segments)
    assert fast == run(every)
    off = {k for k, _ in gross} - (wide if with_covariance else set())
    assert sorted(set(range(lat.size)) - {f.tag for f in fast[0]}) == sorted(off)
