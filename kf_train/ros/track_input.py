"""
The estimator's NavSatFix input: fixes on a track file become along-track measurements.

With ``measurement_type`` ``navsatfix`` the ``measurement`` topic carries
sensor_msgs/NavSatFix and ``track`` names the track's geometry (a GeoJSON LineString
or a CSV with a ``lat,lon`` header: :mod:`kf_train.io.track_geometry`) or a network
(LineStrings joined at switches: :mod:`kf_train.io.track_network`). Each fix goes
through :class:`kf_train.io.track_fixes.TrackFixes` (cross-track gate, direction of
travel), on a network through :class:`kf_train.io.track_network_live.NetworkFixes`
(the same, on the path chosen live), and what it releases is fused as a position
measurement: the node (:mod:`kf_train.ros.estimator_node`) and ``kf-train replay BAG``
both do it through :class:`TrackInput`, so they fuse the same numbers.

* ``status.status`` < 0 (STATUS_NO_FIX): ignored, counted (``fixes.no_fix``).
* ``position_covariance_type`` COVARIANCE_TYPE_UNKNOWN (0): the fix's variance is
  ``fix_variance_m2``, along and across the track; APPROXIMATED (1), DIAGONAL_KNOWN
  (2), KNOWN (3): the east/north block of ``position_covariance`` (ENU, row-major),
  its form along the track. ``measurement_variance`` > 0 overrides the along-track
  variance, as for a pose.
* The message is read by attribute (:func:`kf_train.io.track_fixes.fix_from_msg`), so
  a rosbags message from a bag reads the same as an rclpy one.

The counts go to ``/diagnostics`` (``fixes.*``, ``track_direction``; on a network
``track_element``, the element the train is on) and to the
replay's statistics.
"""

from typing import List, NamedTuple, Optional, Tuple

from kf_train.io import (
    CROSS_TRACK_MAX_M, CROSS_TRACK_SIGMAS, Fix, is_network_file, load_track, NetworkFixes,
    TRACK_DIRECTIONS, TrackError, TrackFixes, TrackNetwork)
from kf_train.ros.param_spec import BIG, ParameterError, ParamSpec

MEASUREMENT_TYPES = ('pose', 'navsatfix')
"""The ``measurement`` topic's type (parameter measurement_type)."""
FIX_VARIANCE_M2 = 3.0
"""Default variance of a fix without covariance [m²]: issue 24's R for real logs."""

_FIXED = ' Fixed at start-up (restart to change).'
_GROUP = 'fixed at start-up (restart to change)'

PARAMETERS_TRACK = (
    ParamSpec(
        'measurement_type', 'string', MEASUREMENT_TYPES[0],
        'The measurement topic: pose (default: geometry_msgs/PoseWithCovarianceStamped, '
        'x along the track) or navsatfix (sensor_msgs/NavSatFix, projected onto the track '
        'file named by track; 1-D position presets only).' + _FIXED,
        choices=MEASUREMENT_TYPES, live=False, group=_GROUP),
    ParamSpec(
        'track', 'string', '',
        "measurement_type navsatfix: the track's geometry, a GeoJSON LineString (bare, a "
        'Feature or a FeatureCollection holding one) or a CSV with a lat,lon header, in '
        'WGS 84; x is the distance along it. Or a network, a GeoJSON FeatureCollection of '
        'LineStrings joined at switches: the path is chosen live from the fixes (map '
        'matching) and x is the distance along the path taken, 0 at the first fix '
        '(track_direction auto).' + _FIXED,
        constraints="a file path, or '' with measurement_type pose", live=False,
        group=_GROUP),
    ParamSpec(
        'track_direction', 'string', TRACK_DIRECTIONS[0],
        'Which way x grows along the track: auto (default: the first fixes are held until '
        'the train has run 20 m along it, which decides; a track drawn against the travel '
        'works), forward (from its first vertex) or reverse (from its last).' + _FIXED,
        choices=TRACK_DIRECTIONS, live=False, group=_GROUP),
    ParamSpec(
        'cross_track_max_m', 'double', CROSS_TRACK_MAX_M,
        'Cross-track gate: a fix farther from the track than this plus cross_track_sigmas '
        'times its cross-track standard deviation is rejected before the filter and counted '
        '(fixes.off_track in /diagnostics).' + _FIXED, range=(0.0, BIG), unit='m',
        live=False, group=_GROUP),
    ParamSpec(
        'cross_track_sigmas', 'double', CROSS_TRACK_SIGMAS,
        "Cross-track gate: how many of the fix's cross-track standard deviations widen the "
        'bound.' + _FIXED, range=(0.0, 1e3), live=False, group=_GROUP),
    ParamSpec(
        'fix_variance_m2', 'double', FIX_VARIANCE_M2,
        'Horizontal variance [m²] of a NavSatFix whose position_covariance_type is '
        'COVARIANCE_TYPE_UNKNOWN (the others carry theirs).' + _FIXED, range=(1e-9, BIG),
        unit='m²', live=False, group=_GROUP),
)
"""The NavSatFix input's parameters (part of the estimator's table)."""


class TrackMeasurement(NamedTuple):
    """A fix on the track, in the fields a position measurement has (session.Measurement)."""

    stamp_ns: int
    frame_id: str
    position_m: float
    variance_m2: float


def check_track_values(values) -> None:
    """Raise ParameterError unless the NavSatFix parameters agree with each other."""
    if values['measurement_type'] == 'navsatfix' and not values['track']:
        raise ParameterError('measurement_type navsatfix needs a track file (track)')


class TrackInput:
    """NavSatFix messages to position measurements on the track (see the module)."""

    def __init__(self, values, measures_velocity: bool) -> None:
        """Load the track named by the parameter values; ParameterError if it cannot be."""
        if measures_velocity:
            raise ParameterError('measurement_type navsatfix needs a preset measuring a '
                                 'position alone')
        try:
            self.fixes = self._fixes(values)
        except (OSError, TrackError) as error:
            raise ParameterError(f"track {values['track']!r}: {error}") from None
        except ImportError:
            raise ParameterError('measurement_type navsatfix needs pyproj (pip install '
                                 "'kf_train[track]')") from None
        self.last_measurement: Optional[TrackMeasurement] = None
        """The newest measurement released (its variance: the gate's reach), or None."""

    @staticmethod
    def _fixes(values) -> TrackFixes:
        """Return the fixes' projection: onto the track file, or live onto a network."""
        gates = (values['fix_variance_m2'], values['cross_track_max_m'],
                 values['cross_track_sigmas'])
        if not is_network_file(values['track']):
            return TrackFixes(load_track(values['track']), *gates, values['track_direction'])
        if values['track_direction'] != TRACK_DIRECTIONS[0]:
            raise TrackError('a network: track_direction must be auto (the path decides)')
        return NetworkFixes(TrackNetwork.from_file(values['track']), *gates)

    def measurements(self, fix: Fix) -> List[TrackMeasurement]:
        """Return the position measurements a fix releases (none, one, or the held ones)."""
        released = self.fixes.add((fix.stamp_ns, fix.frame_id), fix.lat_deg, fix.lon_deg,
                                  fix.covariance_en_m2, fix.has_fix)
        measurements = [TrackMeasurement(f.tag[0], f.tag[1], f.x_m, f.variance_m2)
                        for f in released]
        if measurements:
            self.last_measurement = measurements[-1]
        return measurements

    def values(self) -> List[Tuple[str, str]]:
        """Return the /diagnostics values: the fixes' counts and the direction."""
        counts = self.fixes.counts
        return [('fixes.received', str(counts.fixes)), ('fixes.no_fix', str(counts.no_fix)),
                ('fixes.off_track', str(counts.off_track)),
                ('fixes.pending', str(counts.pending)),
                ('track_direction', counts.direction)] + (
                    [('track_element', '-' if self.fixes.element is None
                      else self.fixes.element[0])]
                    if isinstance(self.fixes, NetworkFixes) else [])
