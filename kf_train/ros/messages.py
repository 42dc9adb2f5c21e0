"""
Conversion between kf_train's plain numbers and standard ROS messages.

The only module that knows message layouts. Conventions (REP 103/105):

* Positions in metres along the x axis of ``frame_id`` (default ``odom``),
  velocities in m/s, orientation identity (the body's x axis along the track), so
  the twist, expressed in ``child_frame_id``, has the velocity in ``linear.x``.
* 6x6 covariances are row-major over (x, y, z, rot x, rot y, rot z). Entry [0] is the
  variance of the estimated or measured quantity; the other diagonal entries are
  :data:`UNESTIMATED_VARIANCE` (this 1-D model does not estimate them) and the
  off-diagonal entries 0. Odometry cannot carry the position-velocity covariance;
  it is not published there.
* Innovation (geometry_msgs/Vector3Stamped, one per gated update): ``vector.x`` the
  innovation y = z - H x⁻ [m], ``vector.y`` its variance S = H P⁻ Hᵀ + R [m²],
  ``vector.z`` the NIS y² / S [-]; stamped with the measurement's stamp.
* Diagnostics (diagnostic_msgs/DiagnosticArray): one status, values as key/value text.
* Regime probabilities (std_msgs/Float64MultiArray, presets with regimes: ``rail``):
  ``data`` the probability of each regime [-], summing to 1; ``layout.dim`` one
  dimension whose ``label`` lists the regimes in the order of ``data``, comma-separated
  (``stand,accelerate,cruise,brake``), ``size`` = ``stride`` = their number,
  ``data_offset`` 0 (:func:`to_regime_msg`, :func:`from_regime_msg`). The message has
  no header: it goes out right after the estimate of the same step, whose stamp it
  belongs to.
* Controls (topic ``control``): the car's commanded acceleration as
  geometry_msgs/AccelStamped ``accel.linear.x`` [m/s²], the robot's measured speed as
  geometry_msgs/TwistStamped ``twist.linear.x`` [m/s]; every other field 0, frame the
  body frame (``child_frame_id``, x along the track). Stamped t_k, a control is the
  input applied over the interval (t_{k-1}, t_k] that ends at its stamp.
* A measured speed (topic ``velocity``, a GNSS receiver's Doppler speed, as the u-blox
  and NMEA drivers publish it; the simulator sends it, the rail preset fuses it):
  geometry_msgs/TwistWithCovarianceStamped, ``twist.twist.linear.x`` [m/s] in the body
  frame (x along the track), variance ``twist.covariance[0]`` [m²/s²], the other
  diagonal entries :data:`UNESTIMATED_VARIANCE` (:func:`to_velocity_msg`), or
  geometry_msgs/TwistStamped ``twist.linear.x`` (:func:`from_velocity_msg`).
* A state of one component (the robot's position) goes out as an Odometry whose
  twist is not estimated: ``twist.twist.linear.x`` 0 with variance
  :data:`UNESTIMATED_VARIANCE`.
* A position-and-velocity measurement (preset ``cv-position-velocity``) is a
  nav_msgs/Odometry laid out as the estimate: position ``pose.pose.position.x`` with
  variance ``pose.covariance[0]``, velocity ``twist.twist.linear.x`` with variance
  ``twist.covariance[0]`` (:func:`to_odometry_msg`, :func:`from_odometry_msg`).
"""

import math
import struct
from typing import List, NamedTuple, Sequence, Tuple

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import (
    AccelStamped, PoseWithCovarianceStamped, TwistStamped, TwistWithCovarianceStamped,
    Vector3Stamped)
from kf_train.estimator import NS_PER_S
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

UNESTIMATED_VARIANCE = 1e9
"""Variance [m² or rad²] given to dimensions the 1-D model does not estimate."""


class Measurement(NamedTuple):
    """A position measurement as the estimator consumes it."""

    stamp_ns: int
    frame_id: str
    position_m: float
    variance_m2: float


def stamp_to_ns(stamp: Time) -> int:
    """Return a ROS stamp as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int) -> Time:
    """Return integer nanoseconds as a ROS stamp."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def stamp_ns_from_serialized(data: bytes) -> int:
    """Return header.stamp [ns] of a serialized (CDR) message that starts with a Header."""
    # A 4-byte encapsulation header (its byte 1 is 1 for little endian), then
    # stamp.sec (int32) and stamp.nanosec (uint32): no need to deserialize the rest.
    sec, nanosec = struct.unpack_from('<iI' if data[1] & 1 else '>iI', data, 4)
    return sec * NS_PER_S + nanosec


def covariance_6x6(first_variance: float) -> Sequence[float]:
    """Return a row-major 6x6 covariance with ``first_variance`` at [0]."""
    covariance = [0.0] * 36
    for i in range(6):
        covariance[7 * i] = UNESTIMATED_VARIANCE
    covariance[0] = float(first_variance)
    return covariance


def to_measurement_msg(stamp_ns: int, frame_id: str, position_m: float,
                       variance_m2: float) -> PoseWithCovarianceStamped:
    """Return a position measurement with its variance in covariance[0]."""
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.pose.pose.position.x = float(position_m)
    msg.pose.pose.orientation.w = 1.0
    msg.pose.covariance = covariance_6x6(variance_m2)
    return msg


def from_measurement_msg(msg: PoseWithCovarianceStamped) -> Measurement:
    """Return the stamp, frame, position and variance of a measurement message."""
    return Measurement(stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                       float(msg.pose.pose.position.x), float(msg.pose.covariance[0]))


_CDR_LE = b'\x00\x01'  # encapsulation id of plain little-endian CDR (XCDR1)
_HEADER_LE = struct.Struct('<iII')  # stamp.sec, stamp.nanosec, frame_id length
_DOUBLE_LE = struct.Struct('<d')


def measurement_from_serialized(data: bytes) -> Measurement:
    """
    Return what :func:`from_measurement_msg` returns, read straight from the CDR bytes.

    Deserialising a PoseWithCovarianceStamped in rclpy costs ~50 µs (it builds the
    whole message and a numpy covariance); the four fields the estimator needs are
    read here in ~2 µs. Layout of plain CDR after the 4-byte encapsulation header,
    offsets from its end: stamp.sec int32 @0, stamp.nanosec uint32 @4, frame_id as
    uint32 length n (with its NUL) @8 and n bytes @12, then the doubles aligned to 8:
    pose.position.x, .y, .z, orientation x, y, z, w, covariance[36]. Anything but
    little-endian plain CDR is deserialised the ordinary way.
    """
    if data[:2] != _CDR_LE or len(data) < 16:
        return from_measurement_msg(deserialize_message(data, PoseWithCovarianceStamped))
    sec, nanosec, n = _HEADER_LE.unpack_from(data, 4)
    position_at = 4 + ((12 + n + 7) & ~7)
    if n < 1 or position_at + 64 > len(data):
        return from_measurement_msg(deserialize_message(data, PoseWithCovarianceStamped))
    frame_id = data[16:15 + n].decode('utf-8')
    return Measurement(sec * NS_PER_S + nanosec, frame_id,
                       _DOUBLE_LE.unpack_from(data, position_at)[0],
                       _DOUBLE_LE.unpack_from(data, position_at + 56)[0])


def to_odometry_msg(stamp_ns: int, frame_id: str, child_frame_id: str,
                    position_m: float, velocity_mps: float,
                    position_variance_m2: float,
                    velocity_variance_m2s2: float) -> Odometry:
    """Return an Odometry with position, velocity and their variances filled in."""
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.pose.pose.position.x = float(position_m)
    msg.pose.pose.orientation.w = 1.0
    msg.pose.covariance = covariance_6x6(position_variance_m2)
    msg.twist.twist.linear.x = float(velocity_mps)
    msg.twist.covariance = covariance_6x6(velocity_variance_m2s2)
    return msg


def to_state_odometry_msg(stamp_ns: int, frame_id: str, child_frame_id: str,
                          x, P) -> Odometry:
    """Return an Odometry from a [position, velocity] mean and its 2x2 covariance."""
    return to_odometry_msg(stamp_ns, frame_id, child_frame_id, x[0], x[1],
                           P[0][0], P[1][1])


class OdometryState(NamedTuple):
    """What :func:`to_odometry_msg` put into an Odometry, read back."""

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    position_m: float
    velocity_mps: float
    position_variance_m2: float
    velocity_variance_m2s2: float


def from_odometry_msg(msg: Odometry) -> OdometryState:
    """Return the stamp, frames, position, velocity and their variances of an Odometry."""
    return OdometryState(stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                         msg.child_frame_id, float(msg.pose.pose.position.x),
                         float(msg.twist.twist.linear.x), float(msg.pose.covariance[0]),
                         float(msg.twist.covariance[0]))


class StateMessage(NamedTuple):
    """A [position, velocity] state and its covariance, as read from an Odometry."""

    stamp_ns: int
    frame_id: str
    x: List[float]
    P: List[List[float]]


def from_state_odometry_msg(msg: Odometry) -> StateMessage:
    """
    Return the state an Odometry carries: position x, velocity twist.linear.x.

    The covariance is diag(pose.covariance[0], twist.covariance[0]): Odometry has no
    place for the position-velocity covariance, which is taken as 0.
    """
    return StateMessage(
        stamp_to_ns(msg.header.stamp), msg.header.frame_id,
        [float(msg.pose.pose.position.x), float(msg.twist.twist.linear.x)],
        [[float(msg.pose.covariance[0]), 0.0], [0.0, float(msg.twist.covariance[0])]])


def to_position_odometry_msg(stamp_ns: int, frame_id: str, child_frame_id: str,
                             position_m: float, position_variance_m2: float) -> Odometry:
    """Return an Odometry of a position-only estimate; the twist is marked unestimated."""
    return to_odometry_msg(stamp_ns, frame_id, child_frame_id, position_m, 0.0,
                           position_variance_m2, UNESTIMATED_VARIANCE)


def to_estimate_msg(stamp_ns: int, frame_id: str, child_frame_id: str, x, P) -> Odometry:
    """Return an Odometry of a [position, velocity] or [position] mean and covariance."""
    if len(x) == 1:
        return to_position_odometry_msg(stamp_ns, frame_id, child_frame_id, x[0], P[0][0])
    return to_state_odometry_msg(stamp_ns, frame_id, child_frame_id, x, P)


class EstimateWriter:
    """
    One reused Odometry for a stream of estimates: fills only what changes.

    :meth:`fill` writes the stamp, position, velocity and their variances into the
    same message every time, which is as :func:`to_estimate_msg` would build it (the
    frames, orientation.w = 1 and the unestimated variances are set once). The
    message may be published and filled again at once: rclpy serialises it during
    ``publish``. Not for a message kept after the next fill.
    """

    def __init__(self, frame_id: str, child_frame_id: str, dim_x: int):
        """Prefill a message for a [position, velocity] (dim_x 2) or [position] state."""
        self.dim_x = dim_x
        self.msg = to_odometry_msg(0, frame_id, child_frame_id, 0.0, 0.0, 0.0,
                                   UNESTIMATED_VARIANCE)
        msg = self.msg
        self._stamp = msg.header.stamp
        self._position = msg.pose.pose.position
        self._velocity = msg.twist.twist.linear
        self._pose_covariance = msg.pose.covariance
        self._twist_covariance = msg.twist.covariance

    def set_frames(self, frame_id: str, child_frame_id: str) -> None:
        """Change header.frame_id and child_frame_id."""
        self.msg.header.frame_id = frame_id
        self.msg.child_frame_id = child_frame_id

    def fill(self, stamp_ns: int, x, P) -> Odometry:
        """Return the message holding state x, covariance P at stamp_ns."""
        sec, nanosec = divmod(stamp_ns, NS_PER_S)
        stamp = self._stamp
        stamp.sec = sec
        stamp.nanosec = nanosec
        if self.dim_x == 1:
            self._position.x = float(x[0])
            self._pose_covariance[0] = float(P[0][0])
            return self.msg
        # x[0], x[1]: a state may hold more (the rail preset's acceleration, ...).
        self._position.x = float(x[0])
        self._velocity.x = float(x[1])
        self._pose_covariance[0] = P[0][0]
        self._twist_covariance[0] = P[1][1]
        return self.msg


class InnovationWriter:
    """One reused Vector3Stamped for the innovation records (see :class:`EstimateWriter`)."""

    def __init__(self, frame_id: str):
        """Prefill the frame."""
        self.msg = to_innovation_msg(0, frame_id, 0.0, 0.0, 0.0)
        self._stamp = self.msg.header.stamp
        self._vector = self.msg.vector

    def set_frame(self, frame_id: str) -> None:
        """Change header.frame_id."""
        self.msg.header.frame_id = frame_id

    def fill(self, stamp_ns: int, innovation: float, innovation_variance: float,
             nis: float) -> Vector3Stamped:
        """Return the message: x = innovation, y = its variance S, z = NIS."""
        sec, nanosec = divmod(stamp_ns, NS_PER_S)
        self._stamp.sec = sec
        self._stamp.nanosec = nanosec
        vector = self._vector
        vector.x = float(innovation)
        vector.y = float(innovation_variance)
        vector.z = float(nis)
        return self.msg


class Control(NamedTuple):
    """A control input as the estimator consumes it (one component, along x)."""

    stamp_ns: int
    frame_id: str
    value: float


def to_accel_msg(stamp_ns: int, frame_id: str, acceleration_mps2: float) -> AccelStamped:
    """Return a commanded acceleration [m/s²] in accel.linear.x; the rest 0."""
    msg = AccelStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.accel.linear.x = float(acceleration_mps2)
    return msg


def from_accel_msg(msg: AccelStamped) -> Control:
    """Return the stamp, frame and accel.linear.x [m/s²] of an AccelStamped."""
    return Control(stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                   float(msg.accel.linear.x))


def to_twist_msg(stamp_ns: int, frame_id: str, velocity_mps: float) -> TwistStamped:
    """Return a measured speed [m/s] in twist.linear.x; the rest 0."""
    msg = TwistStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.twist.linear.x = float(velocity_mps)
    return msg


def from_twist_msg(msg: TwistStamped) -> Control:
    """Return the stamp, frame and twist.linear.x [m/s] of a TwistStamped."""
    return Control(stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                   float(msg.twist.linear.x))


def to_velocity_msg(stamp_ns: int, frame_id: str, speed_mps: float,
                    variance_m2_s2: float) -> TwistWithCovarianceStamped:
    """Return a measured speed [m/s] in twist.linear.x, its variance in covariance[0]."""
    msg = TwistWithCovarianceStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.twist.twist.linear.x = float(speed_mps)
    msg.twist.covariance = covariance_6x6(variance_m2_s2)
    return msg


class Velocity(NamedTuple):
    """A measured speed along the track as the estimator fuses it (topic ``velocity``)."""

    stamp_ns: int
    frame_id: str
    velocity_mps: float
    variance_m2s2: float
    """``twist.covariance[0]``; NaN for a TwistStamped (the node's parameter gives it)."""


def from_velocity_msg(msg) -> Velocity:
    """Return the speed of a TwistWithCovarianceStamped (with its variance) or TwistStamped."""
    if type(msg) is TwistStamped:
        return Velocity(stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                        float(msg.twist.linear.x), math.nan)
    return Velocity(stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                    float(msg.twist.twist.linear.x), float(msg.twist.covariance[0]))


VELOCITY_MESSAGES = {'twist_with_covariance': TwistWithCovarianceStamped,
                     'twist': TwistStamped}
"""The estimator's ``velocity_type`` -> the message type of its ``velocity`` topic."""


CONTROL_MESSAGES = {'acceleration': (AccelStamped, to_accel_msg, from_accel_msg),
                    'velocity': (TwistStamped, to_twist_msg, from_twist_msg)}
"""Control name -> (message type, builder, reader) for the ``control`` topic."""


def to_innovation_msg(stamp_ns: int, frame_id: str, innovation: float,
                      innovation_variance: float, nis: float) -> Vector3Stamped:
    """Return an innovation record: x = innovation, y = its variance S, z = NIS."""
    msg = Vector3Stamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.vector.x = float(innovation)
    msg.vector.y = float(innovation_variance)
    msg.vector.z = float(nis)
    return msg


DIAGNOSTIC_LEVELS = {'OK': DiagnosticStatus.OK, 'WARN': DiagnosticStatus.WARN,
                     'ERROR': DiagnosticStatus.ERROR, 'STALE': DiagnosticStatus.STALE}
"""Level names used by the nodes, and their DiagnosticStatus byte values."""


def to_diagnostics_msg(stamp_ns: int, name: str, hardware_id: str, level: str,
                       message: str, values: Sequence[Tuple[str, str]]) -> DiagnosticArray:
    """Return a DiagnosticArray with one status; ``level`` is a DIAGNOSTIC_LEVELS key."""
    status = DiagnosticStatus(level=DIAGNOSTIC_LEVELS[level], name=name, message=message,
                              hardware_id=hardware_id,
                              values=[KeyValue(key=k, value=v) for k, v in values])
    msg = DiagnosticArray()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.status = [status]
    return msg


def to_clock_msg(stamp_ns: int) -> Clock:
    """Return a /clock message (rosgraph_msgs/Clock) for simulated time."""
    return Clock(clock=ns_to_stamp(stamp_ns))


REGIME_SEPARATOR = ','
"""Separates the regime names in a regime message's layout label."""


def to_regime_msg(names: Sequence[str], probabilities) -> Float64MultiArray:
    """Return the regime probabilities as a Float64MultiArray labelled with their names."""
    names = tuple(names)
    if len(names) != len(probabilities):
        raise ValueError(f'{len(names)} regime names for {len(probabilities)} probabilities')
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=REGIME_SEPARATOR.join(names), size=len(names),
                                          stride=len(names))]
    msg.layout.data_offset = 0
    msg.data = [float(p) for p in probabilities]
    return msg


def from_regime_msg(msg: Float64MultiArray) -> Tuple[Tuple[str, ...], List[float]]:
    """Return (regime names, probabilities) of a message :func:`to_regime_msg` made."""
    if len(msg.layout.dim) != 1:
        raise ValueError(f'a regime message has one dimension, got {len(msg.layout.dim)}')
    names = tuple(msg.layout.dim[0].label.split(REGIME_SEPARATOR))
    data = [float(p) for p in msg.data]
    if len(names) != len(data):
        raise ValueError(f'{len(names)} regime names for {len(data)} probabilities')
    return names, data
