"""
A diagnostic_msgs/msg/DiagnosticArray of one status serialised directly, checked against rosbags.

rosbags builds the message (a KeyValue object per value) and serialises it in
~60 µs (~10 µs here); a replay writes one every ``diagnostics_period_s`` of record time (10⁴ for
a 10⁴ s bag). The message is strings only, so its CDR (little endian, plain
encapsulation ``00 01 00 00``) is written here directly, field by field as rosbags
writes it:

* ``header``: stamp.sec int32, stamp.nanosec uint32, frame_id string;
* ``status``: uint32 count (1), then level (byte), name, message, hardware_id
  (strings), ``values``: uint32 count, then key and value (strings) of each;

where a string is its UTF-8 length + 1 as a uint32 aligned to 4 bytes (counted from
after the encapsulation), its bytes and a NUL. The encodings of the key/value pairs
(most repeat: a fixed set of keys, counts that do not move, '0.000') are kept per
alignment, at most :data:`MAX_CACHED_STRINGS`. :class:`DiagnosticsEncoder`
checks itself against rosbags' serialization of a sample when it is made, and falls
back to rosbags for every message if they differ; a test compares them on many
random statuses.
"""

import struct
from typing import Dict, Sequence, Tuple

from kf_train.filters import NS_PER_S
from kf_train.io.bagio_types import DIAGNOSTICS, TYPESTORE

_ENCAPSULATION = b'\x00\x01\x00\x00'          # CDR, little endian
_STAMP = struct.Struct('<iI')
_U32 = struct.Struct('<I').pack
_PADDING = (b'', b'\x00\x00\x00', b'\x00\x00', b'\x00')   # indexed by position % 4
MAX_CACHED_STRINGS = 4096
"""At most this many key/value encodings are kept (then forgotten): memory stays bounded."""
_T = TYPESTORE.types


def _string(text: str, position: int) -> bytes:
    """Return the CDR of ``text`` written at ``position``: padding, length, bytes, NUL."""
    data = text.encode('utf-8')
    return _PADDING[position & 3] + _U32(len(data) + 1) + data + b'\x00'


def rosbags_diagnostics(stamp_ns: int, frame_id: str, level: int, name: str, message: str,
                        hardware_id: str, values: Sequence[Tuple[str, str]]) -> bytes:
    """Return rosbags' serialization of the DiagnosticArray (the reference)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    status = _T['diagnostic_msgs/msg/DiagnosticStatus'](
        level=level, name=name, message=message, hardware_id=hardware_id,
        values=[_T['diagnostic_msgs/msg/KeyValue'](key=k, value=v) for k, v in values])
    header = _T['std_msgs/msg/Header'](
        stamp=_T['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=frame_id)
    return bytes(TYPESTORE.serialize_cdr(_T[DIAGNOSTICS](header=header, status=[status]),
                                         DIAGNOSTICS, little_endian=True))


class DiagnosticsEncoder:
    """Serialises DiagnosticArrays of one status (see the module doc)."""

    def __init__(self):
        """Check the direct encoding against rosbags on a sample; use it if equal."""
        self._strings: Dict[Tuple[str, int], bytes] = {}
        sample = (1_700_000_123_456_789_012 % (2 ** 31 * NS_PER_S), 'odom', 1,
                  'estimator: filter', 'ü; odd length', 'kf_train',
                  [('a', ''), ('key.two', '12.5'), ('é', 'three3'), ('', 'x' * 7)])
        self.fast = True
        self.fast = self.encode(*sample) == rosbags_diagnostics(*sample)

    def encode(self, stamp_ns: int, frame_id: str, level: int, name: str, message: str,
               hardware_id: str, values: Sequence[Tuple[str, str]]) -> bytes:
        """Return the serialized DiagnosticArray; struct.error if the stamp does not fit."""
        if not self.fast:
            return rosbags_diagnostics(stamp_ns, frame_id, level, name, message, hardware_id,
                                       values)
        sec, nanosec = divmod(stamp_ns, NS_PER_S)
        parts = [_ENCAPSULATION, _STAMP.pack(sec, nanosec), _string(frame_id, 8)]
        position = 8 + len(parts[-1])
        # The status count (a uint32: aligned), then the level (a byte: never padded).
        head = _PADDING[position & 3] + _U32(1) + bytes((level,))
        parts.append(head)
        position += len(head)
        for text in (name, message, hardware_id):
            parts.append(_string(text, position))
            position += len(parts[-1])
        count = _PADDING[position & 3] + _U32(len(values))
        parts.append(count)
        position += len(count)
        cache = self._strings
        if len(cache) > MAX_CACHED_STRINGS:
            cache.clear()
        for key, value in values:
            encoded = cache.get((key, value, position & 3))
            if encoded is None:
                first = _string(key, position)
                encoded = cache[(key, value, position & 3)] = first + _string(
                    value, position + len(first))
            parts.append(encoded)
            position += len(encoded)
        return b''.join(parts)
