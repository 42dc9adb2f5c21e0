"""
An MCAP rosbag2 bag of a simulated run, written from plain values (no rclpy).

:class:`SimulationBag` writes the simulator node's topics with the types and fields
the node publishes (:mod:`kf_train.ros.simulator_node`, kf_train/ros/messages.py):

* ``measurement``: geometry_msgs/msg/PoseWithCovarianceStamped, position in
  ``pose.pose.position.x``, variance in ``pose.covariance[0]``, every other diagonal
  entry 1e9, orientation identity;
* ``ground_truth``: nav_msgs/msg/Odometry, position and velocity, variances 0;
* ``control`` (scenarios with one): geometry_msgs/msg/AccelStamped (``accel.linear.x``)
  or geometry_msgs/msg/TwistStamped (``twist.linear.x``), frame ``child_frame_id``;
* ``ground_truth_accel`` (scenarios with a true acceleration: rail):
  geometry_msgs/msg/AccelStamped, ``accel.linear.x`` [m/s²], frame ``child_frame_id``;
* ``velocity`` (with ``velocity=True``: the rail GNSS receiver's Doppler speed):
  geometry_msgs/msg/TwistWithCovarianceStamped, ``twist.twist.linear.x`` [m/s],
  variance in ``twist.covariance[0]``, every other diagonal entry 1e9, frame
  ``child_frame_id``;
* ``/clock`` (with ``clock=True``, as ``publish_clock``): rosgraph_msgs/msg/Clock.

Each message is one serialized by rosbags once per type and frame, its numbers
overwritten in place (:class:`kf_train.io.bagio_layout.PatchTemplate`, checked against
rosbags), and appended by :class:`kf_train.io.bagio_mcap.MessageAppender`: the bytes
rosbags writes, ~10x faster.

Relative names are resolved in ``namespace``. The bag is written into a temporary
directory beside the target and moved into place by :meth:`close` (a directory, or
for a path ending in ``.mcap`` the single MCAP file); an exception inside the
``with`` block removes it: no partial output.
"""

from pathlib import Path
import struct
from typing import Dict, Optional, Tuple, Union

from kf_train.filters import NS_PER_S
from kf_train.io.bagio_layout import PatchTemplate
from kf_train.io.bagio_mcap import MessageAppender
from kf_train.io.bagio_output import (
    _stamp_error, AtomicBag, header_message, ODOMETRY_FIELDS, odometry_message, topic_prefix)
from kf_train.io.bagio_types import (
    ACCEL, CONTROL_TYPES, ODOMETRY, POSE, TWIST, TWIST_COVARIANCE, TYPESTORE)
import numpy as np

_T = TYPESTORE.types
_STAMP = ((('header', 'stamp', 'sec'), 'i'), (('header', 'stamp', 'nanosec'), 'I'))
MEASUREMENT_FIELDS = _STAMP + ((('pose', 'pose', 'position', 'x'), 'd'),
                               (('pose', 'covariance', 0), 'd'))
CLOCK = 'rosgraph_msgs/msg/Clock'
CLOCK_FIELDS = ((('clock', 'sec'), 'i'), (('clock', 'nanosec'), 'I'))
VELOCITY_FIELDS = _STAMP + ((('twist', 'twist', 'linear', 'x'), 'd'),
                            (('twist', 'covariance', 0), 'd'))
CONTROL_FIELDS = {ACCEL: _STAMP + ((('accel', 'linear', 'x'), 'd'),),
                  TWIST: _STAMP + ((('twist', 'linear', 'x'), 'd'),)}


def _vector3(x: float):
    """Return a geometry_msgs/Vector3 (x, 0, 0)."""
    return _T['geometry_msgs/msg/Vector3'](x=float(x), y=0.0, z=0.0)


def measurement_message(stamp_ns: int, frame_id: str, position_m: float, variance_m2: float):
    """Return the PoseWithCovarianceStamped the simulator publishes."""
    pose = odometry_message(stamp_ns, frame_id, '', [position_m], [[variance_m2]]).pose
    return _T[POSE](header=header_message(stamp_ns, frame_id), pose=pose)


def control_message(kind: str, stamp_ns: int, frame_id: str, value: float):
    """Return an AccelStamped or TwistStamped holding ``value`` along x."""
    zero = _vector3(0.0)
    if kind == ACCEL:
        return _T[ACCEL](header=header_message(stamp_ns, frame_id),
                         accel=_T['geometry_msgs/msg/Accel'](linear=_vector3(value),
                                                             angular=zero))
    return _T[TWIST](header=header_message(stamp_ns, frame_id),
                     twist=_T['geometry_msgs/msg/Twist'](linear=_vector3(value), angular=zero))


def velocity_message(stamp_ns: int, frame_id: str, speed_mps: float, variance_m2_s2: float):
    """Return the TwistWithCovarianceStamped the simulator publishes on ``velocity``."""
    twist = odometry_message(stamp_ns, frame_id, '', [0.0, speed_mps],
                             np.diag([0.0, variance_m2_s2])).twist
    return _T[TWIST_COVARIANCE](header=header_message(stamp_ns, frame_id), twist=twist)


class SimulationBag(AtomicBag):
    """A simulated run being written; use as a context manager (see the module doc)."""

    def __init__(self, path: Union[str, Path], control_name: Optional[str],
                 namespace: str = '', clock: bool = False,
                 truth_acceleration: bool = False, velocity: bool = False):
        """Create the temporary bag for ``path``; ValueError if it cannot be written."""
        if clock and CLOCK not in TYPESTORE.types:
            raise ValueError(f'publish_clock: the rosbags typestore has no {CLOCK}')
        self._start(path)
        try:
            self.control_type = None if control_name is None else CONTROL_TYPES[control_name]
            prefix = topic_prefix(namespace)
            topics = [('measurement', POSE), ('ground_truth', ODOMETRY)]
            if self.control_type is not None:
                topics.append(('control', self.control_type))
            if truth_acceleration:
                topics.append(('ground_truth_accel', ACCEL))
            if velocity:
                topics.append(('velocity', TWIST_COVARIANCE))
            if clock:
                topics.append(('/clock', CLOCK))
            self._connections = {
                name.lstrip('/'): (self._writer.add_connection(
                    name if name.startswith('/') else prefix + name, kind,
                    typestore=TYPESTORE), kind) for name, kind in topics}
        except BaseException:
            self.abort()
            raise
        self.counts = dict.fromkeys(self._connections, 0)
        self._appender = MessageAppender(self._writer)
        self._templates: Dict[Tuple[str, ...], PatchTemplate] = {}

    def write(self, topic: str, record_ns: int, message) -> None:
        """Write ``message`` (a rosbags message) on ``topic`` (a name of :attr:`counts`)."""
        connection, kind = self._connections[topic]
        self._appender.write(connection, int(record_ns), TYPESTORE.serialize_cdr(message, kind))
        self.counts[topic] += 1

    def _write_filled(self, topic: str, frames: Tuple[str, ...], record_ns: int,
                      stamp_ns: int, *values) -> None:
        """Write the topic's message for ``frames`` with the stamp and ``values`` in it."""
        key = (topic,) + frames
        template = self._templates.get(key)
        if template is None:
            template = self._templates[key] = self._template(topic, frames)
        sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
        try:
            raw = template.fill(sec, nanosec, *values)
        except struct.error:
            raise _stamp_error(stamp_ns) from None
        self._appender.write(self._connections[topic][0], int(record_ns), raw)
        self.counts[topic] += 1

    def _template(self, topic: str, frames: Tuple[str, ...]) -> PatchTemplate:
        """Return the patch template of a topic's message in ``frames``."""
        if topic == 'measurement':
            return PatchTemplate(measurement_message(0, frames[0], 0.0, 0.0), POSE,
                                 MEASUREMENT_FIELDS)
        if topic == 'ground_truth':
            return PatchTemplate(odometry_message(0, frames[0], frames[1], [0.0, 0.0],
                                                  np.zeros((2, 2))), ODOMETRY, ODOMETRY_FIELDS)
        if topic == 'clock':
            return PatchTemplate(_T[CLOCK](clock=_T['builtin_interfaces/msg/Time'](
                sec=0, nanosec=0)), CLOCK, CLOCK_FIELDS)
        if topic == 'velocity':
            return PatchTemplate(velocity_message(0, frames[0], 0.0, 0.0), TWIST_COVARIANCE,
                                 VELOCITY_FIELDS)
        if topic == 'ground_truth_accel':
            return PatchTemplate(control_message(ACCEL, 0, frames[0], 0.0), ACCEL,
                                 CONTROL_FIELDS[ACCEL])
        return PatchTemplate(control_message(self.control_type, 0, frames[0], 0.0),
                             self.control_type, CONTROL_FIELDS[self.control_type])

    def write_measurement(self, record_ns: int, stamp_ns: int, frame_id: str,
                          position_m: float, variance_m2: float) -> None:
        """Write a position measurement."""
        self._write_filled('measurement', (frame_id,), record_ns, stamp_ns,
                           float(position_m), float(variance_m2))

    def write_truth(self, record_ns: int, stamp_ns: int, frame_id: str, child_frame_id: str,
                    position_m: float, velocity_mps: float) -> None:
        """Write a ground truth odometry (variances 0)."""
        self._write_filled('ground_truth', (frame_id, child_frame_id), record_ns, stamp_ns,
                           float(position_m), 0.0, float(velocity_mps), 0.0)

    def write_clock(self, record_ns: int, stamp_ns: int) -> None:
        """Write a /clock message holding ``stamp_ns``."""
        self._write_filled('clock', (), record_ns, stamp_ns)

    def write_control(self, record_ns: int, stamp_ns: int, frame_id: str, value: float) -> None:
        """Write a control (the scenario's type)."""
        self._write_filled('control', (frame_id,), record_ns, stamp_ns, float(value))

    def write_truth_accel(self, record_ns: int, stamp_ns: int, frame_id: str,
                          acceleration_mps2: float) -> None:
        """Write the true acceleration (AccelStamped, accel.linear.x)."""
        self._write_filled('ground_truth_accel', (frame_id,), record_ns, stamp_ns,
                           float(acceleration_mps2))

    def write_velocity(self, record_ns: int, stamp_ns: int, frame_id: str, speed_mps: float,
                       variance_m2_s2: float) -> None:
        """Write a measured speed with its variance (TwistWithCovarianceStamped)."""
        self._write_filled('velocity', (frame_id,), record_ns, stamp_ns, float(speed_mps),
                           float(variance_m2_s2))
