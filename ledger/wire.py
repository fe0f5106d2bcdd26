"""The forms ledger reads take over the network: record chunks, and JSON for the rest.

The ledger service answers catch-up and as-of queries with chunks of records in
this form (JSON would cost more than the ledger itself for scans).  A chunk is::

    magic b"SLR2" | u32 record count | records ...

and a record, all integers little-endian::

    i64 global_seq | u64 epoch | u64 seq | i64 valid_time_ns | i64 recorded_time_ns
    | u8 len(type) | u8 len(source) | u16 len(flags) | u32 len(payload)
    | u8 len(signer) | u8 len(signature) | 32 B payload_sha256 | 32 B chain_sha256
    | type | source | flags (comma-joined) | payload | signer | signature

(an unsigned record has empty signer and signature).

:func:`decode_records` raises :class:`ValueError` on anything malformed, never
returns a partial chunk.

Heads, gaps, streams, quarantine entries and stats travel as JSON objects:
``*_to_json`` gives a JSON-ready dict (bytes as hex, or base64 for raw inputs) and
``*_from_json`` the record back; these raise :class:`ValueError` on a missing or
mistyped field.
"""

from __future__ import annotations

import base64
import dataclasses
import struct
from typing import Any, Iterable

from ledger.records import Gap, Head, LedgerStats, QuarantineEntry, RecordedEvent, StreamInfo

MAGIC = b"SLR2"
_CHUNK = struct.Struct("<4sI")
_RECORD = struct.Struct("<qQQqqBBHIBB32s32s")


def encode_records(records: Iterable[RecordedEvent]) -> bytes:
    """One chunk holding ``records`` in order."""
    parts: list[bytes] = []
    n = 0
    pack = _RECORD.pack
    for r in records:
        type_b = r.type.encode()
        source_b = r.source.encode()
        flags_b = ",".join(r.flags).encode()
        signer_b = b"" if r.signer is None else r.signer.encode("ascii")
        signature = b"" if r.signature is None else r.signature
        parts.append(pack(r.global_seq, r.epoch, r.seq, r.valid_time_ns, r.recorded_time_ns,
                          len(type_b), len(source_b), len(flags_b), len(r.payload),
                          len(signer_b), len(signature), r.payload_sha256, r.chain_sha256))
        parts.append(type_b)
        parts.append(source_b)
        parts.append(flags_b)
        parts.append(r.payload)
        if signer_b:
            parts.append(signer_b)
            parts.append(signature)
        n += 1
    return _CHUNK.pack(MAGIC, n) + b"".join(parts)


def decode_records(data: bytes) -> list[RecordedEvent]:
    """Inverse of :func:`encode_records`; raises ValueError on a malformed chunk."""
    view = memoryview(data)
    if len(view) < _CHUNK.size:
        raise ValueError(f"record chunk of {len(view)} bytes is shorter than its header")
    magic, count = _CHUNK.unpack_from(view, 0)
    if magic != MAGIC:
        raise ValueError(f"record chunk has magic {bytes(magic)!r}, expected {MAGIC!r}")
    out: list[RecordedEvent] = []
    pos = _CHUNK.size
    size = _RECORD.size
    unpack = _RECORD.unpack_from
    for i in range(count):
        if pos + size > len(view):
            raise ValueError(f"record chunk truncated in record {i} of {count}")
        (global_seq, epoch, seq, valid, recorded, lt, ls, lf, lp, lk, lg,
         psha, chain) = unpack(view, pos)
        pos += size
        end = pos + lt + ls + lf + lp + lk + lg
        if end > len(view):
            raise ValueError(f"record chunk truncated in record {i} of {count}")
        type_name = bytes(view[pos:pos + lt]).decode()
        pos += lt
        source = bytes(view[pos:pos + ls]).decode()
        pos += ls
        flags_text = bytes(view[pos:pos + lf]).decode()
        pos += lf
        payload = bytes(view[pos:pos + lp])
        pos += lp
        signer = signature = None
        if lk or lg:
            signer = bytes(view[pos:pos + lk]).decode("ascii")
            signature = bytes(view[pos + lk:pos + lk + lg])
            pos += lk + lg
        flags = tuple(flags_text.split(",")) if flags_text else ()
        out.append(RecordedEvent(global_seq, type_name, source, epoch, seq, valid, recorded,
                                 payload, psha, chain, flags, signer, signature))
    if pos != len(view):
        raise ValueError(f"record chunk has {len(view) - pos} bytes after its {count} records")
    return out


# -- JSON forms ------------------------------------------------------------------------------


def head_to_json(head: Head) -> dict[str, Any]:
    """``{"global_seq", "recorded_time_ns", "chain_sha256"}`` (the chain as hex)."""
    return {"global_seq": head.global_seq, "recorded_time_ns": head.recorded_time_ns,
            "chain_sha256": head.chain_sha256.hex()}


def head_from_json(data: dict[str, Any]) -> Head:
    return _build(Head, data, chain_sha256=lambda v: bytes.fromhex(v))


def gap_to_json(gap: Gap) -> dict[str, Any]:
    return dataclasses.asdict(gap)


def gap_from_json(data: dict[str, Any]) -> Gap:
    return _build(Gap, data)


def stream_to_json(stream: StreamInfo) -> dict[str, Any]:
    return dataclasses.asdict(stream)


def stream_from_json(data: dict[str, Any]) -> StreamInfo:
    return _build(StreamInfo, data)


def quarantine_to_json(entry: QuarantineEntry) -> dict[str, Any]:
    """The entry as a dict, its raw bytes as base64 and its chain link as hex."""
    data = dataclasses.asdict(entry)
    data["raw"] = base64.b64encode(entry.raw).decode("ascii")
    data["chain_sha256"] = entry.chain_sha256.hex()
    return data


def quarantine_from_json(data: dict[str, Any]) -> QuarantineEntry:
    return _build(QuarantineEntry, data, raw=lambda v: base64.b64decode(v, validate=True),
                  chain_sha256=lambda v: bytes.fromhex(v))


def stats_to_json(stats: LedgerStats) -> dict[str, Any]:
    """The stats as ``stockpile ledger stats --json`` prints them."""
    data = dataclasses.asdict(stats)
    data["head"] = head_to_json(stats.head)
    return data


def stats_from_json(data: dict[str, Any]) -> LedgerStats:
    def span(value):
        return None if value is None else (int(value[0]), int(value[1]))

    return _build(LedgerStats, data, head=head_from_json, valid_time_range_ns=span,
                  recorded_time_range_ns=span)


def _build(cls, data: dict[str, Any], **convert):
    """``cls(**fields)`` from ``data``, each field through ``convert[name]`` if given."""
    if not isinstance(data, dict):
        raise ValueError(f"{cls.__name__}: expected a JSON object, got {type(data).__name__}")
    fields = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
                continue
            raise ValueError(f"{cls.__name__}: missing field {f.name!r}")
        value = data[f.name]
        try:
            fields[f.name] = convert[f.name](value) if f.name in convert else value
        except (TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"{cls.__name__}.{f.name}: {exc}") from None
    return cls(**fields)
