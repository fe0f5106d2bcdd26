"""Regression tests of issue 43: the six inputs that crashed ``stockpile ledger import``, and
the lines a ledger refuses even to quarantine.

Each hostile line sits between good lines of the same batch; the real CLI imports the file
into a real DuckDB file, and the test reads the ledger back: the good lines are appended,
the hostile one is quarantined with its raw bytes, its file and line number and a reason
code, and no exception escapes (exit 0, no traceback).
Where the store itself was the culprit (a seq below -2^63, a lone surrogate in an
identity field) both backends are driven directly as well.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import duckdb
import pytest

from bad_input_helpers import NOW, V0, joint_reading
from ledger import ManualClock, open_ledger
from ledger.importing import default_rejects_path
from schemas.events import make_event
from schemas.jsonl import event_line

SOURCE = "bwr1.joints"


def good_line(seq: int) -> str:
    return event_line(make_event(joint_reading(V0 + seq), source=SOURCE, epoch=0, seq=seq))


def import_file(path: Path, ledger: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "stockpile.cli", "ledger", "import", str(path), "--ledger",
         str(ledger), "--json", *extra],
        capture_output=True, timeout=300)


def write_lines(path: Path, lines: list[bytes]) -> Path:
    path.write_bytes(b"\n".join(lines) + b"\n")
    return path


def _latin1() -> bytes:  # a lab export's "LOT-é" in Latin-1
    return good_line(2).encode().replace(b'"machine_id":"bwr1"', b'"machine_id":"LOT-\xe9"')


def _body_key_surrogate() -> bytes:
    return good_line(2).replace('"machine_id"', '"\\ud800"').encode()


def _type_surrogate() -> bytes:
    return good_line(2).replace('"type":"joint_reading"', '"type":"joint\\ud800"').encode()


def _source_surrogate() -> bytes:
    return good_line(2).replace(f'"source":"{SOURCE}"', '"source":"bwr\\udfff"').encode()


def _huge_integer() -> bytes:
    return good_line(2).replace('"epoch":0', '"epoch":' + "7" * 5_000).encode()


def _deep_nesting() -> bytes:
    depth = 100_000
    return (f'{{"type":"joint_reading","source":"{SOURCE}","epoch":0,"seq":2,'
            f'"valid_time_ns":{V0 + 2},"body":{{"machine_id":' + "[" * depth + "]" * depth
            + "}}").encode()


HOSTILE = [
    pytest.param(_latin1, "not_utf8", id="latin1-byte"),
    pytest.param(_body_key_surrogate, "lone_surrogate", id="surrogate-in-body-key"),
    pytest.param(_type_surrogate, "lone_surrogate", id="surrogate-in-type"),
    pytest.param(_source_surrogate, "lone_surrogate", id="surrogate-in-source"),
    pytest.param(_huge_integer, "too_large", id="5000-digit-integer"),
    pytest.param(_deep_nesting, "too_deep", id="deep-nesting"),
]


def check_ledger(ledger: Path, seqs: list[int], quarantined: list[tuple[bytes, str, str]]):
    """The ledger holds the good events ``seqs`` of SOURCE and exactly ``quarantined``
    (raw bytes, code, text in the detail), and its chain verifies."""
    with open_ledger(ledger, read_only=True) as store:
        rows = list(store.read())
        entries = store.quarantine()
        report = store.verify()
    assert [(r.source, r.seq) for r in rows] == [(SOURCE, s) for s in seqs]
    assert [(q.raw, q.code) for q in entries] == [(raw, code) for raw, code, _ in quarantined]
    for entry, (_, _, where) in zip(entries, quarantined):
        assert where in entry.detail, entry.detail
    assert report.ok, report.problem
    return entries


@pytest.mark.parametrize("hostile, code", HOSTILE)
def test_hostile_line_is_quarantined_and_its_batch_kept(tmp_path, hostile, code):
    bad = hostile()
    path = write_lines(tmp_path / "in.jsonl", [good_line(0).encode(), good_line(1).encode(), bad,
                                              good_line(3).encode(), good_line(4).encode()])
    ledger = tmp_path / "ledger.duckdb"
    run = import_file(path, ledger)
    assert run.returncode == 0, run.stderr.decode(errors="replace")
    assert b"Traceback" not in run.stderr
    counts = json.loads(run.stdout)
    assert (counts["lines"], counts["appended"], counts["rejected"], counts["to_reject_file"]) \
        == (5, 4, 1, 0)
    assert counts["rejects_file"] is None
    check_ledger(ledger, [0, 1, 3, 4], [(bad, code, f"{path}:3")])
    assert not default_rejects_path(ledger).exists()


def test_surrogate_identity_is_stored_escaped(tmp_path):
    path = write_lines(tmp_path / "in.jsonl", [_type_surrogate(), _source_surrogate()])
    ledger = tmp_path / "ledger.duckdb"
    assert import_file(path, ledger).returncode == 0
    entries = check_ledger(ledger, [], [(_type_surrogate(), "lone_surrogate", ":1"),
                                        (_source_surrogate(), "lone_surrogate", ":2")])
    assert entries[0].type == "joint\\ud800"
    assert entries[1].source == "bwr\\udfff"


def test_seq_below_int64_on_an_existing_stream(tmp_path):
    ledger = tmp_path / "ledger.duckdb"
    first = write_lines(tmp_path / "first.jsonl", [good_line(0).encode(), good_line(1).encode()])
    assert import_file(first, ledger).returncode == 0
    bad = good_line(0).replace('"seq":0', f'"seq":{-2**63 - 5}').encode()
    second = write_lines(tmp_path / "second.jsonl", [good_line(2).encode(), bad,
                                                     good_line(3).encode()])
    run = import_file(second, ledger)
    assert run.returncode == 0, run.stderr.decode(errors="replace")
    assert json.loads(run.stdout)["appended"] == 2
    entries = check_ledger(ledger, [0, 1, 2, 3], [(bad, "bad_identity", f"{second}:2")])
    assert entries[0].seq is None  # not storable as a number; it stays in the raw bytes


def test_lines_the_store_refuses_name_their_file_and_line(tmp_path):
    """Lines that decode but the ledger refuses (a conflict with a stored event, an event
    whose body fails validation) are quarantined with FILE:LINE before their reason."""
    ledger = tmp_path / "ledger.duckdb"
    first = write_lines(tmp_path / "first.jsonl", [good_line(0).encode()])
    assert import_file(first, ledger).returncode == 0
    conflict = good_line(0).replace('"travel_m"', '"slew_rad":1.0,"travel_m"').encode()
    assert conflict != good_line(0).encode()
    invalid = event_line(make_event(joint_reading(V0 + 2), source=SOURCE, epoch=0, seq=2)
                         ).replace(f'"valid_time_ns":{V0 + 2}', '"valid_time_ns":-5').encode()
    second = write_lines(tmp_path / "second.jsonl", [good_line(1).encode(), conflict, invalid,
                                                     good_line(3).encode()])
    run = import_file(second, ledger)
    assert run.returncode == 0, run.stderr.decode(errors="replace")
    assert json.loads(run.stdout)["rejected"] + json.loads(run.stdout)["conflict"] == 2
    with open_ledger(ledger, read_only=True) as store:
        entries = store.quarantine()
        assert store.verify().ok
    assert [e.detail.split(": ")[0] for e in entries] == [f"{second}:2", f"{second}:3"], entries
    assert entries[0].code == "conflict"


@pytest.fixture(params=["memory", "duckdb"])
def store(request, tmp_path):
    path = ":memory:" if request.param == "memory" else tmp_path / "ledger.duckdb"
    with open_ledger(path, ManualClock(NOW)) as opened:
        yield opened


@pytest.mark.parametrize("seq", [-2**63 - 5, 2**64, -1])
def test_store_refuses_seq_outside_int64_on_an_existing_stream(store, seq):
    first = make_event(joint_reading(V0), source=SOURCE, epoch=0, seq=0)
    assert store.append([first]).counts["appended"] == 1
    bad = make_event(joint_reading(V0 + 1), source=SOURCE, epoch=0, seq=0)
    bad = dataclasses.replace(bad, seq=seq)
    after = make_event(joint_reading(V0 + 2), source=SOURCE, epoch=0, seq=1)
    result = store.append([bad, after])
    assert [o.status for o in result.outcomes] == ["rejected", "appended"]
    assert result.outcomes[0].code == "bad_identity"
    assert store.verify().ok


def test_store_quarantines_surrogate_source_escaped(store):
    bad = make_event(joint_reading(V0), source=SOURCE, epoch=0, seq=0)
    bad = dataclasses.replace(bad, source="bwr\ud800")
    good = make_event(joint_reading(V0 + 1), source=SOURCE, epoch=0, seq=0)
    result = store.append([bad, good])
    assert [o.status for o in result.outcomes] == ["rejected", "appended"]
    assert [q.source for q in store.quarantine()] == ["bwr\\ud800"]
    assert store.verify().ok


# --- lines a ledger refuses even in its quarantine -------------------------------------------


def refuse_in_quarantine(ledger: Path, condition: str) -> None:
    """Rebuild the quarantine table of a real ledger file with ``CHECK (condition)``: a ledger
    whose quarantine refuses some entries."""
    con = duckdb.connect(str(ledger))
    try:
        ddl = con.execute("SELECT sql FROM duckdb_tables() WHERE table_name = 'quarantine'"
                          ).fetchone()[0]
        checked = ddl.rstrip().rstrip(";")[:-1] + f", CHECK ({condition}))"
        con.execute("ALTER TABLE quarantine RENAME TO quarantine_before")
        con.execute(checked)
        con.execute("INSERT INTO quarantine SELECT * FROM quarantine_before")
        con.execute("DROP TABLE quarantine_before")
    finally:
        con.close()


def test_unstorable_identity_is_quarantined_as_raw_bytes_only(tmp_path):
    ledger = tmp_path / "ledger.duckdb"
    assert import_file(write_lines(tmp_path / "a.jsonl", [good_line(0).encode()]),
                       ledger).returncode == 0
    refuse_in_quarantine(ledger, "\"source\" <> 'poison.src'")
    bad = b'{"type":"bogus","source":"poison.src","epoch":0,"seq":0,"valid_time_ns":1}'
    path = write_lines(tmp_path / "b.jsonl", [good_line(1).encode(), bad, good_line(2).encode()])
    run = import_file(path, ledger)
    assert run.returncode == 0, run.stderr.decode(errors="replace")
    counts = json.loads(run.stdout)
    assert (counts["appended"], counts["rejected"], counts["to_reject_file"]) == (2, 1, 0)
    entries = check_ledger(ledger, [0, 1, 2], [(bad, "unstorable", f"{path}:2")])
    assert entries[0].source == ""


def test_line_refused_even_as_raw_bytes_goes_to_the_reject_file(tmp_path):
    ledger = tmp_path / "ledger.duckdb"
    assert import_file(write_lines(tmp_path / "a.jsonl", [good_line(0).encode()]),
                       ledger).returncode == 0
    refuse_in_quarantine(ledger, "octet_length(raw) < 200")
    bad = b"not json " + b"x" * 300
    path = write_lines(tmp_path / "b.jsonl", [good_line(1).encode(), bad, good_line(2).encode()])
    rejects = tmp_path / "elsewhere" / "rejected.jsonl"
    rejects.parent.mkdir()
    run = import_file(path, ledger, "--rejects", str(rejects))
    assert run.returncode == 2
    stderr = run.stderr.decode().strip().splitlines()
    assert [line for line in stderr if "error" in line] == [
        f"stockpile: error: 1 line could not be stored even in the quarantine; see {rejects}"]
    counts = json.loads(run.stdout)
    assert (counts["lines"], counts["appended"], counts["rejected"], counts["to_reject_file"]) \
        == (3, 2, 0, 1)
    assert counts["rejects_file"] == str(rejects)
    check_ledger(ledger, [0, 1, 2], [])
    [record] = [json.loads(line) for line in rejects.read_text().splitlines()]
    assert (record["file"], record["line"]) == (str(path), 2)
    assert record["reason"].startswith(f"unstorable: {path}:2: ")
    assert base64.b64decode(record["raw_base64"]) == bad
    assert not default_rejects_path(ledger).exists()


def test_latin1_line_on_standard_input(tmp_path):
    bad = _latin1()
    ledger = tmp_path / "ledger.duckdb"
    run = subprocess.run(
        [sys.executable, "-m", "stockpile.cli", "ledger", "import", "-", "--ledger", str(ledger),
         "--json"], input=b"\n".join([good_line(0).encode(), bad, good_line(3).encode()]),
        capture_output=True, timeout=300)
    assert run.returncode == 0, run.stderr.decode(errors="replace")
    assert json.loads(run.stdout)["appended"] == 2
    check_ledger(ledger, [0, 3], [(bad, "not_utf8", "-:2")])
