"""
The process noise the estimator node's recent measurements suggest, kept for ``/diagnostics``.

Pure (no rclpy). :class:`NoiseAdvisor` is what the node's session
(:mod:`kf_train.ros.session`) feeds with every measurement it fuses, and asks at every
diagnostics period. It keeps the latest ``noise_suggestion_window`` fused measurements
in a :class:`kf_train.batch.RunningNoiseEstimate` (maximum likelihood of q on that
window, with the node's own linear filter and the estimator's R for the newest
message's variances, :meth:`~kf_train.estimator.StreamEstimator.measurement_noise`:
the override is applied by the estimator only), and
recomputes the suggestion only when a window's worth of new measurements came in: a
suggestion costs two runs of a filter batched over a few hundred q values
(:mod:`kf_train.batch.noise_grid`; 7-20 ms for 300 rows, where 25-40 runs of one q
each took 40-60 ms; ~3 ms once its covariance passes are reused, for windows of the
same time steps), so at 10 Hz with the default window it is recomputed every 30 s
(on the window then in, which the previous suggestion did not see), and each fused
measurement costs only an append.

The suggestion exists only where q does: presets whose states are [position,
velocity] under constant velocity (train, car, car-exact, cv-position,
cv-position-velocity, a preset file of that form). Presets without a white-noise
acceleration density (the robot: a position state alone; range-bearing; a preset whose
model is not constant velocity) get no advisor (:attr:`NoiseAdvisor.unavailable`
says why) and their diagnostics no suggestion keys. The likelihood is the linear
Kalman filter's whatever the node's ``filter``: for ekf and ukf on a linear preset it is
the same filter; for the particle filters it is the q of the same model.

Which measurements enter: those fused (the initialising one too; not a rejected one),
in stamp order: one fused out of sequence (older than the newest in the
window) is left out. A reset of the filter empties the window. A control preset's row
takes the newest control received (the node's for the interval, once it has arrived).
"""

import collections
from typing import Callable, Optional, Sequence, Tuple

from kf_train.batch import NoiseSuggestion, RunningNoiseEstimate

DEFAULT_WINDOW = 300
"""Fused measurements the suggestion is estimated from (30 s at 10 Hz)."""
MIN_WINDOW = 10
"""Smaller windows count as this: a q needs a few innovations to be told from R."""
MIN_SAMPLES = 30
"""Innovations needed before a suggestion is shown (or the window, if smaller)."""
REFRESH_FRACTION = 1
"""The suggestion is recomputed after window / REFRESH_FRACTION new measurements (1: a
whole new window; 3 made ``kf-train replay BAG -o X.mcap`` several times slower)."""
CONFIDENCE = 0.95
"""Confidence of the suggestion's interval."""


class NoiseAdvisor:
    """The suggested process_noise_density of a running filter (see the module doc)."""

    def __init__(self, preset, window: int = DEFAULT_WINDOW,
                 first_velocity_std_mps: float = 100.0):
        """Start with an empty window of ``window`` measurements (0: no suggestion)."""
        self.window = 0 if window <= 0 else max(int(window), MIN_WINDOW)
        self.unavailable: Optional[str] = None
        """Why there is no suggestion at all (off, or no q in the preset), else None."""
        self._estimate: Optional[RunningNoiseEstimate] = None
        if self.window == 0:
            self.unavailable = 'noise_suggestion_window is 0'
        else:
            try:
                self._estimate = RunningNoiseEstimate(
                    preset, window=self.window, min_samples=min(MIN_SAMPLES, self.window),
                    first_velocity_std_mps=first_velocity_std_mps, confidence=CONFIDENCE)
            except ValueError as error:
                self.unavailable = str(error)
        self.refresh_every = max(1, self.window // REFRESH_FRACTION)
        self._control: Optional[Tuple[float, ...]] = None
        self._variances: Optional[Tuple[float, ...]] = None
        self._last_stamp_ns: Optional[int] = None
        self._stamps_ns = collections.deque(maxlen=max(self.window, 1))
        self._since = 0          # measurements added since the last suggestion
        self._suggestion: Optional[NoiseSuggestion] = None
        self._due = True         # compute at the next request
        self.span_s = 0.0
        """Time covered by the window of the current suggestion [s]."""

    @property
    def active(self) -> bool:
        """Return whether suggestions are made at all."""
        return self._estimate is not None

    def add_control(self, u: Sequence[float]) -> None:
        """Remember the newest control (presets with a control input)."""
        if self._estimate is not None:
            self._control = tuple(float(v) for v in u)

    def add(self, stamp_ns: int, z: Sequence[float], variances: Sequence[float]) -> None:
        """Take one fused measurement: its values and the variances its message carries."""
        estimate = self._estimate
        if estimate is None:
            return
        if self._last_stamp_ns is not None and stamp_ns <= self._last_stamp_ns:
            return               # fused out of sequence: the window stays in stamp order
        if estimate.preset.dim_u:
            if self._control is None:
                return           # no control yet: the row's input is unknown
            estimate.add(stamp_ns, z, self._control)
        else:
            estimate.add(stamp_ns, z)
        self._last_stamp_ns = stamp_ns
        self._stamps_ns.append(stamp_ns)
        self._variances = tuple(float(v) for v in variances)
        self._since += 1

    def clear(self) -> None:
        """Forget the window (a reset of the filter: the old data judged another track)."""
        if self._estimate is not None:
            self._estimate.clear()
        self._last_stamp_ns = None
        self._stamps_ns.clear()
        self.invalidate()

    def invalidate(self) -> None:
        """Recompute at the next request (the noise parameters changed: R may have)."""
        self._since = 0
        self._suggestion = None
        self._due = True

    def suggestion(self, node_variances: Callable[[Tuple[float, ...]], Sequence[float]]
                   = tuple) -> Optional[NoiseSuggestion]:
        """
        Return the window's suggested q, recomputed when due; None before it means much.

        ``node_variances`` maps the newest message's variances to the variances of the
        estimator's R (the session's reads StreamEstimator.measurement_noise).
        """
        estimate = self._estimate
        if estimate is None or len(estimate) < estimate.min_samples:
            return None
        if self._due or self._since >= self.refresh_every:
            self._since, self._due = 0, False
            try:
                self._suggestion = estimate.suggest(node_variances(self._variances))
            except (ValueError, ArithmeticError):
                # A window the likelihood cannot take (an R of 0, say): no suggestion
                # until the next refresh; the diagnostics must never fail over it.
                self._suggestion = None
                return None
            self.span_s = (self._stamps_ns[-1] - self._stamps_ns[0]) / 1e9
        return self._suggestion
