"""Every command on a PostgreSQL ledger: the real ``stockpile`` CLI in subprocesses against a
real server (``tests/pg_fixtures.py``: a throw-away server, a fresh schema per test).

The ledger moved is the audit tests' (``tests/test_audit.py``: the short simulated yard of
seed 2, a reclaim cut, late, provisional, superseded and stray assays): exported from
DuckDB, imported into PostgreSQL (recorded times kept: the lines carry them), exported
again (identical lines), verified (the same head and chain), and back into a new DuckDB
file.  ``sql``, ``audit`` and ``project`` give the same answers on both; errors are one
line on stderr with exit 2 and no traceback, and no output ever shows the password.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ledger.pg_local import free_port
from test_audit import PILE, SEED, audit_ledger

PYTHON = sys.executable
#: exit codes (README, stockpile/cli.py): ok, verification failed, an error
EXIT_OK, EXIT_ERROR = 0, 2
#: how long one command may take, seconds
COMMAND_TIMEOUT_S = 300


def run(*args: str, secret: str | None = None) -> subprocess.CompletedProcess:
    """``stockpile ARGS`` in a subprocess; fails if a traceback or ``secret`` shows."""
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=COMMAND_TIMEOUT_S)
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    if secret:
        assert secret not in done.stdout and secret not in done.stderr, \
            f"stockpile {args[0]} printed the password"
    return done


def ok(*args: str, secret: str | None = None) -> str:
    """``stockpile ARGS``, which must succeed; its standard output."""
    done = run(*args, secret=secret)
    assert done.returncode == EXIT_OK, f"stockpile {' '.join(args[:2])}: {done.stderr[-2000:]}"
    return done.stdout


def one_line_error(*args: str, secret: str | None = None) -> str:
    """``stockpile ARGS``, which must fail with exit 2 and one line on stderr; that line."""
    done = run(*args, secret=secret)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == EXIT_ERROR, (done.returncode, done.stderr[-2000:])
    assert len(lines) == 1, done.stderr
    assert "error" in lines[0], lines[0]
    return lines[0]


def head_line(verify_out: str) -> str:
    """``head global_seq N, chain HEX`` of ``stockpile ledger verify``'s first line."""
    match = re.search(r"head global_seq (-?\d+), chain ([0-9a-f]{64})", verify_out)
    assert match, verify_out
    return match.group(0)


@pytest.fixture(scope="module")
def duck(small_yard_sim, tmp_path_factory) -> Path:
    """The audit tests' DuckDB ledger (built once per session)."""
    print(f"simulated yard seed {SEED}")
    path, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    return path


def test_a_ledger_moves_to_postgresql_and_back_with_the_same_lines_and_chain(
        duck, pg_url, pg_server, tmp_path):
    secret = pg_server.password
    a = tmp_path / "a.jsonl"
    ok("ledger", "export", "--ledger", str(duck), "--out", str(a))
    imported = json.loads(ok("ledger", "import", str(a), "--ledger", pg_url, "--clock", "events",
                             "--json", secret=secret))
    lines = a.read_text().splitlines()
    assert imported["appended"] == len(lines) > 1000
    assert imported["head_global_seq"] == len(lines) - 1

    b = tmp_path / "b.jsonl"
    ok("ledger", "export", "--ledger", pg_url, "--out", str(b), secret=secret)
    assert b.read_bytes() == a.read_bytes()

    duck_head = head_line(ok("ledger", "verify", "--ledger", str(duck)))
    pg_verify = ok("ledger", "verify", "--ledger", pg_url, secret=secret)
    assert head_line(pg_verify) == duck_head
    assert "FAILED" not in pg_verify

    c = tmp_path / "back.duckdb"
    ok("ledger", "import", str(b), "--ledger", str(c), "--clock", "events")
    again = tmp_path / "c.jsonl"
    ok("ledger", "export", "--ledger", str(c), "--out", str(again))
    assert again.read_bytes() == a.read_bytes()
    assert head_line(ok("ledger", "verify", "--ledger", str(c))) == duck_head

    stats = ok("ledger", "stats", "--ledger", pg_url, secret=secret)
    assert f"events      {len(lines):,}" in stats
    assert "postgresql://postgres:***@" in stats
    info = json.loads(ok("info", pg_url, "--json", secret=secret))
    assert (info["backend"], info["events"], info["size_bytes"]) == ("postgresql", len(lines),
                                                                     None)


def _import(duck: Path, url: str, tmp_path: Path, secret: str) -> None:
    lines = tmp_path / "ledger.jsonl"
    ok("ledger", "export", "--ledger", str(duck), "--out", str(lines))
    ok("ledger", "import", str(lines), "--ledger", url, "--clock", "events", secret=secret)


SQL_QUERIES = (
    "SELECT type, count(*) AS n, min(global_seq) AS first_seq, max(global_seq) AS last_seq "
    "FROM events GROUP BY type ORDER BY type",
    "SELECT assay_id, lot_id, lab_id, status, superseded, recorded_time_ns FROM assays "
    "ORDER BY global_seq",
    "SELECT cut_id, pile_id, bench_id, belt_tonnes FROM reclaim_cuts ORDER BY global_seq",
    "SELECT lot_id, origin, planned_tonnes, global_seq FROM lots ORDER BY lot_id",
    "SELECT count(*) AS open_gaps FROM gaps WHERE closed_recorded_ns IS NULL",
)


def test_sql_audit_and_project_answer_the_same_on_both(duck, pg_url, pg_server, tmp_path):
    secret = pg_server.password
    _import(duck, pg_url, tmp_path, secret)
    for query in SQL_QUERIES:
        on_duck = ok("sql", "--ledger", str(duck), query, "--format", "json")
        on_pg = ok("sql", "--ledger", pg_url, query, "--format", "json", secret=secret)
        assert on_pg == on_duck and on_pg.strip(), query
    table = ok("sql", "--ledger", pg_url, SQL_QUERIES[0], secret=secret)
    assert "reclaim_cut" in table and table.rstrip().endswith("rows)")

    for report in (["cuts", "--pile", PILE], ["assays"]):
        on_duck = json.loads(ok("audit", *report, "--ledger", str(duck), "--json"))
        on_pg = json.loads(ok("audit", *report, "--ledger", pg_url, "--json", secret=secret))
        assert on_pg == on_duck
        assert on_pg["head_global_seq"] >= 0
    assert json.loads(ok("audit", "cuts", "--pile", PILE, "--ledger", pg_url, "--json",
                         secret=secret))["cuts"], "the audit ledger has a reclaim cut"
    on_duck = json.loads(ok("project", "--ledger", str(duck), "--pile", PILE, "--json"))
    on_pg = json.loads(ok("project", "--ledger", pg_url, "--pile", PILE, "--json",
                          secret=secret))
    assert on_pg == on_duck
    assert on_pg["tonnes"] > 0 and on_pg["cuts"]


def test_sql_is_read_only_on_postgresql(duck, pg_url, pg_server, tmp_path):
    secret = pg_server.password
    _import(duck, pg_url, tmp_path, secret)
    before = ok("sql", "--ledger", pg_url, "SELECT count(*) AS n FROM event_log", secret=secret)
    for statement in ("DELETE FROM event_log", "CREATE TABLE x (i int)",
                      "UPDATE ledger_meta SET value = 'x'"):
        line = one_line_error("sql", "--ledger", pg_url, statement, secret=secret)
        assert "read-only transaction" in line, line
    after = ok("sql", "--ledger", pg_url, "SELECT count(*) AS n FROM event_log", secret=secret)
    assert after == before
    # the prompt: every statement answered, a refused one named, exit 2
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", "sql", "--ledger", pg_url,
                           "--format", "csv"], input="SELECT 1 AS one;\nDELETE FROM gaps;\n"
                          "SELECT 2 AS two;\n", capture_output=True, text=True,
                          timeout=COMMAND_TIMEOUT_S)
    assert done.returncode == EXIT_ERROR
    assert done.stdout == "one\n1\ntwo\n2\n"
    assert "read-only transaction" in done.stderr and secret not in done.stderr


def test_errors_are_one_line_without_the_password(pg_server, pg_schemas, tmp_path):
    secret = pg_server.password
    schema = pg_schemas.new_schema("missing")
    wrong = pg_server.url(password="not-the-password") + f"?schema={schema}"
    for args in (["ledger", "stats", "--ledger", wrong],
                 ["audit", "assays", "--ledger", wrong],
                 ["sql", "--ledger", wrong, "SELECT 1"]):
        line = one_line_error(*args, secret="not-the-password")
        assert "password authentication failed" in line, line

    port = free_port()     # nothing listens there
    unreachable = f"postgresql://postgres:{secret}@127.0.0.1:{port}/postgres?schema=x"
    for args in (["ledger", "export", "--ledger", unreachable],
                 ["project", "--ledger", unreachable, "--pile", PILE],
                 ["sql", "--ledger", unreachable, "SELECT 1"]):
        line = one_line_error(*args, secret=secret)
        assert str(port) in line and ("refused" in line or "connect" in line), line

    missing = pg_schemas.url_of(schema)
    for args in (["ledger", "export", "--ledger", missing],
                 ["audit", "cuts", "--pile", PILE, "--ledger", missing],
                 ["sql", "--ledger", missing, "SELECT 1"]):
        line = one_line_error(*args, secret=secret)
        assert schema in line and "no ledger schema" in line, line

    for command in ("backup", "restore"):
        where = ["--to", str(tmp_path / "b")] if command == "backup" else [str(tmp_path)]
        line = one_line_error("ledger", command, *where, "--ledger", missing, secret=secret)
        assert "pg_basebackup" in line and "pg_dump" in line, line
    line = one_line_error("service", "ledger", "--ledger", missing, "--memory-limit-mb", "64",
                          "--site", "x", secret=secret)
    assert "shared_buffers" in line, line
