"""
Rosbag2 in and out with plain values: measurements and controls read, outputs written.

Bags are read and written with the ``rosbags`` library (pure Python; its Jazzy
typestore holds the standard messages), so nothing here needs rclpy or a ROS install:
``pip install 'kf_train[bag]'``.

Reading (:class:`BagInput`): a rosbag2 directory (MCAP or sqlite3 storage, with its
metadata.yaml), a single ``.mcap`` (or ``.db3``) file, or a ROS 1 ``.bag``
(:mod:`kf_train.io.bagio_ros1`: the same messages, converted to CDR). Up to three
topics are used, the rest is ignored:

* the measurement topic, of the type the preset measures (:func:`expected_types`):
  geometry_msgs/msg/PoseWithCovarianceStamped for a position (``pose.pose.position.x``,
  variance ``pose.covariance[0]``), nav_msgs/msg/Odometry for position and velocity
  (``pose.pose.position.x`` / ``pose.covariance[0]``, ``twist.twist.linear.x`` /
  ``twist.covariance[0]``), as the estimator node subscribes them; or
  sensor_msgs/msg/NavSatFix (``measurement_type`` navsatfix), as
  :class:`kf_train.io.track_fixes.Fix` tuples;
* the control topic where the preset has one: geometry_msgs/msg/AccelStamped
  (``accel.linear.x``) or geometry_msgs/msg/TwistStamped (``twist.linear.x``);
* the speeds' topic where the configuration fuses them (the rail preset's
  ``velocity``): geometry_msgs/msg/TwistWithCovarianceStamped (``twist.twist.linear.x``,
  variance ``twist.covariance[0]``) or geometry_msgs/msg/TwistStamped, as
  :class:`Velocity` tuples; left to the default, the bag's ``velocity`` topic if it
  has that type, else none.

A topic name given explicitly must be in the bag (a relative name matches ``/name``).
Left to the default (``measurement``, ``control``), the name is resolved in the bag
(``/measurement``, else the one topic ending in ``/measurement``), and failing that
the only topic of the expected type is taken. Messages come in recorded order
(record time, then file order) as :class:`Measurement` and :class:`Control` tuples
with the record time and the header stamp as integer nanoseconds; memory stays flat.

Messages are decoded as rosbags deserialises them; the few fields needed are read
at offsets learnt from rosbags' serializer and checked against it
(:mod:`kf_train.io.bagio_layout`), several times faster than building each message.
Writing the estimator's outputs: :class:`kf_train.io.bagio_output.OutputBag`.

Every problem with a bag (missing, not a bag, truncated, a topic missing or of the
wrong type, a message that does not decode) raises ``ValueError`` with a one-line
message that names the bag and the problem.
"""

from pathlib import Path
import struct
from typing import Callable, Dict, Iterator, NamedTuple, Optional, Sequence, Tuple, Union

from kf_train.filters import NS_PER_S
from kf_train.io.bagio_layout import FieldReader
from kf_train.io.bagio_ros1 import ROS1_SUFFIX, Ros1Bag, Ros1ReaderError
from kf_train.io.bagio_types import (
    ACCEL, CONTROL_TYPES, MEASUREMENT_TYPES, NAVSATFIX, ODOMETRY, POSE, TWIST, TWIST_COVARIANCE,
    TYPESTORE, VELOCITY_TYPES)
from kf_train.io.track_fixes import fix_from_msg
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError
from rosbags.serde import SerdeError

NAN = float('nan')
__all__ = ['BagInput', 'Control', 'expected_types', 'Measurement', 'NAVSATFIX',
           'resolve_topic', 'Velocity', 'VELOCITY_TYPES']
# At most this many topics are listed in an error message.
LISTED_TOPICS = 8
# What the rosbags reader raises on broken storage; decoding adds SerdeError. A garbled
# record length in an MCAP chunk overflows a seek (OverflowError) or a struct unpack
# (struct.error), or trips one of rosbags' own asserts on the records it found; a file
# cut right after its magic makes rosbags call ord() on an empty read (TypeError).
_STORAGE_ERRORS = (ReaderError, Ros1ReaderError, OSError, KeyError, ValueError, EOFError,
                   IndexError, OverflowError, struct.error, AssertionError, TypeError)


class Measurement(NamedTuple):
    """One measurement message; velocity fields NaN when the type carries none."""

    record_ns: int
    stamp_ns: int
    frame_id: str
    position_m: float
    variance_m2: float
    velocity_mps: float
    velocity_variance_m2s2: float


class Velocity(NamedTuple):
    """One measured speed (the estimator's ``velocity`` topic); variance NaN for a TwistStamped."""

    record_ns: int
    stamp_ns: int
    frame_id: str
    velocity_mps: float
    variance_m2s2: float


class Control(NamedTuple):
    """One control message: the input along x (acceleration [m/s²] or speed [m/s])."""

    record_ns: int
    stamp_ns: int
    frame_id: str
    value: float


def expected_types(measurement_names: Sequence[str],
                   control_names: Sequence[str] = ()) -> Tuple[str, Optional[str]]:
    """Return the measurement and control message types for a preset's names."""
    try:
        measurement = MEASUREMENT_TYPES[tuple(measurement_names)]
    except KeyError:
        raise ValueError(f'no ROS message carries the measurement {tuple(measurement_names)}'
                         f'; bags hold {", ".join(map(str, MEASUREMENT_TYPES))}') from None
    if not control_names:
        return measurement, None
    if len(control_names) != 1 or control_names[0] not in CONTROL_TYPES:
        raise ValueError(f'no ROS message carries the control {tuple(control_names)}')
    return measurement, CONTROL_TYPES[control_names[0]]


def _describe(topics: Dict[str, Optional[str]]) -> str:
    """Return 'topics: /a [type], ...' for an error message."""
    if not topics:
        return 'the bag has no topics'
    listed = [f'{name} [{kind or "mixed types"}]'
              for name, kind in sorted(topics.items())[:LISTED_TOPICS]]
    more = len(topics) - LISTED_TOPICS
    return 'topics: ' + ', '.join(listed) + (f' and {more} more' if more > 0 else '')


def resolve_topic(topics: Dict[str, Optional[str]], role: str, name: Optional[str],
                  default_name: str, expected_type: str) -> str:
    """
    Return the bag topic for ``role`` (measurement or control); see the module doc.

    ``topics`` maps each topic to its type (None when its connections disagree).
    ``name`` None means the default: ``default_name`` resolved, else the only topic
    of ``expected_type``.
    """
    wanted = default_name if name is None else name
    if wanted.startswith('/'):
        candidates = [wanted] if wanted in topics else []
    else:
        exact = '/' + wanted
        candidates = [exact] if exact in topics else sorted(
            t for t in topics if t.endswith('/' + wanted))
    if len(candidates) > 1:
        raise ValueError(f'{role} topic {wanted!r} is ambiguous: {", ".join(candidates)}')
    if candidates:
        topic = candidates[0]
        if topics[topic] != expected_type:
            typed = sorted(t for t, kind in topics.items() if kind == expected_type)
            hint = f'; of that type: {", ".join(typed)}' if typed else ''
            raise ValueError(f'{role} topic {topic} has type {topics[topic] or "(mixed)"}, '
                             f'expected {expected_type}{hint}')
        return topic
    if name is not None:
        raise ValueError(f'{role} topic {name!r} is not in the bag ({_describe(topics)})')
    typed = sorted(t for t, kind in topics.items() if kind == expected_type)
    if len(typed) == 1:
        return typed[0]
    if typed:
        raise ValueError(f'no {role} topic {default_name!r} and several of type '
                         f'{expected_type}: {", ".join(typed)}; choose one')
    raise ValueError(f'no {role} topic: none named {default_name!r} and none of type '
                     f'{expected_type} ({_describe(topics)})')


def _velocity_topic(topics: Dict[str, Optional[str]], kind: Optional[str],
                    name: Optional[str]) -> Optional[str]:
    """Return the speeds' topic: ``name`` (it must exist), else ``velocity`` if so typed."""
    if kind is None:
        if name is not None:
            raise ValueError(f'velocity topic {name!r} given, but this configuration fuses no '
                             'speed (preset rail, velocity_type not none)')
        return None
    if name is not None:
        return resolve_topic(topics, 'velocity', name, 'velocity', kind)
    candidates = [topic for topic in topics
                  if topic == '/velocity' or topic.endswith('/velocity')]
    if len(candidates) == 1 and topics[candidates[0]] == kind:
        return candidates[0]
    return None


_STAMP = ((('header', 'stamp', 'sec'), 'i'), (('header', 'stamp', 'nanosec'), 'I'))
_FIELDS = {
    POSE: _STAMP + ((('pose', 'pose', 'position', 'x'), 'd'), (('pose', 'covariance', 0), 'd')),
    ODOMETRY: _STAMP + ((('pose', 'pose', 'position', 'x'), 'd'), (('pose', 'covariance', 0), 'd'),
                        (('twist', 'twist', 'linear', 'x'), 'd'),
                        (('twist', 'covariance', 0), 'd')),
    ACCEL: _STAMP + ((('accel', 'linear', 'x'), 'd'),),
    TWIST: _STAMP + ((('twist', 'linear', 'x'), 'd'),),
    TWIST_COVARIANCE: _STAMP + ((('twist', 'twist', 'linear', 'x'), 'd'),
                                (('twist', 'covariance', 0), 'd')),
}
"""The fields read from each input type: the stamp, then the values (module doc)."""


def _decoder(kind: str, role: str) -> Callable:
    """Return a function (raw bytes, record time) -> the message of ``role`` for ``kind``."""
    if kind == NAVSATFIX:      # a track.Fix; decoded whole (a fix is rarer than 100 Hz)
        return lambda raw, record_ns: fix_from_msg(TYPESTORE.deserialize_cdr(raw, kind),
                                                   record_ns)
    # FieldReader gives Python floats and ints, whichever way it read them.
    read = FieldReader(kind, _FIELDS[kind]).read

    def measurement(raw, record_ns: int) -> Measurement:
        frame_id, (sec, nanosec, position, variance) = read(raw)
        return Measurement(record_ns, sec * NS_PER_S + nanosec, frame_id, position, variance,
                           NAN, NAN)

    def odometry(raw, record_ns: int) -> Measurement:
        frame_id, (sec, nanosec, position, variance, velocity, velocity_variance) = read(raw)
        return Measurement(record_ns, sec * NS_PER_S + nanosec, frame_id, position, variance,
                           velocity, velocity_variance)

    def control(raw, record_ns: int) -> Control:
        frame_id, (sec, nanosec, value) = read(raw)
        return Control(record_ns, sec * NS_PER_S + nanosec, frame_id, value)

    def velocity(raw, record_ns: int) -> Velocity:
        frame_id, (sec, nanosec, *values) = read(raw)
        return Velocity(record_ns, sec * NS_PER_S + nanosec, frame_id, values[0],
                        values[1] if len(values) > 1 else NAN)

    if role == 'velocity':
        return velocity
    if role == 'control':
        return control
    return odometry if kind == ODOMETRY else measurement


class BagInput:
    """
    An open bag, its measurement (and control) topic chosen; iterate :meth:`messages`.

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, path: Union[str, Path], measurement_type: str = POSE,
                 control_type: Optional[str] = None, measurement_topic: Optional[str] = None,
                 control_topic: Optional[str] = None, velocity_type: Optional[str] = None,
                 velocity_topic: Optional[str] = None):
        """
        Open the bag at ``path`` and choose the topics (module doc); ValueError if not.

        ``velocity_type`` (TwistWithCovarianceStamped or TwistStamped; None: no speeds)
        reads the speeds of ``velocity_topic``; without a name, of ``velocity`` resolved
        in the bag when it has that type, else none.
        """
        if velocity_type not in (None, TWIST_COVARIANCE, TWIST):
            raise ValueError(f'velocity_type must be None, {TWIST_COVARIANCE} or {TWIST}, '
                             f'got {velocity_type!r}')
        if measurement_type not in (POSE, ODOMETRY, NAVSATFIX):
            raise ValueError(f'measurement_type must be {POSE}, {ODOMETRY} or {NAVSATFIX}, '
                             f'got {measurement_type!r}')
        if control_type not in (None, ACCEL, TWIST):
            raise ValueError(f'control_type must be None, {ACCEL} or {TWIST}, '
                             f'got {control_type!r}')
        self.path = Path(path)
        self._reader = _open_reader(self.path)
        try:
            self._choose_topics(measurement_type, control_type, measurement_topic,
                                control_topic, velocity_type, velocity_topic)
        except BaseException:
            self.close()
            raise

    def _choose_topics(self, measurement_type, control_type, measurement_topic,
                       control_topic, velocity_type=None, velocity_topic=None) -> None:
        """Pick the topics and their connections; check their serialisation."""
        try:
            topics = {name: info.msgtype for name, info in self._reader.topics.items()}
        except _STORAGE_ERRORS as error:
            raise self._error('cannot list its topics', error) from None
        try:
            self.measurement_topic = resolve_topic(topics, 'measurement', measurement_topic,
                                                   'measurement', measurement_type)
            self.control_topic = None if control_type is None else resolve_topic(
                topics, 'control', control_topic, 'control', control_type)
            self.velocity_topic = _velocity_topic(topics, velocity_type, velocity_topic)
        except ValueError as error:
            raise ValueError(f'{self.path}: {error}') from None
        self.measurement_type, self.control_type = measurement_type, control_type
        self._connections = [c for c in self._reader.connections if c.topic in (
            self.measurement_topic, self.control_topic, self.velocity_topic)]
        for connection in self._connections:
            serialization = getattr(connection.ext, 'serialization_format', 'cdr')
            if serialization != 'cdr':
                raise ValueError(f'{self.path}: topic {connection.topic} is serialised as '
                                 f'{serialization!r}, not cdr')
        self.measurement_count = sum(c.msgcount for c in self._connections
                                     if c.topic == self.measurement_topic)
        self.control_count = sum(c.msgcount for c in self._connections
                                 if c.topic == self.control_topic)
        self.velocity_count = sum(c.msgcount for c in self._connections
                                  if c.topic == self.velocity_topic)

    def _error(self, what: str, error: BaseException) -> ValueError:
        """Return a one-line ValueError naming the bag, what failed and why."""
        text = ' '.join(str(error).split()) or type(error).__name__
        return ValueError(f'{self.path}: {what}: {text}')

    def messages(self) -> Iterator[Union[Measurement, Control]]:
        """Yield the measurements and controls in recorded order."""
        roles = {self.measurement_topic: 'measurement', self.control_topic: 'control',
                 self.velocity_topic: 'velocity'}
        decoders = {c.id: _decoder(c.msgtype, roles[c.topic]) for c in self._connections}
        index = 0
        try:
            for connection, record_ns, raw in self._reader.messages(self._connections):
                index += 1
                try:
                    yield decoders[connection.id](raw, record_ns)
                except (SerdeError, struct.error, UnicodeDecodeError, AttributeError,
                        TypeError) as error:
                    raise self._error(f'message {index} on {connection.topic} does not '
                                      f'decode as {connection.msgtype}', error) from None
        except _STORAGE_ERRORS as error:
            if isinstance(error, ValueError) and str(error).startswith(f'{self.path}: '):
                raise
            raise self._error(f'cannot read message {index + 1} (truncated or damaged?)',
                              error) from None

    def close(self) -> None:
        """Close the bag (again: nothing)."""
        if self._reader is not None and self._reader.is_open:
            self._reader.close()
        self._reader = None

    def __enter__(self) -> 'BagInput':
        """Return self."""
        return self

    def __exit__(self, *exc_info) -> None:
        """Close the bag."""
        self.close()


def _open_reader(path: Path) -> Union[Reader, Ros1Bag]:
    """Return an open rosbags Reader for ``path``; one-line ValueError if it is no bag."""
    if not path.exists():
        raise ValueError(f'{path}: no such file or directory')
    if path.is_dir() and not (path / 'metadata.yaml').is_file():
        raise ValueError(f'{path}: not a rosbag2 directory (no metadata.yaml)')
    if path.is_file() and path.suffix not in ('.mcap', '.db3', ROS1_SUFFIX):
        raise ValueError(f'{path}: not a bag: expected a rosbag2 directory, a .mcap or a '
                         f'.db3 file, or a ROS 1 .bag')
    try:
        reader = Ros1Bag(path) if path.suffix == ROS1_SUFFIX and path.is_file() \
            else Reader(path)
        reader.open()
    except (*_STORAGE_ERRORS, SerdeError) as error:
        text = ' '.join(str(error).split()) or type(error).__name__
        raise ValueError(f'{path}: not a readable bag (truncated or damaged?): {text}') \
            from None
    return reader
