"""A compact binary form of ledger records, for reads served over the network.

The ledger service answers catch-up and as-of queries with chunks of records in
this form (JSON would cost more than the ledger itself for scans).  A chunk is::

    magic b"SLR1" | u32 record count | records ...

and a record, all integers little-endian::

    i64 global_seq | u64 epoch | u64 seq | i64 valid_time_ns | i64 recorded_time_ns
    | u8 len(type) | u8 len(source) | u16 len(flags) | u32 len(payload)
    | 32 B payload_sha256 | 32 B chain_sha256 | type | source | flags (comma-joined) | payload

:func:`decode_records` raises :class:`ValueError` on anything malformed, never
returns a partial chunk.
"""

from __future__ import annotations

import struct
from typing import Iterable

from ledger.records import RecordedEvent

MAGIC = b"SLR1"
_CHUNK = struct.Struct("<4sI")
_RECORD = struct.Struct("<qQQqqBBHI32s32s")


def encode_records(records: Iterable[RecordedEvent]) -> bytes:
    """One chunk holding ``records`` in order."""
    parts: list[bytes] = []
    n = 0
    pack = _RECORD.pack
    for r in records:
        type_b = r.type.encode()
        source_b = r.source.encode()
        flags_b = ",".join(r.flags).encode()
        parts.append(pack(r.global_seq, r.epoch, r.seq, r.valid_time_ns, r.recorded_time_ns,
                          len(type_b), len(source_b), len(flags_b), len(r.payload),
                          r.payload_sha256, r.chain_sha256))
        parts.append(type_b)
        parts.append(source_b)
        parts.append(flags_b)
        parts.append(r.payload)
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
        (global_seq, epoch, seq, valid, recorded, lt, ls, lf, lp,
         psha, chain) = unpack(view, pos)
        pos += size
        end = pos + lt + ls + lf + lp
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
        flags = tuple(flags_text.split(",")) if flags_text else ()
        out.append(RecordedEvent(global_seq, type_name, source, epoch, seq, valid, recorded,
                                 payload, psha, chain, flags))
    if pos != len(view):
        raise ValueError(f"record chunk has {len(view) - pos} bytes after its {count} records")
    return out
