"""Time units shared by every floor: stamps are integer nanoseconds, as ROS stamps are."""

NS_PER_S = 1_000_000_000


def seconds_to_ns(seconds: float) -> int:
    """Return a duration in whole nanoseconds, rounded to nearest."""
    return int(round(seconds * NS_PER_S))
