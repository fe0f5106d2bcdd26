"""Audit on a hot standby equals audit on the primary, once the standby has replayed.

A streaming replica of the session's server (``LocalPostgres.make_standby``:
``pg_basebackup -R``); the audit tests' ledger (``tests/test_audit.py``) is appended on the
primary with the real ``stockpile ledger import``; once the standby has replayed the
primary's WAL up to the end of that import (``pg_last_wal_replay_lsn() >=`` the primary's
``pg_current_wal_insert_lsn()`` taken after it: with synchronous commit off, the last
commit may not be written yet when the write position is read), ``stockpile audit
cuts|history|assays --json``,
``ledger verify`` and ``sql`` on the standby give what they give on the primary, and
writing to the standby is refused in one line.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import psycopg
import pytest

from test_audit import PILE, SEED, audit_ledger
from test_postgres_cli import EXIT_ERROR, head_line, ok, run

#: how long the standby may take to replay the import, seconds
REPLAY_TIMEOUT_S = 60.0
_POLL_S = 0.05


def on_port(url: str, port: int) -> str:
    """``url`` with its port replaced (the same user, password, database and schema)."""
    parts = urlsplit(url)
    userinfo, _, _hostport = parts.netloc.rpartition("@")
    return urlunsplit(parts._replace(netloc=f"{userinfo}@127.0.0.1:{port}"))


def wait_replayed(primary_admin: str, standby_admin: str) -> str:
    """Block until the standby has replayed the primary's current WAL position; return it."""
    with psycopg.connect(primary_admin, autocommit=True) as con:
        target = con.execute("SELECT pg_current_wal_insert_lsn()").fetchone()[0]
    deadline = time.monotonic() + REPLAY_TIMEOUT_S
    with psycopg.connect(standby_admin, autocommit=True) as con:
        assert con.execute("SELECT pg_is_in_recovery()").fetchone()[0], "not a standby"
        while True:
            caught_up = con.execute("SELECT pg_last_wal_replay_lsn() >= %s::pg_lsn",
                                    [target]).fetchone()[0]
            if caught_up:
                return str(target)
            assert time.monotonic() < deadline, f"the standby did not replay up to {target}"
            time.sleep(_POLL_S)


@pytest.fixture
def standby(pg_server):
    """A hot standby of the session's server, stopped and removed after the test.

    Its directory is a fresh one directly under the temporary directory: run as root, the
    server runs as ``nobody``, who cannot pass through pytest's private ``tmp_path``.
    """
    directory = Path(tempfile.mkdtemp(prefix="stockpile-standby-"))
    try:
        server = pg_server.make_standby(directory)
        try:
            yield server
        finally:
            server.stop()
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def test_audit_on_a_standby_equals_audit_on_the_primary(small_yard_sim, tmp_path_factory,
                                                        pg_server, pg_url, standby, tmp_path):
    print(f"simulated yard seed {SEED}")
    secret = pg_server.password
    duck, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    lines = tmp_path / "ledger.jsonl"
    ok("ledger", "export", "--ledger", str(duck), "--out", str(lines))
    ok("ledger", "import", str(lines), "--ledger", pg_url, "--clock", "events", secret=secret)
    replica = on_port(pg_url, standby.port)
    lsn = wait_replayed(pg_server.url(), standby.url())
    print(f"standby replayed up to {lsn}")

    reports = (["cuts", "--pile", PILE], ["assays"], ["history", "--pile", PILE, "--every", "5min"])
    for report in reports:
        on_primary = json.loads(ok("audit", *report, "--ledger", pg_url, "--json", secret=secret))
        on_standby = json.loads(ok("audit", *report, "--ledger", replica, "--json",
                                   secret=secret))
        assert on_standby == on_primary, report[0]
        assert on_standby["head_global_seq"] == len(lines.read_text().splitlines()) - 1
    assert head_line(ok("ledger", "verify", "--ledger", replica, secret=secret)) == \
        head_line(ok("ledger", "verify", "--ledger", pg_url, secret=secret))
    query = "SELECT type, count(*) AS n FROM events GROUP BY type ORDER BY type"
    assert ok("sql", "--ledger", replica, query, "--format", "csv", secret=secret) == \
        ok("sql", "--ledger", pg_url, query, "--format", "csv", secret=secret)


LOT_LINE = ('{"type":"lot_declared","source":"lims.test","epoch":1,"seq":0,'
            '"valid_time_ns":1790000000000000000,"body":{"lot_id":"LOT-R",'
            '"planned_tonnes":100.0,"time":"2026-09-21T14:13:20Z"}}\n')


def _write_to_standby(pg_server, pg_url: str, standby, tmp_path: Path):
    """One lot appended on the primary and replayed; then ``ledger import`` of a second lot
    into the standby.  Returns (the import's process, its reject file, the second lot's
    file, the standby's URL)."""
    secret = pg_server.password
    events = tmp_path / "one.jsonl"
    events.write_text(LOT_LINE)
    ok("ledger", "import", str(events), "--ledger", pg_url, secret=secret)
    wait_replayed(pg_server.url(), standby.url())
    replica = on_port(pg_url, standby.port)
    more = tmp_path / "more.jsonl"
    more.write_text(LOT_LINE.replace('"seq":0', '"seq":1').replace("LOT-R", "LOT-S"))
    rejects = tmp_path / "refused.rejects.jsonl"
    done = run("ledger", "import", str(more), "--ledger", replica, "--rejects", str(rejects),
               secret=secret)
    return done, rejects, more, replica


def test_writing_to_a_standby_fails_in_one_line_and_changes_nothing(pg_server, pg_url,
                                                                     standby, tmp_path):
    secret = pg_server.password
    done, _rejects, more, replica = _write_to_standby(pg_server, pg_url, standby, tmp_path)
    errors = [line for line in done.stderr.splitlines() if "error" in line]
    assert done.returncode == EXIT_ERROR, done.stderr
    assert len(errors) == 1 and errors[0].startswith("stockpile: error: "), done.stderr
    query = "SELECT lot_id FROM lots ORDER BY lot_id"
    assert ok("sql", "--ledger", replica, query, "--format", "csv", secret=secret) == \
        "lot_id\nLOT-R\n"
    # the primary takes the append, and the standby follows
    ok("ledger", "import", str(more), "--ledger", pg_url, secret=secret)
    wait_replayed(pg_server.url(), standby.url())
    assert ok("sql", "--ledger", replica, query, "--format", "csv", secret=secret) == \
        "lot_id\nLOT-R\nLOT-S\n"


def test_writing_to_a_standby_is_refused_as_a_standby(pg_server, pg_url, standby, tmp_path):
    done, rejects, _more, _replica = _write_to_standby(pg_server, pg_url, standby, tmp_path)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == EXIT_ERROR, done.stderr
    assert not rejects.exists(), "a read-only server is not the line's fault: no reject file"
    assert len(lines) == 1, done.stderr
    assert any(word in lines[0] for word in ("read-only", "recovery", "standby")), lines[0]
