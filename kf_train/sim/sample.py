"""One sample of a simulated stream, the type every scenario stream yields."""

from typing import NamedTuple, Optional


class ScenarioSample(NamedTuple):
    """One sample of a stream."""

    index: int
    t_s: float
    true_position_m: float
    true_velocity_mps: float
    measured_position_m: float
    control: Optional[float]
    """The control of the interval that ends at t_s, or None without control input."""
    true_acceleration_mps2: Optional[float] = None
    """The true acceleration at t_s (ACCELERATION_SCENARIOS), else None."""
