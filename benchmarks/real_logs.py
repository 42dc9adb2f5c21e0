"""
The rail default on real recordings: tp-lib's GNSS logs of Belgian trains (issue 24).

tp-lib (https://github.com/Matdata-eu/tp-lib, Matdata-eu, Apache-2.0) ships in its
``test-data/`` a dozen real GNSS logs of trains on line 36 around Brussels airport
(2.5 Hz, ``log_<id>/log_<id>_<route>.csv``: latitude, longitude, timestamp, the
receiver's position_type) and, per log, tp-lib's own path calculation
(``*-path-calculation.geojson``: the chain of network elements, LineStrings in
WGS 84, the train ran, in order, each with the range of fixes it holds). Nothing of
it is in this repository; docs/real-logs.md says where to get it.

Per log this script

1. reads the fixes and puts them, and the path, in a local metric frame: an
   equirectangular projection about the log's mean latitude and longitude with
   WGS 84's radii of curvature there (x east = N cos(lat0) dlon, y north = M dlat; a
   sphere's mean radius would shrink east-west by 0.3 % at 51° N). A log spans
   < 15 km, so the east scale is off by at most tan(lat0) * 7 km / R, ~0.13 %: < 4 cm
   on the <= 30 m a train runs in 2 s, and the same for fixes and track, so
   cross-track distances keep it too (against the logs' own Lambert 72 coordinates,
   consecutive fixes' distances agree to 0.04 %);
2. chains the path's LineStrings, each turned to start where the previous ended,
   into one polyline, s = 0 at its start, and projects every fix onto it
   (:func:`kf_train.io.track.project_onto_polyline`) within the arc-length range of
   the elements tp-lib assigned it to, widened by WINDOW_MARGIN_M: the along-track
   position x_m (the 1-D series) and the signed cross-track distance cross_m;
3. caches the series as ``<cache>/series/<log>.csv`` (t_s, x_m, cross_m,
   position_type) with a ``.json`` of the log's facts, and reuses them;
4. scores 2-s predictions, made after every fix from WARMUP_S on, against the fix
   2 s later (linearly interpolated between the two fixes around t + 2 s when none is
   within 1 ms, and only when those two are <= MAX_BRACKET_S apart;
   :mod:`kf_train.evaluate.later_fix`): the RMSE and the 2σ coverage (the
   prediction's variance plus the later fix's R: the default's R in use, the learned
   scale applied, not the 3 m² given, which would cover every error), of
   * ``default``: the estimator node's defaults (the rail IMM, χ² gate, lock-out)
     over the series as a bag, variance R_FIX_M2 per fix (the logs carry no
     accuracy), run exactly as ``kf-train replay BAG -o out.csv`` runs it (the node's
     session; a rejected fix's prediction is the newest state's, predicted on);
   * ``CV``, ``CA``: Kalman filters with q and R grid-searched in hindsight on
     that very log (kf_train.sim.rail_baselines' models), the best RMSE kept (and
     cached as ``<cache>/anchors/``, keyed by the series and the grids: they do not
     depend on the node's parameters, so a sweep of those reuses them);
5. prints one table, the artefacts of each log, and the structure function D(τ) of
   the along-track position minus a smooth reference (a centred local cubic over
   ±REFERENCE_HALF_WINDOW_S, within stretches without gaps): the short-τ texture of
   the error, to set beside /work/shared/gnss-receiver-statistics.md.

    PYTHONPATH=. python benchmarks/real_logs.py --data DIR [--cache DIR] [--logs 28876,...]
        [-p NAME:=VALUE ...] [--params-file FILE] [--rebuild] [--json FILE]

DIR (or $KF_TRAIN_TPLIB_DATA) is tp-lib's ``test-data`` (or a checkout holding it);
``--from-git GIT_DIR`` copies the files needed out of a tp-lib clone (bare or not)
into the cache; ``--fetch`` makes that clone first (needs access to GitHub; tp-lib's
PyPI sdist does not contain test-data). Figures only, no assertion.
"""

import argparse
import csv
import datetime
import hashlib
import json
import os
from pathlib import Path
import re
import subprocess
import sys
import time
from typing import Dict, List, Sequence, Tuple

from kf_train.evaluate import later_fix_score as score
from kf_train.io.track import polyline_arc_lengths_m, project_onto_polyline
from kf_train.sim.rail_baselines import (
    INITIAL_ACCELERATION_STD_MPS2, INITIAL_VELOCITY_STD_MPS, transition, white_noise_Q)
from kf_train.sim.rail_eval import format_table, HORIZON_S
import numpy as np

WGS84_A_M = 6378137.0             # WGS 84 semi-major axis
WGS84_E2 = 6.69437999014e-3       # WGS 84 first eccentricity squared
R_FIX_M2 = 3.0                    # the variance given with every fix (issue 24)
WINDOW_MARGIN_M = 100.0           # how far past its assigned elements a fix may land
CLEAN_CROSS_M = 10.0              # a clean log: every fix this close to the path
CLEAN_BEHIND_M = 5.0              # and never this far behind its own furthest fix
REASSIGN_M = 20.0                 # how much nearer elsewhere on the path overrides tp-lib
GAP_S = 1.0                       # a step longer than this is a gap (nominal 0.4 s)
TUNNEL_GAP_S = 10.0               # a gap this long: the receiver lost the sky
STAND_SPEED_MPS = 0.3             # slower than this over ±DWELL_HALF_SPAN_S: standing
DWELL_HALF_SPAN_S = 2.0
REFERENCE_HALF_WINDOW_S = 10.0
TAUS_S = (0.4, 0.8, 2.0, 4.0, 6.0)
CV_Q_GRID = tuple(np.logspace(-3.0, 4.0, 22))     # m²/s³
CA_Q_GRID = tuple(np.logspace(-5.0, 3.0, 25))     # m²/s⁵
R_GRID = tuple(np.logspace(-4.0, 1.0, 11))        # m²
TPLIB_URL = 'https://github.com/Matdata-eu/tp-lib'
DEFAULT_CACHE = Path(os.environ.get('XDG_CACHE_HOME', Path.home() / '.cache')) / \
    'kf_train' / 'tplib'
LOG_DIR = re.compile(r'^log_\d+$')
NS = 1_000_000_000


# -- the data ------------------------------------------------------------------------------

def copy_from_git(git_dir: Path, target: Path) -> Path:
    """Copy LICENSE, test-data's logs and paths out of a tp-lib git clone; return test-data."""
    git = ['git', '--git-dir', str(git_dir)]
    if (git_dir / '.git').is_dir():
        git = ['git', '-C', str(git_dir)]
    names = subprocess.run(git + ['ls-tree', '-r', '--name-only', 'HEAD', 'test-data'],
                           check=True, capture_output=True, text=True).stdout.split()
    wanted = re.compile(r'^test-data/(log_\d+/[^/]+(\.csv|-path-calculation\.geojson)'
                        r'|README\.md|network_airport\.geojson)$')
    for name in ['LICENSE'] + [n for n in names if wanted.match(n)]:
        path = target / name
        path.parent.mkdir(parents=True, exist_ok=True)
        blob = subprocess.run(git + ['show', 'HEAD:' + name], check=True,
                              capture_output=True).stdout
        path.write_bytes(blob)
    return target / 'test-data'


def fetch(cache: Path) -> Path:
    """Clone tp-lib (sparse, test-data only) into the cache; return its test-data."""
    clone = cache / 'tp-lib'
    if not clone.exists():
        subprocess.run(['git', 'clone', '--depth', '1', '--filter=blob:none', '--sparse',
                        TPLIB_URL, str(clone)], check=True)
        subprocess.run(['git', '-C', str(clone), 'sparse-checkout', 'set', 'test-data'],
                       check=True)
    return clone / 'test-data'


def find_logs(data: Path) -> Dict[str, Tuple[Path, Path]]:
    """Return {log name: (fixes CSV, path calculation)} of the log directories under data."""
    if (data / 'test-data').is_dir():
        data = data / 'test-data'
    logs = {}
    for directory in sorted(p for p in data.iterdir() if LOG_DIR.match(p.name)):
        fixes = list(directory.glob('log_*.csv'))
        paths = list(directory.glob('*-path-calculation.geojson'))
        if len(fixes) == 1 and len(paths) == 1:
            logs[directory.name] = (fixes[0], paths[0])
    if not logs:
        raise SystemExit(f'no log_<id>/ directories with a CSV and a path under {data}')
    return logs


def read_fixes(path: Path) -> Tuple[np.ndarray, np.ndarray, np.ndarray, List[str]]:
    """Return (t_unix_s, latitude, longitude, position_type) of a tp-lib GNSS CSV, in order."""
    t, lat, lon, kind = [], [], [], []
    with open(path, newline='') as stream:
        for row in csv.DictReader(stream):
            stamp = datetime.datetime.fromisoformat(row['timestamp'])
            if stamp.tzinfo is None:                   # tp-lib's stamps are UTC
                stamp = stamp.replace(tzinfo=datetime.timezone.utc)
            t.append(stamp.timestamp())
            lat.append(float(row['latitude']))
            lon.append(float(row['longitude']))
            kind.append(row.get('position_type', ''))
    return np.array(t), np.array(lat), np.array(lon), kind


def local_frame(lat0_deg: float, lon0_deg: float):
    """Return lonlat (N, 2) [deg] -> xy (N, 2) [m]: equirectangular about (lat0, lon0)."""
    sin2 = np.sin(np.radians(lat0_deg)) ** 2
    # WGS 84's radii of curvature at lat0: the prime vertical N (east), meridional M (north).
    prime_vertical_m = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin2)
    meridional_m = WGS84_A_M * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * sin2) ** 1.5
    scale_x = prime_vertical_m * np.cos(np.radians(lat0_deg))

    def to_xy(lonlat: np.ndarray) -> np.ndarray:
        lonlat = np.asarray(lonlat, dtype=float)
        return np.column_stack([scale_x * np.radians(lonlat[:, 0] - lon0_deg),
                                meridional_m * np.radians(lonlat[:, 1] - lat0_deg)])
    return to_xy


def chain_path(path: Path, to_xy) -> Tuple[np.ndarray, List[tuple], float]:
    """
    Return (vertices, pieces, widest joint [m]) of tp-lib's path calculation, chained.

    Each LineString is turned so that it starts at the end of the previous one (the
    first so that it ends next to the second); ``pieces`` holds (s_start_m, s_end_m,
    first fix, last fix) of each element in the chain. A joint's gap is a segment.
    """
    features = json.loads(path.read_text())['features']
    lines = [to_xy(f['geometry']['coordinates']) for f in features]
    if len(lines) > 1:
        ends = np.array([lines[1][0], lines[1][-1]])
        if (np.hypot(*(ends - lines[0][0]).T).min()
                < np.hypot(*(ends - lines[0][-1]).T).min()):
            lines[0] = lines[0][::-1]
    widest = 0.0
    for k in range(1, len(lines)):
        end = lines[k - 1][-1]
        if np.hypot(*(lines[k][-1] - end)) < np.hypot(*(lines[k][0] - end)):
            lines[k] = lines[k][::-1]
        widest = max(widest, float(np.hypot(*(lines[k][0] - end))))
    vertices = np.concatenate(lines)
    arc = polyline_arc_lengths_m(vertices)
    first = np.cumsum([0] + [len(line) for line in lines])
    pieces = [(float(arc[first[k]]), float(arc[first[k + 1] - 1]),
               int(f['properties']['gnss_start_index']), int(f['properties']['gnss_end_index']))
              for k, f in enumerate(features)]
    return vertices, pieces, widest


def along_track(fixes: Path, path: Path) -> Tuple[Dict[str, np.ndarray], dict]:
    """Return the 1-D series {t_s, x_m, cross_m, position_type} of one log and its facts."""
    t_unix, lat, lon, kind = read_fixes(fixes)
    to_xy = local_frame(float(lat.mean()), float(lon.mean()))
    vertices, pieces, widest = chain_path(path, to_xy)
    count = t_unix.size
    lo, hi = np.full(count, np.inf), np.full(count, -np.inf)
    for s_start, s_end, first, last in pieces:
        part = slice(max(first, 0), min(last, count - 1) + 1)
        lo[part] = np.minimum(lo[part], s_start - WINDOW_MARGIN_M)
        hi[part] = np.maximum(hi[part], s_end + WINDOW_MARGIN_M)
    unassigned = ~np.isfinite(lo)
    lo[unassigned], hi[unassigned] = -np.inf, np.inf
    points = to_xy(np.column_stack([lon, lat]))
    x_m, cross_m = project_onto_polyline(points, vertices, lo, hi)
    # Where tp-lib's assignment is off (a fix held by an element it is far from), the
    # nearest point of the whole path, unless that is hardly nearer (a path run twice).
    anywhere_m, anywhere_cross_m = project_onto_polyline(points, vertices)
    off = np.abs(anywhere_cross_m) < np.abs(cross_m) - REASSIGN_M
    ids = [f['properties']['netelement_id'] for f in json.loads(path.read_text())['features']]
    if len(set(ids)) < len(ids):               # the path runs an element twice: ambiguous
        off[:] = False
    x_m[off], cross_m[off] = anywhere_m[off], anywhere_cross_m[off]
    # The node takes increasing stamps: a repeated or earlier stamp is dropped here.
    keep = np.concatenate(([True], np.diff(t_unix) > 0.0))
    keep &= t_unix >= np.maximum.accumulate(t_unix)
    names = sorted(set(kind))
    series = {'t_s': t_unix[keep] - t_unix[0], 'x_m': x_m[keep], 'cross_m': cross_m[keep],
              'position_type': np.array([names.index(k) for k in kind])[keep]}
    facts = {'source': str(fixes), 'path': str(path), 't0_unix_s': float(t_unix[0]),
             't0_utc': datetime.datetime.fromtimestamp(
                 t_unix[0], datetime.timezone.utc).isoformat(),
             'fixes_in_file': int(count), 'dropped_stamps': int(count - keep.sum()),
             'unassigned_fixes': int(unassigned.sum()), 'reassigned_fixes': int(off.sum()),
             'path_revisits': len(set(ids)) < len(ids), 'path_length_m': float(
                 polyline_arc_lengths_m(vertices)[-1]),
             'widest_joint_m': widest, 'position_types': names}
    return series, facts


def load_series(name: str, files: Tuple[Path, Path], cache: Path, rebuild: bool = False
                ) -> Tuple[Dict[str, np.ndarray], dict]:
    """Return a log's series from the cache, made and cached first if absent or stale."""
    csv_path, json_path = cache / 'series' / f'{name}.csv', cache / 'series' / f'{name}.json'
    newest_input = max(p.stat().st_mtime for p in files)
    if (rebuild or not csv_path.exists() or not json_path.exists()
            or csv_path.stat().st_mtime < newest_input):
        series, facts = along_track(*files)
        csv_path.parent.mkdir(parents=True, exist_ok=True)
        table = np.column_stack([series[k] for k in ('t_s', 'x_m', 'cross_m', 'position_type')])
        np.savetxt(csv_path, table, delimiter=',', header='t_s,x_m,cross_m,position_type',
                   comments='', fmt=['%.3f', '%.4f', '%.4f', '%d'])
        json_path.write_text(json.dumps(facts, indent=1) + '\n')
    # Always the file's (rounded) numbers: a fresh run and a cached one score alike.
    table = np.loadtxt(csv_path, delimiter=',', skiprows=1, ndmin=2)
    series = dict(zip(('t_s', 'x_m', 'cross_m', 'position_type'), table.T))
    return series, json.loads(json_path.read_text())


def artefacts(series: Dict[str, np.ndarray], facts: dict) -> dict:
    """Return a log's gaps, jumps, reversals, fix types, class and a one-line summary."""
    t, x, cross = series['t_s'], series['x_m'], series['cross_m']
    dt, dx = np.diff(t), np.diff(x)
    behind = np.maximum.accumulate(x) - x          # how far behind its own furthest fix
    kinds = np.bincount(series['position_type'].astype(int),
                        minlength=len(facts['position_types']))
    a = {'gaps': int(np.sum(dt > GAP_S)), 'longest_step_s': float(dt.max()),
         'cross_median_m': float(np.median(np.abs(cross))),
         'cross_p95_m': float(np.percentile(np.abs(cross), 95.0)),
         'cross_max_m': float(np.abs(cross).max()), 'off_20m': int(np.sum(np.abs(cross) > 20.0)),
         'steps_back': int(np.sum(dx < -1.0)), 'behind_max_m': float(behind.max()),
         'fastest_mps': float(np.max(np.abs(dx) / dt))}
    clean = a['cross_max_m'] <= CLEAN_CROSS_M and a['behind_max_m'] <= CLEAN_BEHIND_M
    tunnel = a['longest_step_s'] > TUNNEL_GAP_S
    a['class'] = 'clean' if clean else ('tunnel gap' if tunnel else 'dirty')
    if facts['path_revisits']:    # the chain runs back and forth: x jumps where it turns
        a['class'] = 'bad path'
    types = ', '.join(f'{n} {c}' for n, c in zip(facts['position_types'], kinds))
    a['line'] = (
        f"{a['class']}: dt median {np.median(dt):.2f} s, {a['gaps']} gaps > {GAP_S:g} s "
        f"(longest {a['longest_step_s']:.1f} s), {facts['dropped_stamps']} repeated/backward "
        f"stamps dropped; |cross| median {a['cross_median_m']:.2f} m, p95 "
        f"{a['cross_p95_m']:.1f} m, max {a['cross_max_m']:.0f} m, {a['off_20m']} fixes > 20 m "
        f"off; steps back > 1 m: {a['steps_back']}, furthest behind {a['behind_max_m']:.0f} m; "
        f"fastest step {a['fastest_mps']:.0f} m/s; {facts['reassigned_fixes']} fixes "
        f"reassigned off tp-lib's elements; {types}")
    return a


# -- scoring --------------------------------------------------------------------------------

def batch_polynomial_kf(t: np.ndarray, z: np.ndarray, dim: int, qs: np.ndarray,
                        rs: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """
    Return (mean, variance) (G, N) of 2-s predictions of G CV/CA KFs, one per (q, R).

    The arithmetic of kf_train.sim.rail_baselines.PolynomialKF (start at the first fix
    with v = a = 0 and the rail priors' variances, F(dt) and white-noise Q(dt) of the
    actual step), batched over the grid; the Joseph form as KalmanFilter's.
    """
    G, N = qs.size, t.size
    x = np.zeros((G, dim))
    x[:, 0] = z[0]
    P = np.zeros((G, dim, dim))
    P[:, 0, 0] = rs
    P[:, 1, 1] = INITIAL_VELOCITY_STD_MPS ** 2
    if dim == 3:
        P[:, 2, 2] = INITIAL_ACCELERATION_STD_MPS2 ** 2
    ahead = transition(dim, HORIZON_S)[0]
    q_ahead = white_noise_Q(dim, HORIZON_S, 1.0)[0, 0] * qs
    mean, variance = np.empty((G, N)), np.empty((G, N))
    eye = np.eye(dim)
    for k in range(N):
        if k:
            dt = float(t[k] - t[k - 1])
            F = transition(dim, dt)
            x = x @ F.T
            P = F @ P @ F.T + qs[:, None, None] * white_noise_Q(dim, dt, 1.0)
            S = P[:, 0, 0] + rs
            K = P[:, :, 0] / S[:, None]
            x = x + K * (z[k] - x[:, 0])[:, None]
            I_KH = eye - K[:, :, None] * eye[0][None, None, :]
            P = I_KH @ P @ I_KH.transpose(0, 2, 1) + rs[:, None, None] * K[:, :, None] \
                * K[:, None, :]
        mean[:, k] = x @ ahead
        variance[:, k] = np.einsum('a,gab,b->g', ahead, P, ahead) + q_ahead
    return mean, variance


def tuned(t: np.ndarray, z: np.ndarray, dim: int, q_grid) -> dict:
    """Return the best (q, R) of the grid on this log: its q, R, RMSE and coverage."""
    qs, rs = (a.ravel() for a in np.meshgrid(np.asarray(q_grid), np.asarray(R_GRID)))
    mean, variance = batch_polynomial_kf(t, z, dim, qs, rs)
    best = None
    for g in range(qs.size):
        rmse, coverage, count = score(t, z, mean[g], variance[g], rs[g])
        if best is None or rmse < best['rmse_m']:
            best = {'q': float(qs[g]), 'r_m2': float(rs[g]), 'rmse_m': rmse,
                    'coverage': coverage, 'count': count}
    # The track depends on q and R almost only through q/R: at an edge of that ratio's
    # reach the optimum may lie beyond the grid.
    ratio = qs / rs
    best['on_grid_edge'] = best['q'] / best['r_m2'] in (ratio.min(), ratio.max())
    return best


def tuned_cached(cache: Path, name: str, t: np.ndarray, z: np.ndarray, dim: int,
                 q_grid) -> dict:
    """Return :func:`tuned`'s answer, kept in the cache keyed by the series and the grids."""
    key = hashlib.sha256(b''.join(np.ascontiguousarray(a, dtype=float).tobytes() for a in (
        t, z, np.asarray(q_grid), np.asarray(R_GRID))) + bytes([dim])).hexdigest()[:16]
    path = cache / 'anchors' / f'{name}_{dim}_{key}.json'
    if path.exists():
        return json.loads(path.read_text())
    best = tuned(t, z, dim, q_grid)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(best) + '\n')
    return best


def write_bag(series: Dict[str, np.ndarray], facts: dict, path: Path) -> None:
    """Write the series as the simulator's measurement topic, R_FIX_M2 per fix, real stamps."""
    from kf_train.io import bagio_simulation
    start_ns = int(round(facts['t0_unix_s'] * 1000)) * 1_000_000     # whole ms, as logged
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    with bagio_simulation.SimulationBag(path, None) as bag:
        for t_s, x_m in zip(series['t_s'], series['x_m']):
            stamp_ns = start_ns + int(round(t_s * 1000)) * 1_000_000
            bag.write_measurement(stamp_ns, stamp_ns, 'odom', float(x_m), R_FIX_M2)


def replay_default(series: Dict[str, np.ndarray], facts: dict, bag_path: Path,
                   params_files: Sequence[str] = (), overrides: Sequence[str] = ()) -> dict:
    """
    Return the node defaults' 2-s predictions and counts over the series, as a bag.

    ``kf-train replay BAG`` runs :class:`kf_train.replay.bag.BagRun`; so does this,
    keeping per fix the published prediction (or, for a rejected fix, the newest
    state's predicted to t + 2 s), the velocity estimate, the diagnostics and the
    estimator's reset counts.
    """
    from kf_train.io import bagio
    from kf_train.replay import bag as bag_replay
    write_bag(series, facts, bag_path)         # cheap: always from the current series
    config = bag_replay.load_config(list(params_files), list(overrides))
    horizon_ns = int(round(config.settings.horizon_s * NS))
    count = series['t_s'].size
    mean, variance = np.full(count, np.nan), np.full(count, np.nan)
    velocity, p_stand = np.full(count, np.nan), np.full(count, np.nan)
    r_m2 = np.full(count, float(config.settings.measurement_variance or R_FIX_M2))
    statuses = []
    with bagio.BagInput(bag_path) as bag:
        run = bag_replay.BagRun(config, bag)
        outputs = run.outputs(lambda ns, status: statuses.append(status))
        for k, (_, out) in enumerate(outputs):
            estimator = run.session.estimator
            step = out.step
            if step is not None and step.prediction_stamp_ns - step.stamp_ns == horizon_ns:
                mean[k], variance[k] = step.predicted_x[0], step.predicted_P[0, 0]
                velocity[k] = step.x[1]
            elif estimator.initialized:
                x, P = estimator.predict_to(run.now_ns + horizon_ns)   # record = stamp
                mean[k], variance[k] = x[0], P[0, 0]
            else:   # reset by this fix, not restarted yet: the fix held where it is
                mean[k], variance[k] = series['x_m'][k], R_FIX_M2
            if estimator.initialized:   # the later fix's share of a band: R in use
                r_m2[k] = estimator.variance_in_use(R_FIX_M2)
            modes = estimator.mode_probabilities() if estimator.initialized else None
            if modes is not None and 'stand' in modes[0]:
                p_stand[k] = modes[1][modes[0].index('stand')]
        stats = run.session.estimator.stats()
        rejected = run.session.rejected
    resets = {reason: n for reason, n in stats.resets.items() if n}
    if stats.reacquisitions:      # lock-outs that kept the track (lockout reacquire)
        resets['reacquired'] = stats.reacquisitions
    too_large = sum('too large' in s.message for s in statuses)
    return {'mean': mean, 'variance': variance, 'velocity': velocity, 'p_stand': p_stand,
            'rejected': rejected,
            'resets': resets, 'diagnostics': len(statuses), 'too_large': too_large,
            'horizon_s': config.settings.horizon_s, 'r_m2': r_m2}


def structure_function(t: np.ndarray, x: np.ndarray) -> Dict[float, Tuple[float, int]]:
    """
    Return {τ: (D(τ) [m], pairs)} of x minus a centred local cubic (the smooth reference).

    Within stretches on the nominal step (no gap, no dropped stamp), the reference at
    each fix is a least-squares cubic over ±REFERENCE_HALF_WINDOW_S (fixes whose window
    leaves the stretch are skipped); it absorbs what wanders slower than the window, so
    D(τ) is only meaningful for τ well below it.
    """
    step = float(np.median(np.diff(t)))
    half = int(round(REFERENCE_HALF_WINDOW_S / step))
    offsets = np.arange(-half, half + 1) * step
    basis = np.vander(offsets, 4, increasing=True)
    smoother = np.linalg.pinv(basis)[0]            # the fitted cubic's value at the centre
    breaks = np.flatnonzero(np.abs(np.diff(t) - step) > 0.25 * step) + 1
    pairs: Dict[float, List[np.ndarray]] = {tau: [] for tau in TAUS_S}
    for stretch in np.split(np.arange(t.size), breaks):
        if stretch.size < 2 * half + 1:
            continue
        window = np.lib.stride_tricks.sliding_window_view(x[stretch], 2 * half + 1)
        residual = x[stretch][half:-half] - window @ smoother
        for tau in TAUS_S:
            lag = int(round(tau / step))
            if residual.size > lag:
                pairs[tau].append(residual[lag:] - residual[:-lag])
    result = {}
    for tau, parts in pairs.items():
        both = np.concatenate(parts) if parts else np.empty(0)
        result[tau] = (float(np.sqrt(np.mean(both ** 2))) if both.size else float('nan'),
                       int(both.size))
    return result


# -- the run --------------------------------------------------------------------------------

def standing(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Return the fixes on a dwell: |x(t + 2 s) - x(t - 2 s)| / 4 s < STAND_SPEED_MPS."""
    lag = int(round(DWELL_HALF_SPAN_S / float(np.median(np.diff(t)))))
    speed = np.full(t.size, np.inf)
    if t.size > 2 * lag:
        speed[lag:-lag] = np.abs(x[2 * lag:] - x[:-2 * lag]) / (t[2 * lag:] - t[:-2 * lag])
    return speed < STAND_SPEED_MPS


def evaluate(name: str, series: Dict[str, np.ndarray], facts: dict, cache: Path,
             args: argparse.Namespace) -> dict:
    """Return every figure of one log (artefacts, default replay, tuned CV and CA, D(τ))."""
    t, z = series['t_s'], series['x_m']
    found = artefacts(series, facts)
    print(f'{name}: {found["line"]}', flush=True)
    default = replay_default(series, facts, cache / 'bags' / f'{name}.mcap',
                             args.params_file or (), args.param or ())
    rmse, coverage, count = score(t, z, default['mean'], default['variance'], default['r_m2'])
    missing = int(np.sum(np.isnan(default['velocity'])))
    dwell = standing(t, z) & np.isfinite(default['p_stand'])
    p_stand = default['p_stand'][dwell]
    return {'name': name, 'fixes': int(t.size), 'duration_s': float(t[-1] - t[0]),
            'artefacts': found,
            'default': {'rmse_m': rmse, 'coverage': coverage, 'count': count,
                        'rejected': default['rejected'], 'resets': default['resets'],
                        'min_velocity_mps': float(np.nanmin(default['velocity'])),
                        'diagnostics': default['diagnostics'],
                        'too_large': default['too_large'], 'unpublished': missing,
                        'dwell_fixes': int(dwell.sum()),
                        'p_stand_median': float(np.median(p_stand)) if p_stand.size else None,
                        'p_stand_below_half': float(np.mean(p_stand < 0.5))
                        if p_stand.size else None},
            'CV': tuned_cached(cache, name, t, z, 2, CV_Q_GRID),
            'CA': tuned_cached(cache, name, t, z, 3, CA_Q_GRID),
            'structure': structure_function(t, z)}


def print_tables(results: List[dict]) -> None:
    """Print the score table, the default's counts and D(τ)."""
    rows = []
    for r in results:
        d, cv, ca = r['default'], r['CV'], r['CA']
        best = min(cv['rmse_m'], ca['rmse_m'])
        rows.append((r['name'], r['artefacts']['class'], r['fixes'], f"{r['duration_s']:.0f} s",
                     f"{d['rmse_m']:.2f}", f"{cv['rmse_m']:.2f}", f"{ca['rmse_m']:.2f}",
                     f"{d['rmse_m'] / ca['rmse_m']:.2f}", f"{d['rmse_m'] / best:.2f}",
                     f"{100 * d['coverage']:.1f} %",
                     sum(n for k, n in d['resets'].items() if k != 'reacquired'),
                     d['resets'].get('reacquired', 0)))
    print('\n2-s prediction against the fix 2 s later, RMSE [m]. default: the node defaults, '
          f'R = {R_FIX_M2:g} m²; CV, CA: q and R tuned in hindsight on the log\n')
    print(format_table(('log', 'class', 'fixes', 'duration', 'default', 'CV', 'CA',
                        'default/CA', 'default/best', 'default 2σ cov.', 'resets',
                        'reacquired'), rows))
    rows = []
    for r in results:
        d, cv, ca, a = r['default'], r['CV'], r['CA'], r['artefacts']
        resets = ', '.join(f'{k} {v}' for k, v in d['resets'].items()) or '0'
        stand = '-' if d['p_stand_median'] is None else (
            f"{d['dwell_fixes']}: {d['p_stand_median']:.2f} / "
            f"{100 * d['p_stand_below_half']:.0f} %")
        rows.append((r['name'], f"{a['cross_median_m']:.1f}/{a['cross_p95_m']:.0f}",
                     d['count'], d['rejected'], resets, f"{d['min_velocity_mps']:.2f}", stand,
                     f"{d['too_large']}/{d['diagnostics']}",
                     f"{100 * cv['coverage']:.0f} % (q {cv['q']:.2g}, R {cv['r_m2']:.2g})",
                     f"{100 * ca['coverage']:.0f} % (q {ca['q']:.2g}, R {ca['r_m2']:.2g})"
                     + (' edge' if ca['on_grid_edge'] else '')))
    print("\nThe default in detail; the tuned filters' 2σ coverage and tuning\n")
    print(format_table(('log', '|cross| median/p95 [m]', 'scored', 'rejected',
                        'lock-outs (action)', 'min v [m/s]',
                        'dwell fixes: P(stand) median / < 0.5', "diagnostics 'too large'",
                        'CV cov. (q, R)', 'CA cov. (q, R)'), rows))
    rows = [(r['name'],) + tuple(f'{r["structure"][tau][0]:.3f}' for tau in TAUS_S)
            for r in results]
    print(f'\nD(τ) [m] of x minus a local cubic over ±{REFERENCE_HALF_WINDOW_S:g} s '
          '(stretches without gaps)\n')
    print(format_table(('log',) + tuple(f'{tau:g} s' for tau in TAUS_S), rows))


def data_dir(args: argparse.Namespace, cache: Path) -> Path:
    """Return the test-data directory the arguments name (copied or cloned if asked)."""
    if args.fetch:
        return fetch(cache)
    if args.from_git:
        return copy_from_git(Path(args.from_git), cache)
    data = args.data or os.environ.get('KF_TRAIN_TPLIB_DATA')
    if not data:
        cached = cache / 'test-data'
        if cached.is_dir():
            return cached
        raise SystemExit('name the data: --data DIR, $KF_TRAIN_TPLIB_DATA, --from-git '
                         'GIT_DIR or --fetch (docs/real-logs.md)')
    return Path(data)


def main() -> int:
    """Run the benchmark; print the tables."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--data', help="tp-lib's test-data (default $KF_TRAIN_TPLIB_DATA, "
                                       'else <cache>/test-data)')
    parser.add_argument('--cache', default=str(DEFAULT_CACHE),
                        help='where series, bags and copied data go (default %(default)s)')
    parser.add_argument('--from-git', metavar='GIT_DIR',
                        help='copy the logs out of a tp-lib git clone into the cache first')
    parser.add_argument('--fetch', action='store_true',
                        help=f'clone {TPLIB_URL} (test-data only) into the cache first')
    parser.add_argument('--logs', help='comma-separated log ids or names (default: all)')
    parser.add_argument('--json', metavar='FILE', help='also write every figure as JSON')
    parser.add_argument('--rebuild', action='store_true',
                        help='derive the series again even where the cache has them')
    parser.add_argument('-p', '--param', metavar='NAME:=VALUE', action='append',
                        help="a node parameter for the default's replay, as kf-train "
                             'replay -p (e.g. preset:=train); may be repeated')
    parser.add_argument('--params-file', metavar='FILE', action='append',
                        help="a ROS params file for the default's replay; may be repeated")
    args = parser.parse_args()
    cache = Path(args.cache).expanduser()
    logs = find_logs(data_dir(args, cache))
    if args.logs:
        wanted = {w if w.startswith('log_') else f'log_{w}' for w in args.logs.split(',')}
        logs = {k: v for k, v in logs.items() if k in wanted}
    print(f'data: {len(logs)} logs; series cached in {cache / "series"}; node parameters: '
          f'{" ".join(args.param or []) or "defaults"}'
          f'{"".join(" + " + f for f in args.params_file or [])}', flush=True)
    results = []
    for name, files in logs.items():
        start = time.perf_counter()
        series, facts = load_series(name, files, cache, args.rebuild)
        results.append(evaluate(name, series, facts, cache, args))
        print(f'  ({time.perf_counter() - start:.1f} s)', flush=True)
    print_tables(results)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
