"""How stockpile events are written to MCAP and read back, even from a damaged file.

Conventions (one MCAP message per event; the payload bytes are the event's own):

==================  =================================================================
topic               the Zenoh key expression ``stockpile/<site>/@v1/<type>/<source>``
schema              encoding ``protobuf``, name = the full message name
                    (``foxglove.LaserScan``, ``stockpile.v1.Assay``), data = the
                    message's ``FileDescriptorSet`` (with its imports)
channel             one per (topic, source epoch); message encoding ``protobuf``;
                    metadata ``type``, ``source``, ``epoch`` (decimal), and ``seq_high``
                    (decimal) only for sequence numbers of 2**32 and above
message sequence    the source sequence (its low 32 bits; ``seq_high`` holds the rest)
publish_time        the valid time (UTC ns)
log_time            when it was learned, in site-clock time: the receive time for a
                    recording, the ledger's recorded time for an export
chunks              zstd, with CRCs of every chunk, attachment and the data section
==================  =================================================================

MCAP times are unsigned; a valid or recorded time before 1970 (a negative int64) is
stored as its two's complement and read back exactly (:func:`to_u64`, :func:`from_u64`).

Files also carry metadata records (``stockpile.recording``, ``stockpile.export``,
``stockpile.miss``, ``stockpile.gap``) and, for samples that were not events (no
identity attachment, unknown type), an attachment named ``stockpile.malformed/<n>``
holding the key, the raw payload and attachment and the reason, so a recorder loses
nothing it received.

Reading (:class:`McapScan`) is one linear pass over the data section with an mmap,
which survives what a crash or a bad disk leaves behind: a chunk whose CRC fails or
that does not decompress is skipped and its messages counted as lost (from its
message index, or the summary's statistics); a file that ends early (a recorder
killed mid-write) is read up to the last complete record, and what can be
decompressed of a chunk cut short is salvaged.  :func:`read_entries` turns the
messages into stockpile identities and counts those on channels it does not know.
"""

from __future__ import annotations

import json
import mmap
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import IO, Callable, Iterator, NamedTuple

from schemas.events import EVENT_TYPES, KEY_PREFIX, SCHEMA_VERSION, key_expr, parse_key_expr

MAGIC = b"\x89MCAP0\r\n"
ENCODING = "protobuf"
MASK64 = (1 << 64) - 1
SEQ_LOW_BITS = 32
SEQ_LOW_MASK = (1 << SEQ_LOW_BITS) - 1
#: uncompressed bytes per chunk; a recorder also closes a chunk at every flush
DEFAULT_CHUNK_BYTES = 1 << 20
MALFORMED_PREFIX = "stockpile.malformed/"
MALFORMED_MEDIA_TYPE = "application/json"


def library_id() -> str:
    """The ``library`` string written in every file's header."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"stockpile-ledger/{version('stockpile-ledger')}"
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "stockpile-ledger"


def to_u64(time_ns: int) -> int:
    """An int64 time as MCAP's unsigned 64-bit field (two's complement before 1970)."""
    return int(time_ns) & MASK64


def from_u64(value: int) -> int:
    """Inverse of :func:`to_u64`."""
    return value - (1 << 64) if value >= 1 << 63 else value


class McapFormatError(ValueError):
    """A file that is not an MCAP file at all (one clear line, no traceback)."""


# -- writing ------------------------------------------------------------------------------


@lru_cache(maxsize=None)
def schema_of(type_name: str) -> tuple[str, bytes]:
    """``(full message name, serialized FileDescriptorSet)`` of an event type."""
    from mcap_protobuf.schema import build_file_descriptor_set

    cls = EVENT_TYPES[type_name]
    return cls.DESCRIPTOR.full_name, build_file_descriptor_set(cls).SerializeToString()


def channel_metadata(type_name: str, source: str, epoch: int, seq_high: int = 0) -> dict[str, str]:
    """The metadata of the channel carrying ``(type, source, epoch)`` events."""
    meta = {"type": type_name, "source": source, "epoch": str(int(epoch))}
    if seq_high:
        meta["seq_high"] = str(int(seq_high))
    return meta


class EventWriter:
    """Writes events to one MCAP file with this project's conventions.

    Parameters
    ----------
    output : str, Path or binary stream
        A path (created or truncated) or an open binary stream (not closed here).
    chunk_size_bytes : int
        Uncompressed bytes after which a chunk is closed (and compressed).
    """

    def __init__(self, output: str | Path | IO[bytes], *,
                 chunk_size_bytes: int = DEFAULT_CHUNK_BYTES) -> None:
        from mcap.writer import CompressionType, Writer

        self._own_stream = isinstance(output, (str, Path))
        self.path = str(output) if self._own_stream else getattr(output, "name", "<stream>")
        self._stream = open(output, "wb") if self._own_stream else output  # type: ignore[arg-type]
        self._writer = Writer(self._stream, chunk_size=chunk_size_bytes,
                              compression=CompressionType.ZSTD, enable_crcs=True,
                              enable_data_crcs=True)
        self._writer.start(profile="", library=library_id())
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, int, int], int] = {}
        #: (topic, epoch) -> channel id for sequences below 2**32: the recorder's hot loop
        #: looks channels up here and calls :attr:`add_message` itself (then counts them)
        self.low_channels: dict[tuple[str, int], int] = {}
        self.add_message = self._writer.add_message
        self.messages = 0
        self.malformed = 0
        self.closed = False

    # -- schemas and channels ---------------------------------------------------------

    def _schema_id(self, type_name: str) -> int:
        schema_id = self._schemas.get(type_name)
        if schema_id is None:
            name, data = schema_of(type_name)
            schema_id = self._writer.register_schema(name=name, encoding=ENCODING, data=data)
            self._schemas[type_name] = schema_id
        return schema_id

    def channel_id(self, topic: str, type_name: str, source: str, epoch: int,
                   seq_high: int = 0) -> int:
        """The channel of ``(topic, epoch, seq_high)``, registered on first use."""
        key = (topic, epoch, seq_high)
        channel_id = self._channels.get(key)
        if channel_id is None:
            channel_id = self._writer.register_channel(
                topic=topic, message_encoding=ENCODING, schema_id=self._schema_id(type_name),
                metadata=channel_metadata(type_name, source, epoch, seq_high))
            self._channels[key] = channel_id
            if seq_high == 0:
                self.low_channels[(topic, epoch)] = channel_id
        return channel_id

    # -- records ----------------------------------------------------------------------

    def write(self, topic: str, type_name: str, source: str, epoch: int, seq: int,
              valid_time_ns: int, payload: bytes, log_time_ns: int) -> None:
        """One event on ``topic`` (its key expression); ``log_time_ns`` in site time."""
        channel_id = self._channels.get((topic, epoch, seq >> SEQ_LOW_BITS))
        if channel_id is None:
            channel_id = self.channel_id(topic, type_name, source, epoch, seq >> SEQ_LOW_BITS)
        self._writer.add_message(channel_id, log_time_ns & MASK64, payload,
                                 valid_time_ns & MASK64, seq & SEQ_LOW_MASK)
        self.messages += 1

    def write_event(self, site: str, event, log_time_ns: int) -> None:
        """A :class:`schemas.events.Event` (or a ledger row) of ``site``."""
        self.write(key_expr(site, event.type, event.source), event.type, event.source,
                   event.epoch, event.seq, event.valid_time_ns, event.payload, log_time_ns)

    def add_metadata(self, name: str, data: dict[str, object]) -> None:
        """A metadata record; values are written as strings (JSON for non-strings)."""
        self._writer.add_metadata(name, {str(k): v if isinstance(v, str) else json.dumps(v)
                                         for k, v in data.items()})

    def add_malformed(self, key: str, payload: bytes, attachment: bytes | None, reason: str,
                      log_time_ns: int) -> None:
        """Keep a sample that is not an event (the ledger would quarantine it)."""
        body = {"key": key, "reason": reason, "payload_hex": bytes(payload).hex(),
                "attachment_hex": None if attachment is None else bytes(attachment).hex()}
        self._writer.add_attachment(create_time=0, log_time=log_time_ns & MASK64,
                                    name=f"{MALFORMED_PREFIX}{self.malformed:06d}",
                                    media_type=MALFORMED_MEDIA_TYPE,
                                    data=json.dumps(body).encode())
        self.malformed += 1

    def flush(self) -> None:
        """Close the chunk in progress and hand everything to the OS."""
        self._writer.flush()

    @property
    def bytes_written(self) -> int:
        return self._stream.tell()

    def close(self, metadata: tuple[str, dict[str, object]] | None = None) -> None:
        """Write ``metadata`` (if any), the summary and the footer; close an owned file."""
        if self.closed:
            return
        if metadata is not None:
            self.add_metadata(*metadata)
        self._writer.finish()
        self.closed = True
        if self._own_stream:
            self._stream.close()
        else:
            self._stream.flush()


# -- reading: records ------------------------------------------------------------------

OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_ATTACHMENT, OP_STATISTICS, OP_METADATA = 7, 8, 9, 11, 12
OP_DATA_END = 15
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
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


class _Cursor:
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
        return _U32.unpack(self.take(4))[0]

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


def _parse_schema(c: _Cursor) -> SchemaInfo:
    schema_id, name, encoding = c.u16(), c.string(), c.string()
    return SchemaInfo(schema_id, name, encoding, c.take(c.u32()))


def _parse_channel(c: _Cursor) -> ChannelInfo:
    channel_id, schema_id = c.u16(), c.u16()
    topic, encoding = c.string(), c.string()
    return ChannelInfo(channel_id, schema_id, topic, encoding, c.string_map())


def _parse_message(buf, start: int, end: int) -> RawMessage:
    if end - start < _MESSAGE.size:
        raise IndexError("message record too short")
    channel_id, sequence, log_time, publish_time = _MESSAGE.unpack_from(buf, start)
    return RawMessage(channel_id, sequence, log_time, publish_time,
                      bytes(buf[start + _MESSAGE.size:end]))


def _parse_attachment(c: _Cursor, body_start: int) -> AttachmentRecord:
    log_time, create_time = c.u64(), c.u64()
    name, media_type = c.string(), c.string()
    data = c.take(c.u64())
    crc_at = c.pos
    crc = c.u32()
    if crc and zlib.crc32(c.buf[body_start:crc_at]) != crc:
        raise _BadCrc(f"attachment {name!r}: CRC mismatch")
    return AttachmentRecord(log_time, create_time, name, media_type, data)


class _BadCrc(ValueError):
    pass


# -- reading: the scan ------------------------------------------------------------------


@dataclass
class ScanReport:
    """What a pass over a file found: how many messages, and what was damaged or lost."""

    path: str
    messages: int = 0  # messages read intact (including salvaged ones)
    salvaged: int = 0  # of which from a chunk cut short at the end of the file
    lost: int = 0  # messages known to be lost
    lost_unknown: bool = False  # more may be lost than counted (the file's index is gone)
    bad_chunks: int = 0
    complete: bool = False  # the data section ended properly and the summary was intact
    total: int | None = None  # messages the summary says the file holds
    problems: list[str] = field(default_factory=list)
    unknown: Counter = field(default_factory=Counter)  # (topic, schema, why) -> messages

    @property
    def damaged(self) -> bool:
        return bool(self.lost or self.lost_unknown or self.bad_chunks or self.problems)

    @property
    def unknown_messages(self) -> int:
        return sum(self.unknown.values())

    def loss_text(self) -> str:
        """One line: what was lost (``nothing`` for an intact file)."""
        if not self.damaged:
            return "nothing lost"
        lost = f"{self.lost:,} messages lost" + (" (and an unknown number after the "
                                                 "end of the readable data)"
                                                 if self.lost_unknown else "")
        return f"{lost}; " + "; ".join(self.problems)

    def unknown_text(self) -> str:
        return "; ".join(f"{n:,} on {topic!r} ({schema or 'no schema'}: {why})"
                         for (topic, schema, why), n in self.unknown.most_common())


class McapScan:
    """One damage-tolerant pass over an MCAP file (see the module docstring).

    ``records()`` yields :class:`RawMessage`, :class:`MetadataRecord` and
    :class:`AttachmentRecord` in file order; ``schemas`` and ``channels`` fill in as
    they are met (and from the summary, when it is intact); ``report`` says what was
    read and lost.  Raises :class:`McapFormatError` for a file that is not MCAP.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self.report = ScanReport(self.path)
        self.schemas: dict[int, SchemaInfo] = {}
        self.channels: dict[int, ChannelInfo] = {}
        self._chunk_offsets: list[int] = []
        self._resynced = False
        self._file = open(self.path, "rb")
        try:
            size = Path(self.path).stat().st_size
            if size < len(MAGIC) or self._file.read(len(MAGIC)) != MAGIC:
                raise McapFormatError(f"{self.path} is not an MCAP file (no MCAP magic at its start)")
            self._mm = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        except BaseException:
            self._file.close()
            raise
        self.size = size
        self._summary_ok = self._read_summary()
        #: the first byte after the data section (for progress)
        self.position = len(MAGIC)

    # -- summary --------------------------------------------------------------------

    def _read_summary(self) -> bool:
        mm, size = self._mm, self.size
        footer_at = size - len(MAGIC) - FOOTER_BYTES
        if footer_at < len(MAGIC) or mm[size - len(MAGIC):] != MAGIC:
            return False
        opcode, length = _RECORD.unpack_from(mm, footer_at)
        if opcode != OP_FOOTER or length != 20:
            return False
        summary_start, _offsets, crc = struct.unpack_from("<QQI", mm, footer_at + 9)
        if summary_start == 0:
            return True  # a complete file without a summary
        if not len(MAGIC) <= summary_start <= footer_at:
            self.report.problems.append("the footer points outside the file")
            return False
        if crc and zlib.crc32(mm[summary_start:footer_at + 25]) != crc:
            self.report.problems.append("the summary section fails its CRC (not used)")
            return False
        pos = summary_start
        try:
            while pos < footer_at:
                opcode, length = _RECORD.unpack_from(mm, pos)
                body = pos + 9
                if body + length > footer_at:
                    raise IndexError("summary record overruns the footer")
                c = _Cursor(mm, body, body + length)
                if opcode == OP_SCHEMA:
                    schema = _parse_schema(c)
                    self.schemas.setdefault(schema.id, schema)
                elif opcode == OP_CHANNEL:
                    channel = _parse_channel(c)
                    self.channels.setdefault(channel.id, channel)
                elif opcode == OP_STATISTICS:
                    self.report.total = c.u64()
                elif opcode == OP_CHUNK_INDEX:
                    c.u64(), c.u64()
                    self._chunk_offsets.append(c.u64())
                pos = body + length
        except (IndexError, struct.error, UnicodeDecodeError) as exc:
            self.report.problems.append(f"the summary section is unreadable ({exc})")
            self.report.total = None
            self._chunk_offsets.clear()
            return False
        self._chunk_offsets.sort()
        return True

    # -- the data section -----------------------------------------------------------

    def records(self) -> Iterator[RawMessage | MetadataRecord | AttachmentRecord]:
        """Every message, metadata and attachment record of the data section, in order."""
        mm, size, report = self._mm, self.size, self.report
        pos = len(MAGIC)
        data_crc = zlib.crc32(MAGIC)
        ended = False
        pending_lost = False  # the chunk just before was lost: count its message index
        while True:
            self.position = pos
            if pos + 9 > size:
                report.problems.append(f"the file ends at byte {size:,} without its "
                                       "data-end record (a recording cut short)")
                report.lost_unknown = True
                break
            opcode, length = _RECORD.unpack_from(mm, pos)
            body, end = pos + 9, pos + 9 + length
            if end > size:
                resume = next((o for o in self._chunk_offsets if o > pos), None)
                if resume is None:
                    yield from self._cut_short(opcode, body, size)
                    break
                # a damaged length field: the summary says where the next chunk starts
                report.problems.append(f"record at byte {pos:,} claims {length:,} bytes, past "
                                       f"the end of the file; resumed at the next indexed "
                                       f"chunk (byte {resume:,})")
                self._resynced = True
                pending_lost = False
                pos = resume
                continue
            if opcode == OP_DATA_END:
                self._check_data_crc(data_crc, body, end)
                ended = True
                break
            if opcode == OP_FOOTER:
                ended = True
                break
            if opcode != OP_MESSAGE_INDEX:
                pending_lost = False
            try:
                if opcode == OP_CHUNK:
                    chunk_records = self._chunk(body, end)
                    if chunk_records is None:
                        pending_lost = True
                    else:
                        yield from chunk_records
                elif opcode == OP_MESSAGE_INDEX and pending_lost:
                    c = _Cursor(mm, body, end)
                    c.u16()
                    report.lost += c.u32() // 16
                else:
                    item = self._record(opcode, body, end)
                    if item is not None:
                        yield item
            except (_BadCrc, IndexError, struct.error, UnicodeDecodeError) as exc:
                report.problems.append(f"record at byte {pos:,} is damaged ({exc}); skipped")
            data_crc = zlib.crc32(mm[pos:end], data_crc)
            pos = end
        self._finish(ended)

    def _record(self, opcode: int, body: int, end: int, buf=None):
        mm = self._mm if buf is None else buf
        if opcode == OP_MESSAGE:
            message = _parse_message(mm, body, end)
            return self._counted(message)
        c = _Cursor(mm, body, end)
        if opcode == OP_SCHEMA:
            schema = _parse_schema(c)
            self.schemas[schema.id] = schema
        elif opcode == OP_CHANNEL:
            channel = _parse_channel(c)
            self.channels[channel.id] = channel
        elif opcode == OP_METADATA:
            return MetadataRecord(c.string(), c.string_map())
        elif opcode == OP_ATTACHMENT:
            return _parse_attachment(c, body)
        return None

    def _counted(self, message: RawMessage) -> RawMessage:
        self.report.messages += 1
        return message

    def _chunk(self, body: int, end: int) -> list | None:
        """The records of one chunk, or None when it is lost (bad CRC, undecodable)."""
        c = _Cursor(self._mm, body, end)
        try:
            c.u64(), c.u64()  # message start and end times
            uncompressed_size, crc = c.u64(), c.u32()
            compression = c.string()
            data = _decompress(compression, c.take(c.u64()), uncompressed_size)
            if len(data) != uncompressed_size:
                raise ValueError(f"{len(data):,} bytes where {uncompressed_size:,} were declared")
            if crc and zlib.crc32(data) != crc:
                raise ValueError("CRC mismatch")
            return self._chunk_records(data, strict=True)
        except (ValueError, IndexError, struct.error, UnicodeDecodeError, KeyError) as exc:
            self.report.bad_chunks += 1
            self.report.problems.append(f"chunk at byte {body - 9:,} lost ({exc})")
            return None

    def _chunk_records(self, data: bytes, *, strict: bool) -> list:
        out: list = []
        pos, size = 0, len(data)
        while pos + 9 <= size:
            opcode, length = _RECORD.unpack_from(data, pos)
            body, end = pos + 9, pos + 9 + length
            if end > size:
                if strict:
                    raise IndexError("a record overruns its chunk")
                break
            item = self._record(opcode, body, end, data) if opcode != OP_MESSAGE else \
                _parse_message(data, body, end)
            if item is not None:
                out.append(item)
            pos = end
        if strict and pos != size:
            raise IndexError("trailing bytes in chunk")
        if strict:
            self.report.messages += sum(1 for r in out if type(r) is RawMessage)
        return out

    def _cut_short(self, opcode: int, body: int, size: int) -> Iterator:
        """The last record runs past the end of the file: salvage what a chunk holds."""
        report = self.report
        report.lost_unknown = True
        if opcode != OP_CHUNK:
            report.problems.append(f"the file is cut short inside a record at byte {body - 9:,}")
            return
        try:
            c = _Cursor(self._mm, body, size)
            c.u64(), c.u64(), c.u64(), c.u32()
            compression = c.string()
            c.u64()
            data = _decompress_partial(compression, bytes(self._mm[c.pos:size]))
            records = self._chunk_records(data, strict=False)
        except (ValueError, IndexError, struct.error, UnicodeDecodeError, KeyError):
            records = []
        salvaged = sum(1 for r in records if type(r) is RawMessage)
        report.messages += salvaged
        report.salvaged += salvaged
        report.problems.append(f"the file is cut short inside the chunk at byte {body - 9:,}; "
                               f"{salvaged:,} messages salvaged from it (not CRC-checked)")
        yield from records

    def _check_data_crc(self, crc: int, body: int, end: int) -> None:
        if end - body >= 4:
            stored = _U32.unpack_from(self._mm, body)[0]
            if stored and stored != crc and not self.report.bad_chunks and not self._resynced:
                self.report.problems.append("the data section fails its CRC (a record outside "
                                            "the chunks was changed)")

    def _finish(self, ended: bool) -> None:
        report = self.report
        report.complete = ended and self._summary_ok and not report.problems
        if report.total is not None:
            # the summary's count is exact: it covers chunks lost without an index too
            report.lost = max(0, report.total - report.messages)
            if ended:
                report.lost_unknown = False

    def close(self) -> None:
        try:
            self._mm.close()
        finally:
            self._file.close()

    def __enter__(self) -> McapScan:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        try:
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        except zstandard.ZstdError as exc:
            raise ValueError(f"zstd: {exc}") from None
    if compression == "lz4":
        import lz4.frame

        try:
            return lz4.frame.decompress(data)
        except RuntimeError as exc:
            raise ValueError(f"lz4: {exc}") from None
    raise ValueError(f"unknown compression {compression!r}")


def _decompress_partial(compression: str, data: bytes) -> bytes:
    """As much as can be decompressed from the start of a cut-short chunk."""
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        try:
            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        except zstandard.ZstdError:
            return b""
    if compression == "lz4":
        import lz4.frame

        try:
            return lz4.frame.LZ4FrameDecompressor().decompress(data)
        except RuntimeError:
            return b""
    return b""


# -- reading: stockpile events ------------------------------------------------------------


class Entry(NamedTuple):
    """One event read from a file, with its identity and both times (signed ns)."""

    topic: str
    type: str
    source: str
    epoch: int
    seq: int
    valid_time_ns: int
    log_time_ns: int
    payload: bytes


class MalformedSample(NamedTuple):
    """A recorded sample that was not an event (see :meth:`EventWriter.add_malformed`)."""

    key: str
    payload: bytes
    attachment: bytes | None
    reason: str
    log_time_ns: int


@dataclass(frozen=True)
class Identity:
    """What a channel says about its events."""

    type: str
    source: str
    epoch: int
    seq_base: int


def resolve_channel(channel: ChannelInfo, schema: SchemaInfo | None) -> Identity | str:
    """The identity a channel carries, or why it is not a stockpile event channel."""
    try:
        _site, type_name, source = parse_key_expr(channel.topic)
    except ValueError:
        return f"topic is not {KEY_PREFIX}/<site>/{SCHEMA_VERSION}/<type>/<source>"
    cls = EVENT_TYPES.get(type_name)
    if cls is None:
        return f"unknown event type {type_name!r}"
    if schema is None or schema.encoding != ENCODING or channel.message_encoding != ENCODING:
        return "not protobuf"
    if schema.name != cls.DESCRIPTOR.full_name:
        return f"schema {schema.name!r} is not {cls.DESCRIPTOR.full_name} (the {type_name} message)"
    meta = channel.metadata
    try:
        epoch = int(meta["epoch"])
        seq_high = int(meta.get("seq_high", "0"))
    except (KeyError, ValueError):
        return "channel metadata has no integer epoch"
    if meta.get("source", source) != source or meta.get("type", type_name) != type_name:
        return "channel metadata disagrees with the topic"
    if not 0 <= epoch < 1 << 63 or not 0 <= seq_high < 1 << 31:
        return "epoch or seq_high out of range"
    return Identity(type_name, source, epoch, seq_high << SEQ_LOW_BITS)


def topic_matcher(expressions: list[str] | tuple[str, ...] | None) -> Callable[[str], bool] | None:
    """A predicate: does a topic fall under any of these Zenoh key expressions?"""
    if not expressions:
        return None
    import zenoh

    try:
        exprs = [zenoh.KeyExpr(e) for e in expressions]
    except Exception as exc:  # noqa: BLE001 - zenoh raises its own error type
        raise ValueError(f"bad key expression in --topics: {exc}") from None

    def matches(topic: str) -> bool:
        try:
            key = zenoh.KeyExpr(topic)
        except Exception:  # noqa: BLE001 - a topic that is not a key expression
            return False
        return any(e.includes(key) for e in exprs)

    return matches


def malformed_from_attachment(record: AttachmentRecord) -> MalformedSample | None:
    """The sample a ``stockpile.malformed/<n>`` attachment holds, or None."""
    if not record.name.startswith(MALFORMED_PREFIX):
        return None
    try:
        body = json.loads(record.data)
        attachment = body.get("attachment_hex")
        return MalformedSample(str(body["key"]), bytes.fromhex(body["payload_hex"]),
                               None if attachment is None else bytes.fromhex(attachment),
                               str(body.get("reason", "")), from_u64(record.log_time))
    except (ValueError, KeyError, TypeError):
        return None


def read_entries(scan: McapScan, *, topics: Callable[[str], bool] | None = None,
                 start_offset_ns: int | None = None, until_offset_ns: int | None = None,
                 malformed: list[MalformedSample] | None = None) -> Iterator[Entry]:
    """The stockpile events of a file, in file order.

    Messages on channels that are not stockpile event channels are counted in
    ``scan.report.unknown`` and skipped.  ``topics`` keeps only matching topics.
    The offsets select by log time, in nanoseconds after the start of the file:
    the later of its first message's log and publish times (a ledger's first events
    can carry a recorded time before the site clock started).  ``malformed``, when given, collects the
    kept malformed samples (in file order, interleaved by position only).
    """
    resolved: dict[int, Identity | str | None] = {}
    first_log: int | None = None
    for record in scan.records():
        if type(record) is not RawMessage:
            if malformed is not None and type(record) is AttachmentRecord:
                sample = malformed_from_attachment(record)
                if sample is not None:
                    malformed.append(sample)
            continue
        log_ns = from_u64(record.log_time)
        if first_log is None:
            first_log = max(log_ns, from_u64(record.publish_time))
        ident = resolved.get(record.channel_id, False)
        if ident is False:
            ident = _resolve(scan, record.channel_id, topics)
            resolved[record.channel_id] = ident
        if ident is None:
            continue  # filtered out by topic
        if type(ident) is str:
            channel = scan.channels.get(record.channel_id)
            schema = scan.schemas.get(channel.schema_id) if channel else None
            scan.report.unknown[(channel.topic if channel else f"channel {record.channel_id}",
                                 schema.name if schema else "", ident)] += 1
            continue
        if start_offset_ns is not None and log_ns - first_log < start_offset_ns:
            continue
        if until_offset_ns is not None and log_ns - first_log > until_offset_ns:
            continue
        channel = scan.channels[record.channel_id]
        yield Entry(channel.topic, ident.type, ident.source, ident.epoch,
                    ident.seq_base | record.sequence, from_u64(record.publish_time), log_ns,
                    record.data)


def _resolve(scan: McapScan, channel_id: int,
             topics: Callable[[str], bool] | None) -> Identity | str | None:
    channel = scan.channels.get(channel_id)
    if channel is None:
        return "its channel definition was lost"
    if topics is not None and not topics(channel.topic):
        return None
    return resolve_channel(channel, scan.schemas.get(channel.schema_id))
