"""
``kf-train demo``, second part: one rail run over DDS with the estimator's defaults.

After seed 000 (:mod:`kf_train.cli.demo`) the demo starts the ``simulator`` with
``scenario:=rail`` (a metro run of the demo's seed, from standing at a station through
a departure, a cruise and a braking to a stop at the next station, and some seconds of
the dwell there) and the ``estimator`` with no filter parameter at all: its defaults.
The simulator runs :data:`REAL_TIME_FACTOR` times faster than the wall clock and
publishes ``/clock``; the estimator follows it (``use_sim_time``), so its
future-stamp check holds, and takes its measurements reliably into a queue of
:data:`QUEUE_DEPTH` (``qos_reliability``, ``qos_depth``: transport only), so that no
sample is lost should it fall behind the faster run. A probe records every topic,
the regime probabilities and ``/diagnostics`` included. Then the demo reports, after
a 10-s warm-up, the RMSE of the estimator's 2-s predictions against the exact truth
and the share of them whose 2σ band holds it, next to a constant-velocity and a
constant-acceleration Kalman filter each tuned in hindsight on this very run
(:func:`kf_train.sim.tuned_baselines`); checks that what crossed DDS equals the
offline core (:class:`StreamEstimator` fed the received measurements) and the seeded
offline run; and draws ``rail.png``
(:mod:`kf_train.plots.rail_figure`). Outputs go to ``<output-dir>/rail``.
"""

import dataclasses
import math
import os
from pathlib import Path
import signal
from typing import Dict, NamedTuple, Optional

from kf_train.cli import demo_processes as seed_demo
from kf_train.estimator import NS_PER_S, Rejected, StreamEstimator
from kf_train.ros import demo_nodes, diagnostics, messages
from kf_train.sim import (
    RAIL_HORIZON_S, rail_parameters, rail_run, rail_scenario, RAIL_WARMUP_S, RailRun, Score,
    score_predictions, Track, tuned_baselines)
import numpy as np

FAMILY = 'metro'
RATE_HZ = 10.0
REAL_TIME_FACTOR = 10.0
"""Simulated seconds per wall-clock second (the estimator keeps up with ~10x)."""
QUEUE_DEPTH = 1000
"""The estimator's measurement queue: the whole run, should it fall behind."""
AFTER_ARRIVAL_S = 20.0
"""How long the run goes on after the train stops at the next station [s]."""
MAX_DURATION_S = 240.0


class RailPlan(NamedTuple):
    """The run the demo simulates, known offline in advance."""

    seed: int
    samples: int
    run: RailRun
    scenario: object
    """kf_train.sim.Scenario of exactly these samples (what the simulator publishes)."""
    stop: tuple
    """(arrival s, departure s) of the stop the figure shows."""


class RailSeries(NamedTuple):
    """What crossed DDS, joined by stamp; times from t0 = first stamp - 1/rate_hz."""

    t_s: np.ndarray
    measured_m: np.ndarray
    truth: np.ndarray
    """(N, 3): position, velocity, acceleration as received."""
    estimate_t_s: np.ndarray
    estimate: np.ndarray
    """(M, 4): position, velocity and their variances, one row per published estimate."""
    prediction: np.ndarray
    """(M, 2): position predicted horizon_s ahead, its variance."""
    regimes: np.ndarray
    """(M, k) regime probabilities after each estimate."""
    regime_names: tuple
    rejected: int
    offline_max_abs_diff: float
    simulation_max_abs_diff: float


def plan(seed: int) -> RailPlan:
    """Return the run of ``seed``: until AFTER_ARRIVAL_S after its first station stop."""
    parameters = rail_parameters(FAMILY, seed)
    run = rail_run(parameters, seed)
    moving_stops = [stop for stop in run.stops if stop[0] > 0.0]
    stop = moving_stops[0]
    duration_s = min(stop[0] + AFTER_ARRIVAL_S, MAX_DURATION_S)
    samples = int(math.ceil(duration_s * RATE_HZ))
    # The same seed with a shorter duration: the same plan and noise, samples 1..N.
    scenario, _ = rail_scenario(seed, FAMILY, dataclasses.replace(
        parameters, duration_s=samples / RATE_HZ), RATE_HZ, gnss_model='white')
    return RailPlan(seed, samples, run, scenario, stop)


def run_rail_demo(seed: int, output_dir: Path, timeout_s: float) -> str:
    """Run the rail part; write its outputs to ``output_dir/rail``; return the report."""
    output_dir = Path(output_dir) / 'rail'
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise seed_demo.DemoError(f'cannot create {output_dir}: {error.strerror}') from None
    rail = plan(seed)
    env = seed_demo.demo_environment(os.environ)
    domain_id = int(env['ROS_DOMAIN_ID'])
    seed_demo.progress(
        f'rail: a {FAMILY} run of seed {seed}, {rail.samples / RATE_HZ:g} s at {RATE_HZ:g} Hz '
        f'played {REAL_TIME_FACTOR:g}x faster, the estimator with its defaults')
    series, settings = _run_nodes(
        rail, env, output_dir, timeout_s + rail.samples / RATE_HZ / REAL_TIME_FACTOR)
    # After the run, not beside it: a busy demo process (one GIL with the probe) would
    # make the probe fall behind the nodes' publishers, which keep the last 10 only.
    tuned = tuned_baselines(rail.scenario, rail.run)
    figure = _draw(output_dir, rail, series)
    report = format_rail_report(rail, series, settings, tuned, domain_id, figure)
    (output_dir / 'report.txt').write_text(report + '\n')
    return report


def _run_nodes(rail: RailPlan, env: Dict[str, str], output_dir: Path, timeout_s: float):
    """Start both nodes, record the run, stop them; return (series, estimator settings)."""
    children: Dict[str, seed_demo.Child] = {}
    context = demo_nodes.Context()
    saved_range = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE')
    try:
        # No filter parameter: the defaults. Only the transport is set: reliable with a
        # deep queue, so that no sample is lost while the run is played faster.
        children['estimator'] = seed_demo.start('estimator', [
            '-p', 'use_sim_time:=true', '-p', 'qos_reliability:=reliable',
            '-p', f'qos_depth:={QUEUE_DEPTH}'], env, output_dir)
        children['simulator'] = seed_demo.start('simulator', [
            '-p', 'scenario:=rail', '-p', f'rail_family:={FAMILY}', '-p', f'seed:={rail.seed}',
            '-p', 'rail_gnss_model:=white',  # the development runs' model, as offline
            '-p', f'rate_hz:={RATE_HZ!r}', '-p', f'real_time_factor:={REAL_TIME_FACTOR!r}',
            '-p', 'publish_clock:=true', '-p', f'max_samples:={rail.samples}',
            '-p', f'min_subscribers:={seed_demo.HOLD_SUBSCRIBERS}'], env, output_dir)
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = \
            env['ROS_AUTOMATIC_DISCOVERY_RANGE']
        executor, probe = demo_nodes.start_probe(context, int(env['ROS_DOMAIN_ID']),
                                                 demo_nodes.RAIL_TOPICS, events=True)
        if not seed_demo.spin_until(executor, lambda: _sees_nodes(probe),
                                    seed_demo.DISCOVERY_TIMEOUT_S, children):
            raise seed_demo.DemoError(
                f'rail: discovery timed out after {seed_demo.DISCOVERY_TIMEOUT_S:g} s '
                f'(see the logs in {output_dir})')
        settings = seed_demo.estimator_settings(executor, probe)
        has_regimes = bool(diagnostics.regime_names(StreamEstimator(settings)))
        seed_demo.wait_connected(executor, probe, children, 'rail: ')
        probe.subscribe_measurement()
        problem = demo_nodes.set_parameter(
            executor, probe, 'simulator', 'min_subscribers',
            max(2, probe.count_subscribers('measurement')), seed_demo.DISCOVERY_TIMEOUT_S)
        if problem is not None:
            raise seed_demo.DemoError(f'rail: cannot release the simulator: {problem}')
        seed_demo.progress(f'rail: both nodes up; sampling for '
                           f'{rail.samples / RATE_HZ / REAL_TIME_FACTOR:.1f} s')
        if not seed_demo.spin_until(executor, lambda: _complete(probe, rail.samples, has_regimes),
                                    timeout_s, children, simulator_may_finish=True):
            counts = ', '.join(f'{topic} {n}' for topic, n in probe.counts().items())
            status = probe.estimator_status() or {}
            raise seed_demo.DemoError(
                f'rail: samples missing after {timeout_s:g} s: received {counts} of '
                f'{rail.samples} samples; the estimator took in {status.get("received", "?")} '
                f'and fused {status.get("fused", "?")}')
        children['estimator'].process.send_signal(signal.SIGINT)
        series = build_rail_series(probe, rail, settings)
        seed_demo.expect_exit(children, 'simulator', seed_demo.EXIT_TIMEOUT_S)
        seed_demo.expect_exit(children, 'estimator', seed_demo.EXIT_TIMEOUT_S)
    finally:
        seed_demo.stop(children)
        context.try_shutdown()
        if saved_range is None:
            os.environ.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)
        else:
            os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = saved_range
    return series, settings


def _sees_nodes(probe: demo_nodes.Probe) -> bool:
    """Return whether both nodes' publishers and the estimator's input are in the graph."""
    return (all(probe.count_publishers(topic) >= 1 for topic in (
        'measurement', 'ground_truth', 'ground_truth_accel', 'estimate', 'prediction'))
        and probe.count_subscribers('measurement') >= 1)


def _complete(probe: demo_nodes.Probe, samples: int, has_regimes: bool) -> bool:
    """Return whether every sample arrived and the estimator's outputs for all of them."""
    counts = probe.counts()
    if min(counts['measurement'], counts['ground_truth'], counts['ground_truth_accel']) \
            < samples:
        return False
    status = probe.estimator_status()
    # The status counts what the estimator took in; it goes out after the outputs.
    if status is None or int(status.get('received', 0)) < samples:
        return False
    published = int(status['fused'])
    regimes = counts['regime_probabilities'] if has_regimes else published
    return min(counts['estimate'], counts['prediction'], regimes) >= published


def build_rail_series(probe: demo_nodes.Probe, rail: RailPlan, settings) -> RailSeries:
    """Join what was received by stamp; recompute it with the offline core."""
    measurements = sorted((messages.from_measurement_msg(m)
                           for m in probe.received['measurement']), key=lambda m: m.stamp_ns)
    measurements = measurements[:rail.samples]
    truth = {s.stamp_ns: s for s in map(messages.from_odometry_msg,
                                        probe.received['ground_truth'])}
    accel = {messages.stamp_to_ns(m.header.stamp): m.accel.linear.x
             for m in probe.received['ground_truth_accel']}
    stamps = [m.stamp_ns for m in measurements]
    if any(stamp not in truth or stamp not in accel for stamp in stamps):
        raise seed_demo.DemoError('rail: no ground truth for some measurement stamps')
    t0_ns = stamps[0] - round(NS_PER_S / RATE_HZ)
    estimates = [messages.from_odometry_msg(m) for m in probe.received['estimate']]
    predictions = [messages.from_odometry_msg(m) for m in probe.received['prediction']]
    regimes = [messages.from_regime_msg(m) for m in probe.received['regime_probabilities']]
    names = regimes[0][0] if regimes else ()
    rows = [(e.position_m, e.velocity_mps, e.position_variance_m2, e.velocity_variance_m2s2)
            for e in estimates]
    predicted = [(p.position_m, p.position_variance_m2) for p in predictions]
    series = RailSeries(
        (np.array(stamps) - t0_ns) / NS_PER_S, np.array([m.position_m for m in measurements]),
        np.array([(truth[s].position_m, truth[s].velocity_mps, accel[s]) for s in stamps]),
        (np.array([e.stamp_ns for e in estimates]) - t0_ns) / NS_PER_S,
        np.array(rows).reshape(-1, 4), np.array(predicted).reshape(-1, 2),
        np.array([p for _, p in regimes]).reshape(len(regimes), len(names)), names, 0,
        0.0, 0.0)
    rejected, offline = _offline_difference(measurements, estimates, predictions, regimes,
                                            settings)
    expected = np.column_stack((rail.scenario.z[:, 0], rail.scenario.truth))
    received = np.column_stack((series.measured_m, series.truth))
    simulation = float(np.max(np.abs(received - expected))) if received.shape == \
        expected.shape else math.inf
    return series._replace(rejected=rejected, offline_max_abs_diff=offline,
                           simulation_max_abs_diff=simulation)


def _offline_difference(measurements, estimates, predictions, regimes, settings):
    """Return (rejected, largest |DDS - offline core|) over every published number."""
    offline = StreamEstimator(settings)
    expected, rejected = [], 0
    for m in measurements:
        try:
            step = offline.process(m.stamp_ns, m.position_m, m.variance_m2)
        except Rejected:
            rejected += 1
            continue
        current = offline.mode_probabilities()
        expected.append((step.stamp_ns, step.x[:2], np.diag(step.P)[:2],
                         step.prediction_stamp_ns, step.predicted_x[0],
                         step.predicted_P[0, 0], () if current is None else current[1]))
    if len(expected) != len(estimates) or len(predictions) != len(estimates) or (
            regimes and len(regimes) != len(estimates)):
        return rejected, math.inf
    largest = 0.0
    for k, (stamp, x, var, prediction_stamp, px, pvar, probabilities) in enumerate(expected):
        e, p = estimates[k], predictions[k]
        if e.stamp_ns != stamp or p.stamp_ns != prediction_stamp:
            return rejected, math.inf
        got = [e.position_m, e.velocity_mps, e.position_variance_m2, e.velocity_variance_m2s2,
               p.position_m, p.position_variance_m2] + (list(regimes[k][1]) if regimes else [])
        want = list(x) + list(var) + [px, pvar] + (list(probabilities) if regimes else [])
        largest = max(largest, float(np.max(np.abs(np.subtract(got, want)))))
    return rejected, largest


def dds_track(series: RailSeries) -> Track:
    """Return the estimator's predictions as a rail_eval Track (no timings)."""
    return Track(series.estimate_t_s, series.prediction[:, 0], series.prediction[:, 1],
                 0.0, 0.0)


def format_rail_report(rail: RailPlan, series: RailSeries, settings, tuned, domain_id: int,
                       figure: Optional[str]) -> str:
    """Return the rail part's report: the 2-s prediction against the tuned KFs."""
    settings = settings.resolved()
    params = rail.run.parameters
    ours = score_predictions(dds_track(series), rail.run)
    arrival, departure = rail.stop
    lines = [
        f'kf-train demo: a rail run over DDS (ROS_DOMAIN_ID={domain_id}): {FAMILY}, seed '
        f'{rail.seed}, {len(series.t_s)} samples at {RATE_HZ:g} Hz (σ = 1 m), played '
        f'{REAL_TIME_FACTOR:g}x faster than real time',
        f'train: accel {params.accel_mps2:.2f} m/s², brake {params.brake_mps2:.2f} m/s², jerk '
        f'{params.jerk_mps3:.2f} m/s³, line speed {params.line_speed_mps:.1f} m/s; stops at '
        f'the start and at t = {arrival:.1f} s (dwell until {departure:.1f} s)',
        f'estimator: its defaults (preset {settings.preset}, filter {settings.filter}, '
        f'gate_probability {settings.gate_probability:g}, horizon {settings.horizon_s:g} s): '
        f'{len(series.estimate_t_s)} estimates, {series.rejected} '
        f'measurement{"" if series.rejected == 1 else "s"} rejected by the gate',
        '',
        f'2-s prediction after a {RAIL_WARMUP_S:g}-s warm-up, against the exact truth '
        f'({ours.count} predictions):',
        f'{"":<60}  {"RMSE [m]":>8}  {"2σ coverage":>11}',
        _score_line('estimator defaults, over DDS', ours),
    ]
    for name, label, unit in (('CV', 'constant-velocity KF', 'm²/s³'),
                              ('CA', 'constant-acceleration KF', 'm²/s⁵')):
        best = tuned[name]
        lines.append(_score_line(f'{label}, hindsight-tuned q = {best.q:.3g} {unit}',
                                 best.score))
    best_rmse = min(tuned['CV'].score.rmse_m, tuned['CA'].score.rmse_m)
    lines += [
        f'estimator / best tuned KF: {ours.rmse_m / best_rmse:.2f} (issue 11 target: <= 0.8); '
        f'2σ coverage target 85-99 %',
        '',
        f'DDS vs offline core (StreamEstimator, same stamps and measurements; estimates, '
        f'predictions, regime probabilities): max |difference| = '
        f'{series.offline_max_abs_diff:.3g}',
        f'measurements and truth vs the seeded offline run: max |difference| = '
        f'{series.simulation_max_abs_diff:.3g}',
        f'figure: {figure}' if figure else 'figure: not available (needs matplotlib)',
    ]
    return '\n'.join(lines)


def _score_line(label: str, result: Score) -> str:
    """Return one line of the score table."""
    return f'  {label:<58}  {result.rmse_m:>8.3f}  {100.0 * result.coverage:>9.1f} %'


def _draw(output_dir: Path, rail: RailPlan, series: RailSeries) -> Optional[str]:
    """Draw rail.png with kf_train.plots.rail_figure; return its path (None without it)."""
    try:
        from kf_train.plots import rail_figure
        path = rail_figure(
            str(output_dir / 'rail.png'), series, rail.run, rail.stop, RAIL_HORIZON_S)
    except (ImportError, RuntimeError) as error:
        seed_demo.progress(f'rail: figure not drawn: {error}')
        return None
    seed_demo.progress(f'rail: figure {path}')
    return path
