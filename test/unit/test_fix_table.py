"""``kf-train replay FIXES.csv --track FILE`` equals the replay of the same fixes in a bag."""

import json

from kf_train.cli import main as kf_train_main
import numpy as np
import pytest

pyproj = pytest.importorskip('pyproj')
pytest.importorskip('rosbags')

NS = 1_000_000_000
START = (4.48, 50.90)
GEOD = pyproj.Geod(ellps='WGS84')


def fixes(count=80):
    """Return rows (t_s, lat, lon, accuracy_m or None, has_fix) of a 10-m/s train."""
    rng = np.random.default_rng(11)
    rows = []
    for k in range(count):
        lon, lat, _ = GEOD.fwd(*START, 60.0, 30.0 + 4.0 * k + rng.normal(0.0, 1.0))
        lon, lat, _ = GEOD.fwd(lon, lat, -30.0, 150.0 if k == 50 else rng.normal(0.0, 1.0))
        rows.append((1.7e9 + 0.4 * k, lat, lon, 1.5 if k >= 60 else None, k != 40))
    return rows


def write_inputs(tmp_path, rows):
    """Write the track, the fixes as CSV and as a NavSatFix bag; return their paths."""
    from kf_train.io.bagio_types import NAVSATFIX, TYPESTORE
    from rosbags.rosbag2 import StoragePlugin, Writer
    line = [START, GEOD.fwd(*START, 60.0, 2000.0)[:2]]
    track = tmp_path / 'track.geojson'
    track.write_text(json.dumps({'type': 'LineString', 'coordinates': line[::-1]}))
    table = tmp_path / 'fixes.csv'
    text = ['t,lat,lon,accuracy_m,speed']
    for t_s, lat, lon, accuracy, has_fix in rows:
        cells = (repr(lat), repr(lon)) if has_fix else ('', '')
        text.append(f'{t_s!r},{cells[0]},{cells[1]},{"" if accuracy is None else accuracy},9')
    table.write_text('\n'.join(text) + '\n')
    types = TYPESTORE.types
    with Writer(tmp_path / 'bag', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/fix', NAVSATFIX, typestore=TYPESTORE)
        for t_s, lat, lon, accuracy, has_fix in rows:
            stamp_ns = round(t_s * NS)
            covariance = np.zeros(9)
            if accuracy is not None:
                covariance[0] = covariance[4] = accuracy ** 2
            msg = types[NAVSATFIX](
                header=types['std_msgs/msg/Header'](stamp=types['builtin_interfaces/msg/Time'](
                    sec=stamp_ns // NS, nanosec=stamp_ns % NS), frame_id=''),
                status=types['sensor_msgs/msg/NavSatStatus'](status=0 if has_fix else -1,
                                                             service=1),
                latitude=lat if has_fix else float('nan'),
                longitude=lon if has_fix else float('nan'), altitude=0.0,
                position_covariance=covariance,
                position_covariance_type=0 if accuracy is None else 2)
            writer.write(connection, stamp_ns, TYPESTORE.serialize_cdr(msg, NAVSATFIX))
    return track, table, tmp_path / 'bag'


def test_fix_table_and_bag_are_bit_equal(tmp_path, capsys):
    """Same fixes, same track: the same CSV output; the gate and the no-fix counted."""
    track, table, bag = write_inputs(tmp_path, fixes())
    for source, output in ((table, 'from_table.csv'), (bag, 'from_bag.csv')):
        assert kf_train_main(['replay', str(source), '--track', str(track), '-o',
                              str(tmp_path / output)]) == 0
        assert '80 fixes: 1 without a position, 1 off the track' in capsys.readouterr().err
    from_table = (tmp_path / 'from_table.csv').read_text()
    assert from_table == (tmp_path / 'from_bag.csv').read_text()
    x = np.loadtxt(tmp_path / 'from_table.csv', delimiter=',', skiprows=1, usecols=1)
    assert x.size > 70 and np.all(np.diff(x[5:]) > 0.0)     # x grows: the track reversed


def test_fix_table_errors(tmp_path, capsys):
    """A table without lat/lon, or a bad number: one line naming it, exit 1."""
    track, _, _ = write_inputs(tmp_path, fixes(count=4))
    bad = tmp_path / 'bad.csv'
    for text, expected in (('t,x\n1,2\n', 'needs the columns t, lat, lon'),
                           ('t,lat,lon\n1,50.9,abc\n', 'line 2, column lon')):
        bad.write_text(text)
        assert kf_train_main(['replay', str(bad), '--track', str(track), '-o',
                              str(tmp_path / 'o.csv')]) == 1
        assert expected in capsys.readouterr().err


def test_a_network_track_runs_on_the_path_the_fixes_took(tmp_path, capsys):
    """--track NETWORK: the path chosen live; x is the chosen path's, from the first fix."""
    from kf_train.io import TrackGeometry, TrackNetwork
    from test_track_network import network, run_fixes
    document = network(with_relations=False)
    (tmp_path / 'network.geojson').write_text(json.dumps(document))
    lat, lon = run_fixes(98.0, reverse=False)
    table = tmp_path / 'fixes.csv'
    rows = [f'{1.7e9 + 0.4 * k!r},{a!r},{b!r}\n'
            for k, (a, b) in enumerate(zip(lat.tolist(), lon.tolist()))]
    table.write_text('t,lat,lon\n' + ''.join(rows))
    net = TrackNetwork(document)
    path = net.match(lat, lon)
    assert path == [('A', False), ('C', True)]
    (tmp_path / 'path.geojson').write_text(json.dumps(
        {'type': 'LineString', 'coordinates': net.path_lonlat(path).tolist()}))
    for track in ('network', 'path'):
        assert kf_train_main(['replay', str(table), '--track',
                              str(tmp_path / f'{track}.geojson'), '-o',
                              str(tmp_path / f'{track}.csv')]) == 0
        err = capsys.readouterr().err
        assert '2 off the track' in err and 'direction forward' in err
    # The same filter on the same fixes, x shifted by the path's s of the first fix (the
    # filter is shift-invariant), but for the first fixes past the switch, measured on
    # the nearest branch before the model passed on to C: within 10 m of the switch x
    # on B and on C differ by a (1 - cos 8°) + the noise's share, < 0.1 m.
    first_s_m = TrackGeometry(net.path_lonlat(path)).project(lat[:1], lon[:1])[0][0]
    on_network, on_path = (np.genfromtxt(tmp_path / f'{track}.csv', delimiter=',',
                                         names=True) for track in ('network', 'path'))
    assert on_network.size == on_path.size
    assert np.allclose(on_network['position'] + first_s_m, on_path['position'], rtol=0.0,
                       atol=0.1)
