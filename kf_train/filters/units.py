"""Time units shared by every floor: stamps are integer nanoseconds, as ROS stamps are."""

import numpy as np

NS_PER_S = 1_000_000_000


def seconds_to_ns(seconds: float) -> int:
    """Return a duration in whole nanoseconds, rounded to nearest."""
    return int(round(seconds * NS_PER_S))


def seconds_to_ns_array(seconds: np.ndarray) -> np.ndarray:
    """Return times [s] as whole nanoseconds (int64), rounded to nearest as seconds_to_ns."""
    return np.rint(seconds * NS_PER_S).astype(np.int64)
