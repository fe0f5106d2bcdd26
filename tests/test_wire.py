"""ledger.wire: the binary record chunks the ledger service serves, and its promise to
reject a malformed chunk with ValueError, never returning part of one."""

from __future__ import annotations

import hashlib

import pytest

from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.records import RecordedEvent
from ledger.testing import joint_event
from ledger.wire import MAGIC, decode_records, encode_records


def record(n: int, *, type_name="joint_reading", source="a.src", flags=(), payload=b"p") -> RecordedEvent:
    return RecordedEvent(n, type_name, source, 2**40 + n, 7 + n, -5 + n, 1_000 + n, payload,
                         hashlib.sha256(payload).digest(), bytes([n]) * 32, flags)


RECORDS = [record(0), record(1, source="grü.src", flags=("unknown_lot",), payload=b""),
           record(2, type_name="assay", flags=("a", "b"), payload=bytes(range(256)))._replace(
               signer="0123abcd" * 4, signature=bytes(range(64)))]


def by_hand(r: RecordedEvent) -> bytes:
    """One record as the module docstring lays it out, little-endian."""
    t, s, f = r.type.encode(), r.source.encode(), ",".join(r.flags).encode()
    k, g = (r.signer or "").encode(), r.signature or b""
    return (r.global_seq.to_bytes(8, "little", signed=True) + r.epoch.to_bytes(8, "little")
            + r.seq.to_bytes(8, "little") + r.valid_time_ns.to_bytes(8, "little", signed=True)
            + r.recorded_time_ns.to_bytes(8, "little", signed=True)
            + bytes([len(t), len(s)]) + len(f).to_bytes(2, "little")
            + len(r.payload).to_bytes(4, "little") + bytes([len(k), len(g)])
            + r.payload_sha256 + r.chain_sha256 + t + s + f + r.payload + k + g)


def test_a_chunk_is_the_documented_layout_and_decodes_back():
    chunk = encode_records(RECORDS)
    assert chunk == b"SLR2" + (3).to_bytes(4, "little") + b"".join(by_hand(r) for r in RECORDS)
    assert decode_records(chunk) == RECORDS
    assert decode_records(encode_records([])) == [] and encode_records([]) == MAGIC + bytes(4)


def test_rows_of_a_real_ledger_survive_the_wire(tmp_path):
    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(5))
    store.append([joint_event("a.src", i, i, travel_m=i) for i in range(20)])
    rows = list(store.read())
    assert decode_records(encode_records(rows)) == rows
    assert decode_records(memoryview(encode_records(rows))) == rows
    store.close()


CHUNK = encode_records(RECORDS)
FIRST = len(by_hand(RECORDS[0]))


@pytest.mark.parametrize("data,words", [
    (b"", "shorter than its header"),
    (CHUNK[:7], "shorter than its header"),
    (b"SLR1" + CHUNK[4:], "magic b'SLR1'"),
    (b"slr1" + CHUNK[4:], "magic"),
    (CHUNK[:8 + 10], "truncated in record 0 of 3"),                 # inside a record header
    (CHUNK[:8 + 100], "truncated in record 0 of 3"),                # inside its names/payload
    (CHUNK[:8 + FIRST + 5], "truncated in record 1 of 3"),
    (CHUNK[:-1], "truncated in record 2 of 3"),
    (MAGIC + (4).to_bytes(4, "little") + CHUNK[8:], "truncated in record 3 of 4"),   # count too high
    (MAGIC + (2).to_bytes(4, "little") + CHUNK[8:], "after its 2 records"),          # count too low
    (CHUNK + b"\0", "1 bytes after its 3 records"),
    (MAGIC + bytes(4) + b"junk", "4 bytes after its 0 records"),
])
def test_a_malformed_chunk_is_refused(data, words):
    with pytest.raises(ValueError, match="record chunk") as info:
        decode_records(data)
    assert words in str(info.value)


def test_every_shortened_chunk_is_refused():
    # no prefix of a chunk decodes: the promise is never a partial chunk
    for end in range(len(CHUNK)):
        with pytest.raises(ValueError):
            decode_records(CHUNK[:end])


def test_a_length_that_points_past_the_end_is_refused():
    # the payload length of the last record claims one byte more than is there
    last = 8 + FIRST + len(by_hand(RECORDS[1]))
    length_at = last + 8 * 5 + 4
    n = int.from_bytes(CHUNK[length_at:length_at + 4], "little")
    bad = CHUNK[:length_at] + (n + 1).to_bytes(4, "little") + CHUNK[length_at + 4:]
    with pytest.raises(ValueError, match="truncated in record 2 of 3"):
        decode_records(bad)
