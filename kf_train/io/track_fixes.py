"""
WGS 84 fixes to along-track positions: the cross-track gate and the direction of travel.

:class:`TrackFixes` takes fixes one at a time, in time order (a tag such as the
stamp, latitude, longitude and either a horizontal east/north covariance or none), and
returns the along-track measurements the estimator fuses (:class:`TrackFix`: x in
metres, its variance, the tag). The same object serves the node and the offline
replay, so both fuse the same numbers.

* A fix without a position (the receiver's no-fix status) is dropped and counted.
* **Cross-track gate.** A fix farther from the track than
  ``cross_track_max_m + cross_track_sigmas * σ_cross`` (σ_cross: the fix's standard
  deviation across the track, from its covariance or the default variance) is
  rejected before the filter and counted. Along the track the filter's own χ² gate
  judges a fix; across it only the geometry can: a fix 200 m off a straight line
  moves s by nothing.
* **Direction.** The estimator's x must grow as the train runs. With ``direction``
  ``auto`` (the default) the first fixes are held back until the median of the
  latest DIRECTION_FIXES minus that of the first DIRECTION_FIXES (along the track
  as drawn) exceeds ``direction_min_m`` in size: its sign says whether the track was
  drawn along or against the travel; then the held fixes are released, in order, on
  the chosen orientation. A standing train releases nothing until it has moved;
  ``forward`` or ``reverse`` skip the wait.
* The variance along the track is the covariance's along-track quadratic form
  uᵀCu (u the track's unit direction at the foot point), or the default variance
  when the fix carries none.
"""

from dataclasses import dataclass
from typing import Any, List, NamedTuple, Optional

from kf_train.filters import NS_PER_S
from kf_train.io.track_geometry import TrackGeometry
import numpy as np

CROSS_TRACK_MAX_M = 10.0
"""Default cross-track bound before the σ term [m]: a map's line (OpenStreetMap: a few
metres) against a receiver's fix on one of two or three tracks 4.5 m apart."""
CROSS_TRACK_SIGMAS = 3.0
"""Default number of the fix's cross-track σ added to the bound."""
DIRECTION_MIN_M = 20.0
"""Default along-track run that decides the direction of travel [m]: > 10 σ of a
fix's noise, < 2 s of a train at speed."""
DIRECTION_FIXES = 5
"""How many fixes each median takes when deciding the direction (outlier-proof)."""
PENDING_MAX = 3000
"""Most fixes held while the direction is open (the oldest are dropped past it)."""
TRACK_DIRECTIONS = ('auto', 'forward', 'reverse')
COVARIANCE_TYPE_UNKNOWN = 0
"""sensor_msgs/NavSatFix position_covariance_type without a covariance."""
STATUS_NO_FIX = -1
"""sensor_msgs/NavSatStatus status without a position (below it: none either)."""


def held_run_m(s_m: np.ndarray) -> float:
    """Return how far held fixes ran along a line: latest DIRECTION_FIXES' median minus first's."""
    return ends_run_m(s_m[held_run_ends(s_m.size)])


def held_run_ends(count: int) -> np.ndarray:
    """Return which of count held fixes held_run_m reads: the first k and the latest k."""
    k = min(DIRECTION_FIXES, max(1, count // 2))
    return np.concatenate((np.arange(k), np.arange(count - k, count)))


def ends_run_m(ends_s_m: np.ndarray) -> float:
    """Return held_run_m from the s of the held fixes held_run_ends names alone."""
    half = ends_s_m.size // 2
    return float(np.median(ends_s_m[half:]) - np.median(ends_s_m[:half]))


class Fix(NamedTuple):
    """A sensor_msgs/NavSatFix as the track reads it (and when it was recorded, if read)."""

    stamp_ns: int
    frame_id: str
    has_fix: bool
    lat_deg: float
    lon_deg: float
    covariance_en_m2: Optional[np.ndarray]
    """The east/north block of position_covariance, or None (COVARIANCE_TYPE_UNKNOWN)."""
    record_ns: int = 0


def fix_from_msg(msg, record_ns: int = 0) -> Fix:
    """Return the fields of a NavSatFix, read by attribute: rclpy's or rosbags' message."""
    stamp = msg.header.stamp
    covariance = None
    if int(msg.position_covariance_type) != COVARIANCE_TYPE_UNKNOWN:
        c = msg.position_covariance           # ENU, row-major 3x3
        covariance = np.array([[c[0], c[1]], [c[3], c[4]]], dtype=float)
    return Fix(int(stamp.sec) * NS_PER_S + int(stamp.nanosec), msg.header.frame_id,
               int(msg.status.status) > STATUS_NO_FIX, float(msg.latitude),
               float(msg.longitude), covariance, record_ns)


@dataclass(frozen=True)
class TrackFix:
    """One fix on the track: along-track x [m], its variance [m²], its tag, cross-track [m]."""

    tag: Any
    """What the caller gave with the fix (its time, its frame...), carried through."""
    x_m: float
    variance_m2: float
    cross_m: float


@dataclass
class TrackFixCounts:
    """What happened to the fixes given so far."""

    fixes: int = 0
    fused: int = 0
    no_fix: int = 0
    off_track: int = 0
    pending: int = 0
    dropped_pending: int = 0
    direction: str = 'auto'


class TrackFixes:
    """Fixes in, along-track measurements out (see the module)."""

    def __init__(self, geometry: TrackGeometry, variance_m2: float,
                 cross_track_max_m: float = CROSS_TRACK_MAX_M,
                 cross_track_sigmas: float = CROSS_TRACK_SIGMAS,
                 direction: str = 'auto', direction_min_m: float = DIRECTION_MIN_M) -> None:
        """Set the track, the default variance [m²] of a fix without covariance, and the gates."""
        if direction not in TRACK_DIRECTIONS:
            raise ValueError(f'direction must be one of {TRACK_DIRECTIONS}, got {direction!r}')
        if not variance_m2 > 0.0 or not cross_track_max_m >= 0.0 \
                or not cross_track_sigmas >= 0.0 or not direction_min_m > 0.0:
            raise ValueError('variance_m2 and direction_min_m must be > 0, the cross-track '
                             'bounds >= 0')
        self.geometry = geometry
        self.variance_m2 = float(variance_m2)
        self.cross_track_max_m = float(cross_track_max_m)
        self.cross_track_sigmas = float(cross_track_sigmas)
        self.direction_min_m = float(direction_min_m)
        self.counts = TrackFixCounts(direction=direction)
        self._pending: List[TrackFix] = []

    @property
    def decided(self) -> bool:
        """Whether the direction of travel is known (fixes go straight through)."""
        return self.counts.direction != 'auto'

    def cross_track_bound_m(self, cross_variance_m2: float) -> float:
        """Return the cross-track distance beyond which a fix is rejected [m]."""
        return self.cross_track_max_m + self.cross_track_sigmas * float(
            np.sqrt(max(cross_variance_m2, 0.0)))

    def add(self, tag: Any, lat_deg: float, lon_deg: float,
            covariance_en_m2: Optional[np.ndarray] = None, has_fix: bool = True
            ) -> List[TrackFix]:
        """Take one fix, tagged; return the measurements it releases (none, one, the held)."""
        counts = self.counts
        counts.fixes += 1
        if not has_fix or not (abs(lat_deg) <= 90.0 and abs(lon_deg) <= 180.0):  # NaN too
            counts.no_fix += 1
            return []
        points = self.geometry.to_local([lat_deg], [lon_deg])
        if not np.all(np.isfinite(points)):      # beyond the map's reach: surely off it
            counts.off_track += 1
            return []
        return self._locate(tag, points, covariance_en_m2)

    def _locate(self, tag: Any, points_m: np.ndarray,
                covariance_en_m2: Optional[np.ndarray]) -> List[TrackFix]:
        """Project a fix (its (1, 2) point in the frame) onto the track; gate it; orient it."""
        s_m, cross_m, tangent = self.geometry.project_local(points_m)
        fix = self._gated(tag, float(s_m[0]), float(cross_m[0]), tangent[0], covariance_en_m2)
        if fix is None:
            return []
        counts = self.counts
        if counts.direction == 'reverse':
            fix = self._reverse(fix)
        elif counts.direction == 'auto':
            return self._hold(fix)
        counts.fused += 1
        return [fix]

    def _gated(self, tag: Any, x_m: float, cross_m: float, tangent: np.ndarray,
               covariance_en_m2: Optional[np.ndarray]) -> Optional[TrackFix]:
        """Return the fix at x_m, its variance along the unit tangent; None (counted): off."""
        along, across = tangent, np.array([-tangent[1], tangent[0]])
        if covariance_en_m2 is None:
            variance_m2 = cross_variance_m2 = self.variance_m2
        else:
            # Grid north is true north to within the meridian convergence (< 0.1° within
            # 10 km of the centre): negligible in a variance.
            cov = np.asarray(covariance_en_m2, dtype=float).reshape(2, 2)
            variance_m2 = float(along @ cov @ along)
            cross_variance_m2 = float(across @ cov @ across)
        if abs(cross_m) > self.cross_track_bound_m(cross_variance_m2):
            self.counts.off_track += 1
            return None
        return TrackFix(tag, x_m, variance_m2, cross_m)

    def _reverse(self, fix: TrackFix) -> TrackFix:
        """Return a fix on the track as drawn, re-measured from its far end."""
        return TrackFix(fix.tag, self.geometry.length_m - fix.x_m, fix.variance_m2, -fix.cross_m)

    def _enqueue(self, queue: List[Any], item: Any) -> None:
        """Hold an item in queue: past PENDING_MAX the oldest is dropped; both counted."""
        queue.append(item)
        if len(queue) > PENDING_MAX:
            queue.pop(0)
            self.counts.dropped_pending += 1
        self.counts.pending = len(queue)

    def _hold(self, fix: TrackFix) -> List[TrackFix]:
        """Hold a fix until the direction is decided; then release every held one."""
        counts = self.counts
        self._enqueue(self._pending, fix)
        run_m = held_run_m(np.array([f.x_m for f in self._pending]))
        if abs(run_m) < self.direction_min_m:
            return []
        counts.direction = 'forward' if run_m > 0.0 else 'reverse'
        released = self._pending if run_m > 0.0 else [self._reverse(f) for f in self._pending]
        self._pending = []
        counts.pending = 0
        counts.fused += len(released)
        return released
