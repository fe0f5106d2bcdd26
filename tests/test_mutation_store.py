"""The append planner, the writer state and both backends' commit and read paths, on a
ledger of mixed event types: what the survivors of `make mutate` showed no test checked.

Every test runs on the in-memory store and on a real DuckDB file (reopened where the
state must survive a restart).
"""

from __future__ import annotations

import dataclasses
import hashlib
import struct

import pytest

from ledger.chain import GENESIS, chain_hash
from ledger.clock import EventClock, ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.errors import HeadWentBackwards
from ledger.memory import MemoryStore
from ledger.records import FLAG_UNKNOWN_LOT, AppendOutcome, Head, QuarantineEntry, VerifyReport
from ledger.signing import SigningPolicy, sign_event
from ledger.testing import joint_event
from ledger.testing_signing import assay, key_declared, make_keys
from schemas import pb
from schemas.events import Event, Malformed, make_event, set_timestamp_ns

BACKENDS = ["memory", "duckdb"]


def open_store(backend, tmp_path, clock):
    if backend == "memory":
        return MemoryStore(clock)
    return DuckDBStore(tmp_path / "l.duckdb", clock)


def reopen(store, clock):
    if isinstance(store, MemoryStore):
        return store
    store.close()
    return DuckDBStore(store.path, clock)


def clock_event(seq: int, t: int) -> Event:
    m = pb.Clock()
    set_timestamp_ns(m.time, t)
    return make_event(m, source="sim.clock", epoch=1, seq=seq)


def lot_event(seq: int, lot: str, t: int) -> Event:
    m = pb.LotDeclared(lot_id=lot, planned_tonnes=10.0, planned_grade={"Fe": 60.0})
    set_timestamp_ns(m.time, t)
    return make_event(m, source="plan.lots", epoch=1, seq=seq)


def assay_event(seq: int, assay: str, lot: str, t: int, analytes=None) -> Event:
    m = pb.Assay(assay_id=assay, lot_id=lot, analytes=analytes or {"Fe": 61.0},
                 status=2)  # FINAL
    set_timestamp_ns(m.window_start, t - 10)
    set_timestamp_ns(m.window_end, t - 5)
    set_timestamp_ns(m.reported_time, t)
    return make_event(m, source="lab.assays", epoch=1, seq=seq)


def mixed(store, clock):
    """joint readings of two sources interleaved with lots and assays (one of an unknown
    lot), in three batches at recorded times 100, 200, 300."""
    clock.set_ns(100)
    store.append([joint_event("a.src", 0, 10), lot_event(0, "L1", 11), joint_event("b.src", 0, 12),
                  joint_event("a.src", 1, 13)])
    clock.set_ns(200)
    store.append([assay_event(0, "A1", "L1", 5), joint_event("b.src", 1, 14),
                  assay_event(1, "A2", "L9", 30)])
    clock.set_ns(300)
    store.append([joint_event("a.src", 2, 15), lot_event(1, "L9", 1)])


@pytest.fixture(params=BACKENDS)
def backend(request):
    return request.param


def test_read_filters_types_and_sources_of_a_mixed_ledger(backend, tmp_path):
    clock = ManualClock(0)
    store = open_store(backend, tmp_path, clock)
    mixed(store, clock)
    assert [r.global_seq for r in store.read(types=["lot_declared"])] == [1, 8]
    assert [r.global_seq for r in store.read(types=["assay", "lot_declared"])] == [1, 4, 6, 8]
    assert [r.global_seq for r in store.read(sources=["b.src"])] == [2, 5]
    assert [r.global_seq for r in store.read(sources=["a.src", "lab.assays"])] == [0, 3, 4, 6, 7]
    assert [r.global_seq for r in store.read(2, 7, types=["joint_reading"], sources=["a.src"])] == [3]
    assert [r.global_seq for r in store.read(types=[])] == []
    assert [r.global_seq for r in store.read(0, 0)] == []
    assert [r.global_seq for r in store.read(0, -3)] == []
    assert [r.global_seq for r in store.read(-5, 2)] == [0, 1]
    assert [r.global_seq for r in store.read(7, 100)] == [7, 8]
    store.close()


def test_as_of_filters_types_and_resumes_after_a_position(backend, tmp_path):
    clock = ManualClock(0)
    store = open_store(backend, tmp_path, clock)
    mixed(store, clock)
    # valid times (an assay's is its window's end): 0:10 1:11 2:12 3:13 4:0 5:14 6:25 7:15 8:1
    assert [r.global_seq for r in store.as_of(100, 10**9)] == [4, 8, 0, 1, 2, 3, 5, 7, 6]
    assert [r.global_seq for r in store.as_of(100, 250, types=["assay", "lot_declared"])] == [4, 1, 6]
    assert [r.global_seq for r in store.as_of(12, 10**9, types=["joint_reading"])] == [0, 2]
    assert [r.global_seq for r in store.as_of(13, 200, types=["joint_reading"], after=(12, 2))] == [3]
    assert [r.global_seq for r in store.as_of(100, 10**9, after=(12, 1))] == [2, 3, 5, 7, 6]
    assert [r.global_seq for r in store.as_of(100, 10**9, after=(13, 3))] == [5, 7, 6]
    assert list(store.as_of(100, 99)) == []
    store.close()


def test_rows_read_back_carry_every_field_and_the_unknown_lot_flag(backend, tmp_path):
    clock = ManualClock(0)
    store = open_store(backend, tmp_path, clock)
    mixed(store, clock)
    result = store.append([assay_event(2, "A3", "L7", 40)])
    assert result.outcomes == (AppendOutcome("appended", 9, None, None, (FLAG_UNKNOWN_LOT,)),)
    store = reopen(store, clock)
    rows = list(store.read())
    assert [r.flags for r in rows] == [(), (), (), (), (), (), (FLAG_UNKNOWN_LOT,), (), (),
                                       (FLAG_UNKNOWN_LOT,)]
    # an assay of a lot declared earlier (L1) is not flagged, nor one of a lot declared
    # by then in another batch (L9 after its lot_declared)
    assert store.append([assay_event(3, "A4", "L9", 50)]).outcomes[0].flags == ()
    [again] = store.read(10)
    assert again.flags == () and again.type == "assay" and again.source == "lab.assays"
    assert (again.epoch, again.seq, again.valid_time_ns) == (1, 3, 45)
    assert [r.recorded_time_ns for r in store.as_of(100, 10**9, types=["assay"])] == [200, 200, 300, 300]
    assert [r.flags for r in store.as_of(100, 10**9, types=["assay"])] == [
        (), (FLAG_UNKNOWN_LOT,), (FLAG_UNKNOWN_LOT,), ()]
    store.close()


def test_head_is_the_last_row_and_survives_a_reopen(backend, tmp_path):
    clock = ManualClock(0)
    store = open_store(backend, tmp_path, clock)
    assert store.head() == Head(-1, None, GENESIS)
    mixed(store, clock)
    rows = list(store.read())
    assert store.head() == Head(8, 300, rows[-1].chain_sha256)
    store = reopen(store, clock)
    assert store.head() == Head(8, 300, rows[-1].chain_sha256)
    # the writer state after a reopen: the next row chains on and gets the next number
    clock.set_ns(400)
    store.append([joint_event("b.src", 2, 16)])
    assert store.head().global_seq == 9 and store.verify().ok
    store.close()


def test_a_rejected_event_is_quarantined_with_every_field(backend, tmp_path):
    clock = ManualClock(500)
    store = open_store(backend, tmp_path, clock)
    good = joint_event("a.src", 0, 10)
    bad = Event("joint_reading", "a.src", 3, 7, 11, b"\xff\xff")  # undecodable payload
    result = store.append([good, bad])
    assert result.outcomes[1].status == "rejected"
    assert result.outcomes[1].global_seq is None and result.outcomes[1].code == "undecodable"
    detail = result.outcomes[1].detail
    assert detail and detail.startswith("payload is not a")
    store = reopen(store, clock)
    [entry] = store.quarantine()
    [row] = store.read()
    # a link of the chain after row 0, its fields as ledger/chain.py lays them out
    link = hashlib.sha256(b"".join([
        row.chain_sha256, b"Q", struct.pack("<qqq", 0, 0, 500),
        struct.pack("<Bq", 1, 3), struct.pack("<Bq", 1, 7), struct.pack("<Bq", 1, 11),
        struct.pack("<Bq", 0, 0),
        *(len(t.encode()).to_bytes(4, "little") + t.encode()
          for t in ("joint_reading", "a.src", "undecodable", detail)),
        hashlib.sha256(b"\xff\xff").digest()])).digest()
    assert entry == QuarantineEntry(0, 500, "joint_reading", "a.src", 3, 7, 11, "undecodable",
                                    detail, b"\xff\xff", None, 0, link)
    # quarantine ids go on from the stored ones after a reopen
    clock.set_ns(600)
    store.append([Malformed(b"{not json", "malformed: bad JSON", "scan", "s.src", 1, 2, 3),
                  Malformed(b"x", "no code here")])
    entries = store.quarantine()
    assert [(q.quarantine_id, q.code, q.detail, q.raw) for q in entries] == [
        (0, "undecodable", detail, b"\xff\xff"), (1, "malformed", "bad JSON", b"{not json"),
        (2, "malformed", "no code here", b"x")]
    assert (entries[1].type, entries[1].source, entries[1].epoch, entries[1].seq,
            entries[1].valid_time_ns, entries[1].recorded_time_ns) == ("scan", "s.src", 1, 2, 3, 600)
    assert (entries[2].type, entries[2].source, entries[2].epoch) == ("", "", None)
    store.close()


def test_identity_numbers_that_do_not_fit_are_kept_only_in_the_raw_bytes(backend, tmp_path):
    clock = ManualClock(500)
    store = open_store(backend, tmp_path, clock)
    huge = Event("joint_reading", "a.src", 2**64, 2**70, 2**65, b"")
    neg = Event("joint_reading", "a.src", 4, -1, 9, b"")
    result = store.append([huge, neg])
    assert [o.code for o in result.outcomes] == ["bad_identity", "bad_identity"]
    a, b = store.quarantine()
    assert (a.epoch, a.seq, a.valid_time_ns) == (None, None, None)
    assert (b.epoch, b.seq, b.valid_time_ns) == (4, -1, 9)
    store.close()


def test_quarantine_time_follows_the_event_clock_and_never_goes_back(backend, tmp_path):
    store = open_store(backend, tmp_path, EventClock(start_ns=50))
    store.append([clock_event(0, 1_000), Event("joint_reading", "a.src", 1, 0, 5, b"\xff")])
    # rejected after a tick in the same batch: stamped with the tick's time
    assert [q.recorded_time_ns for q in store.quarantine()] == [1_000]
    # a preserved recorded time in the future moves the head past the clock; a later
    # rejection is stamped at the head, not before it
    e = joint_event("a.src", 1, 6)
    store.append([Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload, 5_000)])
    store.append([Event("joint_reading", "a.src", 1, 9, 7, b"\xff")])
    assert [q.recorded_time_ns for q in store.quarantine()] == [1_000, 5_000]
    store.close()


def test_a_conflict_names_the_stored_row(backend, tmp_path):
    clock = ManualClock(100)
    store = open_store(backend, tmp_path, clock)
    store.append([joint_event("a.src", 0, 1, travel_m=1.0), joint_event("a.src", 1, 2)])
    store = reopen(store, clock)
    rival = joint_event("a.src", 1, 2, travel_m=9.0)
    [outcome] = store.append([rival]).outcomes
    assert outcome == AppendOutcome("conflict", 1, "conflict",
                                    "('a.src', 1, 1) is stored as global_seq 1 with another payload")
    [entry] = store.quarantine()
    assert (entry.code, entry.existing_global_seq, entry.raw) == ("conflict", 1, rival.payload)
    store.close()


def test_a_preserved_recorded_time_before_the_head_is_refused(backend, tmp_path):
    clock = ManualClock(1_000)
    store = open_store(backend, tmp_path, clock)
    store.append([joint_event("a.src", 0, 1)])
    e = joint_event("a.src", 1, 2)
    back = Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload, 999)
    same = Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload, 1_000)
    [refused] = store.append([back]).outcomes
    assert (refused.status, refused.code) == ("rejected", "recorded_time_backwards")
    assert refused.detail == "recorded_time_ns 999 is before the ledger head's 1000"
    assert store.append([same]).outcomes[0].status == "appended"
    assert [r.recorded_time_ns for r in store.read()] == [1_000, 1_000]
    store.close()


def test_gaps_split_and_close_across_batches_and_reopens(backend, tmp_path):
    clock = ManualClock(10)
    store = open_store(backend, tmp_path, clock)
    store.append([joint_event("a.src", 0, 0), joint_event("a.src", 9, 9)])  # gap 1..8
    clock.set_ns(20)
    store.append([joint_event("a.src", 4, 4), joint_event("a.src", 12, 12)])  # 1..3, 5..8; 10..11
    store = reopen(store, clock)
    clock.set_ns(30)
    store.append([joint_event("a.src", 1, 1), joint_event("a.src", 8, 8), joint_event("a.src", 10, 10)])
    open_gaps = [(g.gap_id, g.first_seq, g.last_seq, g.opened_recorded_ns)
                 for g in store.gaps(open_only=True)]
    assert open_gaps == [(4, 2, 3, 10), (5, 5, 7, 10), (6, 11, 11, 20)]
    closed = [(g.gap_id, g.first_seq, g.last_seq, g.closed_recorded_ns)
              for g in store.gaps() if not g.is_open]
    assert {(g.source, g.epoch, g.opened_recorded_ns) for g in store.gaps() if not g.is_open} == {
        ("a.src", 1, 10), ("a.src", 1, 20)}
    assert closed == [(0, 1, 8, 20), (1, 1, 3, 30), (2, 5, 8, 30), (3, 10, 11, 30)]
    [info] = store.streams()
    assert (info.highest_contiguous_seq, info.max_seq, info.open_gaps, info.missing) == (1, 12, 3, 6)
    # a stored seq inside the old range is a duplicate, a missing one fills its gap
    assert store.append([joint_event("a.src", 4, 4)]).outcomes[0].status == "duplicate"
    assert store.append([joint_event("a.src", 3, 3)]).outcomes[0].status == "appended"
    assert [(g.first_seq, g.last_seq) for g in store.gaps(open_only=True)] == [(5, 7), (11, 11), (2, 2)]
    store.close()


def test_duplicates_are_found_in_the_store_and_in_the_batch(backend, tmp_path):
    clock = ManualClock(10)
    store = open_store(backend, tmp_path, clock)
    store.append([joint_event("a.src", s, s) for s in (0, 1, 2)] + [joint_event("b.src", 0, 0)])
    store = reopen(store, clock)
    batch = [joint_event("a.src", 1, 1), joint_event("a.src", 3, 3), joint_event("a.src", 3, 3),
             joint_event("b.src", 0, 0), joint_event("a.src", 0, 0, epoch=2)]
    result = store.append(batch)
    assert [(o.status, o.global_seq) for o in result.outcomes] == [
        ("duplicate", 1), ("appended", 4), ("duplicate", 4), ("duplicate", 3), ("appended", 5)]
    assert result.head_seq == 5
    # a batch of only duplicates writes nothing and keeps the head
    head = store.head()
    assert store.append(batch[:1]).counts["duplicate"] == 1 and store.head() == head
    store.close()


def test_a_batch_that_only_quarantines_still_commits_it(backend, tmp_path):
    clock = ManualClock(10)
    store = open_store(backend, tmp_path, clock)
    store.append([Event("joint_reading", "a.src", 1, 0, 5, b"\xff")])
    store = reopen(store, clock)
    assert len(store.quarantine()) == 1 and store.head().global_seq == -1
    store.close()


def test_lots_declared_in_an_earlier_batch_are_known_after_a_reopen(backend, tmp_path):
    clock = ManualClock(10)
    store = open_store(backend, tmp_path, clock)
    store.append([lot_event(0, "L1", 1)])
    store = reopen(store, clock)
    store.append([lot_event(1, "L2", 2), assay_event(0, "A1", "L1", 3), assay_event(1, "A2", "L2", 4),
                  assay_event(2, "A3", "L3", 5)])
    assert [r.flags for r in store.read(types=["assay"])] == [(), (), (FLAG_UNKNOWN_LOT,)]
    store.close()


def test_the_clock_learns_a_tick_only_when_it_is_newer(backend, tmp_path):
    store = open_store(backend, tmp_path, EventClock(start_ns=0))
    store.append([clock_event(0, 2_000), clock_event(1, 1_500), joint_event("a.src", 0, 1)])
    assert [r.recorded_time_ns for r in store.read()] == [2_000, 2_000, 2_000]
    store = reopen(store, EventClock(start_ns=0))
    store.append([joint_event("a.src", 1, 2)])
    assert [r.recorded_time_ns for r in store.read(3)] == [2_000]
    store.close()


def test_the_memory_store_fails_on_unknown_input():
    from ledger.errors import InterfaceError

    store = MemoryStore(ManualClock(0))
    with pytest.raises(InterfaceError, match="append takes Event or Malformed, not str"):
        store.append(["not an event"])
    store.close()
    with pytest.raises(InterfaceError, match="the memory ledger is closed"):
        store.head()


def test_a_malformed_reason_is_split_into_a_known_code_and_its_detail(backend, tmp_path):
    store = open_store(backend, tmp_path, ManualClock(10))
    reasons = ["undecodable: field 3: bad wire type", "weird: not a code", "malformed",
               "bad_identity:no space"]
    store.append([Malformed(b"x", r) for r in reasons])
    assert [(q.code, q.detail) for q in store.quarantine()] == [
        ("undecodable", "field 3: bad wire type"), ("malformed", "weird: not a code"),
        ("malformed", "malformed"), ("malformed", "bad_identity:no space")]
    store.close()


def test_quarantine_time_is_the_latest_tick_even_before_a_preserved_head(backend, tmp_path):
    clock = EventClock(start_ns=50)
    store = open_store(backend, tmp_path, clock)
    tick = clock_event(0, 1_000)
    # a tick imported with its own recorded time (500) earlier than its valid time
    store.append([Event(tick.type, tick.source, tick.epoch, tick.seq, tick.valid_time_ns,
                        tick.payload, 500)])
    store.append([Event("joint_reading", "a.src", 1, 0, 5, b"\xff")])
    store = reopen(store, clock)
    store.append([Event("joint_reading", "a.src", 1, 1, 5, b"\xff")])
    assert [q.recorded_time_ns for q in store.quarantine()] == [1_000, 1_000]
    store.close()


def test_a_payload_that_is_not_bytes_is_quarantined_with_empty_raw_bytes(backend, tmp_path):
    store = open_store(backend, tmp_path, ManualClock(10))
    e = joint_event("a.src", 0, 1)
    result = store.append([Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, 3),
                           Event(e.type, e.source, e.epoch, 1, e.valid_time_ns, bytearray(e.payload))])
    assert [(o.status, o.code) for o in result.outcomes] == [("rejected", "undecodable"),
                                                             ("appended", None)]
    [entry] = store.quarantine()
    assert (entry.raw, entry.detail) == (b"", "payload is not bytes")
    assert [r.payload for r in store.read()] == [e.payload]
    store.close()


def test_a_row_with_two_flags_reads_back_as_two(tmp_path):
    # the planner sets one flag at most; the DuckDB store keeps them comma-joined
    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(10))
    store.append([assay_event(0, "A1", "L1", 5), joint_event("a.src", 0, 1)])
    path = store.path
    store.close()
    import duckdb

    con = duckdb.connect(str(path))
    con.execute("UPDATE event_log SET flags = 'unknown_lot,late lab' WHERE global_seq = 0")
    con.close()
    store = DuckDBStore(path, ManualClock(10), read_only=True)
    assert [r.flags for r in store.read()] == [("unknown_lot", "late lab"), ()]
    assert [r.flags for r in store.as_of(10, 10)] == [("unknown_lot", "late lab"), ()]
    store.close()


def test_a_stored_event_after_a_malformed_one_in_a_batch_is_a_duplicate(backend, tmp_path):
    clock = ManualClock(10)
    store = open_store(backend, tmp_path, clock)
    e = joint_event("a.src", 0, 1)
    store.append([e])
    store = reopen(store, clock)
    result = store.append([Malformed(b"x", "malformed: junk"), e])
    assert [o.status for o in result.outcomes] == ["rejected", "duplicate"]
    store.close()


def test_stored_payloads_are_bytes_whatever_buffer_came_in(tmp_path):
    store = MemoryStore(ManualClock(10))
    e = joint_event("a.src", 0, 1)
    store.append([Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, bytearray(e.payload))])
    [row] = store.read()
    assert type(row.payload) is bytes and row.payload == e.payload


def test_events_after_a_preserved_tick_are_stamped_with_the_tick(backend, tmp_path):
    store = open_store(backend, tmp_path, EventClock(start_ns=50))
    # no tick yet: the clock's start, whatever the event's own valid time
    store.append([joint_event("a.src", 0, 5)])
    tick = clock_event(0, 1_000)
    store.append([Event(tick.type, tick.source, tick.epoch, tick.seq, tick.valid_time_ns,
                        tick.payload, 500)])
    store.append([joint_event("a.src", 1, 6)])
    assert [r.recorded_time_ns for r in store.read()] == [50, 500, 1_000]
    store.close()


def test_the_assays_view_gains_a_column_for_each_new_analyte(tmp_path):
    # the writer recreates the views in the batch that first stores an analyte
    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(10))
    store.append([lot_event(0, "L1", 1), assay_event(0, "A1", "L1", 20, {"Fe": 61.0}),
                  joint_event("a.src", 0, 2)])
    store.append([assay_event(1, "A2", "L1", 30, {"SiO2": 4.0})])
    store.append([assay_event(2, "A3", "L1", 40, {"Fe": 60.0})])
    store.append([assay_event(3, "A4", "L1", 50, {"P": 0.1, "Fe": 59.0})])
    con = store._con
    names = [d[0] for d in con.execute("SELECT * FROM assays LIMIT 0").description]
    assert {"Fe", "SiO2", "P"} <= set(names)
    rows = con.execute('SELECT assay_id, "Fe", "SiO2", "P" FROM assays ORDER BY assay_id').fetchall()
    assert rows == [("A1", 61.0, None, None), ("A2", None, 4.0, None), ("A3", 60.0, None, None),
                    ("A4", 59.0, None, 0.1)]
    store.close()


def test_a_failed_commit_leaves_the_writer_state_as_it_was(tmp_path):
    # the event_log table renamed behind the store's back: the batch's INSERT fails, so the
    # lot it declared must stay unknown (the planner copies the known lots before changing them)
    from ledger.errors import DatabaseError

    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(10))
    store.append([lot_event(0, "L1", 1)])
    store._con.execute("ALTER TABLE event_log RENAME TO event_log_away")
    with pytest.raises(DatabaseError):
        store.append([lot_event(1, "L2", 2)])
    store._con.execute("ALTER TABLE event_log_away RENAME TO event_log")
    assert store.head().global_seq == 0
    result = store.append([assay_event(0, "A1", "L1", 3), assay_event(1, "A2", "L2", 4)])
    assert [o.flags for o in result.outcomes] == [(), (FLAG_UNKNOWN_LOT,)]
    assert [r.global_seq for r in store.read()] == [0, 1, 2] and store.verify().ok
    store.close()


def test_an_assay_without_analytes_is_stored(tmp_path):
    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(10))
    m = pb.Assay(assay_id="A0", lot_id="L1", status=2)
    set_timestamp_ns(m.window_start, 1)
    set_timestamp_ns(m.window_end, 2)
    result = store.append([make_event(m, source="lab.assays", epoch=1, seq=0)])
    assert result.outcomes[0].status == "appended"
    assert [r.type for r in store.read()] == ["assay"]
    store.close()


def test_a_ledger_whose_gapped_stream_lost_its_rows_opens_and_fails_verify(tmp_path):
    # rows deleted behind the ledger's back (the last ones: the chain of the rest still
    # holds), their stream's open gap left: the writer state is rebuilt from the gap alone
    # (no stored row, max seq -1), so the file opens for writing and for reading, and
    # verify names the gap with no rows above it
    path = tmp_path / "l.duckdb"
    store = DuckDBStore(path, ManualClock(10))
    store.append([joint_event("a.src", 0, 0), joint_event("b.src", 0, 1), joint_event("b.src", 3, 2)])
    store._con.execute("DELETE FROM event_log WHERE source = 'b.src'")
    store.close()
    # the head sidecar saw the lost rows: a writer opens only once a human accepts the loss
    with pytest.raises(HeadWentBackwards, match="global_seq 2"):
        DuckDBStore(path, ManualClock(20))
    for read_only in (False, True):
        store = DuckDBStore(path, ManualClock(20), read_only=read_only,
                            accept_loss=not read_only)
        infos = [(i.source, i.max_seq, i.open_gaps, i.missing) for i in store.streams()]
        assert infos == [("a.src", 0, 0, 0), ("b.src", -1, 1, 2)]
        report = store.verify()
        assert not report.ok and "b.src" in report.problem
        store.close()


# -- quarantine links, signatures and the key registry ----------------------------------------

LINK_MISMATCH = "chain hash mismatch (the entry was edited, or one before it deleted)"


def edit_quarantine(store, sql: str, entry_edit):
    """Edit the stored quarantine entries behind the store's back (``sql`` on the DuckDB
    file, ``entry_edit`` on the memory store's list)."""
    if isinstance(store, MemoryStore):
        store._quarantine[:] = [entry_edit(q) for q in store._quarantine]
    else:
        store._con.execute(sql)
    return store


def test_verify_names_an_edited_entry_before_a_row_with_the_rows_checked(backend, tmp_path):
    store = open_store(backend, tmp_path, ManualClock(10))
    store.append([joint_event("a.src", 0, 1), joint_event("a.src", 1, 2)])
    store.append([Malformed(raw=b"\x01", reason="not json")])
    store.append([joint_event("a.src", 2, 3)])
    assert [q.after_global_seq for q in store.quarantine()] == [1]
    assert store.verify() == VerifyReport(True, 3)
    edit_quarantine(store, "UPDATE quarantine SET detail = detail || 'x'",
                    lambda q: dataclasses.replace(q, detail=q.detail + "x"))
    assert store.verify() == VerifyReport(False, 2, None, f"quarantine entry 0: {LINK_MISMATCH}")
    store.close()


@pytest.mark.parametrize("edit", ["detail", "placed_later"])
def test_verify_names_an_entry_after_the_last_row_with_the_rows_checked(backend, tmp_path, edit):
    store = open_store(backend, tmp_path, ManualClock(10))
    store.append([joint_event("a.src", 0, 1), joint_event("a.src", 1, 2)])
    store.append([Malformed(raw=b"\x01", reason="not json")])
    assert store.verify() == VerifyReport(True, 2)
    if edit == "detail":
        edit_quarantine(store, "UPDATE quarantine SET detail = detail || 'x'",
                        lambda q: dataclasses.replace(q, detail=q.detail + "x"))
        expected = f"quarantine entry 0: {LINK_MISMATCH}"
    else:  # placed after a row the ledger does not hold (its link is not even checked)
        edit_quarantine(store, "UPDATE quarantine SET after_global_seq = 5",
                        lambda q: dataclasses.replace(q, after_global_seq=5))
        expected = "quarantine entry 0 is placed after global_seq 5, the ledger holds 2 rows"
    assert store.verify() == VerifyReport(False, 2, None, expected)
    store.close()


def test_verify_rechecks_the_anchor_against_the_admin_key_the_site_pins(tmp_path):
    # a ledger written without a pinned admin key took the first self-declared one; opened
    # by a site that pins another admin key, verify refuses the anchor (as the writer would)
    keys = make_keys(tmp_path / "keys", "rogue", "lab", "admin")
    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(1_000))
    rogue, lab = keys["rogue"], keys["lab"]
    result = store.append([key_declared(rogue, rogue, "admin", "rogue", 0, 10),
                           key_declared(rogue, lab, "lab", "lab1", 1, 20),
                           sign_event(assay(0, 1_000), lab)])
    assert [o.status for o in result.outcomes] == ["appended"] * 3
    assert store.verify() == VerifyReport(True, 3, signatures=3)
    store.close()
    pinned = DuckDBStore(tmp_path / "l.duckdb", ManualClock(2_000), read_only=True,
                         signing=SigningPolicy(frozenset(), keys["admin"].key_id))
    report = pinned.verify()
    assert (report.ok, report.rows_checked, report.first_bad_seq) == (False, 0, 0)
    assert report.problem.startswith("signature: unknown_key: self-declared admin key"), report
    pinned.close()


def test_signatures_are_checked_on_every_signed_event_and_key_declaration(backend, tmp_path):
    # no signing policy: a signed event of any type is still checked, and a key declaration
    # must be signed whatever the policy
    keys = make_keys(tmp_path / "keys", "admin", "lab", "stranger")
    store = open_store(backend, tmp_path, ManualClock(1_000))
    admin, lab = keys["admin"], keys["lab"]
    unsigned_declaration = dataclasses.replace(key_declared(admin, lab, "lab", "lab1", 1, 20),
                                               signer=None, signature=None)
    result = store.append([key_declared(admin, admin, "admin", "site admin", 0, 10),
                           unsigned_declaration,
                           sign_event(joint_event("a.src", 0, 5), keys["stranger"]),
                           joint_event("a.src", 1, 6)])
    assert [(o.status, o.code) for o in result.outcomes] == [
        ("appended", None), ("rejected", "unsigned"), ("rejected", "unknown_key"),
        ("appended", None)]
    assert [(r.type, r.source, r.seq) for r in store.read()] == [
        ("source_key_declared", "site-admin", 0), ("joint_reading", "a.src", 1)]
    # the lab key was never declared: its signature is refused
    assert store.append([sign_event(assay(0, 1_000), lab)]).outcomes[0].code == "unknown_key"
    assert store.verify().ok
    store.close()


def test_a_failed_commit_forgets_the_keys_its_batch_declared(tmp_path):
    # the planner copies the key registry before it learns a key: a batch whose INSERT
    # fails must leave the writer's registry without the key it declared
    from ledger.errors import DatabaseError

    keys = make_keys(tmp_path / "keys", "admin", "lab")
    admin, lab = keys["admin"], keys["lab"]
    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(1_000))
    assert store.append([key_declared(admin, admin, "admin", "site admin", 0, 10)]).appended == 1
    store._con.execute("ALTER TABLE event_log RENAME TO event_log_away")
    with pytest.raises(DatabaseError):
        store.append([key_declared(admin, lab, "lab", "lab1", 1, 20)])
    store._con.execute("ALTER TABLE event_log_away RENAME TO event_log")
    result = store.append([sign_event(assay(0, 1_000), lab)])
    assert result.outcomes[0].code == "unknown_key"
    # declared again (the same seq: the failed batch stored nothing), the key signs
    result = store.append([key_declared(admin, lab, "lab", "lab1", 1, 20),
                           sign_event(assay(1, 1_000), lab)])
    assert [o.status for o in result.outcomes] == ["appended", "appended"]
    assert store.verify() == VerifyReport(True, 3, signatures=3)
    store.close()


@pytest.mark.parametrize("layout", ["entry_after_head", "entry_before_head", "entry_only"])
def test_a_reopened_ledger_chains_its_next_row_from_the_last_link(tmp_path, layout):
    # the writer state rebuilt on opening: the next row's previous link is the last
    # quarantine entry's when it was stored after the head row, else the head row's
    path = tmp_path / "l.duckdb"
    store = DuckDBStore(path, ManualClock(10))
    bad = Malformed(raw=b"\x01", reason="not json")
    batches = {"entry_after_head": [[joint_event("a.src", 0, 1)], [bad]],
               "entry_before_head": [[bad], [joint_event("a.src", 0, 1)]],
               "entry_only": [[bad]]}[layout]
    for batch in batches:
        store.append(batch)
    [entry] = store.quarantine()
    rows = list(store.read())
    last = entry.chain_sha256 if layout != "entry_before_head" else rows[-1].chain_sha256
    store.close()
    store = DuckDBStore(path, ManualClock(20))
    event = joint_event("a.src", 1, 2)
    assert store.append([event]).outcomes[0].status == "appended"
    row = list(store.read())[-1]
    assert row.chain_sha256 == chain_hash(last, len(rows), event.type, event.source, event.epoch,
                                          event.seq, event.valid_time_ns, 20,
                                          hashlib.sha256(event.payload).digest())
    assert store.verify() == VerifyReport(True, len(rows) + 1)
    store.close()
