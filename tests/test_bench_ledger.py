"""Smoke test of ``bench/ledger.py``: ``--quick`` runs to its end as a process, and its
append and re-append tables carry the PostgreSQL columns (ours on PostgreSQL and
eventsourcing's PostgreSQL recorder, on a server the bench starts itself) filled with
numbers.  No figure is judged against a target: the machine is shared and noisy.

Without PostgreSQL server binaries the columns are ``n/a`` with the reason, which
:func:`test_no_server_binaries_make_the_columns_na` checks on an empty binaries folder.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # bench/ is a folder of scripts, imported from the root

from bench._ledger_pg import NO_BINARIES, SKIPPED, PgColumns  # noqa: E402
from ledger.pg_local import PostgresNotFound, find_bindir  # noqa: E402

BENCH = ROOT / "bench" / "ledger.py"
PG_COLUMNS = ("pg_events", "pg", "es_pg", "pg/es_pg", "pg/duckdb")
#: rows of the append table: 2 workloads x 4 batch sizes
APPEND_ROWS = 8
#: wall time the quick run may take before the test gives up, seconds
RUN_TIMEOUT_S = 600

_NUMBER = re.compile(r"^\d{1,3}(,\d{3})*$")
_RATIO = re.compile(r"^\d+(\.\d+)?(e[-+]?\d+)?x$")


def _server_binaries() -> bool:
    try:
        find_bindir()
    except PostgresNotFound:
        return False
    return True


needs_postgres = pytest.mark.skipif(not _server_binaries(),
                                    reason="no PostgreSQL server binaries on this machine")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> str:
    """``bench/ledger.py --quick`` (a small as-of ledger): its standard output."""
    tmp = tmp_path_factory.mktemp("bench-ledger")
    proc = subprocess.run(
        [sys.executable, str(BENCH), "--quick", "--events-1m", "2000", "--tmpdir", str(tmp)],
        capture_output=True, text=True, timeout=RUN_TIMEOUT_S, cwd=ROOT)
    print(proc.stdout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def _table(stdout: str, title_prefix: str) -> tuple[list[str], list[dict[str, str]]]:
    """The header and rows (column -> cell) of the table under the line starting with
    ``title_prefix``."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(title_prefix))
    head = next(i for i in range(start, len(lines)) if lines[i].startswith("workload"))
    columns = [c.strip() for c in lines[head].split(" | ")]
    rows = []
    for line in lines[head + 2:]:
        if not line.strip() or line.startswith("   "):
            break
        cells = [c.strip() for c in line.split(" | ")]
        rows.append(dict(zip(columns, cells)))
    return columns, rows


def _number(cell: str) -> int:
    assert _NUMBER.match(cell), f"not a number: {cell!r}"
    return int(cell.replace(",", ""))


def _check_pg_cells(row: dict[str, str]) -> None:
    _number(row["pg_events"].rstrip("*"))
    for column in ("pg", "es_pg"):
        assert _number(row[column]) > 0, row
    for column in ("pg/es_pg", "pg/duckdb"):
        assert _RATIO.match(row[column]), f"{column} not a ratio: {row}"


@needs_postgres
def test_append_table_has_postgres_columns_with_numbers(quick_run):
    columns, rows = _table(quick_run, "1. Append throughput")
    assert all(c in columns for c in PG_COLUMNS), columns
    assert len(rows) == APPEND_ROWS, rows
    assert {(r["workload"], r["batch"]) for r in rows} == {
        (w, b) for w in ("scan", "yard mix") for b in ("1", "100", "1,000", "10,000")}
    for row in rows:
        _check_pg_cells(row)
        events, pg_events = _number(row["events"]), _number(row["pg_events"].rstrip("*"))
        if row["batch"] == "1":
            assert row["pg_events"].endswith("*") and pg_events < events, row
        else:
            assert pg_events == events and not row["pg_events"].endswith("*"), row
    assert "* batch 1 on PostgreSQL: the first 100 events only" in quick_run


@needs_postgres
def test_reappend_table_has_postgres_columns_with_numbers(quick_run):
    columns, rows = _table(quick_run, "2. Idempotent re-append")
    assert all(c in columns for c in PG_COLUMNS), columns
    assert [r["workload"] for r in rows] == ["scan (re-append)", "yard mix (re-append)"]
    for row in rows:
        _check_pg_cells(row)
        assert _number(row["pg_events"]) == _number(row["events"]), row


@needs_postgres
def test_header_names_the_server(quick_run):
    line = next(x for x in quick_run.splitlines() if x.startswith("postgresql"))
    assert "n/a" not in line and "fsync on" in line, line
    assert "load average" in quick_run.splitlines()[2], quick_run.splitlines()[:4]


def test_no_server_binaries_make_the_columns_na(tmp_path, monkeypatch):
    monkeypatch.setenv("STOCKPILE_PG_BINDIR", str(tmp_path))  # a folder without binaries
    columns = PgColumns.start()
    try:
        assert not columns.available
        assert columns.reason == NO_BINARIES
        assert columns.describe() == f"postgresql   : {NO_BINARIES}"
    finally:
        columns.stop()


def test_no_postgres_flag_makes_the_columns_na():
    columns = PgColumns.start(enabled=False)
    assert not columns.available and columns.reason == SKIPPED and columns.server is None
