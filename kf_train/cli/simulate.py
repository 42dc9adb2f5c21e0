"""
``kf-train simulate``: write a simulated run straight to a bag or a CSV, without DDS.

The run is the simulator node's (:mod:`kf_train.ros.simulator_node`): the same
parameter table (:mod:`kf_train.ros.simulator_params`: ``scenario``, ``rate_hz``,
``seed``, ``noise_std``, the fault parameters, frames, ...; from ``--params-file``
(node ``simulator``) and ``-p NAME:=VALUE``, checked as the node checks them), the
same sample streams (:func:`kf_train.sim.make_stream`) and fault injection
(:class:`kf_train.sim.FaultInjector`), so a seed gives the node's numbers.
``--scenario`` and ``--seed`` are short for ``-p scenario:=`` and ``-p seed:=``.
``--duration S`` gives round(S·rate_hz) samples; sample k is taken at t_k = k/rate_hz
(+ ``--start S``), and its stamp is t_k (plus a clock jump, if injected).

The node's live-only parameters, decided offline:

* ``max_samples`` (N > 0) caps the run at N samples, as it stops the node; with it,
  ``--duration`` may be left out. One of the two is needed (0, the node's "forever",
  has no end offline).
* ``publish_clock`` true writes ``/clock`` (rosgraph_msgs/msg/Clock, from rosbags'
  Jazzy typestore) into a bag: each sample's stamp (jumped with the clock, as the node
  publishes it), recorded at the sample time, before the sample's other messages. A
  CSV has no topics (its ``t`` is the stamp already): publish_clock with a CSV output
  is refused with a one-line error.
* ``min_subscribers`` only makes the node wait before its first sample; the samples
  and stamps do not depend on it, so it is accepted and has nothing to do offline.

Output (``--output``):

* ``X.mcap`` or a directory: a rosbag2 MCAP bag with ``measurement``
  (PoseWithCovarianceStamped), ``ground_truth`` (Odometry), for car and robot
  ``control`` (AccelStamped / TwistStamped) and for rail ``ground_truth_accel``
  (AccelStamped, the true acceleration), the node's types and fields (with
  ``rail_gnss_model`` receiver, the default: the variance is each fix's hAcc², and
  an epoch without a fix has no measurement, and the Doppler speed goes out on
  ``velocity``, TwistWithCovarianceStamped, as the node publishes it). Each
  message is recorded at its sample time; a measurement delayed by ``delay_s`` at
  sample time + delay_s, a reordered one with the next sample. ``kf-train replay
  X.mcap`` replays it with the estimator node's session.
* ``X.csv``: one row per sample: ``t`` [s] (the stamp), ``z_position`` (empty when the
  sample was dropped, or the receiver had no fix; no variance, no Doppler speed),
  ``u`` (scenarios with a control), ``true_position``, ``true_velocity`` and, for
  rail, ``true_acceleration``. ``kf-train replay X.csv --preset NAME`` reads it (a dropped
  sample is a row without measurement; a backward clock jump makes ``t`` decrease,
  which a CSV replay refuses).

Errors (a bad parameter, an output that cannot be written) are one line, exit 1, and
no output is left behind.
"""

import argparse
import collections
import math
import sys
import time
from typing import Iterator, List, NamedTuple, Optional

from kf_train.filters import NS_PER_S
from kf_train.io import check_output_path, write_atomic
from kf_train.ros import param_spec, simulator_params
from kf_train.sim import ACCELERATION_SCENARIOS, CONTROL_NAMES, FaultInjector, make_stream

EXIT_OK = 0
EXIT_ERROR = 1
MAX_SAMPLES = 100_000_000
CSV_ROWS_PER_CHUNK = 4096


class Event(NamedTuple):
    """One message of the run: its topic, record time, stamp and value(s)."""

    topic: str
    """measurement, control, ground_truth or clock."""
    record_ns: int
    stamp_ns: int
    index: int
    """The sample it belongs to."""
    values: tuple


def run_events(config, samples: int, start_ns: int = 0) -> Iterator[Event]:
    """Yield the run's messages in record order, as the simulator node publishes them."""
    seed = None if config.seed < 0 else config.seed
    stream = make_stream(config.scenario, config.rate_hz, seed, **config.stream)
    faults = FaultInjector(config.faults, seed)
    delay_ns = round(config.faults.delay_s * NS_PER_S)
    has_control = CONTROL_NAMES[config.scenario] is not None
    clock = config.options.publish_clock
    pending = collections.deque()   # delayed measurements, in due order (a fixed delay)
    for _ in range(samples):
        sample = stream.next_sample()
        sample_ns = start_ns + round(sample.index * NS_PER_S / config.rate_hz)
        while pending and pending[0].record_ns <= sample_ns:
            yield pending.popleft()
        stamp_ns = faults.jumped_stamp_ns(sample.t_s, sample_ns)
        if clock:
            yield Event('clock', sample_ns, stamp_ns, sample.index, ())
        if has_control:
            yield Event('control', sample_ns, stamp_ns, sample.index, (sample.control,))
        variance = (stream.noise_std_m ** 2 if sample.measurement_variance_m2 is None
                    else sample.measurement_variance_m2)   # a receiver's hAcc²
        deliveries = []  # a receiver's epoch without a fix has nothing to deliver
        if sample.measured_position_m is not None:
            deliveries = faults.apply(sample.index, sample.t_s, sample_ns,
                                      sample.measured_position_m)
        if sample.index == samples:
            deliveries += faults.flush()
        for delivery in deliveries:
            event = Event('measurement', sample_ns + delay_ns, delivery.stamp_ns,
                          delivery.index, (delivery.position_m, variance))
            if delay_ns or pending:
                pending.append(event)
            else:
                yield event
        if sample.doppler_speed_mps is not None:   # as the node: after the measurement
            yield Event('velocity', sample_ns, stamp_ns, sample.index,
                        (sample.doppler_speed_mps, sample.doppler_variance_m2_s2))
        yield Event('ground_truth', sample_ns, stamp_ns, sample.index,
                    (sample.true_position_m, sample.true_velocity_mps))
        if sample.true_acceleration_mps2 is not None:
            yield Event('ground_truth_accel', sample_ns, stamp_ns, sample.index,
                        (sample.true_acceleration_mps2,))
    yield from pending


def receiver_velocity(config) -> bool:
    """Return whether the run has a Doppler speed (rail with rail_gnss_model receiver)."""
    return config.stream.get('rail', {}).get('gnss_model') == 'receiver'


def write_bag(config, samples: int, path: str, start_ns: int) -> dict:
    """Write the run as an MCAP bag at ``path``; return the message counts."""
    from kf_train.io import bagio_simulation   # needs rosbags: imported when used
    options = config.options
    frame, child = options.frame_id, options.child_frame_id
    with bagio_simulation.SimulationBag(
            path, CONTROL_NAMES[config.scenario], clock=options.publish_clock,
            truth_acceleration=config.scenario in ACCELERATION_SCENARIOS,
            velocity=receiver_velocity(config)) as bag:
        for event in run_events(config, samples, start_ns):
            if event.topic == 'measurement':
                bag.write_measurement(event.record_ns, event.stamp_ns, frame, *event.values)
            elif event.topic == 'control':
                bag.write_control(event.record_ns, event.stamp_ns, child, *event.values)
            elif event.topic == 'clock':
                bag.write_clock(event.record_ns, event.stamp_ns)
            elif event.topic == 'velocity':
                bag.write_velocity(event.record_ns, event.stamp_ns, child, *event.values)
            elif event.topic == 'ground_truth_accel':
                bag.write_truth_accel(event.record_ns, event.stamp_ns, child, *event.values)
            else:
                bag.write_truth(event.record_ns, event.stamp_ns, frame, child, *event.values)
        return dict(bag.counts)


def csv_header(scenario: str) -> List[str]:
    """Return the CSV columns for a scenario."""
    control = ['u'] if CONTROL_NAMES[scenario] is not None else []
    acceleration = ['true_acceleration'] if scenario in ACCELERATION_SCENARIOS else []
    return ['t', 'z_position'] + control + ['true_position', 'true_velocity'] + acceleration


def _csv_chunks(config, samples: int, start_ns: int, counts: dict) -> Iterator[str]:
    """Yield the CSV text: one row per sample, in sample order (held in memory)."""
    rows = {}        # sample index -> [stamp ns, (u,) true position, true velocity]
    measured = {}    # sample index -> measured position (a reordered one comes late)
    for event in run_events(config, samples, start_ns):
        if event.topic == 'measurement':
            measured[event.index] = event.values[0]
            counts['measurement'] += 1
        elif event.topic == 'velocity':
            continue  # not a CSV column yet (a bag has it)
        else:
            rows.setdefault(event.index, [event.stamp_ns]).extend(event.values)
            counts[event.topic] += 1
    yield ','.join(csv_header(config.scenario)) + '\n'
    for first in range(1, samples + 1, CSV_ROWS_PER_CHUNK):
        yield ''.join(_csv_line(rows[index], measured.get(index))
                      for index in range(first, min(first + CSV_ROWS_PER_CHUNK, samples + 1)))


def _csv_line(row: list, position_m: Optional[float]) -> str:
    """Return one CSV line: t, z_position ('' if lost), [u], true position, velocity."""
    stamp_ns, values = row[0], row[1:]
    cells = [repr(stamp_ns / NS_PER_S), '' if position_m is None else repr(float(position_m))]
    return ','.join(cells + [repr(float(v)) for v in values]) + '\n'


def write_csv(config, samples: int, path: str, start_ns: int) -> dict:
    """Write the run as a CSV at ``path`` (atomically); return the message counts."""
    check_output_path(path)
    counts = {'measurement': 0, 'ground_truth': 0, 'control': 0, 'ground_truth_accel': 0}
    try:
        write_atomic(path, _csv_chunks(config, samples, start_ns, counts))
    except OSError as error:
        raise ValueError(f'cannot write {path}: {error.strerror or error}') from None
    return counts


def _parser() -> argparse.ArgumentParser:
    """Return the argument parser."""
    parser = argparse.ArgumentParser(
        prog='kf-train simulate',
        description='Write a simulated run (measurements, controls, ground truth) to a '
                    "rosbag2 MCAP bag or a CSV, with the simulator node's parameters and "
                    'no DDS.',
        epilog='Parameters: ' + ', '.join(spec.name for spec in simulator_params.PARAMETERS.specs)
               + ' (kf-train simulator --ros-args ... describes them).')
    parser.add_argument('--scenario', metavar='NAME', default=None,
                        help="the scenario (-p scenario:=NAME; default the node's, train)")
    parser.add_argument('--duration', metavar='S', type=float, default=None,
                        help='simulated time [s]: round(S * rate_hz) samples (capped by '
                             '-p max_samples:=N; one of the two is needed)')
    parser.add_argument('--seed', type=int, default=None, help='-p seed:=N (default 0)')
    parser.add_argument('--start', metavar='S', type=float, default=0.0,
                        help='time of sample 0 [s] (default 0: sample k at k / rate_hz)')
    parser.add_argument('--output', '-o', metavar='X.mcap|DIR|X.csv', required=True,
                        help='a bag (X.mcap or a new directory) or a CSV (X.csv)')
    parser.add_argument('--params-file', metavar='FILE', action='append', default=[],
                        help='a ROS params file (node simulator); may be repeated')
    parser.add_argument('-p', dest='parameter', metavar='NAME:=VALUE', action='append',
                        default=[], help='set one simulator parameter')
    return parser


def load_config(args: argparse.Namespace):
    """Return the node's SimulatorConfig; ParameterError (one line) if invalid."""
    files = []
    for path in args.params_file:
        try:
            files.append(param_spec.read_params_file(path))
        except OSError as error:
            raise param_spec.ParameterError(
                f'cannot read params file {path}: {error.strerror or error}') from None
    overrides = list(args.parameter)
    if args.scenario is not None:
        overrides.insert(0, f'scenario:={args.scenario}')
    if args.seed is not None:
        overrides.insert(0, f'seed:={args.seed}')
    return simulator_params.load_simulator_config(files, overrides)


def sample_count(duration_s: Optional[float], config) -> int:
    """Return the samples to take: --duration's, capped by max_samples (module doc)."""
    cap = config.options.max_samples
    if duration_s is None:
        if not cap:
            raise ValueError('give --duration S or -p max_samples:=N (the run needs an end)')
        return cap
    if not (math.isfinite(duration_s) and duration_s > 0.0):
        raise ValueError(f'--duration must be a finite number > 0, got {duration_s}')
    samples = round(duration_s * config.rate_hz)
    if not 1 <= samples <= MAX_SAMPLES:
        raise ValueError(f'--duration {duration_s} s at {config.rate_hz} Hz gives '
                         f'{samples} samples; 1 to {MAX_SAMPLES} are possible')
    return min(samples, cap) if cap else samples


def simulate(args: argparse.Namespace) -> str:
    """Write the run the arguments describe; return a summary; ValueError (one line)."""
    config = load_config(args)
    if not math.isfinite(args.start) or abs(args.start) > 2.0 ** 31 / 2:
        raise ValueError(f'--start must be a finite number of seconds, got {args.start}')
    samples = sample_count(args.duration, config)
    start_ns = round(args.start * NS_PER_S)
    to_csv = args.output.lower().endswith('.csv')
    if to_csv and config.options.publish_clock:
        raise ValueError('publish_clock writes /clock into a bag; a CSV has no topics (its t '
                         'is the stamp): give a bag output or leave publish_clock false')
    writer = write_csv if to_csv else write_bag
    counts = writer(config, samples, args.output, start_ns)
    listed = ', '.join(f'{n} {topic}' for topic, n in counts.items()
                       if n or topic in ('measurement', 'ground_truth'))
    return (f'{samples} samples of {config.scenario} (seed {config.seed}): {listed} '
            f'-> {args.output}')


def main(argv: Optional[List[str]] = None) -> int:
    """Run ``kf-train simulate``; return the exit code."""
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    try:
        summary = simulate(args)
    except ValueError as error:
        print(f'kf-train simulate: error: {" ".join(str(error).split())}', file=sys.stderr)
        return EXIT_ERROR
    print(f'kf-train simulate: {summary} ({time.perf_counter() - start:.3f} s)',
          file=sys.stderr)
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
