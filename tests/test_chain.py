"""The hash chain (ledger.chain) against its documented format, computed here by hand.

The expected digests are laid out byte by byte from the format in ledger/chain.py's
docstring with hashlib and int.to_bytes, never with ledger.chain, so a change of the
format or a field left out of the hash fails here.  Tamper cases on stored rows are in the
backend contract (ledger.testing: every hashed field, whole rows, first and last rows).
"""

from __future__ import annotations

import hashlib

import pytest

from ledger.chain import GENESIS, chain_hash, payload_hash, quarantine_hash
from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.memory import MemoryStore
from ledger.testing import joint_event


def by_hand(previous: bytes, global_seq: int, type_name: str, source: str, epoch: int,
            seq: int, valid_ns: int, recorded_ns: int, payload: bytes) -> bytes:
    """chain[n] = sha256(chain[n-1] || global_seq, epoch, seq, valid_time_ns,
    recorded_time_ns (little-endian i64) || len(type) type || len(source) source ||
    sha256(payload)), lengths as little-endian u16 of the UTF-8 bytes."""
    out = bytearray(previous)
    for value in (global_seq, epoch, seq, valid_ns, recorded_ns):
        out += value.to_bytes(8, "little", signed=True)
    for text in (type_name, source):
        raw = text.encode("utf-8")
        out += len(raw).to_bytes(2, "little") + raw
    out += hashlib.sha256(payload).digest()
    return hashlib.sha256(bytes(out)).digest()


# one row's fields: non-ASCII in the source (length in bytes, not characters), a negative
# valid time (signed), an epoch beyond 32 bits
ROW = dict(global_seq=7, type_name="joint_reading", source="bwr1.jöint", epoch=2**40 + 3,
           seq=12, valid_ns=-5, recorded_ns=1_793_491_200_000_000_123)
PAYLOAD = b"\x08\x01payload"
PREVIOUS = bytes(range(32))
# by_hand(PREVIOUS, **ROW, payload=PAYLOAD), written down when the test was made: the
# format of every ledger ever written, so it may never change
KNOWN_HEX = "8bb7ae8fe17e9399f1fdf9b2529e5164350071b77e4414f71e117518c90237cf"


def call(previous=PREVIOUS, payload=PAYLOAD, **fields):
    row = dict(ROW, **fields)
    return chain_hash(previous, row["global_seq"], row["type_name"], row["source"],
                      row["epoch"], row["seq"], row["valid_ns"], row["recorded_ns"],
                      hashlib.sha256(payload).digest())


def test_the_chain_hash_is_the_documented_layout():
    assert call() == by_hand(PREVIOUS, **ROW, payload=PAYLOAD)
    assert by_hand(PREVIOUS, **ROW, payload=PAYLOAD).hex() == KNOWN_HEX
    assert len(GENESIS) == 32 and GENESIS == b"\0" * 32
    assert payload_hash(PAYLOAD) == hashlib.sha256(PAYLOAD).digest()


@pytest.mark.parametrize("field,value", [
    ("global_seq", 8), ("type_name", "joint_readinh"), ("source", "bwr1.jöinu"),
    ("epoch", 2**40 + 4), ("seq", 13), ("valid_ns", -4), ("recorded_ns", 1_793_491_200_000_000_124),
])
def test_every_field_changes_the_chain_value(field, value):
    assert call(**{field: value}) != call()
    assert call(**{field: value}) == by_hand(PREVIOUS, **dict(ROW, **{field: value}), payload=PAYLOAD)


def test_the_payload_and_the_previous_value_change_the_chain_value():
    assert call(payload=PAYLOAD + b"\0") != call()
    assert call(previous=GENESIS) != call()
    assert call(previous=GENESIS) == by_hand(GENESIS, **ROW, payload=PAYLOAD)


def test_the_names_are_length_prefixed():
    # without the lengths ("ab", "c") and ("a", "bc") would hash alike
    assert call(type_name="ab", source="c") != call(type_name="a", source="bc")
    assert call(type_name="ab", source="c") == by_hand(PREVIOUS, **dict(ROW, type_name="ab", source="c"),
                                                       payload=PAYLOAD)


@pytest.mark.parametrize("backend", ["memory", "duckdb"])
def test_a_ledger_stores_the_chain_computed_by_hand(backend, tmp_path):
    clock = ManualClock(1_000)
    store = MemoryStore(clock) if backend == "memory" else DuckDBStore(tmp_path / "l.duckdb", clock)
    events = [joint_event("a.src", 0, 100, travel_m=1.0), joint_event("b.src", 4, 50, epoch=9)]
    store.append(events[:1])
    clock.set_ns(2_000)
    store.append(events[1:])
    previous = GENESIS
    expected = []
    for n, (e, recorded) in enumerate(zip(events, (1_000, 2_000))):
        previous = by_hand(previous, n, e.type, e.source, e.epoch, e.seq, e.valid_time_ns,
                           recorded, e.payload)
        expected.append(previous)
    rows = list(store.read())
    assert [r.chain_sha256 for r in rows] == expected
    assert [r.payload_sha256 for r in rows] == [hashlib.sha256(e.payload).digest() for e in events]
    assert store.head().chain_sha256 == expected[-1]
    store.close()


# -- quarantine entries: links of the same chain -------------------------------------------

def quarantine_by_hand(previous: bytes, quarantine_id: int, after_global_seq: int,
                       recorded_ns: int, optional: tuple, texts: tuple[bytes, ...],
                       raw: bytes) -> bytes:
    """link = sha256(previous || b"Q" || quarantine_id, after_global_seq, recorded_time_ns
    (little-endian i64) || epoch, seq, valid_time_ns, existing_global_seq (each a presence
    byte then i64; absent: 0 then eight zero bytes) || len(type) type || len(source) source
    || len(code) code || len(detail) detail (lengths little-endian u32, the texts given here
    as their UTF-8 bytes, lone surrogates kept) || sha256(raw))."""
    out = bytearray(previous) + b"Q"
    for value in (quarantine_id, after_global_seq, recorded_ns):
        out += value.to_bytes(8, "little", signed=True)
    for value in optional:
        out += b"\0" + bytes(8) if value is None else b"\1" + value.to_bytes(8, "little", signed=True)
    for raw_text in texts:
        out += len(raw_text).to_bytes(4, "little") + raw_text
    out += hashlib.sha256(raw).digest()
    return hashlib.sha256(bytes(out)).digest()


def test_a_quarantine_link_is_the_documented_layout():
    # a conflict (existing global seq set) of a source with non-ASCII and a detail with a
    # lone surrogate (as text decoded with surrogateescape carries it): encoded, not refused
    link = quarantine_hash(PREVIOUS, 3, 7, 1_793_491_200_000_000_123, 2**40 + 3, 12, -5, 6,
                           "joint_reading", "bwr1.jöint", "conflict", "bad \udcff byte", b"\x08raw")
    assert link == quarantine_by_hand(
        PREVIOUS, 3, 7, 1_793_491_200_000_000_123, (2**40 + 3, 12, -5, 6),
        (b"joint_reading", b"bwr1.j\xc3\xb6int", b"conflict", b"bad \xed\xb3\xbf byte"), b"\x08raw")
    # the stored existing global seq is part of the link: present (even 0) or absent differ
    without = quarantine_hash(PREVIOUS, 3, 7, 1_793_491_200_000_000_123, 2**40 + 3, 12, -5, None,
                              "joint_reading", "bwr1.jöint", "conflict", "bad \udcff byte", b"\x08raw")
    assert without != link
    assert without == quarantine_by_hand(
        PREVIOUS, 3, 7, 1_793_491_200_000_000_123, (2**40 + 3, 12, -5, None),
        (b"joint_reading", b"bwr1.j\xc3\xb6int", b"conflict", b"bad \xed\xb3\xbf byte"), b"\x08raw")
    zero = quarantine_hash(GENESIS, 0, -1, 5, None, None, None, 0, "", "", "malformed", "", b"")
    assert zero == quarantine_by_hand(GENESIS, 0, -1, 5, (None, None, None, 0),
                                      (b"", b"", b"malformed", b""), b"")
    assert zero != quarantine_hash(GENESIS, 0, -1, 5, None, None, None, None, "", "", "malformed",
                                   "", b"")
