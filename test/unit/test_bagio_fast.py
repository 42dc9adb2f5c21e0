"""
The fast bag writing paths give rosbags' own bytes.

The MCAP appender, the /diagnostics encoder, the regime_probabilities template.
"""

import random

from kf_train.io.bagio_diagnostics import DiagnosticsEncoder, rosbags_diagnostics
from kf_train.io.bagio_mcap import CHUNK_BYTES, MessageAppender
from kf_train.io.bagio_output import MULTIARRAY, OutputBag, regime_message
from kf_train.io.bagio_types import DIAGNOSTICS, ODOMETRY, POSE, TYPESTORE, VECTOR3
import numpy as np
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


@pytest.mark.parametrize('compression', [None, CompressionMode.STORAGE])
def test_appender_writes_the_bytes_rosbags_writes(tmp_path, compression):
    """Several chunks, four topics, times out of order: the files are identical."""
    messages = records(12_000)
    assert sum(len(data) + 31 for _, _, data in messages) > 2 * CHUNK_BYTES
    (tmp_path / 'a').mkdir()
    (tmp_path / 'b').mkdir()
    appender = write(tmp_path / 'a' / 'bag', messages, fast=True, compression=compression)
    assert appender.fast
    write(tmp_path / 'b' / 'bag', messages, fast=False, compression=compression)
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


@pytest.mark.parametrize('names', [('stand', 'accelerate', 'cruise', 'brake'), ('one',),
                                   tuple(f'r{i}' for i in range(20))])
def test_regime_messages_equal_rosbags(tmp_path, names):
    """regime_probabilities: the template's bytes are rosbags' (20 regimes: rosbags')."""
    rng = np.random.default_rng(5)
    written = []
    with OutputBag(tmp_path / 'o.mcap', regime_names=names) as out:
        assert out._regimes.fast == (len(names) <= 14)
        for k in range(30):
            p = rng.dirichlet(np.ones(len(names)))
            if k % 10 == 9:
                p = np.append(p, 0.5)            # a count that is not the names': as given
            written.append(p)
            out.write_regimes(1000 + k, p if k % 2 else p.tolist())
    with Reader(tmp_path / 'o.mcap') as reader:
        raws = [bytes(raw) for c, _, raw in reader.messages()
                if c.topic == '/regime_probabilities']
    assert raws == [bytes(TYPESTORE.serialize_cdr(regime_message(names, p), MULTIARRAY))
                    for p in written]
