"""The protobuf wire format, as much of it as the recordings need, without code generation.

Recordings (format version 2) carry protobuf messages whose bulk is *packed* repeated fixed-width
numbers (``repeated double``, ``repeated sfixed64``, ``repeated bool``): on the wire these are one
length-delimited field holding the little-endian array, so they are written from
``ndarray.tobytes()`` and read back with ``numpy.frombuffer`` — no per-point Python. The scalar
fields around them are few, and are encoded and parsed here field by field.

Also builds the ``FileDescriptorSet`` of calstation's own message types (the MCAP schema data of
a protobuf channel), so standard readers decode them like any generated message.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from calstation.errors import RecordingError

VARINT, I64, LEN, I32 = 0, 1, 2, 5
"""Wire types."""

_DOUBLE = struct.Struct("<d")
_FIXED32 = struct.Struct("<I")


# --- encoding ------------------------------------------------------------------------------
def varint(n: int) -> bytes:
    """A base-128 varint; negative numbers as their 64-bit two's complement (int64 fields)."""
    if n < 0:
        n += 1 << 64
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def tag(field: int, wire_type: int) -> bytes:
    """The key of a field."""
    return varint((field << 3) | wire_type)


def len_field(field: int, payload: bytes | bytearray | memoryview) -> bytes:
    """A length-delimited field (string, bytes, sub-message or packed array)."""
    return tag(field, LEN) + varint(len(payload)) + bytes(payload)


def varint_field(field: int, n: int) -> bytes:
    """An int64/uint32/bool/enum field."""
    return tag(field, VARINT) + varint(n)


def double_field(field: int, x: float) -> bytes:
    """A double field."""
    return tag(field, I64) + _DOUBLE.pack(x)


def fixed32_field(field: int, n: int) -> bytes:
    """A fixed32 field."""
    return tag(field, I32) + _FIXED32.pack(n)


def string_field(field: int, text: str) -> bytes:
    """A string field."""
    return len_field(field, text.encode("utf-8"))


# --- decoding ------------------------------------------------------------------------------
def read_varint(buf: bytes | memoryview, pos: int) -> tuple[int, int]:
    """(value, position after it) of the varint at ``pos``."""
    result = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if b < 0x80:
            return result, pos
        shift += 7
        if shift > 63:
            raise RecordingError("malformed protobuf: varint longer than 10 bytes")


def fields(buf: bytes | memoryview) -> list[tuple[int, int, int | bytes | memoryview]]:
    """The top-level fields of a message: (field number, wire type, value).

    The value is an int (varint), 8 or 4 bytes (fixed 64/32) or a memoryview of the payload
    (length-delimited, no copy). Raises :class:`RecordingError` on a malformed buffer.
    """
    # this runs for every message of a recording: varints are decoded inline, not by calls
    view = memoryview(buf)
    n = len(view)
    pos = 0
    out: list[tuple[int, int, int | bytes | memoryview]] = []
    append = out.append
    try:
        while pos < n:
            key = view[pos]
            pos += 1
            if key >= 0x80:
                key, pos = read_varint(view, pos - 1)
            wire = key & 7
            if wire in (LEN, VARINT):
                v = view[pos]
                pos += 1
                if v >= 0x80:
                    v &= 0x7F
                    shift = 7
                    while True:
                        b = view[pos]
                        pos += 1
                        v |= (b & 0x7F) << shift
                        if b < 0x80:
                            break
                        shift += 7
                        if shift > 63:
                            raise RecordingError("malformed protobuf: varint longer than 10 bytes")
                if wire == VARINT:
                    append((key >> 3, wire, v))
                else:
                    append((key >> 3, wire, view[pos : pos + v]))
                    pos += v
            elif wire == I64:
                append((key >> 3, wire, view[pos : pos + 8]))
                pos += 8
            elif wire == I32:
                append((key >> 3, wire, view[pos : pos + 4]))
                pos += 4
            else:
                raise RecordingError(f"malformed protobuf: unsupported wire type {wire}")
    except IndexError:
        raise RecordingError("malformed protobuf: the message ends inside a field") from None
    if pos > n:
        raise RecordingError("malformed protobuf: a field runs past the message end")
    return out


def as_double(value: int | bytes | memoryview) -> float:
    """A decoded double field."""
    if isinstance(value, int) or len(value) != 8:
        raise RecordingError("malformed protobuf: a double field is not 8 bytes")
    return float(_DOUBLE.unpack(value)[0])


def as_int64(value: int | bytes | memoryview) -> int:
    """A decoded int64 (varint) field, sign restored."""
    if not isinstance(value, int):
        raise RecordingError("malformed protobuf: an integer field is not a varint")
    return value - (1 << 64) if value >= 1 << 63 else value


# --- descriptors (schemas of calstation's own messages) ------------------------------------
TYPE_DOUBLE, TYPE_INT64, TYPE_UINT32, TYPE_BOOL, TYPE_SFIXED64 = 1, 3, 13, 8, 16
LABEL_OPTIONAL, LABEL_REPEATED = 1, 3

Field = tuple[str, int, int, int]
"""(name, number, type, label) of a message field."""


def file_descriptor_set(
    file_name: str, package: str, messages: Sequence[tuple[str, Sequence[Field]]]
) -> bytes:
    """A serialised ``google.protobuf.FileDescriptorSet`` of one proto3 file holding
    ``messages`` (name, fields) of scalar fields: the schema data of an MCAP protobuf channel."""
    file_proto = string_field(1, file_name) + string_field(2, package)
    for name, message_fields in messages:
        body = string_field(1, name)
        for fname, number, ftype, label in message_fields:
            field_proto = (
                string_field(1, fname)
                + varint_field(3, number)
                + varint_field(4, label)
                + varint_field(5, ftype)
                + string_field(10, _json_name(fname))
            )
            body += len_field(2, field_proto)
        file_proto += len_field(4, body)
    file_proto += string_field(12, "proto3")
    return len_field(1, file_proto)


def _json_name(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(part[:1].upper() + part[1:] for part in rest)
