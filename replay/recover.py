"""``stockpile record --recover BROKEN FIXED``: salvage what a crash or a bad disk left.

Reads BROKEN with :class:`replay.mcap_scan.McapScan` (every intact chunk, what can
be decompressed of a chunk cut short, metadata and attachments) and writes FIXED as
a complete MCAP file: the same schemas, channels (with their metadata), messages
(times and sequence numbers unchanged) and records, with a proper summary.  A
``stockpile.recovered`` metadata record says what was lost.  Channels that are not
stockpile events are copied too: recovery keeps whatever was recorded.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, Writer

from replay.mcap_format import DEFAULT_CHUNK_BYTES, library_id
from replay.mcap_records import AttachmentRecord, MetadataRecord, RawMessage
from replay.mcap_scan import McapScan, ScanReport


@dataclass
class RecoverResult:
    broken: str
    fixed: str
    messages: int  # messages written to FIXED
    orphaned: int  # messages whose channel definition was lost (not written)
    report: ScanReport


def recover(broken: str | Path, fixed: str | Path) -> RecoverResult:
    """Copy every readable record of ``broken`` into a complete file ``fixed``."""
    broken, fixed = Path(broken), Path(fixed)
    if fixed.exists() and fixed.resolve() == broken.resolve():
        raise ValueError("FIXED must be a new file, not BROKEN itself")
    partial = fixed.with_name(fixed.name + ".partial")
    with McapScan(broken) as scan:
        try:
            with open(partial, "wb") as stream:
                writer = Writer(stream, chunk_size=DEFAULT_CHUNK_BYTES,
                                compression=CompressionType.ZSTD, enable_crcs=True,
                                enable_data_crcs=True)
                writer.start(profile="", library=library_id())
                messages, orphaned = _copy(scan, writer)
                report = scan.report
                writer.add_metadata("stockpile.recovered", {
                    "from": str(broken), "messages": str(messages), "lost": str(report.lost),
                    "lost_unknown": str(report.lost_unknown).lower(),
                    "salvaged_from_cut_chunk": str(report.salvaged),
                    "orphaned": str(orphaned), "problems": "; ".join(report.problems)})
                writer.finish()
            os.replace(partial, fixed)
        except BaseException:
            with contextlib.suppress(OSError):
                partial.unlink()
            raise
    return RecoverResult(str(broken), str(fixed), messages, orphaned, scan.report)


def _copy(scan: McapScan, writer) -> tuple[int, int]:
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    messages = orphaned = 0
    for record in scan.records():
        kind = type(record)
        if kind is RawMessage:
            new_id = channel_ids.get(record.channel_id)
            if new_id is None:
                new_id = _channel(scan, writer, record.channel_id, schema_ids)
                if new_id is None:
                    orphaned += 1
                    continue
                channel_ids[record.channel_id] = new_id
            writer.add_message(new_id, record.log_time, record.data, record.publish_time,
                               record.sequence)
            messages += 1
        elif kind is MetadataRecord:
            writer.add_metadata(record.name, record.metadata)
        elif kind is AttachmentRecord:
            writer.add_attachment(record.create_time, record.log_time, record.name,
                                  record.media_type, record.data)
    return messages, orphaned


def _channel(scan: McapScan, writer, channel_id: int, schema_ids: dict[int, int]) -> int | None:
    channel = scan.channels.get(channel_id)
    if channel is None:
        return None
    schema_id = 0
    if channel.schema_id:
        schema = scan.schemas.get(channel.schema_id)
        if schema is None:
            return None
        schema_id = schema_ids.get(schema.id, 0)
        if not schema_id:
            schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
            schema_ids[schema.id] = schema_id
    return writer.register_channel(channel.topic, channel.message_encoding, schema_id,
                                   dict(channel.metadata))
