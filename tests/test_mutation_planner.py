"""The append planner's origins and analyte checks, and the DuckDB commit's views and head
sidecar: what the survivors of `make mutate` showed no test checked.

The planner tests run on the in-memory store and on a real DuckDB file; the views and the
head sidecar are the DuckDB store's own, read back from the file.
"""

from __future__ import annotations

import duckdb
import pytest

from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.errors import InterfaceError
from ledger.head_file import read_head
from ledger.memory import MemoryStore
from ledger.records import FLAG_UNKNOWN_LOT, AppendOutcome
from ledger.testing import joint_event
from ledger.views import ASSAY_FIXED_COLUMNS
from schemas import pb
from schemas.analytes import DEFAULT_ANALYTES, AnalytePolicy
from schemas.events import Event, make_event, set_timestamp_ns

BACKENDS = ["memory", "duckdb"]

#: a site that declares two analytes and quarantines any other
STRICT = AnalytePolicy(("Fe", "SiO2"), "quarantine")


@pytest.fixture(params=BACKENDS)
def backend(request):
    return request.param


def open_store(backend, tmp_path, clock, analytes=None):
    if backend == "memory":
        return MemoryStore(clock, analytes=analytes)
    return DuckDBStore(tmp_path / "l.duckdb", clock, analytes=analytes)


def assay_event(seq: int, assay: str, t: int, analytes: dict[str, float]) -> Event:
    """An assay of lot L1 (never declared) with ``analytes``, reported at ``t`` ns."""
    m = pb.Assay(assay_id=assay, lot_id="L1", analytes=analytes, status=2)  # FINAL
    set_timestamp_ns(m.window_start, t - 10)
    set_timestamp_ns(m.window_end, t - 5)
    set_timestamp_ns(m.reported_time, t)
    return make_event(m, source="lab.assays", epoch=1, seq=seq)


# -- origins ---------------------------------------------------------------------------------

def test_origins_prefix_each_refused_event_and_a_stored_key_is_still_found(backend, tmp_path):
    clock = ManualClock(100)
    store = open_store(backend, tmp_path, clock)
    store.append([joint_event("a.src", 0, 10), joint_event("a.src", 1, 11)])
    clock.set_ns(200)
    # a duplicate and a conflict of stored rows (found by the store's lookup), a new row
    result = store.append(
        [joint_event("a.src", 0, 10), joint_event("a.src", 1, 11, travel_m=5.0),
         joint_event("a.src", 2, 12)],
        origins=["in.jsonl:1", "in.jsonl:2", "in.jsonl:3"])
    detail = "in.jsonl:2: ('a.src', 1, 1) is stored as global_seq 1 with another payload"
    assert result.outcomes == (AppendOutcome("duplicate", 0),
                               AppendOutcome("conflict", 1, "conflict", detail),
                               AppendOutcome("appended", 2))
    [entry] = store.quarantine()
    assert (entry.code, entry.detail, entry.existing_global_seq) == ("conflict", detail, 1)
    assert [r.seq for r in store.read()] == [0, 1, 2]
    store.close()


def test_origins_of_another_length_are_refused_before_anything_is_stored(backend, tmp_path):
    clock = ManualClock(100)
    store = open_store(backend, tmp_path, clock)
    with pytest.raises(InterfaceError) as info:
        store.append([joint_event("a.src", 0, 10), joint_event("a.src", 1, 11),
                      joint_event("a.src", 2, 12)], origins=["in.jsonl:1", "in.jsonl:2"])
    assert str(info.value) == "2 origins for 3 events"
    assert store.head().global_seq == -1 and store.quarantine() == []
    store.close()


# -- the site's analyte policy -----------------------------------------------------------

def test_the_sites_analyte_policy_decides_each_assay(backend, tmp_path):
    clock = ManualClock(100)
    store = open_store(backend, tmp_path, clock, analytes=STRICT)
    result = store.append(
        [assay_event(0, "A1", 50, {"Fe": 61.0, "SiO2": 4.0}),
         assay_event(1, "A2", 60, {"Fe": 60.0, "Al2O3": 2.0})],  # Al2O3: not declared here
        origins=["lab.jsonl:7", "lab.jsonl:8"])
    detail = "lab.jsonl:8: analytes names 'Al2O3', not on the declared list (Fe,SiO2)"
    assert result.outcomes == (
        AppendOutcome("appended", 0, None, None, (FLAG_UNKNOWN_LOT,)),
        AppendOutcome("rejected", None, "unknown_analyte", detail))
    [entry] = store.quarantine()
    assert (entry.type, entry.source, entry.epoch, entry.seq, entry.valid_time_ns) == (
        "assay", "lab.assays", 1, 1, 55)
    assert (entry.code, entry.detail, entry.recorded_time_ns) == ("unknown_analyte", detail, 100)
    assert [r.seq for r in store.read()] == [0]
    store.close()


def test_without_a_policy_an_undeclared_default_analyte_is_stored(backend, tmp_path):
    # the counterpart of the strict site: the default list declares Al2O3, flags unknowns
    clock = ManualClock(100)
    store = open_store(backend, tmp_path, clock)
    result = store.append([assay_event(0, "A2", 60, {"Fe": 60.0, "Al2O3": 2.0}),
                           assay_event(1, "A3", 70, {"Zn": 0.5})])
    assert [o.status for o in result.outcomes] == ["appended", "appended"]
    assert store.quarantine() == []
    store.close()


# -- the DuckDB commit: views and the head sidecar -------------------------------------------

def test_the_assays_view_reads_every_stored_spelling_of_a_declared_analyte(tmp_path):
    # FE and sio2 spell Fe and SiO2: the writer recreates the views when a spelling first
    # appears, with every spelling stored so far (a batch without assays in between)
    path = tmp_path / "l.duckdb"
    store = DuckDBStore(path, ManualClock(100))
    store.append([assay_event(0, "A1", 50, {"FE": 62.0})])
    store.append([joint_event("a.src", 0, 10)])
    store.append([assay_event(1, "A2", 60, {"sio2": 5.0})])
    store.close()
    con = duckdb.connect(str(path), read_only=True)  # the views as the writer left them
    try:
        names = [d[0] for d in con.execute("SELECT * FROM assays LIMIT 0").description]
        assert [n for n in names if n not in ASSAY_FIXED_COLUMNS] == list(DEFAULT_ANALYTES)
        rows = con.execute('SELECT assay_id, "Fe", "SiO2", unrecognised_analytes::VARCHAR '
                           "FROM assays ORDER BY global_seq").fetchall()
    finally:
        con.close()
    assert rows == [("A1", 62.0, None, "[]"), ("A2", None, 5.0, "[]")]


def test_the_head_sidecar_records_each_committed_head(tmp_path):
    path = tmp_path / "l.duckdb"
    clock = ManualClock(100)
    store = DuckDBStore(path, clock)
    store.append([joint_event("a.src", 0, 10)])
    clock.set_ns(250)
    store.append([joint_event("a.src", 1, 11), joint_event("a.src", 2, 12)])
    head = store.head()
    sidecar = read_head(path)
    assert sidecar is not None
    assert (sidecar.global_seq, sidecar.recorded_time_ns, sidecar.chain_sha256) == (
        2, 250, head.chain_sha256)
    assert head.recorded_time_ns == 250
    store.close()
