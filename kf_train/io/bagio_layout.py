"""
Fast reading and writing of a few fixed fields in serialized messages, layouts from rosbags.

rosbags builds and (de)serialises a message as nested dataclasses: 30-80 µs per
PoseWithCovarianceStamped or Odometry here, more than the whole filter step. A replay
reads one or two numbers per input message and writes a handful per output, so here a
message's layout is *learnt from rosbags' own serializer* and then used directly:

* where a field lies: a copy of a real message gets a distinct sentinel value in each
  field, rosbags serialises it, and each sentinel's bytes are found (exactly once) in
  the result;
* :class:`PatchTemplate` (writing): one serialized message whose fields are
  overwritten in place per message, in ~2 µs;
* :class:`FieldReader` (reading): the fields unpacked at the learnt offsets.

Both check themselves against rosbags when they learn: a template filled with test
values must equal rosbags' serialization of the same message byte for byte, and a
layout must read the message it was learnt from exactly as rosbags deserialises it.
What fails the check (or a sentinel that is not found exactly once) is not used:
the caller falls back to rosbags for every message.

Layouts of a header-first message (all of kf_train's) differ only by the length of
the strings: after the 4-byte encapsulation, stamp.sec and .nanosec, header.frame_id
is a uint32 length and its bytes, and every field read here comes after the last
string (or in the stamp), so a layout is keyed by the encapsulation, frame_id's
length and the message's total length (fields after the strings sit at fixed
distances from the end).
"""

import copy
import struct
from typing import Callable, Dict, Optional, Sequence, Tuple

from kf_train.io.bagio_types import TYPESTORE

FieldPath = Tuple[object, ...]
"""Attribute names and list indices from the message to a field, e.g. ('pose', 'covariance', 0)."""

# Distinct sentinel values, one per field: doubles far from anything a message holds
# (each has a different mantissa pattern) and 32-bit integers likewise.
_DOUBLE_SENTINELS = tuple(float.fromhex(f'0x1.{i:x}5a5a5a5a5a5ap-777') for i in range(1, 15))
_INT_SENTINELS = tuple(0x35A5A5A0 + i for i in range(1, 15))
_FORMATS = {'d': 8, 'i': 4, 'I': 4}
# header.frame_id's uint32 length sits here in plain CDR (after the encapsulation,
# stamp.sec and stamp.nanosec); its bytes follow.
_FRAME_LENGTH_AT = 12
_FRAME_AT = _FRAME_LENGTH_AT + 4


def get_field(message, path: FieldPath):
    """Return the field at ``path``."""
    for step in path:
        message = message[step] if isinstance(step, int) else getattr(message, step)
    return message


def set_field(message, path: FieldPath, value) -> None:
    """Set the field at ``path`` to ``value``."""
    for step in path[:-1]:
        message = message[step] if isinstance(step, int) else getattr(message, step)
    if isinstance(path[-1], int):
        message[path[-1]] = value
    else:
        setattr(message, path[-1], value)


def _locate(message, kind: str, fields: Sequence[Tuple[FieldPath, str]],
            little_endian: bool) -> Optional[Tuple[bytes, Tuple[int, ...]]]:
    """Return the serialized sentinel probe and each field's offset, or None."""
    forms = [form for _, form in fields]
    if forms.count('d') > len(_DOUBLE_SENTINELS) or \
            len(forms) - forms.count('d') > len(_INT_SENTINELS):
        return None                          # more fields than sentinels: rosbags writes
    probe = copy.deepcopy(message)
    order = '<' if little_endian else '>'
    packed = []
    doubles, ints = iter(_DOUBLE_SENTINELS), iter(_INT_SENTINELS)
    for path, form in fields:
        sentinel = next(doubles) if form == 'd' else next(ints)
        set_field(probe, path, sentinel)
        packed.append(struct.pack(order + form, sentinel))
    raw = bytes(TYPESTORE.serialize_cdr(probe, kind, little_endian=little_endian))
    offsets = []
    for needle in packed:
        at = raw.find(needle)
        if at < 0 or raw.find(needle, at + 1) >= 0:
            return None
        offsets.append(at)
    return raw, tuple(offsets)


class PatchTemplate:
    """A serialized message whose ``fields`` are overwritten per message (module doc)."""

    def __init__(self, message, kind: str, fields: Sequence[Tuple[FieldPath, str]]):
        """Learn where ``fields`` of ``message`` (a rosbags message of type ``kind``) lie."""
        self.kind = kind
        self.fields = tuple(fields)
        self._message = copy.deepcopy(message)
        located = _locate(message, kind, self.fields, little_endian=True)
        self._packers: Optional[Tuple[Callable, ...]] = None
        if located is not None and self._check(*located):
            self._buffer = bytearray(located[0])
            self._packers = tuple(
                struct.Struct('<' + form).pack_into for _, form in self.fields)
            self._offsets = located[1]

    def _check(self, raw: bytes, offsets: Tuple[int, ...]) -> bool:
        """Whether patching test values equals rosbags' own serialization of them."""
        values = [2.5 + i if form == 'd' else 1000 + i
                  for i, (_, form) in enumerate(self.fields)]
        buffer = bytearray(raw)
        for value, offset, (_, form) in zip(values, offsets, self.fields):
            struct.pack_into('<' + form, buffer, offset, value)
        return bytes(buffer) == self.serialize_slowly(values)

    @property
    def fast(self) -> bool:
        """Whether the learnt layout is used (else rosbags serialises every message)."""
        return self._packers is not None

    def serialize_slowly(self, values: Sequence) -> bytes:
        """Return rosbags' serialization of the message with ``values`` in the fields."""
        message = copy.deepcopy(self._message)
        for value, (path, _) in zip(values, self.fields):
            set_field(message, path, value)
        return bytes(TYPESTORE.serialize_cdr(message, self.kind))

    def fill(self, *values):
        """Return the serialized message holding ``values`` (a buffer reused next call)."""
        if self._packers is None:
            return self.serialize_slowly(values)
        buffer = self._buffer
        for pack, offset, value in zip(self._packers, self._offsets, values):
            pack(buffer, offset, value)
        return buffer


class FieldReader:
    """
    Reads ``fields`` (and header.frame_id) of serialized messages of one type.

    :meth:`read` returns ``(frame_id, values)``, equal to what rosbags deserialises
    (as Python floats and ints):
    from a learnt layout when the message's key has one, else from rosbags (learning
    a layout for the key). Every field read must lie in the stamp or after the last
    string of the message (true of the header-first messages kf_train reads).
    """

    def __init__(self, kind: str, fields: Sequence[Tuple[FieldPath, str]]):
        """Read ``fields`` of messages of type ``kind``."""
        self.kind = kind
        self.fields = tuple(fields)
        self._layouts: Dict[tuple, Optional[tuple]] = {}

    def read(self, raw) -> Tuple[str, tuple]:
        """Return header.frame_id and the fields' values of one serialized message."""
        if len(raw) < _FRAME_AT:
            message = TYPESTORE.deserialize_cdr(raw, self.kind)  # raises: too short
            return self._values(message)
        key = (raw[1], bytes(raw[_FRAME_LENGTH_AT:_FRAME_AT]), len(raw))
        layout = self._layouts.get(key)
        if layout is not None:
            return _unpack(layout, raw)
        message = TYPESTORE.deserialize_cdr(raw, self.kind)
        result = self._values(message)
        if key not in self._layouts:
            self._layouts[key] = self._learn(message, raw, result)
        return result

    def _values(self, message) -> Tuple[str, tuple]:
        """Return header.frame_id and the fields of a deserialised message as Python numbers."""
        return message.header.frame_id, tuple(
            float(get_field(message, path)) if form == 'd' else int(get_field(message, path))
            for path, form in self.fields)

    def _learn(self, message, raw, expected) -> Optional[tuple]:
        """Return the layout of messages like ``raw``, checked on it, or None."""
        little_endian = bool(raw[1])
        located = _locate(message, self.kind, self.fields, little_endian)
        if located is None or len(located[0]) != len(raw):
            return None
        offsets, forms = located[1], [form for _, form in self.fields]
        if any(offsets[i] + _FORMATS[forms[i]] > offsets[i + 1]
               for i in range(len(offsets) - 1)):
            return None  # not in field order: rosbags reads these messages
        order = '<' if little_endian else '>'
        frame_end = _FRAME_AT + struct.unpack_from(order + 'I', raw, _FRAME_LENGTH_AT)[0] - 1
        layout = (_one_struct(order, offsets, forms), frame_end)
        try:
            frame_id, values = _unpack(layout, raw)
        except (struct.error, UnicodeDecodeError):
            return None
        same = frame_id == expected[0] and all(
            struct.pack('<d', float(a)) == struct.pack('<d', float(b))
            for a, b in zip(values, expected[1]))
        return layout if same else None


def _one_struct(order: str, offsets: Sequence[int], forms: Sequence[str]) -> Callable:
    """
    Return unpack_from(raw) -> the fields' values, in field order, in one struct call.

    The fields at ``offsets`` (increasing, not overlapping) with pad bytes between. A
    layout is for one key (module doc): one total length and one frame_id length, so
    every offset is fixed, those after the strings included.
    """
    text, at = order, 0
    for offset, form in zip(offsets, forms):
        text += f'{offset - at}x{form}' if offset > at else form
        at = offset + _FORMATS[form]
    return struct.Struct(text).unpack_from


def _unpack(layout: tuple, raw) -> Tuple[str, tuple]:
    """Return header.frame_id and the field values of ``raw`` read by ``layout``."""
    unpack, frame_end = layout
    return str(raw[_FRAME_AT:frame_end], 'utf-8'), unpack(raw)
