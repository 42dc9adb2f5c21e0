"""
An MCAP rosbag2 bag of the estimator's outputs, written from plain values (no rclpy).

:class:`OutputBag` writes ``estimate`` and ``prediction`` (nav_msgs/msg/Odometry),
``innovation`` (geometry_msgs/msg/Vector3Stamped), ``/diagnostics``
(diagnostic_msgs/msg/DiagnosticArray) and, given regime names, ``regime_probabilities``
(std_msgs/msg/Float64MultiArray, the names comma-separated in ``layout.dim[0].label``),
filled as the estimator node fills them
(kf_train/ros/messages.py): position in ``pose.pose.position.x`` with its variance in
``pose.covariance[0]``, velocity in ``twist.twist.linear.x`` with its variance in
``twist.covariance[0]``, every other diagonal entry 1e9 (not estimated), orientation
identity; a one-state estimate has velocity 0 with variance 1e9. The relative names
are resolved in ``namespace``; each message's record time is given by the caller
(a replay gives the record time of the input message that caused it).

The bag is written into a temporary directory beside the target; :meth:`close` moves
it into place (a directory, or for a path ending in ``.mcap`` the single MCAP file,
which replaces an existing file of that name), and an exception inside the ``with``
block (or :meth:`abort`) removes it: no partial output. Foxglove opens the bag and
``ros2 bag play`` plays it (the schemas are the ROS 2 message definitions).
"""

import os
from pathlib import Path
import shutil
import struct
import tempfile
from typing import Optional, Sequence, Tuple, Union

from kf_train.filters import NS_PER_S, regime_columns
from kf_train.io.bagio_diagnostics import DiagnosticsEncoder
from kf_train.io.bagio_layout import PatchTemplate
from kf_train.io.bagio_mcap import MessageAppender
from kf_train.io.bagio_types import (
    DIAGNOSTIC_LEVELS, DIAGNOSTICS, ODOMETRY, TYPESTORE, UNESTIMATED_VARIANCE, VECTOR3)
from kf_train.io.paths import check_output_path
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

_T = TYPESTORE.types
_Time = _T['builtin_interfaces/msg/Time']
_Header = _T['std_msgs/msg/Header']
_Odometry = _T[ODOMETRY]
_PoseWithCovariance = _T['geometry_msgs/msg/PoseWithCovariance']
_Pose = _T['geometry_msgs/msg/Pose']
_Point = _T['geometry_msgs/msg/Point']
_Quaternion = _T['geometry_msgs/msg/Quaternion']
_TwistWithCovariance = _T['geometry_msgs/msg/TwistWithCovariance']
_Twist = _T['geometry_msgs/msg/Twist']
_Vector3 = _T['geometry_msgs/msg/Vector3']
_Vector3Stamped = _T[VECTOR3]
_DiagnosticArray = _T[DIAGNOSTICS]
_DiagnosticStatus = _T['diagnostic_msgs/msg/DiagnosticStatus']
_KeyValue = _T['diagnostic_msgs/msg/KeyValue']
_STAMP = ((('header', 'stamp', 'sec'), 'i'), (('header', 'stamp', 'nanosec'), 'I'))
ODOMETRY_FIELDS = _STAMP + (
    (('pose', 'pose', 'position', 'x'), 'd'), (('pose', 'covariance', 0), 'd'),
    (('twist', 'twist', 'linear', 'x'), 'd'), (('twist', 'covariance', 0), 'd'))
VECTOR3_FIELDS = _STAMP + tuple(((('vector', axis), 'd') for axis in 'xyz'))


def header_message(stamp_ns: int, frame_id: str):
    """Return a std_msgs/Header at ``stamp_ns``."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return _Header(stamp=_Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


def _covariance(first_variance: float) -> 'list':
    """Return a row-major 6x6 covariance with ``first_variance`` at [0], 1e9 elsewhere."""
    covariance = [0.0] * 36
    for i in range(6):
        covariance[7 * i] = UNESTIMATED_VARIANCE
    covariance[0] = float(first_variance)
    return covariance


def odometry_message(stamp_ns: int, frame_id: str, child_frame_id: str, x, P):
    """Return the Odometry holding a [position] or [position, velocity] state x, cov. P."""
    position = float(x[0])
    if len(x) == 1:
        velocity, var_velocity = 0.0, UNESTIMATED_VARIANCE
    else:
        velocity, var_velocity = float(x[1]), float(P[1][1])
    return _Odometry(
        header=header_message(stamp_ns, frame_id), child_frame_id=child_frame_id,
        pose=_PoseWithCovariance(
            pose=_Pose(position=_Point(x=position, y=0.0, z=0.0),
                       orientation=_Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.array(_covariance(P[0][0]))),
        twist=_TwistWithCovariance(
            twist=_Twist(linear=_Vector3(x=velocity, y=0.0, z=0.0),
                         angular=_Vector3(x=0.0, y=0.0, z=0.0)),
            covariance=np.array(_covariance(var_velocity))))


class AtomicBag:
    """
    A bag written into a temporary folder and moved into place only when complete.

    Subclasses call :meth:`_start`, which sets ``path``, ``single_file``, ``_writer`` (an
    open rosbags Writer), ``_written`` (the bag folder it writes) and ``_temporary`` (the
    folder holding it), and set ``_appender`` when they write through a
    :class:`MessageAppender`.
    """

    _appender: Optional[MessageAppender] = None

    def _start(self, path: Union[str, Path]) -> None:
        """Check ``path`` and open the writer in a new temporary folder beside it."""
        self.path = Path(path)
        self.single_file = self.path.suffix == '.mcap'
        _check_target(self.path, self.single_file)
        self._temporary = Path(tempfile.mkdtemp(prefix=f'.{self.path.name}.',
                                                dir=self.path.parent))
        # The bag directory inside it: the target's name (its stem for a single file,
        # whose MCAP file inside is then named as the target).
        self._written = self._temporary / (self.path.stem if self.single_file
                                           else self.path.name)
        try:
            self._writer = Writer(self._written, version=9, storage_plugin=StoragePlugin.MCAP)
            self._writer.open()
        except BaseException:
            self.abort()
            raise

    def close(self) -> Path:
        """Finish the bag and move it into place; return its path."""
        try:
            if self._appender is not None:
                self._appender.flush()
            self._writer.close()
            if self.single_file:
                os.replace(self._written / f'{self.path.stem}.mcap', self.path)
            else:
                os.rename(self._written, self.path)
        except OSError as error:
            self.abort()
            raise ValueError(f'cannot write {self.path}: {error.strerror or error}') \
                from None
        shutil.rmtree(self._temporary, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        """Drop everything written: no output at all."""
        shutil.rmtree(self._temporary, ignore_errors=True)

    def __enter__(self) -> 'AtomicBag':
        """Return self."""
        return self

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        """Close the bag, or drop it if the block raised."""
        if exc_type is None:
            self.close()
        else:
            self.abort()


class OutputBag(AtomicBag):
    """A bag being written; use as a context manager (see the module doc)."""

    def __init__(self, path: Union[str, Path], namespace: str = '', frame_id: str = 'odom',
                 child_frame_id: str = 'base_link', regime_names: Sequence[str] = ()):
        """Create the temporary bag for ``path``; ValueError if it cannot be written."""
        self.regime_names = tuple(regime_names)
        self.frame_id, self.child_frame_id = frame_id, child_frame_id
        self._start(path)
        try:
            prefix = topic_prefix(namespace)
            self._connections = {
                name: self._writer.add_connection(topic, kind, typestore=TYPESTORE)
                for name, topic, kind in (
                    ('estimate', prefix + 'estimate', ODOMETRY),
                    ('prediction', prefix + 'prediction', ODOMETRY),
                    ('innovation', prefix + 'innovation', VECTOR3),
                    ('diagnostics', '/diagnostics', DIAGNOSTICS))}
            if self.regime_names:
                self._connections['regime_probabilities'] = self._writer.add_connection(
                    prefix + 'regime_probabilities', MULTIARRAY, typestore=TYPESTORE)
        except BaseException:
            self.abort()
            raise
        self.counts = dict.fromkeys(self._connections, 0)
        self._odometry = PatchTemplate(
            odometry_message(0, frame_id, child_frame_id, [0.0, 0.0], [[0.0, 0.0], [0.0, 0.0]]),
            ODOMETRY, ODOMETRY_FIELDS)
        self._vector3 = PatchTemplate(
            _Vector3Stamped(header=header_message(0, frame_id),
                            vector=_Vector3(x=0.0, y=0.0, z=0.0)),
            VECTOR3, VECTOR3_FIELDS)
        self._diagnostics = DiagnosticsEncoder()
        count = len(self.regime_names)
        self._regimes = PatchTemplate(
            regime_message(self.regime_names, [0.0] * count), MULTIARRAY,
            tuple(((('data', i), 'd') for i in range(count)))) if count else None
        # Every message goes through the appender (rosbags' bytes, ~4x faster).
        self._appender = MessageAppender(self._writer)
        self._write_raw = self._appender.write

    def _write_odometry(self, name: str, record_ns: int, stamp_ns: int, x, P) -> None:
        """Write an Odometry holding state x ([position] or [position, velocity]), cov. P."""
        sec, nanosec = divmod(stamp_ns, NS_PER_S)
        try:
            raw = self._odometry.fill(sec, nanosec, *_odometry_values(x, P))
        except struct.error:
            raise _stamp_error(stamp_ns) from None
        self._write_raw(self._connections[name], record_ns, raw)
        self.counts[name] += 1

    def write_estimate(self, record_ns: int, stamp_ns: int, x, P) -> None:
        """Write an ``estimate``: state x ([position] or [position, velocity]), cov. P."""
        self._write_odometry('estimate', record_ns, stamp_ns, x, P)

    def write_prediction(self, record_ns: int, stamp_ns: int, x, P) -> None:
        """Write a ``prediction`` (stamped the time it is predicted for)."""
        self._write_odometry('prediction', record_ns, stamp_ns, x, P)

    def write_innovation(self, record_ns: int, stamp_ns: int, innovation_m: float,
                         variance_m2: float, nis: float) -> None:
        """Write an ``innovation``: y, its variance S and the NIS in vector x, y, z."""
        sec, nanosec = divmod(stamp_ns, NS_PER_S)
        try:
            raw = self._vector3.fill(sec, nanosec, float(innovation_m), float(variance_m2),
                                     float(nis))
        except struct.error:
            raise _stamp_error(stamp_ns) from None
        self._write_raw(self._connections['innovation'], record_ns, raw)
        self.counts['innovation'] += 1

    def write_diagnostics(self, record_ns: int, stamp_ns: int, name: str, hardware_id: str,
                          level: str, message: str,
                          values: Sequence[Tuple[str, str]]) -> None:
        """Write one ``/diagnostics`` status; ``level`` is OK, WARN, ERROR or STALE."""
        if level not in DIAGNOSTIC_LEVELS:
            raise ValueError(f'level must be one of {", ".join(DIAGNOSTIC_LEVELS)}, '
                             f'got {level!r}')
        try:
            raw = self._diagnostics.encode(stamp_ns, '', DIAGNOSTIC_LEVELS[level], name,
                                           message, hardware_id, values)
        except struct.error:
            raise _stamp_error(stamp_ns) from None
        self._write_raw(self._connections['diagnostics'], record_ns, raw)
        self.counts['diagnostics'] += 1

    def write_regimes(self, record_ns: int, probabilities) -> None:
        """Write a ``regime_probabilities`` (the bag's regime_names, in their order)."""
        values = np.asarray(probabilities, dtype=np.float64).tolist()
        if len(values) == len(self.regime_names):       # the template's fields
            raw = self._regimes.fill(*values)
        else:                                           # (as the node: whatever it has)
            raw = TYPESTORE.serialize_cdr(regime_message(self.regime_names, values),
                                          MULTIARRAY)
        self._write_raw(self._connections['regime_probabilities'], record_ns, raw)
        self.counts['regime_probabilities'] += 1


MULTIARRAY = 'std_msgs/msg/Float64MultiArray'


def regime_message(names: Sequence[str], probabilities):
    """Return the Float64MultiArray the estimator node publishes on regime_probabilities."""
    dimension = _T['std_msgs/msg/MultiArrayDimension'](
        label=','.join(names), size=len(names), stride=len(names))
    layout = _T['std_msgs/msg/MultiArrayLayout'](dim=[dimension], data_offset=0)
    return _T[MULTIARRAY](layout=layout, data=np.array(probabilities, dtype=np.float64))


def _odometry_values(x, P) -> Tuple[float, float, float, float]:
    """Return position, its variance, velocity and its variance of a 1- or 2-state x, P."""
    if type(x) is np.ndarray and type(P) is np.ndarray:   # a replay's: read in C
        if x.shape[0] == 1:
            return x.item(0), P.item(0), 0.0, UNESTIMATED_VARIANCE
        return x.item(0), P.item(0), x.item(1), P.item(1, 1)
    if len(x) == 1:
        return float(x[0]), float(P[0][0]), 0.0, UNESTIMATED_VARIANCE
    return float(x[0]), float(P[0][0]), float(x[1]), float(P[1][1])


def topic_prefix(namespace: str) -> str:
    """Return the prefix of a namespace's topics: '/' or '/a/b/' ('a/b', '/a/b/' alike)."""
    prefix = '/'.join(part for part in namespace.split('/') if part)
    return '/' + prefix + '/' if prefix else '/'


def _stamp_error(stamp_ns: int) -> ValueError:
    """Return the error for a stamp that a ROS Time (int32 seconds) cannot hold."""
    return ValueError(f'stamp {stamp_ns} ns is out of range of a ROS stamp (int32 seconds)')


def _check_target(path: Path, single_file: bool) -> None:
    """Raise a one-line ValueError if the bag cannot be written at ``path``."""
    # The checks every output shares (parent exists and is writable, a file is no
    # directory), then the bag's own: a bag directory is never overwritten.
    check_output_path(str(path), dataset=not single_file)
    if not single_file and path.exists():
        raise ValueError(f'cannot write {path}: it exists (a bag directory is never '
                         f'overwritten)')


def read_output_bag(path: Union[str, Path]) -> dict:
    """
    Return the columns of an output bag as a replay CSV names them (one row per estimate).

    ``t`` (the estimate's stamp [s]), ``position``, ``velocity`` and their ``var_``,
    ``predicted_position`` and its variance, ``p_<regime>`` when the bag has
    ``regime_probabilities`` (the k-th after the k-th estimate, as written), and ``nis``
    of the innovation recorded with the estimate (NaN for none). One-line ValueError.
    """
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.serde import SerdeError
    rows, regimes, names = [], [], ()
    try:
        with Reader(Path(path)) as reader:
            for connection, record_ns, raw in reader.messages():
                topic = connection.topic.rsplit('/', 1)[-1]
                if topic not in ('estimate', 'prediction', 'innovation',
                                 'regime_probabilities'):
                    continue
                message = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
                if topic == 'estimate':
                    stamp = message.header.stamp
                    rows.append([record_ns, stamp.sec + stamp.nanosec / NS_PER_S,
                                 message.pose.pose.position.x, message.twist.twist.linear.x,
                                 message.pose.covariance[0], message.twist.covariance[0],
                                 np.nan, np.nan, np.nan])
                elif topic == 'prediction' and rows:
                    rows[-1][6:8] = [message.pose.pose.position.x, message.pose.covariance[0]]
                elif topic == 'innovation' and rows and rows[-1][0] == record_ns:
                    rows[-1][8] = message.vector.z
                elif topic == 'regime_probabilities':
                    names = tuple(message.layout.dim[0].label.split(','))
                    regimes.append(message.data.tolist())
    except (ReaderError, SerdeError, OSError, ValueError, KeyError, IndexError,
            AttributeError, struct.error) as error:
        raise ValueError(f'{path}: not a readable output bag: {error}') from None
    if not rows:
        raise ValueError(f'{path}: no estimate messages')
    table = np.array(rows)
    columns = dict(zip(['t', 'position', 'velocity', 'var_position', 'var_velocity',
                        'predicted_position', 'var_predicted_position', 'nis'],
                       table[:, 1:].T))
    if regimes and len(regimes) == len(rows):
        columns.update(zip(regime_columns(names), np.array(regimes).T))
    return columns
