"""``stockpile service lab`` as a real process: LIMS files in a real drop folder, a real
Zenoh router (mutual TLS, the generated access control) and a real ledger service that
requires signed assays; what the ledger holds is read back through the ledger service.

Each test has its own source (its own certificate and signing key) and folder against one
router and ledger.  Nothing waits on a sleep: every wait is on a condition (a log line, a
file in the archive, the ledger's count) with a timeout.  The simulator's lab results are
drawn from the run's seed (``--seed N`` or ``STOCKPILE_TEST_SEED=N``; it is printed).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from schemas import pb
from schemas.times import parse_time_ns as utc
from security.event_keys import load_signing_key
from services import lab as LAB
from services.lims_map import RefusedRow
from services.ledger_client import LedgerClient
from sim import lims as S
from sim import messages
from sim.grades import BeltGrade, LabModel, table_5_4_lots
from stockpile.demo_signing import prepare_signing
from zenoh_helpers import (
    PYTHON,
    client_args,
    log_lines,
    open_router,
    site_pki,
    stockpile,
    stop,
    wait_liveliness,
    wait_until,
)

from seeding import session_seed

SEED = session_seed()
SITE = "labtest"
TIMEOUT_S = 120.0  # generous: a loaded machine starts a process in tens of seconds
T0_NS = utc("2026-11-20T00:00:00Z")
NS_PER_H = 3600 * 10**9
SOURCES = ("lab-dup", "lab-bad", "lab-sim", *(f"lab-{p}" for p in LAB.HALT_POINTS))
MAP = """
[file]
format = "csv"
[time]
format = "iso8601"
[columns]
sample_id = "sample"
lot = "lot"
window_start = "from"
window_end = "to"
status = "status"
reported_time = "reported"
revision = "rev"
[lab]
id = "lab-test"
[status]
P = "PROVISIONAL"
F = "FINAL"
[analytes]
Fe = { column = "fe" }
SiO2 = { column = "sio2" }
"""
HEADER = "sample,lot,from,to,status,reported,rev,fe,sio2"


def _row(sample: str, hour: int, *, rev: int = 0, status: str = "P", fe: str = "60.1") -> str:
    start = "2026-11-20T%02d:00:00Z" % hour
    return (f"{sample},LOT-A,{start},{start.replace(':00:00', ':20:00')},{status},"
            f"2026-11-20T{hour + 3:02d}:00:00Z,{rev},{fe},4.5")


def _drop(folder: Path, name: str, data: bytes) -> Path:
    """Put a file into the drop folder whole: written under a hidden name, renamed."""
    temp = folder / f".{name}.part"
    temp.write_bytes(data)
    os.replace(temp, folder / name)
    return folder / name


@dataclass
class Yard:
    base: Path
    pki: Path
    endpoint: str
    client: LedgerClient
    keys: Path
    map_path: Path

    def assays(self, source: str) -> list:
        return self.client.read(0, types=["assay"], sources=[source])

    def wait_count(self, source: str, n: int) -> list:
        wait_until(lambda: len(self.assays(source)) >= n, TIMEOUT_S,
                   f"{n} assays of {source} in the ledger", interval_s=0.1)
        return self.assays(source)


@pytest.fixture(scope="module")
def yard(tmp_path_factory):
    base = tmp_path_factory.mktemp("lab-yard")
    pki = site_pki(base / "pki", SITE, {"ledger": "ledger", **{s: "lab" for s in SOURCES}})
    ledger_path = base / "ledger.duckdb"
    signing = prepare_signing(base, ledger_path, {s: "lab" for s in SOURCES}, T0_NS - NS_PER_H)
    router, endpoint = open_router(pki, SITE)
    ledger = stockpile("service", "ledger", "--ledger", str(ledger_path), "--site", SITE,
                       "--status-period", "1", *client_args(endpoint, pki, "ledger"),
                       *signing.ledger_args, stderr_path=base / "ledger.log")
    map_path = base / "lims.toml"
    map_path.write_text(MAP)
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", TIMEOUT_S)
        yield Yard(base, pki, endpoint, LedgerClient(router, SITE, timeout_s=20),
                   base / "keys" / "sources", map_path)
        assert yard_quarantine_is_empty(LedgerClient(router, SITE, timeout_s=20))
    finally:
        code = stop(ledger)
        router.close()
    assert code == 0, (base / "ledger.log").read_text()[-3000:]


def yard_quarantine_is_empty(client: LedgerClient) -> bool:
    """No conflict (a re-sent identity with another payload), no bad signature."""
    entries = client.quarantine()
    assert entries == [], entries
    return True


def _start_lab(yard: Yard, source: str, folder: Path, log: Path, *extra: str,
               halt_at: str | None = None, map_path: Path | None = None) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != LAB.HALT_ENV}
    if halt_at:
        env[LAB.HALT_ENV] = halt_at
    args = ["service", "lab", "--watch", str(folder), "--map", str(map_path or yard.map_path),
            "--site", SITE, "--source", source, "--signing-key",
            str(yard.keys / f"{source}.sign.key"), "--settle", "0", "--poll", "0.05",
            "--status-period", "0.5", *client_args(yard.endpoint, yard.pki, source), *extra]
    process = subprocess.Popen([PYTHON, "-m", "stockpile.cli", *args], env={
        **env, "PYTHONUNBUFFERED": "1"}, stdout=subprocess.DEVNULL, stderr=open(log, "w"))
    process.stderr_path = log
    wait_until(lambda: any(line.get("msg") == "ready" for line in log_lines(log))
               or process.poll() is not None, TIMEOUT_S, f"the lab adapter {source} ready")
    assert process.poll() is None, log.read_text()[-3000:]
    return process


def _lines(log: Path, msg: str) -> list[dict]:
    return [line for line in log_lines(log) if line.get("msg") == msg]


def _wait_log(log: Path, msg: str, n: int = 1, process: subprocess.Popen | None = None) -> list:
    wait_until(lambda: len(_lines(log, msg)) >= n or (process and process.poll() is not None),
               TIMEOUT_S, f"{n} {msg!r} lines in {log.name}")
    return _lines(log, msg)


def _stop_and_published(process: subprocess.Popen, log: Path) -> tuple[int, int]:
    """Stop the adapter (exit 0 required) and return its ``published`` (epoch, count)."""
    assert stop(process) == 0, log.read_text()[-3000:]
    (line,) = _lines(log, "published")
    return int(line["epoch"]), int(line["count"])


def _check_stream(yard: Yard, source: str, expected_ids: list[str], epoch: int) -> list:
    """The ledger holds exactly ``expected_ids`` for ``source``: one epoch, seqs 0..n-1 in
    file order, each signed by the source's key, no open gap; returns the messages."""
    rows = yard.assays(source)
    assert len(rows) == len(expected_ids), [pb.Assay.FromString(r.payload).assay_id
                                            for r in rows]
    assert {r.epoch for r in rows} == {epoch}
    by_seq = sorted(rows, key=lambda r: r.seq)
    assert [r.seq for r in by_seq] == list(range(len(expected_ids)))
    key_id = load_signing_key(yard.keys / f"{source}.sign.key").key_id
    assert {r.signer for r in rows} == {key_id}
    msgs = [pb.Assay.FromString(r.payload) for r in by_seq]
    assert [m.assay_id for m in msgs] == expected_ids
    assert [g for g in yard.client.gaps(open_only=True) if g["source"] == source] == []
    return msgs


# -- the same file twice, bad rows, a revision -------------------------------------------


def test_the_same_file_twice_also_under_another_name_goes_in_once(yard, tmp_path):
    source = "lab-dup"
    folder = tmp_path / "drop"
    folder.mkdir()
    data = "\n".join([HEADER, _row("S1", 1), _row("S2", 2), _row("S3", 3)]).encode() + b"\n"
    log = tmp_path / "lab.log"
    process = _start_lab(yard, source, folder, log)
    try:
        _drop(folder, "batch1.csv", data)
        _wait_log(log, "file done", 1, process)
        yard.wait_count(source, 3)
        _drop(folder, "batch1.csv", data)           # the same name again
        _drop(folder, "copy of batch1.csv", data)   # another name
        _drop(folder, "notes.txt", b"not an export")
        dups = _wait_log(log, "duplicate file", 2, process)
    finally:
        epoch, count = _stop_and_published(process, log)
    assert sorted(d["file"] for d in dups) == ["batch1.csv", "copy of batch1.csv"]
    assert {d["first_name"] for d in dups} == {"batch1.csv"}
    archive = folder / "archive"
    assert (archive / "batch1.csv").read_bytes() == data
    assert sorted(p.name for p in (archive / "duplicates").iterdir()) == [
        "batch1.csv", "copy of batch1.csv"]
    assert sorted(p.name for p in folder.iterdir()) == [".stockpile-lab", "archive",
                                                        "notes.txt"]
    assert count == 3
    _check_stream(yard, source, ["S1", "S2", "S3"], epoch)
    stopped = _lines(log, "stopped")[-1]
    assert (stopped["files"], stopped["published"], stopped["duplicates"]) == ("1", "3", "2")

    # a restart: the finished file is not published again, the stream goes on; a
    # cumulative export repeating S2 adds only its new result
    process = _start_lab(yard, source, folder, log)
    try:
        _drop(folder, "batch2.csv", "\n".join([HEADER, _row("S2", 2), _row("S4", 4)]).encode())
        (done,) = _wait_log(log, "file done", 1, process)
        yard.wait_count(source, 4)
    finally:
        epoch2, count2 = _stop_and_published(process, log)
    assert (epoch2, count2) == (epoch, 4)
    assert (done["assays"], done["repeated"], done["refused"]) == ("1", "1", "0")
    assert _lines(log, "republished") == []
    _check_stream(yard, source, ["S1", "S2", "S3", "S4"], epoch)
    repeated = (archive / "batch2.csv.refused.csv").read_text().splitlines()
    assert repeated[1:] == ["2,already published from batch1.csv (the same result)"]


def test_bad_rows_are_refused_beside_the_file_and_the_good_rows_go_in(yard, tmp_path):
    source = "lab-bad"
    folder = tmp_path / "drop"
    folder.mkdir()
    rows = [HEADER,
            _row("G1", 1),                                  # line 2
            _row("B1", 2, fe="n/a"),                        # 3: not a number
            _row("B2", 3, status="X"),                      # 4: unknown status code
            _row("G2", 4),                                  # 5
            _row("B3", 5, fe="99.5"),                       # 6: Fe + SiO2 > 100 %
            _row("B4", 6).replace("T06:20", "T05:20"),      # 7: window ends before it starts
            "G3,LOT-A,2026-11-20T07:00:00Z",                # 8: too few fields
            _row("G1", 1),                                  # 9: the same sample and revision
            _row("G4", 8)]                                  # 10
    log = tmp_path / "lab.log"
    process = _start_lab(yard, source, folder, log)
    try:
        _drop(folder, "mixed.csv", ("\n".join(rows) + "\n").encode())
        (done,) = _wait_log(log, "file done", 1, process)
        yard.wait_count(source, 3)
    finally:
        epoch, count = _stop_and_published(process, log)
    assert (done["assays"], done["refused"]) == ("3", "6")
    assert count == 3
    _check_stream(yard, source, ["G1", "G2", "G4"], epoch)
    refused = (folder / "archive" / "mixed.csv.refused.csv").read_text().splitlines()
    assert refused[0] == "line,reason"
    lines = [int(r.split(",", 1)[0]) for r in refused[1:]]
    assert lines == [3, 4, 6, 7, 8, 9]
    text = "\n".join(refused)
    for reason in ("'n/a' is not a number", "status 'X'", "analyte_sum",
                   "ends before it starts", "3 fields, the header has 9", "already on line 2"):
        assert reason in text, reason
    assert not (folder / "mixed.csv").exists()
    assert _lines(log, "stopped")[-1]["refused_rows"] == "6"


def _sim_results(rng: np.random.Generator) -> list:
    lot = table_5_4_lots()[0]
    start = T0_NS + 1_000_000_007
    belt = BeltGrade(lot, start, start + 5 * NS_PER_H, rng)
    results = LabModel(provisional_fraction=0.5).assays(belt, start, start + 5 * NS_PER_H,
                                                        rng, [0])
    return sorted(results, key=lambda r: (r.reported_ns, r.assay_id))


def test_the_simulators_lims_files_go_in_as_its_assays_revisions_superseding(yard, tmp_path):
    print(f"sim LIMS files through the adapter: seed {SEED} (--seed {SEED} reproduces it)")
    results = _sim_results(np.random.default_rng(SEED))
    assert any(r.supersedes for r in results), "the draw has no provisional result"
    source = "lab-sim"
    folder = tmp_path / "drop"
    map_path = S.write_map(tmp_path / "lims.toml")
    writer = S.LimsDropWriter(folder)
    batches = [results[i:i + 3] for i in range(0, len(results), 3)]
    log = tmp_path / "lab.log"
    process = _start_lab(yard, source, folder, log, map_path=map_path)
    try:
        for batch in batches:
            writer.write(batch[-1].reported_ns, batch)
        _wait_log(log, "file done", len(batches), process)
        yard.wait_count(source, len(results))
    finally:
        epoch, count = _stop_and_published(process, log)
    assert count == len(results)
    msgs = _check_stream(yard, source, [writer.assay_ids[r.assay_id] for r in results], epoch)
    for msg, r in zip(msgs, results):
        expected = messages.assay(r)
        expected.assay_id = writer.assay_ids[r.assay_id]
        expected.supersedes = writer.assay_ids[r.supersedes] if r.supersedes else ""
        assert msg == expected, r.assay_id
    revised = [m for m in msgs if m.supersedes]
    assert revised and all(m.assay_id == f"{m.supersedes}-r1" and m.status == pb.FINAL
                           for m in revised)
    assert {m.assay_id for m in msgs} >= {m.supersedes for m in revised}
    assert len(list((folder / "archive").glob("*.csv"))) == len(batches)

    # --resend publishes every journaled assay again with its identity: nothing doubles
    # (the file after them arrives after them: one publisher, one key, in order)
    process = _start_lab(yard, source, folder, log, "--resend", map_path=map_path)
    try:
        again = _lines(log, "republished")
        assert [int(line["count"]) for line in again] == [len(b) for b in batches]
        last = results[-1]
        extra = [dataclasses.replace(last, assay_id="AS-EXTRA", supersedes="")]
        writer.write(last.reported_ns, extra)
        _wait_log(log, "file done", 1, process)
        yard.wait_count(source, len(results) + 1)
    finally:
        assert _stop_and_published(process, log) == (epoch, len(results) + 1)
    assert _lines(log, "stopped")[-1]["republished"] == str(len(results))
    _check_stream(yard, source, [*(writer.assay_ids[r.assay_id] for r in results),
                                 "AS-EXTRA"], epoch)


# -- a crash between reading and archiving -----------------------------------------------


@pytest.mark.parametrize("halt_at", LAB.HALT_POINTS)
def test_a_crash_between_reading_and_archiving_loses_nothing_and_doubles_nothing(
        yard, tmp_path, halt_at):
    source = f"lab-{halt_at}"
    folder = tmp_path / "drop"
    folder.mkdir()
    ids = [f"K{i}" for i in range(6)]
    data = "\n".join([HEADER, *(_row(s, i + 1) for i, s in enumerate(ids)),
                      _row("BAD", 9, fe="?")]).encode()
    first_log, second_log = tmp_path / "lab1.log", tmp_path / "lab2.log"
    process = _start_lab(yard, source, folder, first_log, halt_at=halt_at)
    try:
        _drop(folder, "crash.csv", data)
        (halt,) = _wait_log(first_log, "halting", 1, process)
        assert halt["at"] == halt_at
        # what reached the ledger before the kill: none, half, or all of the file
        sent = {"begun": 0, "publishing": 3}.get(halt_at, 6)
        if sent:
            yard.wait_count(source, sent)
        process.kill()
        assert process.wait(TIMEOUT_S) == -9
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert (folder / "crash.csv").exists()          # not archived
    (watching,) = _lines(first_log, "watching")
    epoch = int(watching["epoch"])
    assert len(yard.assays(source)) == sent

    process = _start_lab(yard, source, folder, second_log)
    try:
        if halt_at != "archiving":
            (again,) = _wait_log(second_log, "republished", 1, process)
            assert (again["first_seq"], again["count"]) == ("0", "6")
        wait_until(lambda: (folder / "archive" / "crash.csv").exists(), TIMEOUT_S,
                   "the file archived")
        yard.wait_count(source, 6)
        # the stream goes on after the restart: the next file gets seqs 6 and 7
        _drop(folder, "next.csv", "\n".join([HEADER, _row("N1", 12), _row("N2", 13)]).encode())
        _wait_log(second_log, "file done", 1, process)
        yard.wait_count(source, 8)
    finally:
        epoch2, count = _stop_and_published(process, second_log)
    assert (epoch2, count) == (epoch, 8)
    if halt_at == "archiving":
        assert _lines(second_log, "republished") == []
    _check_stream(yard, source, [*ids, "N1", "N2"], epoch)
    assert (folder / "archive" / "crash.csv").read_bytes() == data
    assert not (folder / "crash.csv").exists()
    refused = (folder / "archive" / "crash.csv.refused.csv").read_text().splitlines()
    assert refused[1].startswith("8,") and "'?' is not a number" in refused[1]
    assert not list(folder.glob("archive/duplicates/*"))


# -- the journal --------------------------------------------------------------------------


def test_the_journal_cuts_a_torn_last_line_and_refuses_damage_and_another_source(tmp_path):
    path = tmp_path / "journal.jsonl"
    journal = LAB.Journal(path, "lab1")
    entry = LAB.FileEntry("ab" * 32, "a.csv", 0, [b"\x0a\x01x", b"\x0a\x01y"],
                          [RefusedRow(3, "bad")])
    journal.begin(entry)
    journal.mark_published(entry, "archive/a.csv")
    whole = path.read_bytes()
    with open(path, "ab") as f:
        f.write(b'{"kind":"archived","sha2')           # a crash while writing the line
    again = LAB.Journal(path, "lab1")
    assert path.read_bytes() == whole
    assert again.epoch == journal.epoch and again.next_seq == 2
    (got,) = again.files.values()
    assert (got.payloads, got.refused, got.published, got.archived, got.archive) == (
        entry.payloads, entry.refused, True, False, "archive/a.csv")
    with pytest.raises(ValueError, match="is source 'lab1'"):
        LAB.Journal(path, "lab2")
    path.write_bytes(whole.replace(b'"kind":"published"', b'"kind":"publishd"'))
    with pytest.raises(ValueError, match="line 3 is damaged"):
        LAB.Journal(path, "lab1")


def test_bad_options_are_one_line_and_exit_2(tmp_path):
    bad_map = tmp_path / "bad.toml"
    bad_map.write_text(MAP.replace('sample_id = "sample"\n', ""))
    out = subprocess.run([PYTHON, "-m", "stockpile.cli", "service", "lab", "--watch",
                          str(tmp_path), "--map", str(bad_map)], capture_output=True, text=True,
                         timeout=TIMEOUT_S)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"stockpile: error: --map {bad_map}: columns.sample_id is missing"]
    good_map = tmp_path / "good.toml"
    good_map.write_text(MAP)
    out = subprocess.run([PYTHON, "-m", "stockpile.cli", "service", "lab", "--watch",
                          str(tmp_path / "nowhere"), "--map", str(good_map)],
                         capture_output=True, text=True, timeout=TIMEOUT_S)
    assert out.returncode == 2
    (line,) = [ln for ln in out.stderr.splitlines() if ln.startswith("ts=")]
    assert "cannot start" in line and "no such folder" in line


def test_the_folder_takes_matching_names_once_they_have_settled(tmp_path):
    for name in ("a.csv", "B.CSV", ".hidden.csv", "c.csv.part", "d.json"):
        (tmp_path / name).write_text("x")
    (tmp_path / "sub.csv").mkdir()
    at_once = LAB._Folder(tmp_path, ".csv", 0.0)  # noqa: SLF001 - the rule itself
    assert [p.name for p in at_once.ready()] == ["B.CSV", "a.csv"]
    now = [100.0]  # a clock the test moves, seconds
    folder = LAB._Folder(tmp_path, ".csv", 5.0, clock=lambda: now[0])  # noqa: SLF001
    assert folder.ready() == []                   # first sight starts each file's clock
    now[0] = 104.9
    assert folder.ready() == []
    os.utime(tmp_path / "a.csv", ns=(1, 2))       # a.csv changes: its clock restarts
    now[0] = 105.0
    assert [p.name for p in folder.ready()] == ["B.CSV"]
    now[0] = 109.9
    assert [p.name for p in folder.ready()] == ["B.CSV"]
    now[0] = 110.0
    assert [p.name for p in folder.ready()] == ["B.CSV", "a.csv"]
