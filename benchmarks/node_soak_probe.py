"""
Soak helper node: count drops, NaN and latency over time on measurement and estimate.

``node_soak_probe.py RATE_HZ WINDOW_S``: prints ``up``, ``ready`` once both topics
have a matched publisher, and after SIGINT one JSON line {measurement, estimate, nan,
windows, diagnostics} (diagnostics: the estimator's last filter status). The
simulator stamps sample k exactly ``start + k / rate_hz``, so a message's sequence
number is its stamp's offset in periods: a gap in the numbers is a message
lost on the way (to the probe, for ``measurement``; through the estimator, for
``estimate``). Each window of WINDOW_S seconds of arrivals gives the estimates'
latency percentiles: an estimate's arrival minus the arrival of its measurement, both
at the probe (the estimator's transport and filter step; the same clock), and the
measurements' stamp lag at the window's end (arrival minus stamp: how far the
simulator runs behind its own schedule on a loaded machine).
"""

import itertools
import json
import math
import struct
import sys
import time
from typing import Dict, List, Tuple

from bench_common import percentile
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.ros import messages
from kf_train.ros.runner import run
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message

_DOUBLE = struct.Struct('<d')
MAX_PENDING = 20_000


class Sequence:
    """Gaps and duplicates in a topic's stamp sequence."""

    def __init__(self, period_ns: float):
        """Count against the simulator's period."""
        self.period_ns = period_ns
        self.first_ns = None
        self.last_index = -1
        self.count = self.gaps = self.lost = self.reordered = 0

    def add(self, stamp_ns: int) -> None:
        """Take one stamp."""
        self.count += 1
        if self.first_ns is None:
            self.first_ns = stamp_ns
        index = round((stamp_ns - self.first_ns) / self.period_ns)
        if index > self.last_index + 1 and self.last_index >= 0:
            self.gaps += 1
            self.lost += index - self.last_index - 1
        elif index <= self.last_index:
            self.reordered += 1
        self.last_index = max(self.last_index, index)

    def result(self) -> Dict[str, int]:
        """Return the counts."""
        return {'count': self.count, 'gaps': self.gaps, 'lost': self.lost,
                'reordered': self.reordered, 'span': self.last_index + 1}


def odometry_values(data: bytes) -> Tuple[int, float, float, float, float]:
    """
    Return stamp, position x, its variance, velocity x, its variance of a raw Odometry.

    Plain little-endian CDR (offsets after the 4-byte encapsulation header): stamp @0,
    frame_id (uint32 length, bytes), child_frame_id aligned to 4, then the doubles
    aligned to 8: pose position x @p, pose covariance[0] @p+56, twist linear x
    @p+344, twist covariance[0] @p+392. Deserialising in rclpy would cost the probe
    ~50 µs a message, a fifth of its budget at 1 kHz beside the nodes on a shared CPU.
    """
    if data[:2] != b'\x00\x01':
        msg = deserialize_message(data, Odometry)
        return (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
                msg.pose.pose.position.x, msg.pose.covariance[0], msg.twist.twist.linear.x,
                msg.twist.covariance[0])
    sec, nanosec, n = struct.unpack_from('<iII', data, 4)
    child_at = (12 + n + 3) & ~3
    m = struct.unpack_from('<I', data, 4 + child_at)[0]
    p = 4 + ((child_at + 4 + m + 7) & ~7)
    return (sec * 1_000_000_000 + nanosec, _DOUBLE.unpack_from(data, p)[0],
            _DOUBLE.unpack_from(data, p + 56)[0], _DOUBLE.unpack_from(data, p + 344)[0],
            _DOUBLE.unpack_from(data, p + 392)[0])


def main(argv: List[str]) -> int:
    """Record both topics until SIGINT; print the JSON result."""
    rate_hz, window_s = float(argv[0]), float(argv[1])
    period_ns = 1e9 / rate_hz
    sequences = {'measurement': Sequence(period_ns), 'estimate': Sequence(period_ns)}
    windows: List[dict] = []
    current: List[float] = []
    state = {'window_end': None, 'nan': 0}
    diagnostics: Dict[str, str] = {}

    arrived: Dict[int, int] = {}  # measurement stamp -> its arrival at the probe [ns]
    lags: List[float] = []

    def close_window(now_s: float) -> None:
        latencies = sorted(current)
        windows.append({'t_s': round(now_s, 3), 'count': len(latencies),
                        'p50_ms': percentile(latencies, 0.5) if latencies else math.nan,
                        'p99_ms': percentile(latencies, 0.99) if latencies else math.nan,
                        'max_ms': latencies[-1] if latencies else math.nan,
                        'stamp_lag_ms': lags[-1] if lags else math.nan})
        current.clear()
        lags.clear()

    def make_node() -> Node:
        node = Node('soak_probe')
        start = time.monotonic()

        def on_measurement(data: bytes) -> None:
            arrival_ns = time.time_ns()
            stamp_ns = messages.stamp_ns_from_serialized(data)
            sequences['measurement'].add(stamp_ns)
            arrived[stamp_ns] = arrival_ns
            lags.append((arrival_ns - stamp_ns) / 1e6)
            if len(arrived) > MAX_PENDING:  # measurements the estimator never answered
                for stamp in list(itertools.islice(arrived, MAX_PENDING // 2)):
                    del arrived[stamp]

        def on_estimate(data: bytes) -> None:
            arrival_ns = time.time_ns()
            stamp_ns, *values = odometry_values(data)
            sequences['estimate'].add(stamp_ns)
            if not all(math.isfinite(v) for v in values):
                state['nan'] += 1
            measured_ns = arrived.pop(stamp_ns, None)
            if measured_ns is not None:
                current.append((arrival_ns - measured_ns) / 1e6)
            now_s = time.monotonic() - start
            if state['window_end'] is None:
                state['window_end'] = now_s + window_s
            elif now_s >= state['window_end']:
                close_window(now_s)
                state['window_end'] += window_s

        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
        measurement = node.create_subscription(PoseWithCovarianceStamped, 'measurement',
                                               on_measurement, qos, raw=True)
        estimate = node.create_subscription(Odometry, 'estimate', on_estimate, qos, raw=True)

        def on_diagnostics(msg: DiagnosticArray) -> None:
            for status in msg.status:
                if status.name.endswith(': filter'):
                    diagnostics.update((v.key, v.value) for v in status.values)
        node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics,
                                 QoSProfile(depth=10))
        announced = []

        def on_timer() -> None:
            if not announced and measurement.get_publisher_count() >= 1 and \
                    estimate.get_publisher_count() >= 1:
                announced.append(True)
                print('ready', flush=True)
        node.create_timer(0.02, on_timer)
        print('up', flush=True)
        return node

    code = run(make_node, ['soak_probe'], executor='events')
    if current:
        close_window(math.nan)
    print(json.dumps({name: sequence.result() for name, sequence in sequences.items()}
                     | {'nan': state['nan'], 'windows': windows,
                        'diagnostics': diagnostics}), flush=True)
    return code


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
