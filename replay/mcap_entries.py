"""The stockpile events of an MCAP file: identities from channels, malformed samples kept.

:func:`read_entries` turns the messages of a :class:`~replay.mcap_scan.McapScan` into
:class:`Entry` items (type, source, epoch, sequence, both times); a channel's
:class:`Identity` comes from its topic, schema and metadata (:func:`resolve_channel`),
and messages on channels that are not stockpile event channels are counted, not
yielded; the ledger's checkpoints (:func:`ledger.checkpoint.is_checkpoint_channel`) are
neither events nor unknown, and are passed over.  A signed event's signer and signature
come from the message on its companion signature channel (:func:`resolve_signature_channel`)
that precedes it with the same sequence: the :class:`Entry` carries them; a file without
signature channels reads as before.  :func:`malformed_from_attachment` reads back a
sample the recorder kept as ``stockpile.malformed/<n>``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Callable, Iterator, NamedTuple

from ledger.checkpoint import is_checkpoint_channel
from replay.mcap_format import (
    ENCODING,
    MALFORMED_PREFIX,
    SEQ_LOW_BITS,
    SIGNATURE_ENCODING,
    SIGNATURE_KIND,
    SIGNATURE_SUFFIX,
    decode_signature,
    from_u64,
)
from replay.mcap_records import AttachmentRecord, ChannelInfo, RawMessage, SchemaInfo
from replay.mcap_scan import McapScan
from schemas.events import EVENT_TYPES, KEY_PREFIX, SCHEMA_VERSION, parse_key_expr

__all__ = ["Entry", "Identity", "MalformedSample", "SignatureChannel",
           "malformed_from_attachment", "read_entries", "resolve_channel",
           "resolve_signature_channel"]


class Entry(NamedTuple):
    """One event read from a file, with its identity, both times (signed ns) and, when
    it was signed, the signer's key id and the signature."""

    topic: str
    type: str
    source: str
    epoch: int
    seq: int
    valid_time_ns: int
    log_time_ns: int
    payload: bytes
    signer: str | None = None
    signature: bytes | None = None


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


def resolve_channel(channel: ChannelInfo, schema: SchemaInfo | None, *,
                    check_schema: bool = True) -> Identity | str:
    """The identity a channel carries, or why it is not a stockpile event channel
    (``check_schema=False``: from its topic and metadata only)."""
    try:
        _site, type_name, source = parse_key_expr(channel.topic)
    except ValueError:
        return f"topic is not {KEY_PREFIX}/<site>/{SCHEMA_VERSION}/<type>/<source>"
    cls = EVENT_TYPES.get(type_name)
    if cls is None:
        return f"unknown event type {type_name!r}"
    if not check_schema:
        pass
    elif schema is None or schema.encoding != ENCODING or channel.message_encoding != ENCODING:
        return "not protobuf"
    elif schema.name != cls.DESCRIPTOR.full_name:
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


@dataclass(frozen=True)
class SignatureChannel:
    """A signature channel: the topic of the event channel it accompanies, and that
    channel's identity."""

    topic: str
    identity: Identity


def is_signature_channel(channel: ChannelInfo) -> bool:
    """Whether a channel is a signature channel (:data:`SIGNATURE_KIND` in its metadata)."""
    return channel.metadata.get("kind") == SIGNATURE_KIND


def resolve_signature_channel(channel: ChannelInfo) -> SignatureChannel | str:
    """The event channel a signature channel accompanies, or why it is not a valid one."""
    if not channel.topic.endswith(SIGNATURE_SUFFIX) or channel.schema_id != 0 \
            or channel.message_encoding != SIGNATURE_ENCODING:
        return f"signature channel is not <topic>{SIGNATURE_SUFFIX}, schema-less, " \
               f"{SIGNATURE_ENCODING}"
    topic = channel.topic[:-len(SIGNATURE_SUFFIX)]
    meta = {k: v for k, v in channel.metadata.items() if k != "kind"}
    ident = resolve_channel(ChannelInfo(channel.id, 0, topic, ENCODING, meta), None,
                            check_schema=False)
    return ident if type(ident) is str else SignatureChannel(topic, ident)


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

    A signature message is held until the event of its (topic, epoch, sequence) comes,
    which then carries its signer and signature; ``topics`` selects signature channels
    by the topic of their events.  A signature message that cannot be read is counted
    in ``scan.report.unknown`` and its event read unsigned.
    """
    resolved: dict[int, Identity | SignatureChannel | str | None] = {}
    pending: dict[tuple[str, int, int], tuple[str, bytes]] = {}
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
        if type(ident) is SignatureChannel:
            _hold_signature(scan, record, ident, pending)
            continue
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
        seq = ident.seq_base | record.sequence
        signed = pending.pop((channel.topic, ident.epoch, seq), None) if pending else None
        if signed is None:
            yield Entry(channel.topic, ident.type, ident.source, ident.epoch, seq,
                        from_u64(record.publish_time), log_ns, record.data)
        else:
            yield Entry(channel.topic, ident.type, ident.source, ident.epoch, seq,
                        from_u64(record.publish_time), log_ns, record.data, *signed)


def _hold_signature(scan: McapScan, record: RawMessage, channel: SignatureChannel,
                    pending: dict[tuple[str, int, int], tuple[str, bytes]]) -> None:
    """Keep a signature message for its event (or count it as unreadable)."""
    try:
        signed = decode_signature(record.data)
    except ValueError as exc:
        scan.report.unknown[(channel.topic + SIGNATURE_SUFFIX, "", str(exc))] += 1
        return
    ident = channel.identity
    pending[(channel.topic, ident.epoch, ident.seq_base | record.sequence)] = signed


def _resolve(scan: McapScan, channel_id: int, topics: Callable[[str], bool] | None
             ) -> Identity | SignatureChannel | str | None:
    channel = scan.channels.get(channel_id)
    if channel is None:
        return "its channel definition was lost"
    if is_signature_channel(channel):   # selected by the topic of its events
        signatures = resolve_signature_channel(channel)
        if topics is not None and not topics(
                signatures.topic if type(signatures) is SignatureChannel else channel.topic):
            return None
        return signatures
    if topics is not None and not topics(channel.topic):
        return None
    if is_checkpoint_channel(channel.topic, channel.message_encoding):
        return None     # the ledger's checkpoints: kept in the file, not events
    return resolve_channel(channel, scan.schemas.get(channel.schema_id))
