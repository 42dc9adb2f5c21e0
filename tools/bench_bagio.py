#!/usr/bin/env python3
"""
Time kf_train.io.bagio on a bag of N measurements (default 100 000: 10⁴ s at 10 Hz).

    .venv/bin/python tools/bench_bagio.py [--count N]

Prints, for an MCAP bag of seed-000-like PoseWithCovarianceStamped messages:
reading with BagInput (rosbags storage, fields at learnt offsets), the same messages
read and fully deserialised by rosbags (the reference), the memory held while reading
(tracemalloc peak over the iteration), and writing estimate + prediction + innovation
per measurement with OutputBag. Figures only; nothing is asserted.
"""

import argparse
import os
from pathlib import Path
import sys
import tempfile
import time
import tracemalloc

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from kf_train.io.bagio import BagInput  # noqa: E402
from kf_train.io.bagio_output import OutputBag  # noqa: E402
from kf_train.io.bagio_types import POSE, TYPESTORE  # noqa: E402
import numpy as np  # noqa: E402
from rosbags.rosbag2 import Reader, StoragePlugin, Writer  # noqa: E402

NS = 1_000_000_000
PERIOD_NS = 100_000_000


def write_input(path: Path, count: int) -> float:
    """Write ``count`` measurements at 10 Hz; return the seconds it took."""
    types = TYPESTORE.types
    rng = np.random.default_rng(0)
    covariance = np.zeros(36)
    covariance[0] = 1.0
    started = time.perf_counter()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/measurement', POSE, typestore=TYPESTORE)
        for k, noise in enumerate(rng.standard_normal(count), start=1):
            stamp = k * PERIOD_NS
            message = types[POSE](
                header=types['std_msgs/msg/Header'](
                    stamp=types['builtin_interfaces/msg/Time'](sec=stamp // NS,
                                                               nanosec=stamp % NS),
                    frame_id='odom'),
                pose=types['geometry_msgs/msg/PoseWithCovariance'](
                    pose=types['geometry_msgs/msg/Pose'](
                        position=types['geometry_msgs/msg/Point'](
                            x=10.0 * k / 10 + noise, y=0.0, z=0.0),
                        orientation=types['geometry_msgs/msg/Quaternion'](
                            x=0.0, y=0.0, z=0.0, w=1.0)),
                    covariance=covariance))
            writer.write(connection, stamp + 1_000_000, TYPESTORE.serialize_cdr(message, POSE))
    return time.perf_counter() - started


def time_read(path: Path) -> tuple:
    """Return (wall seconds, CPU seconds, messages) of reading with BagInput."""
    started, cpu = time.perf_counter(), time.process_time()
    count = 0
    with BagInput(path) as bag:
        for _ in bag.messages():
            count += 1
    return time.perf_counter() - started, time.process_time() - cpu, count


def time_rosbags_read(path: Path) -> tuple:
    """Return (wall seconds, CPU seconds, messages) of reading with rosbags alone."""
    started, cpu = time.perf_counter(), time.process_time()
    count = 0
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            count += 1
    return time.perf_counter() - started, time.process_time() - cpu, count


def peak_read_memory(path: Path) -> int:
    """Return the tracemalloc peak [bytes] while iterating the bag (slower run)."""
    with BagInput(path) as bag:
        tracemalloc.start()
        for _ in bag.messages():
            pass
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def time_write(path: Path, count: int) -> tuple:
    """Return (wall, CPU) seconds to write 3 outputs per measurement with OutputBag."""
    x = np.array([1.0, 10.0])
    P = np.array([[0.1, 0.01], [0.01, 0.02]])
    started, cpu = time.perf_counter(), time.process_time()
    with OutputBag(path) as out:
        for k in range(1, count + 1):
            stamp = k * PERIOD_NS
            out.write_estimate(stamp, stamp, x, P)
            out.write_prediction(stamp, stamp + 2 * NS, x, P)
            out.write_innovation(stamp, stamp, 0.5, 1.1, 0.25 / 1.1)
    return time.perf_counter() - started, time.process_time() - cpu


def main() -> int:
    """Run the measurements and print them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--count', type=int, default=100_000)
    count = parser.parse_args().count
    with tempfile.TemporaryDirectory() as directory:
        bag = Path(directory) / 'input'
        seconds = write_input(bag, count)
        size = sum(f.stat().st_size for f in bag.iterdir())
        data_s = count * PERIOD_NS / NS
        print(f'input bag: {count} PoseWithCovarianceStamped, {data_s:g} s of data at 10 Hz, '
              f'{size / 2 ** 20:.1f} MiB; written by rosbags in {seconds:.2f} s')
        wall, cpu, read = time_read(bag)
        print(f'BagInput read: {wall:.2f} s wall ({cpu:.2f} s CPU), '
              f'{wall / read * 1e6:.1f} µs/message, {read / wall:,.0f} messages/s, '
              f'{data_s / wall:,.0f}× real time')
        wall, cpu, read = time_rosbags_read(bag)
        print(f'rosbags read + full deserialize (reference): {wall:.2f} s wall '
              f'({cpu:.2f} s CPU), {wall / read * 1e6:.1f} µs/message')
        print(f'memory while reading (tracemalloc peak): '
              f'{peak_read_memory(bag) / 2 ** 20:.2f} MiB')
        wall, cpu = time_write(Path(directory) / 'output.mcap', count)
        print(f'OutputBag write of {3 * count} messages (estimate, prediction, innovation): '
              f'{wall:.2f} s wall ({cpu:.2f} s CPU), {wall / count * 1e6:.1f} µs per '
              f'measurement')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
