"""Writing stockpile events to MCAP with this project's conventions (:mod:`replay.mcap_format`).

:class:`EventWriter` writes one file: zstd chunks with CRCs, one channel per (topic,
source epoch) with the event's identity in its metadata (:func:`channel_metadata`),
the protobuf schemas of the event types (:func:`schema_of`), metadata records,
samples that were not events kept as ``stockpile.malformed/<n>`` attachments, the
ledger's checkpoints, byte for byte, on a schema-less JSON channel
(:meth:`EventWriter.write_checkpoint`, :mod:`ledger.checkpoint`), and a signed event's
signer and signature on the companion signature channel of its event channel
(:meth:`EventWriter.write_signature`, :func:`signature_channel_metadata`), just before
the event itself.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import IO

from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from ledger.checkpoint import MCAP_ENCODING as CHECKPOINT_ENCODING
from replay.mcap_format import (
    DEFAULT_CHUNK_BYTES,
    ENCODING,
    MALFORMED_MEDIA_TYPE,
    MALFORMED_PREFIX,
    MASK64,
    SEQ_LOW_BITS,
    SEQ_LOW_MASK,
    SIGNATURE_ENCODING,
    SIGNATURE_KIND,
    SIGNATURE_SUFFIX,
    encode_signature,
    library_id,
)
from schemas.events import EVENT_TYPES, key_expr

__all__ = ["EventWriter", "channel_metadata", "schema_of", "signature_channel_metadata"]


@lru_cache(maxsize=None)
def schema_of(type_name: str) -> tuple[str, bytes]:
    """``(full message name, serialized FileDescriptorSet)`` of an event type."""
    cls = EVENT_TYPES[type_name]
    return cls.DESCRIPTOR.full_name, build_file_descriptor_set(cls).SerializeToString()


def channel_metadata(type_name: str, source: str, epoch: int, seq_high: int = 0) -> dict[str, str]:
    """The metadata of the channel carrying ``(type, source, epoch)`` events."""
    meta = {"type": type_name, "source": source, "epoch": str(int(epoch))}
    if seq_high:
        meta["seq_high"] = str(int(seq_high))
    return meta


def signature_channel_metadata(type_name: str, source: str, epoch: int,
                               seq_high: int = 0) -> dict[str, str]:
    """The metadata of the signature channel beside the ``(type, source, epoch)`` channel."""
    return {"kind": SIGNATURE_KIND, **channel_metadata(type_name, source, epoch, seq_high)}


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
        self.checkpoints = 0
        self.signatures = 0
        self._checkpoint_channels: dict[str, int] = {}
        self._signature_channels: dict[tuple[str, int, int], int] = {}
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

    def signature_channel_id(self, topic: str, type_name: str, source: str, epoch: int,
                             seq_high: int = 0) -> int:
        """The signature channel beside the event channel of ``(topic, epoch, seq_high)``
        (topic ``<topic>/@signature``, schema-less JSON), registered on first use."""
        key = (topic, epoch, seq_high)
        channel_id = self._signature_channels.get(key)
        if channel_id is None:
            channel_id = self._writer.register_channel(
                topic=topic + SIGNATURE_SUFFIX, message_encoding=SIGNATURE_ENCODING, schema_id=0,
                metadata=signature_channel_metadata(type_name, source, epoch, seq_high))
            self._signature_channels[key] = channel_id
        return channel_id

    # -- records ----------------------------------------------------------------------

    def write(self, topic: str, type_name: str, source: str, epoch: int, seq: int,
              valid_time_ns: int, payload: bytes, log_time_ns: int,
              signer: str | None = None, signature: bytes | None = None) -> None:
        """One event on ``topic`` (its key expression); ``log_time_ns`` in site time.
        A signed event (``signer`` and ``signature``) has its signature message written
        first (:meth:`write_signature`)."""
        channel_id = self._channels.get((topic, epoch, seq >> SEQ_LOW_BITS))
        if channel_id is None:
            channel_id = self.channel_id(topic, type_name, source, epoch, seq >> SEQ_LOW_BITS)
        if signer is not None and signature is not None:
            self.write_signature(topic, type_name, source, epoch, seq, valid_time_ns,
                                 log_time_ns, signer, signature)
        self._writer.add_message(channel_id, log_time_ns & MASK64, payload,
                                 valid_time_ns & MASK64, seq & SEQ_LOW_MASK)
        self.messages += 1

    def write_signature(self, topic: str, type_name: str, source: str, epoch: int, seq: int,
                        valid_time_ns: int, log_time_ns: int, signer: str,
                        signature: bytes) -> None:
        """The signature message of the event ``(topic, epoch, seq)``: on its signature
        channel, with the event's sequence, log and publish times; written before the
        event so that a reader in file order holds it when the event comes."""
        channel_id = self.signature_channel_id(topic, type_name, source, epoch,
                                               seq >> SEQ_LOW_BITS)
        self._writer.add_message(channel_id, log_time_ns & MASK64,
                                 encode_signature(signer, signature),
                                 valid_time_ns & MASK64, seq & SEQ_LOW_MASK)
        self.signatures += 1

    def write_event(self, site: str, event, log_time_ns: int) -> None:
        """A :class:`schemas.events.Event` (or a ledger row) of ``site``, with its
        signature when it is signed."""
        self.write(key_expr(site, event.type, event.source), event.type, event.source,
                   event.epoch, event.seq, event.valid_time_ns, event.payload, log_time_ns,
                   event.signer, event.signature)

    def write_checkpoint(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        """A ledger checkpoint as received on ``topic`` (``stockpile/<site>/@ledger/checkpoint``):
        its JSON bytes unchanged, on a schema-less channel with message encoding ``json``;
        the message's sequence counts the file's checkpoints, both times are ``log_time_ns``.
        Not an event: readers of events skip the channel."""
        channel_id = self._checkpoint_channels.get(topic)
        if channel_id is None:
            channel_id = self._writer.register_channel(
                topic=topic, message_encoding=CHECKPOINT_ENCODING, schema_id=0,
                metadata={"kind": "ledger.checkpoint"})
            self._checkpoint_channels[topic] = channel_id
        self._writer.add_message(channel_id, log_time_ns & MASK64, bytes(payload),
                                 log_time_ns & MASK64, self.checkpoints & SEQ_LOW_MASK)
        self.checkpoints += 1

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
