"""The fast bag writing paths give rosbags' own bytes: MCAP appender, /diagnostics encoder."""

import random

from kf_train.io.bagio_diagnostics import DiagnosticsEncoder, rosbags_diagnostics
from kf_train.io.bagio_mcap import CHUNK_BYTES, MessageAppender
from kf_train.io.bagio_types import DIAGNOSTICS, ODOMETRY, POSE, TYPESTORE, VECTOR3
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

TOPICS = (('/estimate', ODOMETRY), ('/innovation', VECTOR3), ('/diagnostics', DIAGNOSTICS),
          ('/measurement', POSE))


def records(count):
    """Return (topic index, record time, payload) with sizes and times that vary."""
    rng = random.Random(7)
    out = []
    for k in range(count):
        # Times mostly increase but also step back, as interleaved topics may.
        stamp = 1_000 + 10 * k + rng.choice((0, 0, 0, -25, 3))
        payload = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 400)))
        out.append((rng.randrange(len(TOPICS)), stamp, payload))
    return out


def write(path, messages, fast, compression=None):
    """Write the messages into a bag at ``path`` with the appender or rosbags alone."""
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression is not None:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    writer.open()
    connections = [writer.add_connection(topic, kind, typestore=TYPESTORE)
                   for topic, kind in TOPICS]
    appender = MessageAppender(writer) if fast else None
    for index, stamp, data in messages:
        if fast:
            appender.write(connections[index], stamp, data)
        else:
            writer.write(connections[index], stamp, data)
    if fast:
        appender.flush()
    writer.close()
    return appender


def test_appender_writes_the_bytes_rosbags_writes(tmp_path):
    """Several chunks, four topics, times out of order: the files are identical."""
    messages = records(12_000)
    assert sum(len(data) + 31 for _, _, data in messages) > 2 * CHUNK_BYTES
    (tmp_path / 'a').mkdir()
    (tmp_path / 'b').mkdir()
    appender = write(tmp_path / 'a' / 'bag', messages, fast=True)
    assert appender.fast
    write(tmp_path / 'b' / 'bag', messages, fast=False)
    for name in ('bag.mcap', 'metadata.yaml'):
        fast = (tmp_path / 'a' / 'bag' / name).read_bytes()
        slow = (tmp_path / 'b' / 'bag' / name).read_bytes()
        assert fast == slow, name
    with Reader(tmp_path / 'a' / 'bag') as reader:
        read = [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]
    expected = sorted(((TOPICS[i][0], t, d) for i, t, d in messages), key=lambda r: r[1])
    assert sorted(read, key=lambda r: r[1]) == expected


def test_appender_falls_back_to_rosbags_for_per_message_compression(tmp_path):
    """Compressed messages are rosbags' business: every write goes through Writer.write."""
    messages = records(50)
    appender = write(tmp_path / 'bag', messages, fast=True, compression=CompressionMode.MESSAGE)
    assert not appender.fast
    with Reader(tmp_path / 'bag') as reader:
        assert reader.message_count == 50


def test_appender_with_no_message_leaves_a_valid_empty_bag(tmp_path):
    """Nothing written: the same empty bag as rosbags'."""
    (tmp_path / 'a').mkdir()
    (tmp_path / 'b').mkdir()
    write(tmp_path / 'a' / 'bag', [], fast=True)
    write(tmp_path / 'b' / 'bag', [], fast=False)
    assert ((tmp_path / 'a' / 'bag' / 'bag.mcap').read_bytes()
            == (tmp_path / 'b' / 'bag' / 'bag.mcap').read_bytes())


def random_text(rng):
    """Return a short string with multi-byte characters, possibly empty."""
    return ''.join(rng.choice('ab9 _.:é✓\u00ff') for _ in range(rng.randrange(0, 14)))


def test_diagnostics_encoder_equals_rosbags():
    """Random statuses (lengths, alignments, UTF-8, levels, stamps): the same bytes."""
    encoder = DiagnosticsEncoder()
    assert encoder.fast
    rng = random.Random(3)
    for _ in range(1500):
        values = [(random_text(rng), random_text(rng)) for _ in range(rng.randrange(0, 40))]
        args = (rng.randrange(0, 2 ** 31 * 10 ** 9), random_text(rng), rng.randrange(4),
                random_text(rng), random_text(rng), random_text(rng), values)
        assert encoder.encode(*args) == rosbags_diagnostics(*args), args


def test_diagnostics_encoder_cache_stays_bounded():
    """Ever new values: the string cache is forgotten past its bound (flat memory)."""
    from kf_train.io import bagio_diagnostics
    encoder = DiagnosticsEncoder()
    for k in range(3 * bagio_diagnostics.MAX_CACHED_STRINGS):
        raw = encoder.encode(k, '', 0, 'n', 'm', 'h', [('received', str(k))])
        assert raw == rosbags_diagnostics(k, '', 0, 'n', 'm', 'h', [('received', str(k))])
    assert len(encoder._strings) <= bagio_diagnostics.MAX_CACHED_STRINGS + 2


def test_diagnostics_stamp_out_of_range_is_a_struct_error():
    """A stamp beyond an int32 of seconds raises struct.error, as rosbags does."""
    import struct
    with pytest.raises(struct.error):
        DiagnosticsEncoder().encode(2 ** 31 * 10 ** 9, '', 0, 'n', 'm', 'h', [])
