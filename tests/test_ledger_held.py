"""Reading a ledger file that a running ledger service holds.

DuckDB lets one process write a file or many read it, never both.  The read commands
given a file held by ``stockpile service ledger`` read through the service's queryables
(the holder file beside the ledger says where), and say so in one line on stderr.
Ground truth is the same command on a byte copy of the file made before the service
opened it, read directly from DuckDB.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from ledger import LedgerLocked, open_ledger
from ledger.holder import (LedgerHolder, holder_path, open_held, read_holder, remove_holder,
                           write_holder)
from ledger.wire import (gap_from_json, gap_to_json, head_from_json, head_to_json,
                         quarantine_from_json, quarantine_to_json, stats_from_json, stats_to_json,
                         stream_from_json, stream_to_json)
from schemas.events import Event, Malformed, set_timestamp_ns
from schemas.stockpile.v1 import events_pb2 as pb
from services.ledger_client import LedgerClient, RemoteLedger
from services.publishing import EventPublisher
from test_audit import CUT, PILE, audit_ledger
from zenoh_helpers import PYTHON, client_args, open_router, stockpile, stop, wait_liveliness

SITE = "held"
T0_NS = 1_790_000_000 * 1_000_000_000


def _start_ledger(path: Path, endpoint: str, log: Path) -> subprocess.Popen:
    return stockpile("service", "ledger", "--ledger", str(path), "--site", SITE,
                     *client_args(endpoint), stderr_path=log)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def held_audit_ledger(small_yard_sim, tmp_path_factory):
    """``(held, copy, router, endpoint, service)``: the audit tests' ledger, one byte copy
    held by a running ledger service (through a router), one read directly."""
    original, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    base = tmp_path_factory.mktemp("held")
    held, copy = base / "held.duckdb", base / "copy.duckdb"
    shutil.copyfile(original, held)
    shutil.copyfile(original, copy)
    router, endpoint = open_router()
    service = _start_ledger(held, endpoint, base / "ledger.log")
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
        yield held, copy, router, endpoint, service
    finally:
        code = stop(service)
        router.close()
    assert code == 0
    assert not holder_path(held).exists(), "the service left its holder file behind"


def test_an_audit_of_a_held_ledger_reads_through_the_service(held_audit_ledger):
    held, copy, _router, endpoint, service = held_audit_ledger
    holder = read_holder(held)
    assert holder is not None and holder.pid == service.pid and holder.site == SITE
    assert holder.endpoints == (endpoint,)
    # the file really is locked: DuckDB alone cannot open it
    from ledger.duckdb_store import DuckDBStore
    with pytest.raises(LedgerLocked) as locked:
        DuckDBStore(held, read_only=True)
    assert locked.value.holder_pid == service.pid

    for args in (["audit", "cuts", "--pile", PILE, "--json", "--no-progress"],
                 ["audit", "assays", "--json"],
                 ["audit", "history", "--pile", PILE, "--every", "5min", "--json",
                  "--no-progress"]):
        through = _run(*args, "--ledger", str(held))
        direct = _run(*args, "--ledger", str(copy))
        assert through.returncode == 0 == direct.returncode, through.stderr + direct.stderr
        assert through.stdout == direct.stdout and json.loads(through.stdout)
        notes = [line for line in through.stderr.splitlines() if "reading through" in line]
        assert notes == [f"stockpile: {held} is held by the ledger service of site {SITE} "
                         f"(pid {service.pid}); reading through its queryables at {endpoint}"]
        assert "reading through" not in direct.stderr
    cuts = json.loads(_run("audit", "cuts", "--pile", PILE, "--json", "--no-progress",
                           "--ledger", str(held)).stdout)
    assert [c["cut_id"] for c in cuts["cuts"]] == [CUT]


def test_the_other_read_commands_of_a_held_ledger(held_audit_ledger, tmp_path):
    held, copy, *_ = held_audit_ledger
    for args in (["ledger", "stats", "--json"], ["ledger", "verify"],
                 ["project", "--pile", PILE, "--json"]):
        through = _run(*args, "--ledger", str(held))
        direct = _run(*args, "--ledger", str(copy))
        assert through.returncode == 0 == direct.returncode, through.stderr
        assert through.stdout == direct.stdout
    exported = [tmp_path / "held.jsonl", tmp_path / "copy.jsonl"]
    for path, out in zip((held, copy), exported):
        assert _run("ledger", "export", "--ledger", str(path), "--out", str(out)).returncode == 0
    assert exported[0].read_bytes() == exported[1].read_bytes()
    info = _run("info", str(held), "--json")
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["events"] == json.loads(_run("info", str(copy), "--json")
                                                          .stdout)["events"]


def test_sql_and_a_second_writer_name_the_service(held_audit_ledger, tmp_path):
    held, _copy, _router, _endpoint, service = held_audit_ledger
    sql = _run("sql", "--ledger", str(held), "SELECT count(*) FROM events")
    assert sql.returncode == 2 and sql.stdout == ""
    assert sql.stderr.count("\n") == 1
    assert f"held by the ledger service of site {SITE} (pid {service.pid})" in sql.stderr
    jsonl = tmp_path / "one.jsonl"
    jsonl.write_text("")
    write = _run("ledger", "import", str(jsonl), "--ledger", str(held))
    assert write.returncode == 2 and write.stderr.count("\n") == 1
    assert f"(pid {service.pid}): publish to it, or stop it first" in write.stderr


def test_a_remote_ledger_equals_the_file_page_by_page(held_audit_ledger):
    """RemoteLedger in pages of 997 records (and of 7 over a short stretch): every read
    gives what DuckDB gives."""
    held, copy, router, *_ = held_audit_ledger
    client = LedgerClient(router, SITE, timeout_s=30)
    with open_ledger(copy, read_only=True) as direct, \
            RemoteLedger(client, page_records=997) as remote, \
            RemoteLedger(client, page_records=7) as small:
        assert remote.head() == direct.head() == small.head()
        rows = list(direct.read())
        assert len(rows) > 3 * 997 and list(remote.read()) == rows
        assert list(small.read(3, 60)) == rows[3:60]
        assert list(small.read(0, types=["assay", "stack_started"])) == \
            list(direct.read(0, types=["assay", "stack_started"]))
        valid = sorted(r.valid_time_ns for r in rows)
        known = sorted(r.recorded_time_ns for r in rows)
        for v, k in ((valid[-1], known[-1]), (valid[len(valid) // 2], known[len(known) // 3])):
            expected = list(direct.as_of(v, k))
            assert len(expected) > 997 and list(remote.as_of(v, k)) == expected
            position = (expected[5].valid_time_ns, expected[5].global_seq)
            assert list(small.as_of(v, k, after=position, types=["assay", "lot_declared"])) == \
                list(direct.as_of(v, k, after=position, types=["assay", "lot_declared"]))
        assert remote.gaps() == direct.gaps()
        assert remote.quarantine() == direct.quarantine()
        assert remote.streams() == direct.streams()
        assert remote.stats() == direct.stats()
        assert remote.verify() == direct.verify()


def test_a_remote_ledger_reads_as_of_the_head_it_opened_at(tmp_path):
    """Events committed after a RemoteLedger opened stay out of its reads (a new one sees
    them); gaps and quarantine come back as the service has them."""
    path = tmp_path / "live.duckdb"
    with open_ledger(path) as store:
        store.append([_clock_event(seq) for seq in (0, 1, 2, 5)]
                     + [Malformed(b"\x01\x02", "decode: not a Clock", "clock", "bad.one")])
        expected_gaps, expected_quarantine = store.gaps(), store.quarantine()
    router, endpoint = open_router()
    service = _start_ledger(path, endpoint, tmp_path / "ledger.log")
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
        client = LedgerClient(router, SITE, timeout_s=30)
        remote = RemoteLedger(client, page_records=2)
        assert remote.head().global_seq == 3
        assert remote.gaps() == expected_gaps and [g.first_seq for g in expected_gaps] == [3]
        assert remote.quarantine() == expected_quarantine
        assert [q.source for q in expected_quarantine] == ["bad.one"]
        publisher = EventPublisher(router, SITE, "sim.clock", epoch=9)
        for seq in range(5):
            publisher.publish(_clock_message(100 + seq))
        client.wait_for(lambda h: h["global_seq"] >= 8, 30)
        assert [r.seq for r in remote.read()] == [0, 1, 2, 5]
        assert [r.seq for r in remote.as_of(2**62, 2**62)] == [0, 1, 2, 5]
        assert remote.head().global_seq == 3
        later = RemoteLedger(client, page_records=2)
        assert [(r.epoch, r.seq) for r in later.read(4)] == [(9, s) for s in range(5)]
        assert later.head().global_seq == 8
    finally:
        code = stop(service)
        router.close()
    assert code == 0


def _clock_message(i: int) -> pb.Clock:
    msg = pb.Clock()
    set_timestamp_ns(msg.time, T0_NS + i * 1_000_000_000)
    return msg


def _clock_event(seq: int) -> Event:
    return Event("clock", "sim.clock", 3, seq, T0_NS + seq * 1_000_000_000,
                 _clock_message(seq).SerializeToString())


# -- the holder file and the JSON forms, without a service ---------------------------------


def test_holder_file_round_trip_and_ownership(tmp_path):
    ledger = tmp_path / "x.duckdb"
    assert read_holder(ledger) is None
    holder = LedgerHolder("demo", 4242, ("tcp/127.0.0.1:7447",), T0_NS, "box")
    path = write_holder(ledger, holder)
    assert path == holder_path(ledger) and read_holder(ledger) == holder
    remove_holder(ledger, 1)                 # another pid's removal leaves it
    assert read_holder(ledger) == holder
    remove_holder(ledger, 4242)
    assert not path.exists()
    path.write_text("{not json")
    assert read_holder(ledger) is None


def test_a_lock_without_a_matching_holder_is_one_clear_error(tmp_path):
    ledger = tmp_path / "x.duckdb"
    write_holder(ledger, LedgerHolder("demo", 4242, ("tcp/127.0.0.1:7447",), T0_NS))
    with pytest.raises(LedgerLocked, match=r"open for writing by process 99, which serves no reads"):
        open_held(ledger, LedgerLocked("locked", 99))


def test_json_forms_round_trip(held_audit_ledger):
    _held, copy, *_ = held_audit_ledger
    with open_ledger(copy, read_only=True) as store:
        stats, head = store.stats(), store.head()
        gaps, streams, quarantine = store.gaps(), store.streams(), store.quarantine()
    assert head_from_json(json.loads(json.dumps(head_to_json(head)))) == head
    assert stats_from_json(json.loads(json.dumps(stats_to_json(stats)))) == stats
    assert [gap_from_json(gap_to_json(g)) for g in gaps] == gaps
    assert [stream_from_json(stream_to_json(s)) for s in streams] == streams
    assert [quarantine_from_json(quarantine_to_json(q)) for q in quarantine] == quarantine
    with pytest.raises(ValueError, match="missing field 'chain_sha256'"):
        head_from_json({"global_seq": 1, "recorded_time_ns": 2})
    with pytest.raises(ValueError, match="Head.chain_sha256"):
        head_from_json({"global_seq": 1, "recorded_time_ns": 2, "chain_sha256": "zz"})
