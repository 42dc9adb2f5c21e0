"""
Stale input topics and QoS mismatches: the ``<node>: inputs`` status of ``/diagnostics``.

Pure (no rclpy). The node calls :meth:`InputWatch.check` from a steady-clock timer with
each input topic's message count: a topic whose count has not moved for
``stale_warn_periods`` expected periods is WARN, for ``stale_error_periods`` ERROR,
and OK again once a message arrives. The age is timed from the check that first saw
the newest count, so it is late by at most one check period (the node checks every
half expected period at most): counting messages costs nothing per message, which a
clock read on every message at 1 kHz would not. A topic is watched from its first
message on: before any, the filter status's ``timeout_s`` speaks for the measurement
and a preset's control may simply not be wired.

QoS mismatches (rclpy's incompatible-QoS events) are recorded by topic and policy and
make the status WARN, naming both, until the node restarts.
"""

from typing import Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

MIN_CHECK_PERIOD_S = 0.005
MAX_CHECK_PERIOD_S = 1.0
LEVELS = ('OK', 'WARN', 'ERROR')
"""The levels of the inputs status, in order of severity."""
STATUS_SUFFIX = 'inputs'
"""The status is named '<node name>: inputs'."""


def watch_period_s(expected_period_s: float) -> float:
    """Return the check period for an expected input period: half of it, within bounds."""
    return min(max(expected_period_s / 2.0, MIN_CHECK_PERIOD_S), MAX_CHECK_PERIOD_S)


class InputsStatus(NamedTuple):
    """The inputs status: level, message, values, and the topics in ERROR."""

    level: str
    message: str
    values: List[Tuple[str, str]]
    stale: Tuple[str, ...]
    """Topics silent for stale_error_periods (the estimate is stale)."""


class _Topic:
    """What the watch knows about one input topic."""

    __slots__ = ('count', 'since_s', 'level')

    def __init__(self):
        self.count = 0
        self.since_s: Optional[float] = None
        self.level = 'OK'


class InputWatch:
    """Watches the input topics' silence and the QoS mismatches (see the module doc)."""

    def __init__(self, topics: Sequence[str]):
        """Watch ``topics`` (names as the status shows them)."""
        self._topics: Dict[str, _Topic] = {topic: _Topic() for topic in topics}
        self.qos_incompatible: Dict[Tuple[str, str], int] = {}
        """(topic, policy name) -> events counted."""

    @property
    def topics(self) -> Tuple[str, ...]:
        """Return the watched topics."""
        return tuple(self._topics)

    @property
    def stale(self) -> Tuple[str, ...]:
        """Return the topics in ERROR as of the last check."""
        return tuple(name for name, topic in self._topics.items() if topic.level == 'ERROR')

    def add_qos_incompatible(self, topic: str, policy: str, count: int = 1) -> bool:
        """Record a QoS mismatch on ``topic``; return True the first time for that policy."""
        key = (topic, policy)
        first = key not in self.qos_incompatible
        self.qos_incompatible[key] = self.qos_incompatible.get(key, 0) + count
        return first

    def check(self, counts: Mapping[str, int], now_s: float, period_s: float,
              warn_periods: float, error_periods: float) -> List[Tuple[str, str, str]]:
        """
        Update each topic from its message count; return its level changes.

        Each change is (topic, new level, a line to log). ``period_s`` is the
        expected period of every input topic.
        """
        changes = []
        for name, topic in self._topics.items():
            count = counts.get(name, 0)
            if count != topic.count:
                topic.count, topic.since_s = count, now_s
            if topic.since_s is None:
                continue
            age = now_s - topic.since_s
            level = ('ERROR' if age >= error_periods * period_s
                     else 'WARN' if age >= warn_periods * period_s else 'OK')
            if level != topic.level:
                topic.level = level
                changes.append((name, level, _line(name, level, age, period_s)))
        return changes

    def status(self, now_s: float, period_s: float) -> InputsStatus:
        """Return the inputs status as of the last check."""
        level, reasons, values = 'OK', [], []
        for name, topic in self._topics.items():
            age = None if topic.since_s is None else now_s - topic.since_s
            values += [(f'{name}.expected_period_s', f'{period_s:g}'),
                       (f'{name}.age_s', 'never' if age is None else f'{age:.3f}'),
                       (f'{name}.state', topic.level)]
            if topic.level != 'OK':
                reasons.append(_line(name, topic.level, age, period_s))
                level = _worse(level, topic.level)
        for (topic, policy), count in sorted(self.qos_incompatible.items()):
            values.append((f'qos_incompatible.{topic}', f'{policy} ({count})'))
            reasons.append(f'incompatible QoS on {topic}: {policy}')
            level = _worse(level, 'WARN')
        message = '; '.join(reasons) if reasons else 'ok'
        return InputsStatus(level, message, values, self.stale)


def _worse(a: str, b: str) -> str:
    """Return the more severe of two levels."""
    return a if LEVELS.index(a) >= LEVELS.index(b) else b


def _line(topic: str, level: str, age: Optional[float], period_s: float) -> str:
    """Return the text of a topic's level."""
    if level == 'OK':
        return f'{topic}: messages again'
    word = 'stale' if level == 'ERROR' else 'late'
    return (f'{topic} {word}: no message for {age:.3f} s ({age / period_s:.1f} expected '
            f'periods of {period_s:g} s)')
