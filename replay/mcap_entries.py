"""The stockpile events of an MCAP file: identities from channels, malformed samples kept.

:func:`read_entries` turns the messages of a :class:`~replay.mcap_scan.McapScan` into
:class:`Entry` items (type, source, epoch, sequence, both times); a channel's
:class:`Identity` comes from its topic, schema and metadata (:func:`resolve_channel`),
and messages on channels that are not stockpile event channels are counted, not
yielded; the ledger's checkpoints (:func:`ledger.checkpoint.is_checkpoint_channel`) are
neither events nor unknown, and are passed over.  :func:`malformed_from_attachment` reads back a sample the recorder kept as
``stockpile.malformed/<n>``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Callable, Iterator, NamedTuple

from ledger.checkpoint import is_checkpoint_channel
from replay.mcap_format import ENCODING, MALFORMED_PREFIX, SEQ_LOW_BITS, from_u64
from replay.mcap_records import AttachmentRecord, ChannelInfo, RawMessage, SchemaInfo
from replay.mcap_scan import McapScan
from schemas.events import EVENT_TYPES, KEY_PREFIX, SCHEMA_VERSION, parse_key_expr

__all__ = ["Entry", "Identity", "MalformedSample", "malformed_from_attachment", "read_entries",
           "resolve_channel"]


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
    ``scan.report.unknown`` and skipped; checkpoint messages are skipped uncounted.  ``topics`` keeps only matching topics.
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
    if is_checkpoint_channel(channel.topic, channel.message_encoding):
        return None     # the ledger's checkpoints: kept in the file, not events
    return resolve_channel(channel, scan.schemas.get(channel.schema_id))
