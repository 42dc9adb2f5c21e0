"""
``kf-train replay BAG`` on bad bags, MCAP and sqlite3 alike: one line, exit 1, no output.

test_bag_replay.py covers bad MCAP inputs that fail when the bag is opened; here
every kind of bad bag is tried in both storages, including bags that break only
after many messages were replayed (a message that does not decode, a damaged
chunk), when output has already been produced and must be dropped.
"""

import os
from pathlib import Path

from kf_train.io.bagio_types import POSE, TYPESTORE
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from test_bag_replay import pose_message, replay, T

NS = 1_000_000_000
PERIOD_NS = 100_000_000
COUNT = 3000
"""Messages in a bad bag: more than one CSV chunk and (MCAP) more than one chunk."""
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'


def write_raw(path, storage, topic, kind, payloads):
    """Write serialized payloads at 10 Hz on one topic; return the bag directory."""
    with Writer(path, version=9, storage_plugin=STORAGES[storage]) as writer:
        connection = writer.add_connection(topic, kind, typestore=TYPESTORE)
        for k, raw in enumerate(payloads, 1):
            writer.write(connection, k * PERIOD_NS + 1, raw)
    return Path(path)


def pose_payloads(count, damaged_at=None):
    """Return serialized measurements; the one at ``damaged_at`` (1-based) cut short."""
    payloads = []
    for k in range(1, count + 1):
        raw = bytes(TYPESTORE.serialize_cdr(pose_message(k * PERIOD_NS, 10.0 * k * 0.1),
                                            POSE))
        payloads.append(raw[:40] if k == damaged_at else raw)
    return payloads


def the_file(bag, storage):
    """Return the storage file inside a bag directory."""
    (path,) = bag.glob('*.mcap' if storage == 'mcap' else '*.db3')
    return path


def bad_bag(tmp_path, storage, case):
    """Return the path of a bad bag of kind ``case`` in ``storage``."""
    if case in ('missing-topic', 'wrong-type'):
        # A PoseStamped: neither named measurement nor of the type, or named but mistyped.
        header = T['std_msgs/msg/Header'](
            stamp=T['builtin_interfaces/msg/Time'](sec=1, nanosec=0), frame_id='odom')
        message = T[POSE_STAMPED](header=header, pose=pose_message(1, 0.0).pose.pose)
        raw = bytes(TYPESTORE.serialize_cdr(message, POSE_STAMPED))
        topic = '/gps' if case == 'missing-topic' else '/measurement'
        return write_raw(tmp_path / 'bag', storage, topic, POSE_STAMPED, [raw] * 5)
    if case == 'not-a-bag':
        path = tmp_path / ('notes.mcap' if storage == 'mcap' else 'notes.db3')
        path.write_text('t,z_position\n0.1,1.0\n')
        return path
    if case == 'truncated':
        bag = write_raw(tmp_path / 'bag', storage, '/measurement', POSE, pose_payloads(COUNT))
        path = the_file(bag, storage)
        data = path.read_bytes()
        path.write_bytes(data[:int(len(data) * 0.9)])
        return bag
    if case == 'cut-after-magic':
        # MCAP: the 8 magic bytes and nothing else; sqlite3: the 16-byte header string.
        bag = write_raw(tmp_path / 'bag', storage, '/measurement', POSE, pose_payloads(COUNT))
        path = the_file(bag, storage)
        path.write_bytes(path.read_bytes()[:8 if storage == 'mcap' else 16])
        return bag
    if case == 'undecodable-message-late':
        return write_raw(tmp_path / 'bag', storage, '/measurement', POSE,
                         pose_payloads(COUNT, damaged_at=COUNT - 10))
    raise AssertionError(case)


BAD = {'missing-topic': ['no measurement topic', '/gps', POSE],
       'wrong-type': ['/measurement', POSE_STAMPED, 'expected ' + POSE],
       'not-a-bag': ['not a readable bag'],
       'truncated': ['truncated'],
       'cut-after-magic': ['truncated'],
       'undecodable-message-late': [f'message {COUNT - 10} on /measurement does not decode']}


@pytest.mark.parametrize('output', ['out.csv', 'out.mcap', 'outdir'])
@pytest.mark.parametrize('case', sorted(BAD))
@pytest.mark.parametrize('storage', sorted(STORAGES))
def test_bad_bag_one_line_and_no_output(tmp_path, capsys, storage, case, output):
    """Every bad bag in either storage: exit 1, one line naming it, nothing written."""
    bag = bad_bag(tmp_path, storage, case)
    out_dir = tmp_path / 'out'
    out_dir.mkdir()
    assert replay(bag, '--output', out_dir / output) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith(f'kf-train replay: error: {bag}'), err
    for word in BAD[case]:
        assert word in err, (word, err)
    assert os.listdir(out_dir) == []


def test_a_damaged_chunk_after_good_ones_leaves_no_output(tmp_path, capsys):
    """MCAP: records of the last chunk overwritten, index intact: one line, no output."""
    bag = write_raw(tmp_path / 'bag', 'mcap', '/measurement', POSE, pose_payloads(20_000))
    path = the_file(bag, 'mcap')
    data = bytearray(path.read_bytes())
    # The last chunk's records start ~1 MiB before the summary; garble a stretch there.
    middle = len(data) - 400_000
    data[middle:middle + 4096] = b'\xff' * 4096
    path.write_bytes(bytes(data))
    out_dir = tmp_path / 'out'
    out_dir.mkdir()
    for output in ('out.csv', 'out.mcap'):
        assert replay(bag, '--output', out_dir / output) == 1
        err = capsys.readouterr().err
        assert err.count('\n') == 1 and err.startswith('kf-train replay: error: '), err
        assert os.listdir(out_dir) == []
