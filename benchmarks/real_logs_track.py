"""
NavSatFix on a track file against the hand projection, on tp-lib's real logs (issue 25).

benchmarks/real_logs.py projects tp-lib's fixes onto tp-lib's path by hand (an
equirectangular frame, tp-lib's element windows) and gives the node along-track x.
This script gives the node what a user has instead: the fixes as sensor_msgs/NavSatFix
(latitude, longitude, no covariance: ``fix_variance_m2``) in a bag, and tp-lib's path
calculation chained into one LineString as the ``track`` file, with the node's
defaults (``measurement_type:=navsatfix``: kf_train.ros.track_input, the cross-track
gate, the direction of travel decided by the node). Per log it reports

* the fixes the cross-track gate rejected: of the gross ones (farther than
  GROSS_CROSS_M from tp-lib's path by the hand projection) and of the good ones
  (within GOOD_CROSS_M);
* the lock-out resets, and the (re)starts from a gross fix;
* the 2-s prediction RMSE and 2σ coverage, as real_logs.py scores them, for both
  modes, each against its own along-track fixes (the hand x for the hand mode, the
  track's x for this one: the two frames' scales differ by up to 0.13 %), over every
  later fix and over the good later fixes only;
* with ``--reverse``, the same with the track file drawn against the travel.

    PYTHONPATH=. python benchmarks/real_logs_track.py [--logs 29083,...] [--cache DIR]
        [-p NAME:=VALUE ...] [--reverse] [--network [--live | --cost [--rounds N]]]

``--network`` instead chooses each log's path on tp-lib's ``network_airport.geojson``
from its fixes (:mod:`kf_train.io.track_network`, offline map matching) and compares it
with tp-lib's path calculation, element by element. ``--network --live`` replays each
log twice: on that path (chosen offline, from every fix, as one track) and on the
network itself (the path chosen live, fix by fix: :mod:`kf_train.io.track_network_live`),
each scored against the later fix it released (its own x), with the elements run, the
fixes the gate rejected and the lock-outs (resets and re-acquisitions).

``--network --cost`` times the projection alone, without the node: per log, µs a fix
of NetworkFixes on the network and of TrackFixes on the path chosen offline as one
track (the median of ``--rounds`` runs, the two in turn), with a digest of all each
published (every x, variance and cross-track distance to the bit, the element after
each fix, the counts): equal digests, equal outputs. Run it with another checkout
first on PYTHONPATH to compare two versions.

The data are real_logs.py's (its cache, ``--data`` or ``$KF_TRAIN_TPLIB_DATA``; tp-lib,
Apache-2.0, is not in this repository). Needs pyproj and rosbags. Figures only.
"""

import argparse
import hashlib
import json
from pathlib import Path
import shutil
import sys
import time
from typing import Dict, List, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent))

from kf_train.evaluate import later_fix  # noqa: E402
from kf_train.sim import RAIL_WARMUP_S  # noqa: E402
from kf_train.sim.rail_eval import format_table  # noqa: E402
import numpy as np  # noqa: E402
import real_logs  # noqa: E402

GROSS_CROSS_M = 30.0      # a gross fix: this far off tp-lib's path (the hand projection)
GOOD_CROSS_M = 10.0       # a good fix: this close (real_logs.CLEAN_CROSS_M)
NS = real_logs.NS


def chained_track(path: Path, target: Path, reverse: bool = False) -> Path:
    """Write tp-lib's path calculation, chained in travel order, as one GeoJSON LineString."""
    vertices, _, _ = real_logs.chain_path(path, lambda lonlat: np.asarray(lonlat)[:, :2])
    keep = np.concatenate(([True], np.any(np.diff(vertices, axis=0) != 0.0, axis=1)))
    vertices = vertices[keep][::-1] if reverse else vertices[keep]
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps({'type': 'LineString', 'coordinates': vertices.tolist()}))
    return target


def fixes_in_order(csv_path: Path) -> Dict[str, np.ndarray]:
    """Return the log's fixes (unix t, lat, lon) kept as real_logs.along_track keeps them."""
    t_unix, lat, lon, _ = real_logs.read_fixes(csv_path)
    keep = np.concatenate(([True], np.diff(t_unix) > 0.0))
    keep &= t_unix >= np.maximum.accumulate(t_unix)
    return {'t_unix': t_unix[keep], 'lat': lat[keep], 'lon': lon[keep]}


def write_fix_bag(fixes: Dict[str, np.ndarray], path: Path) -> None:
    """Write the fixes as NavSatFix on /fix (no covariance), stamps in whole ms, as logged."""
    from kf_train.io.bagio_types import NAVSATFIX, TYPESTORE
    from rosbags.rosbag2 import StoragePlugin, Writer
    types = TYPESTORE.types
    shutil.rmtree(path, ignore_errors=True)     # a rosbag2 directory
    path.parent.mkdir(parents=True, exist_ok=True)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/fix', NAVSATFIX, typestore=TYPESTORE)
        for t_unix, lat, lon in zip(fixes['t_unix'], fixes['lat'], fixes['lon']):
            stamp_ns = int(round(t_unix * 1000)) * 1_000_000
            sec, nanosec = divmod(stamp_ns, NS)
            msg = types[NAVSATFIX](
                header=types['std_msgs/msg/Header'](stamp=types['builtin_interfaces/msg/Time'](
                    sec=sec, nanosec=nanosec), frame_id='gps'),
                status=types['sensor_msgs/msg/NavSatStatus'](status=0, service=1),
                latitude=float(lat), longitude=float(lon), altitude=0.0,
                position_covariance=np.zeros(9), position_covariance_type=0)
            writer.write(connection, stamp_ns, TYPESTORE.serialize_cdr(msg, NAVSATFIX))


def replay_track(bag_path: Path, track: Path, overrides: List[str], gross: np.ndarray
                 ) -> dict:
    """Run the node's session over the fix bag; per fix the 2-s prediction and the gate."""
    from kf_train.io import bagio
    from kf_train.replay import bag as bag_replay
    from kf_train.ros.session import EstimatorSession
    config = bag_replay.load_config([], ['measurement_type:=navsatfix', f'track:={track}']
                                    + list(overrides))
    horizon_ns = int(round(config.settings.horizon_s * NS))
    mean, variance, x_track = (np.full(gross.size, np.nan) for _ in range(3))
    off_track = np.zeros(gross.size, dtype=bool)
    starts = []
    with bagio.BagInput(bag_path, bagio.NAVSATFIX) as bag:
        now = [0.0]
        session = EstimatorSession(config, lambda: now[0])
        estimator, fixes = session.estimator, session.track.fixes
        released, elements = {}, []
        measurements = session.track.measurements

        def capture(fix):
            """Keep each released fix's x by its stamp (the node's own, as fused)."""
            out = measurements(fix)
            released.update((m.stamp_ns, m.position_m) for m in out)
            return out

        session.track.measurements = capture
        for k, message in enumerate(bag.messages()):
            now[0] = message.record_ns / NS
            before, was_initialized = fixes.counts.off_track, estimator.initialized
            session.on_fix(message, message.record_ns)
            off_track[k] = fixes.counts.off_track > before
            element = getattr(fixes, 'element', None)      # a network: the element now
            if element is not None and (not elements or elements[-1] != element[0]):
                elements.append(element[0])
            if estimator.initialized and not was_initialized:
                starts.append(k)
            if estimator.initialized:
                x, P = estimator.predict_to(message.stamp_ns + horizon_ns)
                mean[k], variance[k] = x[0], P[0, 0]
        counts = fixes.counts
        stamps = [m.stamp_ns for m in _all(bag_path)]
        if not elements:
            # Every fix's own along-track x on the chosen orientation: the score's target.
            s_m, _, _ = fixes.geometry.project(
                np.array([m.lat_deg for m in _all(bag_path)]),
                np.array([m.lon_deg for m in _all(bag_path)]))
            x_track = fixes.geometry.length_m - s_m if counts.direction == 'reverse' else s_m
        stats = estimator.stats()
    return {'mean': mean, 'variance': variance, 'x_m': x_track, 'off_track': off_track,
            'starts': starts, 'resets': {k: n for k, n in stats.resets.items() if n},
            'rejected': session.rejected, 'direction': counts.direction,
            'released_x_m': np.array([released.get(stamp, np.nan) for stamp in stamps]),
            'elements': elements, 'reacquisitions': stats.reacquisitions,
            'r_m2': config.settings.measurement_variance or config.options.fix_variance_m2}


def _all(bag_path: Path) -> list:
    """Return every fix of the bag (a second pass: cheap)."""
    from kf_train.io import bagio
    with bagio.BagInput(bag_path, bagio.NAVSATFIX) as bag:
        return list(bag.messages())


def scores(t: np.ndarray, z: np.ndarray, mean: np.ndarray, variance: np.ndarray,
           r_m2, good: np.ndarray) -> dict:
    """
    Return RMSE and coverage over every later fix and over the good later fixes.

    ``r_m2``: the later fix's R, one for all or one per fix (real_logs.py's R in use).
    """
    # Before the direction is decided the node holds the fixes: no prediction to score.
    target, valid = later_fix(t, z)
    scored = valid & np.isfinite(mean) & np.isfinite(target) & (t >= t[0] + RAIL_WARMUP_S)
    error = mean[scored] - target[scored]
    band = 2.0 * np.sqrt(np.maximum(variance[scored], 0.0)
                         + np.broadcast_to(r_m2, t.shape)[scored])
    rmse, coverage = float(np.sqrt(np.mean(error ** 2))), float(np.mean(np.abs(error) <= band))
    count = int(scored.sum())
    later_good, _ = later_fix(t, good.astype(float))
    scored &= later_good == 1.0
    error = mean[scored] - target[scored]
    return {'rmse_m': rmse, 'coverage': coverage, 'count': count,
            'rmse_good_m': float(np.sqrt(np.mean(error ** 2))), 'count_good': int(scored.sum())}


def evaluate(name: str, files, cache: Path, args: argparse.Namespace) -> dict:
    """Return both modes' figures on one log."""
    series, facts = real_logs.load_series(name, files, cache)
    fixes = fixes_in_order(files[0])
    t = series['t_s']
    assert t.size == fixes['t_unix'].size, 'the series and the fixes disagree'
    cross = np.abs(series['cross_m'])
    gross, good = cross > GROSS_CROSS_M, cross <= GOOD_CROSS_M
    hand = real_logs.replay_default(series, facts, cache / 'bags' / f'{name}.mcap',
                                    (), args.param or ())
    result = {'name': name, 'fixes': int(t.size), 'gross': int(gross.sum()),
              'good': int(good.sum()),
              'hand': scores(t, series['x_m'], hand['mean'], hand['variance'], hand['r_m2'],
                             good) | {'resets': hand['resets'], 'rejected': hand['rejected']}}
    bag_path = cache / 'bags' / f'{name}-fix'
    write_fix_bag(fixes, bag_path)
    for label, reverse in (('track', False),) + ((('reversed', True),) if args.reverse else ()):
        track = chained_track(files[1], cache / 'tracks' / f'{name}-{label}.geojson', reverse)
        run = replay_track(bag_path, track, args.param or [], gross)
        # The chain's direction is tp-lib's path order, the travel's: +x with the travel.
        result[label] = scores(t, run['x_m'], run['mean'], run['variance'], run['r_m2'],
                               good) | {
            'gross_rejected': int((run['off_track'] & gross).sum()),
            'good_rejected': int((run['off_track'] & good).sum()),
            'off_track': int(run['off_track'].sum()), 'resets': run['resets'],
            'starts': len(run['starts']),
            'starts_from_gross': int(sum(gross[k] for k in run['starts'])),
            'rejected': run['rejected'], 'direction': run['direction']}
    return result


def _resets(mode: dict) -> str:
    """Return a mode's resets by reason, in a few words."""
    return ', '.join(f'{k} {v}' for k, v in mode['resets'].items()) or 'no reset'


def network_paths(data: Path, logs: dict) -> None:
    """Print, per log, whether the path chosen on the network is tp-lib's path calculation."""
    from kf_train.io.track_network import TrackNetwork
    network = TrackNetwork.from_file(data / 'network_airport.geojson')
    rows = []
    for name, (fixes, path) in logs.items():
        _, lat, lon, _ = real_logs.read_fixes(fixes)
        ours = [element for element, _ in network.match(lat, lon)]
        theirs = [f['properties']['netelement_id']
                  for f in json.loads(path.read_text())['features']]
        same = next((k for k, (a, b) in enumerate(zip(ours, theirs)) if a != b),
                    min(len(ours), len(theirs)))
        rows.append((name, 'yes' if ours == theirs else 'no', len(theirs), len(ours),
                     same, len(set(theirs)) < len(theirs)))
    print(format_table(('log', "tp-lib's path", "tp-lib's elements", 'ours',
                        'first elements equal', "tp-lib's path runs an element twice"), rows))


def network_replays(data: Path, logs: dict, cache: Path, args: argparse.Namespace) -> None:
    """Print, per log, the node on the path chosen offline and on the network, live."""
    from kf_train.io.track_network import TrackNetwork
    network_file = data / 'network_airport.geojson'
    network = TrackNetwork.from_file(network_file)
    rows = []
    for name, files in logs.items():
        start = time.perf_counter()
        series, _ = real_logs.load_series(name, files, cache)
        fixes = fixes_in_order(files[0])
        t, cross = series['t_s'], np.abs(series['cross_m'])
        gross, good = cross > GROSS_CROSS_M, cross <= GOOD_CROSS_M
        bag_path = cache / 'bags' / f'{name}-fix'
        write_fix_bag(fixes, bag_path)
        path = network.match(fixes['lat'], fixes['lon'])
        offline = cache / 'tracks' / f'{name}-offline-path.geojson'
        offline.write_text(json.dumps({'type': 'LineString',
                                       'coordinates': network.path_lonlat(path).tolist()}))
        names = [element for element, _ in path]
        for label, track in (('offline path', offline), ('live', network_file)):
            run = replay_track(bag_path, track, args.param or [], gross)
            # Each mode against the later fix it released, its own x (NaN: not released).
            d = scores(t, run['released_x_m'], run['mean'], run['variance'], run['r_m2'],
                       good)
            elements = run['elements'] or names
            rows.append((
                name, label, len(elements), 'yes' if elements == names else 'no',
                int(np.isfinite(run['released_x_m']).sum()), int(run['off_track'].sum()),
                f"{int((run['off_track'] & gross).sum())} / {int(gross.sum())}",
                f"{int((run['off_track'] & good).sum())} / {int(good.sum())}",
                sum(run['resets'].values()) + run['reacquisitions'],
                f"{len(run['starts'])} / {int(sum(gross[k] for k in run['starts']))}",
                f"{d['rmse_m']:.2f}", f"{d['rmse_good_m']:.2f}", f"{100 * d['coverage']:.1f} %"))
        print(f'{name} ({time.perf_counter() - start:.1f} s)', flush=True)
    print(format_table(('log', 'mode', 'elements', 'as offline', 'released', 'off track',
                        'gross rejected', 'good rejected', 'lock-outs', 'starts / from gross',
                        'RMSE all [m]', 'RMSE good [m]', '2σ cov.'), rows))


def _published(fixes, lat: np.ndarray, lon: np.ndarray) -> Tuple[float, str]:
    """Return (s a fix, digest of what was published) of one run of fixes over a log."""
    digest = hashlib.sha256()
    start = time.perf_counter()
    for k in range(lat.size):
        out = fixes.add(k, lat[k], lon[k])
        digest.update(repr([(f.tag, f.x_m.hex(), f.variance_m2.hex(), f.cross_m.hex())
                            for f in out] + [getattr(fixes, 'element', None)]).encode())
    elapsed_s = time.perf_counter() - start
    digest.update(repr(fixes.counts).encode())
    return elapsed_s / lat.size, digest.hexdigest()[:12]


def network_cost(data: Path, logs: dict, rounds: int) -> None:
    """Print, per log, µs a fix of the path chosen live and of one track, and their digests."""
    from kf_train.io import NetworkFixes, TrackFixes, TrackGeometry, TrackNetwork
    from kf_train.ros.track_input import FIX_VARIANCE_M2
    network = TrackNetwork.from_file(data / 'network_airport.geojson')
    rows = []
    for name, files in logs.items():
        fixes = fixes_in_order(files[0])
        lat, lon = fixes['lat'], fixes['lon']
        track = TrackGeometry(network.path_lonlat(network.match(lat, lon)))
        runs = {'network': [], 'track': []}
        for _ in range(rounds):         # the two in turn: the machine's drift hits both
            runs['network'].append(_published(NetworkFixes(network, FIX_VARIANCE_M2), lat, lon))
            runs['track'].append(_published(TrackFixes(track, FIX_VARIANCE_M2), lat, lon))
        assert all(len({d for _, d in r}) == 1 for r in runs.values()), 'runs disagree'
        rows.append((name, lat.size) + tuple(
            x for r in runs.values() for x in (f'{1e6 * np.median([s for s, _ in r]):.0f}',
                                               r[0][1])))
    print(format_table(('log', 'fixes', 'network [µs/fix]', 'network digest',
                        'one track [µs/fix]', 'track digest'), rows))


def print_table(results: List[dict], labels) -> None:
    """Print one row per log and mode."""
    rows = []
    for r in results:
        h = r['hand']
        rows.append((r['name'], 'hand x', r['fixes'], r['gross'], '-', '-',
                     sum(h['resets'].values()), '-', f"{h['rejected']} ({_resets(h)})",
                     f"{h['rmse_m']:.2f}", f"{h['rmse_good_m']:.2f}",
                     f"{100 * h['coverage']:.1f} %"))
        for label in labels:
            d = r[label]
            rows.append((
                r['name'], f"NavSatFix ({label}: {d['direction']})", r['fixes'], r['gross'],
                f"{d['gross_rejected']} ({100 * d['gross_rejected'] / max(r['gross'], 1):.1f} %)",
                f"{d['good_rejected']} ({100 * d['good_rejected'] / max(r['good'], 1):.1f} %)",
                sum(d['resets'].values()), f"{d['starts']} / {d['starts_from_gross']}",
                f"{d['rejected']} ({_resets(d)})",
                f"{d['rmse_m']:.2f}", f"{d['rmse_good_m']:.2f}",
                f"{100 * d['coverage']:.1f} %"))
    print(format_table(('log', 'mode', 'fixes', 'gross', 'gross rejected', 'good rejected',
                        'resets', 'starts / from gross', 'χ² rejected (resets)', 'RMSE all [m]',
                        'RMSE good [m]', '2σ cov.'), rows))


def main() -> int:
    """Run both modes on the logs; print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--data', help="tp-lib's test-data (as real_logs.py)")
    parser.add_argument('--cache', default=str(real_logs.DEFAULT_CACHE))
    parser.add_argument('--from-git', metavar='GIT_DIR')
    parser.add_argument('--fetch', action='store_true')
    parser.add_argument('--logs', help='comma-separated log ids (default: all)')
    parser.add_argument('--reverse', action='store_true',
                        help='also run with the track drawn against the travel')
    parser.add_argument('-p', '--param', metavar='NAME:=VALUE', action='append',
                        help='a node parameter for both replays; may be repeated')
    parser.add_argument('--json', metavar='FILE', help='also write the figures as JSON')
    parser.add_argument('--network', action='store_true',
                        help="only choose each log's path on network_airport.geojson and "
                             "compare it with tp-lib's path calculation")
    parser.add_argument('--live', action='store_true',
                        help='with --network: replay each log on the path chosen offline and '
                             'on the network, the path chosen live, and compare')
    parser.add_argument('--cost', action='store_true',
                        help='with --network: µs a fix of the path chosen live and of one '
                             'track, without the node, and digests of their outputs')
    parser.add_argument('--rounds', type=int, default=5, help='runs per log with --cost')
    args = parser.parse_args()
    cache = Path(args.cache).expanduser()
    data = real_logs.data_dir(args, cache)
    logs = real_logs.find_logs(data)
    if args.logs:
        wanted = {w if w.startswith('log_') else f'log_{w}' for w in args.logs.split(',')}
        logs = {k: v for k, v in logs.items() if k in wanted}
    if args.network:
        data = data if (data / 'network_airport.geojson').exists() else data / 'test-data'
        if args.cost:
            network_cost(data, logs, args.rounds)
        elif args.live:
            network_replays(data, logs, cache, args)
        else:
            network_paths(data, logs)
        return 0
    results = []
    for name, files in logs.items():
        start = time.perf_counter()
        results.append(evaluate(name, files, cache, args))
        print(f'{name} ({time.perf_counter() - start:.1f} s)', flush=True)
    print_table(results, ('track', 'reversed') if args.reverse else ('track',))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
