"""The MCAP record layout: opcodes, the records a reader keeps, and their parsers.

:class:`Cursor` reads little-endian fields out of a bytes-like object (an mmap or a
decompressed chunk) and raises IndexError when a record ends early; ``parse_*`` turn
one record body into :class:`SchemaInfo`, :class:`ChannelInfo`, :class:`RawMessage`
or :class:`AttachmentRecord` (:class:`BadCrc` when an attachment fails its CRC).
:mod:`replay.mcap_scan` walks a file with them.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import NamedTuple

OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_ATTACHMENT, OP_STATISTICS, OP_METADATA = 7, 8, 9, 11, 12
OP_DATA_END = 15
RECORD_HEADER = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")
_U16, U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
FOOTER_BYTES = 9 + 20


@dataclass(frozen=True)
class SchemaInfo:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class ChannelInfo:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


class RawMessage(NamedTuple):
    """A message as stored: MCAP's unsigned times, the 32-bit sequence."""

    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


class MetadataRecord(NamedTuple):
    name: str
    metadata: dict[str, str]


class AttachmentRecord(NamedTuple):
    log_time: int
    create_time: int
    name: str
    media_type: str
    data: bytes


class Cursor:
    """Little-endian fields out of a bytes-like object; IndexError when it runs out."""

    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf, pos: int = 0, end: int | None = None) -> None:
        self.buf, self.pos = buf, pos
        self.end = len(buf) if end is None else end

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > self.end:
            raise IndexError("record ends early")
        out = bytes(self.buf[self.pos:self.pos + n])
        self.pos += n
        return out

    def u16(self) -> int:
        return _U16.unpack(self.take(2))[0]

    def u32(self) -> int:
        return U32.unpack(self.take(4))[0]

    def u64(self) -> int:
        return _U64.unpack(self.take(8))[0]

    def string(self) -> str:
        return self.take(self.u32()).decode("utf-8")

    def string_map(self) -> dict[str, str]:
        length = self.u32()
        end = self.pos + length
        out = {}
        while self.pos < end:
            key = self.string()
            out[key] = self.string()
        if self.pos != end:
            raise IndexError("map overruns its length")
        return out


def parse_schema(c: Cursor) -> SchemaInfo:
    schema_id, name, encoding = c.u16(), c.string(), c.string()
    return SchemaInfo(schema_id, name, encoding, c.take(c.u32()))


def parse_channel(c: Cursor) -> ChannelInfo:
    channel_id, schema_id = c.u16(), c.u16()
    topic, encoding = c.string(), c.string()
    return ChannelInfo(channel_id, schema_id, topic, encoding, c.string_map())


def parse_message(buf, start: int, end: int) -> RawMessage:
    if end - start < _MESSAGE.size:
        raise IndexError("message record too short")
    channel_id, sequence, log_time, publish_time = _MESSAGE.unpack_from(buf, start)
    return RawMessage(channel_id, sequence, log_time, publish_time,
                      bytes(buf[start + _MESSAGE.size:end]))


def parse_attachment(c: Cursor, body_start: int) -> AttachmentRecord:
    log_time, create_time = c.u64(), c.u64()
    name, media_type = c.string(), c.string()
    data = c.take(c.u64())
    crc_at = c.pos
    crc = c.u32()
    if crc and zlib.crc32(c.buf[body_start:crc_at]) != crc:
        raise BadCrc(f"attachment {name!r}: CRC mismatch")
    return AttachmentRecord(log_time, create_time, name, media_type, data)


class BadCrc(ValueError):
    pass
