"""The head sidecar (``<ledger>.head``): a ledger whose head went backwards is refused with
the numbers, ``--accept-loss`` overrides it, a database ahead of its sidecar brings it
forward, and a stale copy of the file taken without its WAL fails ``verify``."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ledger import errors, open_ledger
from ledger.clock import ManualClock
from ledger.head_file import head_path, read_head, write_head
from ledger.records import Head
from ledger.testing import joint_event
from schemas.jsonl import event_line
from zenoh_helpers import PYTHON

BATCH = 50


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=120)


def _append(path: Path, first_batch: int, batches: int, **kwargs) -> int:
    """Append ``batches`` batches of BATCH joint readings; the head's global_seq."""
    with open_ledger(path, ManualClock(1_000), **kwargs) as store:
        for b in range(first_batch, first_batch + batches):
            store.append([joint_event("head.src", b * BATCH + i, b * BATCH + i)
                          for i in range(BATCH)])
        return store.head().global_seq


def _jsonl(path: Path, first_seq: int, n: int) -> Path:
    """``n`` joint readings as canonical JSON lines (``ledger import`` input)."""
    path.write_text("".join(event_line(joint_event("jsonl.src", s, s)) + "\n"
                            for s in range(first_seq, first_seq + n)))
    return path


@pytest.fixture
def went_backwards(tmp_path) -> tuple[Path, int, int]:
    """``(ledger, sidecar head, database head)``: a ledger file replaced by an older copy
    of itself while its sidecar kept the newer head."""
    path = tmp_path / "yard.duckdb"
    older_head = _append(path, 0, 2)
    shutil.copyfile(path, tmp_path / "older.duckdb")
    newer_head = _append(path, 2, 3)
    shutil.copyfile(tmp_path / "older.duckdb", path)
    return path, newer_head, older_head


def test_write_and_read_the_sidecar(tmp_path):
    ledger = tmp_path / "a.duckdb"
    assert read_head(ledger) is None
    write_head(ledger, Head(41, 7_000, bytes(range(32))))
    found = read_head(ledger)
    assert (found.global_seq, found.recorded_time_ns, found.chain_sha256) == (41, 7_000,
                                                                              bytes(range(32)))
    assert sorted(os.listdir(tmp_path)) == ["a.duckdb.head"]   # no temporary file left
    head_path(ledger).write_text('{"global_seq": 41, "chain_sha256": "zz"}\n')
    with pytest.raises(errors.HeadWentBackwards, match="damaged"):
        read_head(ledger)


def test_a_new_ledger_starts_a_sidecar_and_each_batch_moves_it(tmp_path):
    path = tmp_path / "new.duckdb"
    with open_ledger(path, ManualClock(1_000)) as store:
        assert read_head(path).global_seq == -1
        for b in range(3):
            store.append([joint_event("s", b * 10 + i, b * 10 + i) for i in range(10)])
            sidecar = read_head(path)
            head = store.head()
            assert (sidecar.global_seq, sidecar.chain_sha256) == (head.global_seq,
                                                                   head.chain_sha256)
            assert sidecar.recorded_time_ns == head.recorded_time_ns


def test_an_older_ledger_without_a_sidecar_gets_one_with_a_log_line(tmp_path):
    path = tmp_path / "old.duckdb"
    head = _append(path, 0, 2)
    head_path(path).unlink()          # as a ledger written before sidecars existed
    result = _run("ledger", "import", str(_jsonl(tmp_path / "in.jsonl", 0, 5)),
                  "--ledger", str(path))
    assert result.returncode == 0, result.stderr
    assert "no head sidecar" in result.stderr and f"global_seq={head}" in result.stderr
    assert read_head(path).global_seq == head + 5


def test_a_ledger_whose_head_went_backwards_is_refused_with_the_numbers(went_backwards):
    path, sidecar_head, db_head = went_backwards
    with pytest.raises(errors.HeadWentBackwards) as refused:
        open_ledger(path, ManualClock(0))
    message = str(refused.value)
    assert f"records global_seq {sidecar_head} " in message
    assert f"the database holds global_seq {db_head} " in message
    assert f"{sidecar_head - db_head:,} committed events missing" in message
    assert "--accept-loss" in message and "stockpile ledger restore" in message
    assert read_head(path).global_seq == sidecar_head    # the refusal changed nothing


def test_import_refuses_it_in_one_line_and_accept_loss_overrides(went_backwards, tmp_path):
    path, sidecar_head, db_head = went_backwards
    lines = _jsonl(tmp_path / "in.jsonl", 0, 7)
    refused = _run("ledger", "import", str(lines), "--ledger", str(path))
    assert refused.returncode == 2 and refused.stdout == ""
    assert refused.stderr.count("\n") == 1 and refused.stderr.startswith("stockpile: error: ")
    assert f"global_seq {sidecar_head}" in refused.stderr
    assert f"global_seq {db_head}" in refused.stderr
    with open_ledger(path, read_only=True) as store:
        assert store.head().global_seq == db_head         # nothing was appended

    accepted = _run("ledger", "import", str(lines), "--ledger", str(path), "--accept-loss")
    assert accepted.returncode == 0, accepted.stderr
    assert "ACCEPTING LOSS" in accepted.stderr and "level=warning" in accepted.stderr
    assert read_head(path).global_seq == db_head + 7
    again = _run("ledger", "import", str(lines), "--ledger", str(path))   # accepted for good
    assert again.returncode == 0 and "7 duplicate" in again.stdout, again.stderr


def test_the_ledger_service_refuses_it_too(went_backwards, tmp_path):
    path, sidecar_head, db_head = went_backwards
    # it refuses before it opens a Zenoh session (peer mode, scouting off, no listener)
    service = subprocess.run(
        [PYTHON, "-m", "stockpile.cli", "service", "ledger", "--ledger", str(path),
         "--site", "headtest"], capture_output=True, text=True, timeout=60)
    assert service.returncode == 2
    assert "cannot open the ledger" in service.stderr
    assert f"records global_seq {sidecar_head}" in service.stderr
    assert f"holds global_seq {db_head}" in service.stderr


def test_a_database_ahead_of_its_sidecar_brings_it_forward(tmp_path):
    path = tmp_path / "yard.duckdb"
    _append(path, 0, 1)
    shutil.copyfile(head_path(path), tmp_path / "early.head")
    head = _append(path, 1, 2)
    # a stop between a commit and the sidecar write leaves the sidecar behind
    shutil.copyfile(tmp_path / "early.head", head_path(path))
    assert read_head(path).global_seq == BATCH - 1
    verified = _run("ledger", "verify", "--ledger", str(path))
    assert verified.returncode == 0, verified.stdout
    with open_ledger(path, ManualClock(0)) as store:
        assert store.head().global_seq == head
    assert read_head(path).global_seq == head


def test_another_history_at_the_sidecars_head_is_refused(tmp_path):
    path = tmp_path / "yard.duckdb"
    head = _append(path, 0, 2)
    sidecar = read_head(path)
    write_head(path, Head(BATCH - 1, sidecar.recorded_time_ns, bytes(32)))
    with pytest.raises(errors.HeadWentBackwards, match=f"row global_seq {BATCH - 1} has "
                       "another chain hash"):
        open_ledger(path, ManualClock(0))
    verified = _run("ledger", "verify", "--ledger", str(path))
    assert verified.returncode == 1
    assert "FAILED: head sidecar" in verified.stdout and f"head global_seq {head})" in \
        verified.stdout


# The writer commits 3 batches (in its WAL: never checkpointed), says "ready" and waits.
HOLDER = textwrap.dedent(f"""
    import sys
    from ledger import open_ledger
    from ledger.clock import ManualClock
    from ledger.testing import joint_event

    store = open_ledger(sys.argv[1], ManualClock(1_000))
    store.append([joint_event("copy.src", i, i) for i in range({BATCH})])
    store.close()                   # the first batch is in the file itself
    store = open_ledger(sys.argv[1], ManualClock(1_000))
    for b in range(1, 4):
        store.append([joint_event("copy.src", b * {BATCH} + i, i) for i in range({BATCH})])
    print("ready", flush=True)
    sys.stdin.readline()
""")


def test_a_copy_taken_without_its_wal_fails_verify(tmp_path):
    """The README used to say a copy of the file "between batches" is a backup: taken
    while committed batches are still only in the WAL, it held stale data and verified ok."""
    path = tmp_path / "live" / "yard.duckdb"
    path.parent.mkdir()
    writer = subprocess.Popen([sys.executable, "-c", HOLDER, str(path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout.readline() == "ready\n"
        assert Path(str(path) + ".wal").stat().st_size > 0
        copy = tmp_path / "copy"
        copy.mkdir()
        for name in os.listdir(path.parent):        # everything beside it but the WAL
            if not name.endswith(".wal"):
                shutil.copyfile(path.parent / name, copy / name)
    finally:
        writer.stdin.close()
        writer.wait(timeout=60)
    verified = _run("ledger", "verify", "--ledger", str(copy / "yard.duckdb"))
    assert verified.returncode == 1, verified.stdout
    assert "FAILED: head sidecar" in verified.stdout
    assert f"records global_seq {4 * BATCH - 1} " in verified.stdout
    assert f"holds global_seq {BATCH - 1} " in verified.stdout
    # and it cannot be opened for writing as if nothing happened
    refused = _run("ledger", "import", str(_jsonl(tmp_path / "in.jsonl", 0, 1)), "--ledger",
                   str(copy / "yard.duckdb"))
    assert refused.returncode == 2 and "went backwards" in refused.stderr
    json.loads(head_path(copy / "yard.duckdb").read_text())    # untouched, still readable


def test_a_failed_sidecar_write_is_logged_and_the_next_batch_writes_it(tmp_path, capsys):
    """A sidecar that cannot be written (here a directory stands in its place) does not
    fail the append; it is logged, and once the path is writable again the next batch
    brings the sidecar to the head."""
    path = tmp_path / "blocked.duckdb"
    with open_ledger(path, ManualClock(1_000)) as store:
        store.append([joint_event("b.src", 0, 0)])
        head_path(path).unlink()
        head_path(path).mkdir()                   # os.replace onto a directory fails
        store.append([joint_event("b.src", 1, 1)])
        assert store.head().global_seq == 1       # the batch is committed
        assert "cannot write the head sidecar" in capsys.readouterr().err
        head_path(path).rmdir()
        store.append([joint_event("b.src", 2, 2)])
        sidecar = read_head(path)
        assert (sidecar.global_seq, sidecar.chain_sha256) == (2, store.head().chain_sha256)
