"""Reading an MCAP file in one damage-tolerant linear pass: :class:`McapScan`.

The pass goes over the data section with an mmap and survives what a crash or a bad
disk leaves behind: a chunk whose CRC fails or that does not decompress is skipped and
its messages counted as lost (from its message index, or the summary's statistics); a
file that ends early (a recorder killed mid-write) is read up to the last complete
record, and what can be decompressed of a chunk cut short is salvaged.
:class:`ScanReport` says what was read and what was lost.
"""

from __future__ import annotations

import mmap
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import zstandard

from replay.mcap_format import MAGIC, McapFormatError
from replay.mcap_records import (
    FOOTER_BYTES,
    OP_ATTACHMENT,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_METADATA,
    OP_SCHEMA,
    OP_STATISTICS,
    RECORD_HEADER,
    U32,
    AttachmentRecord,
    BadCrc,
    ChannelInfo,
    Cursor,
    MetadataRecord,
    RawMessage,
    SchemaInfo,
    parse_attachment,
    parse_channel,
    parse_message,
    parse_schema,
)

__all__ = ["McapScan", "ScanReport"]


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
        opcode, length = RECORD_HEADER.unpack_from(mm, footer_at)
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
                opcode, length = RECORD_HEADER.unpack_from(mm, pos)
                body = pos + 9
                if body + length > footer_at:
                    raise IndexError("summary record overruns the footer")
                c = Cursor(mm, body, body + length)
                if opcode == OP_SCHEMA:
                    schema = parse_schema(c)
                    self.schemas.setdefault(schema.id, schema)
                elif opcode == OP_CHANNEL:
                    channel = parse_channel(c)
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
            opcode, length = RECORD_HEADER.unpack_from(mm, pos)
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
                    c = Cursor(mm, body, end)
                    c.u16()
                    report.lost += c.u32() // 16
                else:
                    item = self._record(opcode, body, end)
                    if item is not None:
                        yield item
            except (BadCrc, IndexError, struct.error, UnicodeDecodeError) as exc:
                report.problems.append(f"record at byte {pos:,} is damaged ({exc}); skipped")
            data_crc = zlib.crc32(mm[pos:end], data_crc)
            pos = end
        self._finish(ended)

    def _record(self, opcode: int, body: int, end: int, buf=None):
        mm = self._mm if buf is None else buf
        if opcode == OP_MESSAGE:
            message = parse_message(mm, body, end)
            return self._counted(message)
        c = Cursor(mm, body, end)
        if opcode == OP_SCHEMA:
            schema = parse_schema(c)
            self.schemas[schema.id] = schema
        elif opcode == OP_CHANNEL:
            channel = parse_channel(c)
            self.channels[channel.id] = channel
        elif opcode == OP_METADATA:
            return MetadataRecord(c.string(), c.string_map())
        elif opcode == OP_ATTACHMENT:
            return parse_attachment(c, body)
        return None

    def _counted(self, message: RawMessage) -> RawMessage:
        self.report.messages += 1
        return message

    def _chunk(self, body: int, end: int) -> list | None:
        """The records of one chunk, or None when it is lost (bad CRC, undecodable)."""
        c = Cursor(self._mm, body, end)
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
            opcode, length = RECORD_HEADER.unpack_from(data, pos)
            body, end = pos + 9, pos + 9 + length
            if end > size:
                if strict:
                    raise IndexError("a record overruns its chunk")
                break
            item = self._record(opcode, body, end, data) if opcode != OP_MESSAGE else \
                parse_message(data, body, end)
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
            c = Cursor(self._mm, body, size)
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
            stored = U32.unpack_from(self._mm, body)[0]
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
        try:
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        except zstandard.ZstdError as exc:
            raise ValueError(f"zstd: {exc}") from None
    if compression == "lz4":
        import lz4.frame  # deferred: lz4 is optional (not a declared dependency)

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
        try:
            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        except zstandard.ZstdError:
            return b""
    if compression == "lz4":
        import lz4.frame  # deferred: lz4 is optional (not a declared dependency)

        try:
            return lz4.frame.LZ4FrameDecompressor().decompress(data)
        except RuntimeError:
            return b""
    return b""
