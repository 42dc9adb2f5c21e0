"""
``kf-train demo``: seed 000 over DDS, with both nodes in processes of their own.

The demo starts the ``estimator`` (``initialization:=prior``, seed 000's start) and the
``simulator`` (100 samples at 10 Hz) as separate processes in a ROS domain of this
run's own, records every message with a probe node, and then checks and reports:

* the final position and velocity estimates (±1σ) against the ground truth;
* the position predicted for t = 12 s (2 s past the last sample) against the true
  120 m, next to seed 000's two baselines (the Kalman position at the last sample
  plus 2 s times the running-average or the raw-difference velocity);
* that the numbers that crossed DDS equal the offline core's (:class:`StreamEstimator`
  fed the same stamps and measurements).

It writes ``report.txt``, ``series.csv`` and the nodes' logs to ``--output-dir``.

Then (unless ``--skip-rail``) one rail run over DDS with the estimator's defaults:
its 2-s prediction error against the truth next to CV and CA Kalman filters tuned in
hindsight on the same run, the 2σ coverage, and a figure
(:mod:`kf_train.cli.demo_rail`; outputs in ``--output-dir``/rail).
Exit codes: 0 success, 1 a node failed, discovery timed out or samples were missing,
2 bad command line, 130 interrupted.
"""

import argparse
import csv
import math
import os
from pathlib import Path
import signal
import sys
from typing import Dict, NamedTuple, Optional, Sequence

from kf_train.cli.demo_processes import (
    Child, demo_environment, DemoError, DISCOVERY_TIMEOUT_S, estimator_settings,
    EXIT_TIMEOUT_S, expect_exit, HOLD_SUBSCRIBERS, progress, raise_on_sigterm, spin_until,
    start, stop, Terminated, wait_connected)
from kf_train.estimator import EstimatorSettings, NS_PER_S, StreamEstimator
from kf_train.ros import demo_nodes, messages
from kf_train.sim import extrapolate, raw_difference_velocity, running_average, TrainSimulation
import numpy as np

# Seed 000's scenario; the simulator's and the estimator's defaults give the rest
# (x0 = 0, v = 10 m/s, σ = 1 m; prior [0, 5] with P0 = I, Q = 0, horizon 2 s).
SAMPLES = 100
RATE_HZ = 10.0
HORIZON_S = 2.0
WINDOW = 5
"""Seed 000's running-average window [samples]."""


TOPICS = demo_nodes.TOPICS
"""The topics the probe records, with their message types."""

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class DemoSeries(NamedTuple):
    """The run's messages joined by stamp, as arrays over the samples."""

    stamp_ns: np.ndarray
    t_s: np.ndarray
    """Time since the start t0 = first stamp - 1/rate_hz, where the seed's prior holds."""
    dt_s: float
    measured_m: np.ndarray
    variance_m2: np.ndarray
    truth_m: np.ndarray
    true_velocity_mps: np.ndarray
    x_hist: np.ndarray
    """Estimated [position, velocity] per sample, shape (N, 2), as received."""
    var_hist: np.ndarray
    """Received variances [position, velocity], shape (N, 2)."""
    P_hist: np.ndarray
    """Full covariances (N, 2, 2) from the offline core (Odometry carries no P[0, 1])."""
    prediction_stamp_ns: np.ndarray
    predicted_x: np.ndarray
    predicted_var: np.ndarray
    raw_velocity_mps: np.ndarray
    """Seed 000's raw-difference velocity, N + 1 values (index 0 is t0)."""
    running_average_mps: np.ndarray
    """Its running average over WINDOW samples, N + 1 values."""
    offline_max_abs_diff: float
    """Largest |DDS - offline core| over estimates, variances and predictions."""
    simulation_max_abs_diff: float
    """Largest |received - seeded offline simulation| over measurements and truth."""


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the demo; return the exit code."""
    parser = argparse.ArgumentParser(
        prog='kf-train demo',
        description='Run seed 000 over DDS: the simulator and the estimator as separate '
                    'processes in a ROS domain of their own, checked against the offline '
                    "core and the seed's baselines.")
    parser.add_argument('--seed', type=int, default=0,
                        help='seed of the measurement noise (default: %(default)s)')
    parser.add_argument('--output-dir', default=os.path.join('out', 'demo'),
                        help='where report.txt, series.csv and the node logs go '
                             '(default: %(default)s)')
    parser.add_argument('--timeout-s', type=float, default=30.0,
                        help='how long to wait for all samples once discovery is done '
                             '(default: %(default)s)')
    parser.add_argument('--skip-rail', action='store_true',
                        help='show seed 000 only, without the rail run')
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:  # --help, or a usage error already printed
        return EXIT_OK if exit_.code in (0, None) else EXIT_USAGE
    if not 0 <= args.seed < 2 ** 31:
        print(f'kf-train demo: error: --seed must be in [0, 2^31 - 1], got {args.seed}',
              file=sys.stderr)
        return EXIT_USAGE
    if not (math.isfinite(args.timeout_s) and args.timeout_s > 0.0):
        print(f'kf-train demo: error: --timeout-s must be > 0, got {args.timeout_s}',
              file=sys.stderr)
        return EXIT_USAGE
    previous_sigterm = raise_on_sigterm()
    try:
        report = run_demo(args.seed, Path(args.output_dir), args.timeout_s)
        if not args.skip_rail:
            print(report + '\n', flush=True)
            from kf_train.cli import demo_rail  # (imported when its run is asked for)
            report = demo_rail.run_rail_demo(args.seed, Path(args.output_dir),
                                             args.timeout_s)
    except DemoError as error:
        print(f'kf-train demo: error: {error}', file=sys.stderr)
        return EXIT_FAILED
    except (KeyboardInterrupt, demo_nodes.ExternalShutdownException, Terminated):
        print('kf-train demo: interrupted; nodes stopped', file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous_sigterm is not None:
            signal.signal(signal.SIGTERM, previous_sigterm)
    print(report)
    return EXIT_OK


def run_demo(seed: int, output_dir: Path, timeout_s: float) -> str:
    """Run the nodes, check what they published and write the outputs; return the report."""
    try:
        output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise DemoError(f'cannot create the output directory {output_dir}: '
                        f'{error.strerror}') from None
    env = demo_environment(os.environ)
    domain_id = int(env['ROS_DOMAIN_ID'])
    progress(f'ROS_DOMAIN_ID={domain_id}: seed 000, {SAMPLES} samples at {RATE_HZ:g} Hz, '
             f'noise seed {seed}; node logs in {output_dir}')
    children: Dict[str, Child] = {}
    context = demo_nodes.Context()
    saved_range = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE')
    try:
        _start_nodes(children, seed, env, output_dir)
        progress(f'started the estimator (pid {children["estimator"].process.pid}) and '
                 f'the simulator (pid {children["simulator"].process.pid})')
        # rcl reads the discovery range from the environment at init.
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = env['ROS_AUTOMATIC_DISCOVERY_RANGE']
        executor, probe = demo_nodes.start_probe(context, domain_id)
        if not spin_until(executor, probe.sees_nodes, DISCOVERY_TIMEOUT_S, children):
            raise DemoError(
                f'discovery timed out after {DISCOVERY_TIMEOUT_S:g} s: the probe does not '
                f'see both nodes in ROS_DOMAIN_ID={domain_id} (see the logs in {output_dir})')
        # Seeing the estimator does not mean it sees the probe (discovery is not
        # symmetric): its answer to a service call does, and then it also knows the
        # probe's older estimate and prediction subscriptions.
        settings = estimator_settings(executor, probe)
        wait_connected(executor, probe, children)
        # Everything else is subscribed. The simulator waits for every measurement
        # subscriber the probe knows of (the estimator, the probe, anyone else's in a
        # user-chosen domain), so no sample goes out before the probe listens.
        probe.subscribe_measurement()
        subscribers = max(2, probe.count_subscribers('measurement'))
        problem = demo_nodes.set_parameter(executor, probe, 'simulator', 'min_subscribers',
                                           subscribers, DISCOVERY_TIMEOUT_S)
        if problem is not None:
            raise DemoError(f'cannot release the simulator: {problem}')
        progress(f'both nodes up; sampling for {SAMPLES / RATE_HZ:g} s')
        if not spin_until(executor, lambda: _complete(probe), timeout_s, children,
                          simulator_may_finish=True):
            counts = ', '.join(f'{topic} {n}' for topic, n in probe.counts().items())
            raise DemoError(f'samples missing after {timeout_s:g} s: received {counts} '
                            f'of {SAMPLES} each')
        children['estimator'].process.send_signal(signal.SIGINT)
        # The data and the figures while the simulator flushes its last samples;
        # the report only once both nodes have exited cleanly.
        series = build_series(probe, seed, settings)
        _write_data(output_dir, series)
        expect_exit(children, 'simulator', EXIT_TIMEOUT_S)
        expect_exit(children, 'estimator', EXIT_TIMEOUT_S)
    finally:
        stop(children)
        context.try_shutdown()
        if saved_range is None:
            os.environ.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)
        else:
            os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = saved_range
    report = format_report(series, domain_id, seed, settings)
    (output_dir / 'report.txt').write_text(report + '\n')
    progress(f'wrote report.txt and series.csv to {output_dir}')
    return report


def _start_nodes(children: Dict[str, Child], seed: int, env: Dict[str, str],
                 output_dir: Path) -> None:
    """Start the estimator and the simulator (holding its samples) into ``children``."""
    # The estimator first: its subscription exists before the simulator looks.
    # Seed 000 is one switch away from the defaults (the rail preset, the gate on).
    children['estimator'] = start('estimator', [
        '-p', 'preset:=train', '-p', 'initialization:=prior', '-p', 'gate_probability:=1.0',
        '-p', f'horizon_s:={HORIZON_S!r}'], env, output_dir)
    children['simulator'] = start('simulator', [
        '-p', f'seed:={seed}', '-p', f'rate_hz:={RATE_HZ!r}',
        '-p', f'max_samples:={SAMPLES}',
        # Hold the first sample until told how many subscribers to wait for.
        '-p', f'min_subscribers:={HOLD_SUBSCRIBERS}'], env, output_dir)


def _complete(probe: demo_nodes.Probe) -> bool:
    """Return whether every topic has delivered all samples."""
    return all(n >= SAMPLES for n in probe.counts().values())


def build_series(probe: demo_nodes.Probe, seed: int, settings: EstimatorSettings) -> DemoSeries:
    """Join the recorded messages by stamp and recompute everything offline."""
    settings = settings.resolved()  # the preset's values where the settings leave None
    measurements = sorted((messages.from_measurement_msg(m)
                           for m in probe.received['measurement']), key=lambda m: m.stamp_ns)
    truth = {s.stamp_ns: s for s in map(messages.from_odometry_msg,
                                        probe.received['ground_truth'])}
    estimates = {s.stamp_ns: s for s in map(messages.from_odometry_msg,
                                            probe.received['estimate'])}
    predictions = {s.stamp_ns: s for s in map(messages.from_odometry_msg,
                                              probe.received['prediction'])}
    measurements = measurements[:SAMPLES]
    stamps = [m.stamp_ns for m in measurements]
    if len(set(stamps)) != len(stamps):
        raise DemoError('two measurements carry the same stamp')
    missing = [name for name, table in (('ground_truth', truth), ('estimate', estimates))
               if any(stamp not in table for stamp in stamps)]
    if missing:
        raise DemoError(f'no {" or ".join(missing)} message for some measurement stamps')

    period_ns = round(NS_PER_S / RATE_HZ)
    t0_ns = stamps[0] - period_ns
    offline = StreamEstimator(settings)
    x_hist, var_hist, P_hist = [], [], []
    prediction_stamps, predicted_x, predicted_var = [], [], []
    diffs = [0.0]
    for m in measurements:
        step = offline.process(m.stamp_ns, m.position_m, m.variance_m2)
        e = estimates[m.stamp_ns]
        if step.prediction_stamp_ns not in predictions:
            raise DemoError(f'no prediction stamped {step.prediction_stamp_ns} ns '
                            f'({settings.horizon_s:g} s after a measurement)')
        p = predictions[step.prediction_stamp_ns]
        received = np.array([e.position_m, e.velocity_mps, e.position_variance_m2,
                             e.velocity_variance_m2s2, p.position_m, p.velocity_mps,
                             p.position_variance_m2, p.velocity_variance_m2s2])
        expected = np.concatenate((step.x, np.diag(step.P), step.predicted_x,
                                   np.diag(step.predicted_P)))
        diffs.append(float(np.max(np.abs(received - expected))))
        x_hist.append(received[0:2])
        var_hist.append(received[2:4])
        P_hist.append(step.P)
        prediction_stamps.append(p.stamp_ns)
        predicted_x.append(received[4:6])
        predicted_var.append(received[6:8])

    measured = np.array([m.position_m for m in measurements])
    truth_m = np.array([truth[s].position_m for s in stamps])
    true_velocity = np.array([truth[s].velocity_mps for s in stamps])
    simulation = TrainSimulation(seed=seed).generate(SAMPLES)  # the nodes' defaults
    simulation_diff = float(max(np.max(np.abs(measured - simulation.measured_position_m)),
                                np.max(np.abs(truth_m - simulation.true_position_m))))
    dt_s = period_ns / NS_PER_S
    # Seed 000: v = [0, diff([x0, z1, …, zN]) / dt], then MATLAB's causal filter.
    raw = raw_difference_velocity(measured, dt_s, first_position_m=0.0)
    return DemoSeries(
        np.array(stamps), (np.array(stamps) - t0_ns) / NS_PER_S, dt_s, measured,
        np.array([m.variance_m2 for m in measurements]), truth_m, true_velocity,
        np.array(x_hist), np.array(var_hist), np.array(P_hist), np.array(prediction_stamps),
        np.array(predicted_x), np.array(predicted_var), raw, running_average(raw, WINDOW),
        max(diffs), simulation_diff)


def format_report(series: DemoSeries, domain_id: int, seed: int,
                  settings: EstimatorSettings) -> str:
    """Return the demo's report: estimates, predictions and baselines against the truth."""
    settings = settings.resolved()  # the preset's values where the settings leave None
    x, var = series.x_hist[-1], series.var_hist[-1]
    t_end = series.t_s[-1]
    horizon_s = (int(series.prediction_stamp_ns[-1]) - int(series.stamp_ns[-1])) / NS_PER_S
    t_future = t_end + horizon_s
    # True position at the predicted time: x_true(t_N) + v_true · horizon.
    truth_future = series.truth_m[-1] + series.true_velocity_mps[-1] * horizon_s
    # Seed 000's projections: Kalman position at t_N + horizon · baseline velocity.
    running = float(extrapolate(x[0], series.running_average_mps[-1], horizon_s))
    raw = float(extrapolate(x[0], series.raw_velocity_mps[-1], horizon_s))
    rows = [
        (f'final position [m] (t = {t_end:.1f} s)', x[0], math.sqrt(var[0]),
         series.truth_m[-1]),
        (f'final velocity [m/s] (t = {t_end:.1f} s)', x[1], math.sqrt(var[1]),
         series.true_velocity_mps[-1]),
        (f'position at t = {t_future:.1f} s [m]: Kalman', series.predicted_x[-1][0],
         math.sqrt(series.predicted_var[-1][0]), truth_future),
        (f'  running average ({WINDOW} samples) baseline', running, None, truth_future),
        ('  raw difference baseline', raw, None, truth_future),
    ]
    width = max(len(row[0]) for row in rows)
    header = (f'{"":<{width}}  {"estimate":>10}  {"±1σ":>8}  {"truth":>9}  {"error":>8}'
              f'  {"error/σ":>7}')
    lines = [
        f'kf-train demo: seed 000 over DDS (ROS_DOMAIN_ID={domain_id}), '
        f'{len(series.t_s)} samples at {1.0 / series.dt_s:g} Hz, noise seed {seed}',
        f'estimator: initialization={settings.initialization}, '
        f'initial_state={list(settings.initial_state)}, '
        f'initial_covariance={list(settings.initial_covariance)}, '
        f'q={settings.process_noise_density:g}',
        f'baselines (seed 000): the Kalman position at t = {t_end:.1f} s + {horizon_s:g} s × '
        'the baseline velocity',
        '',
        header,
    ]
    for label, value, sigma, truth in rows:
        error = value - truth
        sigma_text = f'±{sigma:.3f}' if sigma is not None else '-'
        ratio_text = f'{error / sigma:+.2f}' if sigma else '-'
        lines.append(f'{label:<{width}}  {value:>10.3f}  {sigma_text:>8}  {truth:>9.3f}  '
                     f'{error:>+8.3f}  {ratio_text:>7}')
    lines += [
        '',
        f'DDS vs offline core (StreamEstimator, same stamps and measurements): '
        f'max |difference| = {series.offline_max_abs_diff:.3g}',
        f'measurements and truth vs the seeded offline simulation: '
        f'max |difference| = {series.simulation_max_abs_diff:.3g}',
    ]
    return '\n'.join(lines)


CSV_COLUMNS = (
    'stamp_ns', 't_s', 'measured_m', 'measurement_variance_m2', 'truth_m',
    'true_velocity_mps', 'position_m', 'velocity_mps', 'var_position_m2',
    'var_velocity_m2s2', 'cov_position_velocity_m2s', 'prediction_stamp_ns',
    'predicted_position_m', 'predicted_velocity_mps', 'var_predicted_position_m2',
    'var_predicted_velocity_m2s2', 'raw_velocity_mps', 'running_average_velocity_mps')
"""Columns of series.csv; floats are written with repr() so they read back exactly."""


def _write_data(output_dir: Path, series: DemoSeries) -> None:
    """Write series.csv and the figures."""
    with open(output_dir / 'series.csv', 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(CSV_COLUMNS)
        for k in range(len(series.t_s)):
            # Index k + 1 in the baselines: their index 0 is t0, before the first sample.
            writer.writerow([int(series.stamp_ns[k])] + [repr(float(v)) for v in (
                series.t_s[k], series.measured_m[k], series.variance_m2[k],
                series.truth_m[k], series.true_velocity_mps[k], series.x_hist[k][0],
                series.x_hist[k][1], series.var_hist[k][0], series.var_hist[k][1],
                series.P_hist[k][0, 1])] + [int(series.prediction_stamp_ns[k])] + [
                repr(float(v)) for v in (
                    series.predicted_x[k][0], series.predicted_x[k][1],
                    series.predicted_var[k][0], series.predicted_var[k][1],
                    series.raw_velocity_mps[k + 1], series.running_average_mps[k + 1])])
    _write_figures(output_dir, series)


def _write_figures(output_dir: Path, series: DemoSeries) -> None:
    """
    Draw seed 000's figures with kf_train.plots, when matplotlib is available.

    The single call site of the plotting module. x_hist and P_hist hold the N samples
    (no prior row); P_hist is the offline core's full covariance, equal to the received
    variances on its diagonal.
    """
    try:
        from kf_train.plots import seed000_figures
    except (ImportError, AttributeError):
        progress('figures: not available')
        return
    paths = seed000_figures(str(output_dir), series.t_s, series.measured_m, series.truth_m,
                            series.x_hist, series.P_hist, series.dt_s)
    progress('figures: ' + ', '.join(os.path.basename(str(p)) for p in paths or ()))


if __name__ == '__main__':
    sys.exit(main())
