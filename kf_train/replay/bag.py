"""
``kf-train replay BAG``: run the estimator node's own session over a rosbag2 bag, offline.

BAG is a rosbag2 directory (MCAP or sqlite3), a single ``.mcap`` (or ``.db3``) file or
a ROS 1 ``.bag`` (converted message by message: :mod:`kf_train.io.bagio_ros1`), read
by :mod:`kf_train.io.bagio`. The estimator is configured exactly as the node is:
``--params-file FILE`` (ROS params format, the sections for node ``estimator``; may be
repeated, later over earlier) and ``-p NAME:=VALUE`` overrides, the node's parameter
names, defaults and validation (:mod:`kf_train.ros.estimator_params`). The bag's
messages are handed to :class:`kf_train.ros.session.EstimatorSession`, the code the
node's callbacks run, in recorded order, with the record time as the node clock (the
future-stamp check, clock-jump resets) and as the steady clock (warning throttle,
diagnostics' rates and ages). So the outputs are what the live node publishes for
those messages: rejections, out-of-sequence fusion and corrected re-publishes after a
late control included.

Topics: ``--topic`` the measurement topic (default ``measurement`` resolved in the
bag, else the only one of the preset's type), ``--control-topic`` likewise where the
preset has a control input, ``--velocity-topic`` the measured speeds the rail preset
fuses (``velocity_type``: TwistWithCovarianceStamped by default; default topic: the
bag's ``velocity`` if it has that type, as the live node subscribes it; ``-p
velocity_type:=none`` fuses none). Speeds go through the session's
:meth:`~kf_train.ros.session.EstimatorSession.on_velocity`, as the node's callback.
With ``-p measurement_type:=navsatfix -p track:=FILE`` (or ``--track FILE``) the
measurement topic is a sensor_msgs/NavSatFix one (default: ``measurement``, else the
only NavSatFix topic, e.g. ``/fix``), projected onto the track as the node does
(:meth:`~kf_train.ros.session.EstimatorSession.on_fix`).

Output (``--output``):

* ``X.csv``: one row per published estimate: ``t`` (its stamp [s]), the state by name
  (``position``, ``velocity``), ``var_<state>``, ``predicted_<state>`` and
  ``var_predicted_<state>`` (at t + horizon_s), for a preset with regimes (``rail``)
  ``p_<regime>`` (the regime probabilities after the step, as the bag output's
  ``regime_probabilities``), ``nis`` (of the measurement that step
  fused; empty when it fused none: the filter's initialisation, a correction after a
  late control, a speed). Numbers as Python's shortest round-trip ``repr``.
* a directory or ``X.mcap``: a rosbag2 MCAP bag (:class:`kf_train.io.bagio_output.
  OutputBag`) with ``estimate``, ``prediction``, ``innovation``, ``/diagnostics``
  (every ``diagnostics_period_s`` of record time, stamped with it) and, for a preset
  with regimes (``rail``), ``regime_probabilities`` after each estimate, each message
  recorded at the record time of the input that caused it.

A bad bag, parameter or output path: a one-line error, exit 1, no output at all.
"""

import itertools
import math
import time
from typing import Callable, Iterator, List, NamedTuple, Optional

from kf_train.estimator import is_rail, resolve_preset
from kf_train.filters import NS_PER_S, regime_columns
from kf_train.io import bagio, bagio_output, check_output_path, csvio, Fix, write_atomic
from kf_train.replay.progress import counted
from kf_train.ros import estimator_params, param_spec, session as estimator_session
import numpy as np

CSV_ROWS_PER_CHUNK = 4096


class BagReplaySummary(NamedTuple):
    """What a bag replay did."""

    measurements: int
    controls: int
    estimates: int
    rejected: int
    record_span_s: float
    seconds: float
    measurement_topic: str
    velocities: int = 0
    """Speeds read (0 without a velocity topic)."""
    velocity_topic: Optional[str] = None
    velocities_rejected: int = 0
    fixes: Optional[dict] = None
    """measurement_type navsatfix: the fixes' counts (fixes.received, fixes.off_track...)."""


def load_config(params_files: List[str], overrides: List[str]):
    """Return the node's EstimatorConfig; ParameterError (one line) if invalid."""
    files = []
    for path in params_files:
        try:
            files.append(param_spec.read_params_file(path))
        except OSError as error:
            raise param_spec.ParameterError(
                f'cannot read params file {path}: {error.strerror or error}') from None
    return estimator_params.load_estimator_config(files, overrides)


class BagRun:
    """The session run over an open bag; the record time is its clock."""

    def __init__(self, config, bag: 'bagio.BagInput'):
        """Prepare to run ``config`` over ``bag``."""
        self.config, self.bag = config, bag
        self.preset = resolve_preset(config.settings.preset)   # the estimator's, unbuilt
        self.session = None
        self.now_ns = self.first_ns = 0

    def seconds(self) -> float:
        """Return the record time of the message being replayed [s] (the steady clock)."""
        return self.now_ns / NS_PER_S

    def outputs(self, diagnostics: Optional[Callable] = None) -> Iterator[tuple]:
        """
        Yield (record_ns, Outputs) for every bag message, in recorded order.

        ``diagnostics(record_ns, status)`` is called every ``diagnostics_period_s`` of
        record time (from the first message's), before the first message at or after.
        """
        messages = counted(self.bag.messages(), self.bag.measurement_count
                           + self.bag.control_count + self.bag.velocity_count, 'msg',
                           'replay')   # a bar after 2 s
        first = next(messages, None)
        if first is None:
            return
        self.now_ns = self.first_ns = first.record_ns
        session = estimator_session.EstimatorSession(self.config, self.seconds)
        self.session = session
        period_ns = max(1, round(self.config.options.diagnostics_period_s * NS_PER_S))
        next_diagnostics_ns = first.record_ns + period_ns
        on_measurement, on_control = session.on_measurement, session.on_control
        measurement_type, velocity_type = bagio.Measurement, bagio.Velocity
        for message in itertools.chain((first,), messages):
            record_ns = message.record_ns
            while diagnostics is not None and record_ns >= next_diagnostics_ns:
                self.now_ns = next_diagnostics_ns
                diagnostics(next_diagnostics_ns, session.diagnostics(next_diagnostics_ns))
                next_diagnostics_ns += period_ns
            self.now_ns = record_ns
            kind = type(message)
            if kind is measurement_type:
                yield record_ns, on_measurement(message, record_ns)
            elif kind is velocity_type:
                yield record_ns, session.on_velocity(message, record_ns)
            elif kind is Fix:      # measurement_type navsatfix: none, one or the held ones
                for outputs in session.on_fix(message, record_ns):
                    yield record_ns, outputs
            else:
                yield record_ns, on_control(message, record_ns)


def csv_header(state_names, regime_names=()) -> List[str]:
    """Return the CSV output's columns (``p_<regime>`` before ``nis`` as a table's)."""
    header = ['t']
    for prefix in ('', 'predicted_'):
        header += [prefix + name for name in state_names]
        header += ['var_' + prefix + name for name in state_names]
    return header + regime_columns(regime_names) + ['nis']


def _csv_values(step, update, diagonal: slice, regimes=()) -> list:
    """Return one CSV row's numbers for a published step (NaN for no nis)."""
    row = [step.stamp_ns / NS_PER_S] + step.x.tolist()
    row += step.P.ravel().tolist()[diagonal]
    row += step.predicted_x.tolist()
    row += step.predicted_P.ravel().tolist()[diagonal]
    row += list(regimes)
    row.append(math.nan if update is None else update.nis)
    return row


def _csv_block(rows: list, no_nis: list) -> bytes:
    """
    Return rows of numbers as CSV text, each number as ``repr`` writes it.

    Formatted in bulk by :func:`kf_train.io.csvio.format_rows` (the text ``repr``
    gives, vectorised); the rows listed in ``no_nis`` (no update that step: the
    filter's initialisation, a correction) get an empty ``nis`` cell instead of 'nan'.
    """
    if not rows:
        return b''
    table = np.array(rows, dtype=np.float64)
    text = csvio.format_rows(list(table.T))
    if no_nis:
        lines = text.split(b'\n')
        for index in no_nis:
            lines[index] = lines[index][:-len(b'nan')]
        text = b'\n'.join(lines)
    return text


def _csv_chunks(run: BagRun, counts: dict) -> Iterator:
    """Yield the CSV output in chunks of lines."""
    state_names, regime_names = run.preset.state_names, _regime_names(run.preset)
    yield ','.join(csv_header(state_names, regime_names)) + '\n'
    diagonal = slice(None, None, len(state_names) + 1)   # P[i, i] of the flattened P
    rows, no_nis = [], []
    for _, outputs in run.outputs():
        step = outputs.step
        if step is not None:
            if outputs.update is None:
                no_nis.append(len(rows))
            regimes = run.session.estimator.mode_probabilities()[1] if regime_names else ()
            rows.append(_csv_values(step, outputs.update, diagonal, regimes))
            if len(rows) >= CSV_ROWS_PER_CHUNK:
                counts['estimates'] += len(rows)
                yield _csv_block(rows, no_nis)
                rows, no_nis = [], []
    counts['estimates'] += len(rows)
    yield _csv_block(rows, no_nis)


def write_csv(run: BagRun, path: str, counts: dict) -> None:
    """Replay into a CSV at ``path`` (atomically)."""
    check_output_path(path)
    try:
        write_atomic(path, _csv_chunks(run, counts))
    except OSError as error:
        raise ValueError(f'cannot write {path}: {error.strerror or error}') from None


def _regime_names(preset) -> tuple:
    """Return the regimes the outputs carry: the rail preset's, as the node publishes."""
    return tuple(preset.mode_names) if is_rail(preset) else ()


def write_bag(run: BagRun, path: str, counts: dict) -> None:
    """Replay into an MCAP bag at ``path`` (atomically)."""
    options = run.config.options
    regimes = _regime_names(run.preset)
    with bagio_output.OutputBag(path, frame_id=options.frame_id,
                                child_frame_id=options.child_frame_id,
                                regime_names=regimes) as out:

        def diagnostics(record_ns, status):
            out.write_diagnostics(record_ns, record_ns, 'estimator: filter', 'kf_train',
                                  status.level, status.message, status.values)

        for record_ns, outputs in run.outputs(diagnostics):
            step = outputs.step
            if step is not None:
                counts['estimates'] += 1
                out.write_estimate(record_ns, step.stamp_ns, step.x, step.P)
                out.write_prediction(record_ns, step.prediction_stamp_ns, step.predicted_x,
                                     step.predicted_P)
                if regimes:  # as the node: after the step, the newest state's
                    out.write_regimes(record_ns, run.session.estimator.mode_probabilities()[1])
            update = outputs.update
            if update is not None:
                out.write_innovation(record_ns, outputs.innovation_stamp_ns,
                                     update.innovation[0], update.innovation_covariance[0, 0],
                                     update.nis)


def replay_bag(bag_path: str, output_path: str, config, topic: Optional[str] = None,
               control_topic: Optional[str] = None,
               velocity_topic: Optional[str] = None) -> BagReplaySummary:
    """Replay ``bag_path`` with the node configuration ``config``; ValueError (one line)."""
    start = time.perf_counter()
    preset = resolve_preset(config.settings.preset)
    measurement_type, control_type = bagio.expected_types(preset.measurement_names,
                                                          preset.control_names)
    if config.options.measurement_type == 'navsatfix':
        measurement_type = bagio.NAVSATFIX
    # The speeds the node subscribes: the rail preset's, unless velocity_type is none.
    velocity_type = bagio.VELOCITY_TYPES.get(config.options.velocity_type) \
        if is_rail(preset) else None
    with bagio.BagInput(bag_path, measurement_type, control_type, topic,
                        control_topic, velocity_type, velocity_topic) as bag:
        return replay_source(bag, output_path, config, start)


def replay_source(bag, output_path: str, config, start: Optional[float] = None
                  ) -> BagReplaySummary:
    """Replay an open bag (or a table read as one: replay.fix_table) into ``output_path``."""
    start = time.perf_counter() if start is None else start
    counts = {'estimates': 0}
    run = BagRun(config, bag)
    (write_csv if output_path.endswith('.csv') else write_bag)(run, output_path, counts)
    session = run.session
    return BagReplaySummary(
        session.received if session else 0, session.controls_received if session else 0,
        counts['estimates'], session.rejected if session else 0,
        (run.now_ns - run.first_ns) / NS_PER_S, time.perf_counter() - start,
        bag.measurement_topic, session.velocities_received if session else 0,
        bag.velocity_topic, session.velocities_rejected if session else 0,
        dict(session.track.values()) if session and session.track else None)
