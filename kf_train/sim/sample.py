"""One sample of a simulated stream, the type every scenario stream yields."""

from typing import NamedTuple, Optional


class ScenarioSample(NamedTuple):
    """One sample of a stream."""

    index: int
    t_s: float
    true_position_m: float
    true_velocity_mps: float
    measured_position_m: Optional[float]
    """The measured position [m]; None at a GNSS receiver's epoch without a fix."""
    control: Optional[float]
    """The control of the interval that ends at t_s, or None without control input."""
    true_acceleration_mps2: Optional[float] = None
    """The true acceleration at t_s (ACCELERATION_SCENARIOS), else None."""
    measurement_variance_m2: Optional[float] = None
    """The reported variance of the measurement (a receiver's hAcc²) [m²], else None."""
    doppler_speed_mps: Optional[float] = None
    """A receiver's Doppler speed along the track [m/s], else None."""
    doppler_variance_m2_s2: Optional[float] = None
    """Its reported variance (speedAcc²) [m²/s²], else None."""
