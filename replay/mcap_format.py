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
signature channel   a signed event's companion: topic ``<event topic>/@signature``,
                    schema-less, message encoding ``json``, metadata ``kind`` =
                    ``stockpile.signature`` plus the event channel's ``type``,
                    ``source``, ``epoch`` (and ``seq_high``); one message per signed
                    event, written just before it with the same sequence and times,
                    holding ``{"signer": key id, "signature": base64}``
==================  =================================================================

MCAP times are unsigned; a valid or recorded time before 1970 (a negative int64) is
stored as its two's complement and read back exactly (:func:`to_u64`, :func:`from_u64`).

Files also carry metadata records (``stockpile.recording``, ``stockpile.export``,
``stockpile.miss``, ``stockpile.gap``) and, for samples that were not events (no
identity attachment, unknown type), an attachment named ``stockpile.malformed/<n>``
holding the key, the raw payload and attachment and the reason, so a recorder loses
nothing it received.

This module holds the conventions' constants and time conversions.  Writing is
:mod:`replay.mcap_writer` (:class:`~replay.mcap_writer.EventWriter`); reading is
:mod:`replay.mcap_records` (the record layout and its parsers),
:mod:`replay.mcap_scan` (:class:`~replay.mcap_scan.McapScan`, one damage-tolerant
linear pass over a file) and :mod:`replay.mcap_entries`
(:func:`~replay.mcap_entries.read_entries`: the messages as stockpile identities).
"""

from __future__ import annotations

import base64
import binascii
import json
from importlib.metadata import PackageNotFoundError, version

MAGIC = b"\x89MCAP0\r\n"
ENCODING = "protobuf"
MASK64 = (1 << 64) - 1
SEQ_LOW_BITS = 32
SEQ_LOW_MASK = (1 << SEQ_LOW_BITS) - 1
#: uncompressed bytes per chunk; a recorder also closes a chunk at every flush
DEFAULT_CHUNK_BYTES = 1 << 20
MALFORMED_PREFIX = "stockpile.malformed/"
MALFORMED_MEDIA_TYPE = "application/json"
#: a signed event's companion channel: topic = the event's topic + this suffix
SIGNATURE_SUFFIX = "/@signature"
SIGNATURE_ENCODING = "json"
SIGNATURE_KIND = "stockpile.signature"


def library_id() -> str:
    """The ``library`` string written in every file's header."""
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


def encode_signature(signer: str, signature: bytes) -> bytes:
    """A signature channel's message: ``{"signer": key id, "signature": base64}`` (the
    field names of JSON lines), compact JSON."""
    return json.dumps({"signer": signer, "signature": base64.b64encode(signature).decode()},
                      separators=(",", ":")).encode()


def decode_signature(data: bytes) -> tuple[str, bytes]:
    """Inverse of :func:`encode_signature`: ``(signer, signature)``; raises ValueError."""
    try:
        body = json.loads(data)
        signer, text = body["signer"], body["signature"]
        if not isinstance(signer, str) or not signer or not isinstance(text, str):
            raise ValueError("signer and signature must be non-empty strings")
        signature = base64.b64decode(text, validate=True)
    except (KeyError, TypeError, binascii.Error, UnicodeDecodeError) as exc:
        raise ValueError(f"not a signature message: {exc}") from None
    if not signature or len(signature) > 255 or not signer.isascii() or len(signer) > 255:
        raise ValueError("signer must be ASCII and both at most 255 bytes, signature not empty")
    return signer, signature


class McapFormatError(ValueError):
    """A file that is not an MCAP file at all (one clear line, no traceback)."""
