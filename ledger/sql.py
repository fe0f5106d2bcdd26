"""``stockpile sql``: the ledger's SQL views, read-only, one query or a small prompt.

The ledger file is opened read-only with the DuckDB the product runs on, so a write
statement fails (one line, exit 2) and the file is never changed.  With a QUERY the
result is printed once (``--format table|csv|json``; json is one JSON object per row,
JSON lines); without one, statements are read from standard input, each ending with
``;``, and every result is printed; end of input ends the session.

DuckDB writes the version of the library that created a file into the file's header;
when it differs from the running DuckDB a one-line warning says so (the running
DuckDB still reads the file when its storage format allows; when it does not, the
error names both versions).

A PostgreSQL ledger (``--ledger postgresql://...[?schema=NAME]``) is queried through
psycopg with the ledger's schema first on the ``search_path``, each statement (each
query, or each statement of the prompt) in its own ``REPEATABLE READ, READ ONLY``
transaction: one snapshot per answer, whole batches only, a write refused by the
server; the output formats are the same.  The same views hold the same columns there,
so the SQL of the README runs unchanged (``psql`` with the reader role reads them too).
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import decimal
import json
import sys
import uuid
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence, TextIO

import duckdb

from common.options import add_ledger, describe_ledger, is_ledger_url
from ledger.holder import read_holder

from ledger.errors import InterfaceError

EXIT_OK, EXIT_USAGE = 0, 2
FORMATS = ("table", "csv", "json")
MCAP_MAGIC = b"\x89MCAP0\r\n"
#: DuckDB's main file header: 8-byte checksum, b"DUCK", then (u64 storage version,
#: 4 x u64 flags, 32-byte library version string, 32-byte git hash)
_DUCK_MAGIC_AT = 8
_DUCK_VERSION_AT = 52
_DUCK_VERSION_BYTES = 32
#: the auditors' views and tables (ledger.views, ledger.duckdb_store), for the prompt's banner
RELATIONS = ("events", "assays", "reclaim_cuts", "stack_passes", "lots", "gaps", "quarantine")


class SqlError(InterfaceError):
    """A query or a ledger file DuckDB refused (the message is one line)."""


def is_duckdb_file(path: str | Path) -> bool:
    """Whether the file starts with DuckDB's header (``DUCK`` after the checksum)."""
    with open(path, "rb") as handle:
        head = handle.read(_DUCK_MAGIC_AT + 4)
    return head[_DUCK_MAGIC_AT:_DUCK_MAGIC_AT + 4] == b"DUCK"


def created_by_version(path: str | Path) -> str | None:
    """The DuckDB version that created a database file (``v1.4.1``), from its header.

    None when the file is not a DuckDB file or its header predates the field.
    """
    with open(path, "rb") as handle:
        head = handle.read(_DUCK_VERSION_AT + _DUCK_VERSION_BYTES)
    if (head[_DUCK_MAGIC_AT:_DUCK_MAGIC_AT + 4] != b"DUCK"
            or len(head) < _DUCK_VERSION_AT + _DUCK_VERSION_BYTES):
        return None
    raw = head[_DUCK_VERSION_AT:_DUCK_VERSION_AT + _DUCK_VERSION_BYTES].split(b"\0", 1)[0]
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        return None
    return text if text.startswith("v") else None


def version_warning(path: str | Path) -> str | None:
    """One line when the file was created by another DuckDB version than the running one."""
    written = created_by_version(path)
    running = duckdb.__version__
    if written is None or written.lstrip("v").split("-")[0] == running:
        return None
    return (f"warning: {path} was created by DuckDB {written}; this is DuckDB v{running} "
            "(results are this version's reading of the file)")


def one_line(exc: BaseException) -> str:
    """An exception's message, first line only (DuckDB appends context lines)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def connect_read_only(path: str | Path) -> duckdb.DuckDBPyConnection:
    """A read-only DuckDB connection to a ledger file; :class:`SqlError` when it is not one."""
    path = Path(path)
    if not path.exists():
        raise SqlError(f"no such file: {path}")
    if not path.is_file():
        raise SqlError(f"{path} is not a file")
    with open(path, "rb") as handle:
        if handle.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
            raise SqlError(f"{path} is an MCAP file, not a ledger (try: stockpile info {path})")
    if not is_duckdb_file(path):
        raise SqlError(f"{path} is not a ledger (not a DuckDB file)")
    try:
        con = duckdb.connect(str(path), read_only=True)
    except duckdb.Error as exc:
        holder = read_holder(path)
        if holder is not None and "lock" in str(exc).lower():
            raise SqlError(f"{path} is held by {holder.describe()}, and SQL needs the file "
                           f"itself: stop the service, or query a copy (stockpile ledger export "
                           f"--ledger {path} | stockpile ledger import - --ledger COPY)") from None
        raise SqlError(f"cannot open {path} read-only with DuckDB v{duckdb.__version__}: "
                       f"{one_line(exc)}") from None
    try:
        tables = {r[0] for r in con.execute(
            "SELECT table_name FROM information_schema.tables").fetchall()}
    except duckdb.Error as exc:
        con.close()
        raise SqlError(f"{path}: {one_line(exc)}") from None
    if not {"ledger_meta", "event_log"} <= tables:
        con.close()
        raise SqlError(f"{path} is a DuckDB file but not a ledger (no ledger_meta/event_log)")
    return con


def run_query(con: duckdb.DuckDBPyConnection, query: str) -> tuple[list[str], list[tuple]]:
    """Column names and rows of a query (the last statement's, for several)."""
    try:
        result = con.execute(query)
        if result.description is None:
            return [], []
        columns = [d[0] for d in result.description]
        return columns, result.fetchall()
    except duckdb.Error as exc:
        raise SqlError(one_line(exc)) from None


def _json_value(value: Any) -> Any:
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, decimal.Decimal):
        return float(value)
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    if isinstance(value, (dt.datetime, dt.date, dt.time)):
        return value.isoformat()
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _json_value(v) for k, v in value.items()}
    if isinstance(value, (uuid.UUID, dt.timedelta)):
        return str(value)
    return str(value)


def _cell(value: Any) -> str:
    if value is None:
        return "NULL"
    if isinstance(value, float):
        return f"{value:.10g}"
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value).hex()
    if isinstance(value, (dict, list)):   # PostgreSQL's jsonb and arrays
        return json.dumps(_json_value(value))
    return str(value).replace("\n", " ")


def write_result(columns: Sequence[str], rows: Iterable[tuple], fmt: str, out: TextIO) -> int:
    """Print a result as ``table`` (aligned, numbers right), ``csv`` or ``json`` lines.

    Returns the number of rows written.
    """
    rows = list(rows)
    if not columns:
        return 0
    if fmt == "csv":
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(columns)
        for row in rows:
            writer.writerow(["" if v is None else _cell(v) for v in row])
    elif fmt == "json":
        for row in rows:
            out.write(json.dumps({c: _json_value(v) for c, v in zip(columns, row)}) + "\n")
    elif fmt == "table":
        cells = [[_cell(v) for v in row] for row in rows]
        numeric = [bool(rows) and all(isinstance(r[i], (int, float, decimal.Decimal))
                                      and not isinstance(r[i], bool)
                                      for r in rows if r[i] is not None)
                   for i in range(len(columns))]
        widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(columns)]

        def line(values: Sequence[str]) -> str:
            return "  ".join(v.rjust(w) if num else v.ljust(w)
                             for v, w, num in zip(values, widths, numeric)).rstrip()

        out.write(line(columns) + "\n")
        out.write("  ".join("-" * w for w in widths) + "\n")
        for r in cells:
            out.write(line(r) + "\n")
        out.write(f"({len(rows):,} row{'' if len(rows) == 1 else 's'})\n")
    else:
        raise ValueError(f"unknown format {fmt!r}; one of {', '.join(FORMATS)}")
    return len(rows)


def statements(lines: Iterable[str]) -> Iterable[str]:
    """Statements from input lines: text up to a line that ends with ``;``."""
    buffer: list[str] = []
    for line in lines:
        buffer.append(line.rstrip("\n"))
        if line.rstrip().endswith(";"):
            text = "\n".join(buffer).strip()
            buffer = []
            if text.rstrip(";").strip():
                yield text
    rest = "\n".join(buffer).strip()
    if rest:
        yield rest


Query = Callable[[str], "tuple[list[str], list[tuple]]"]


def interactive(run: Query, fmt: str, stdin: TextIO, out: TextIO, err: TextIO, *,
                engine: str = f"DuckDB v{duckdb.__version__}") -> int:
    """Run statements read from ``stdin`` through ``run`` until end of input; exit 2 if any
    failed.  ``engine`` names the database in the prompt's banner."""
    tty = stdin.isatty()
    if tty:
        print(f"{engine}, read-only. Views and tables: "
              f"{', '.join(RELATIONS)}. End each statement with ';', Ctrl-D to quit.",
              file=err)

    def prompted() -> Iterable[str]:
        first = True
        while True:
            if tty:
                err.write("sql> " if first else "...> ")
                err.flush()
            line = stdin.readline()
            if not line:
                if tty:
                    err.write("\n")
                return
            first = line.rstrip().endswith(";")
            yield line

    failed = False
    for statement in statements(prompted()):
        try:
            columns, rows = run(statement)
        except SqlError as exc:
            failed = True
            print(f"stockpile sql: error: {exc}", file=err)
            continue
        write_result(columns, rows, fmt, out)
        out.flush()
    return EXIT_USAGE if failed else EXIT_OK


def cmd_sql(args: argparse.Namespace, *, stdin: TextIO | None = None,
            stdout: TextIO | None = None, stderr: TextIO | None = None) -> int:
    """``stockpile sql``: errors are one line on stderr and exit 2."""
    stdin = stdin or sys.stdin
    out = stdout or sys.stdout
    err = stderr or sys.stderr
    if is_ledger_url(args.ledger):
        return _sql_postgres(args, stdin, out, err)
    try:
        con = connect_read_only(args.ledger)
    except (SqlError, OSError) as exc:
        print(f"stockpile sql: error: {one_line(exc)}", file=err)
        return EXIT_USAGE
    try:
        warning = version_warning(args.ledger)
        if warning:
            print(f"stockpile sql: {warning}", file=err)
        return _answer(lambda query: run_query(con, query), args, stdin, out, err,
                       engine=f"DuckDB v{duckdb.__version__}")
    finally:
        con.close()


def _answer(run: Query, args: argparse.Namespace, stdin: TextIO, out: TextIO, err: TextIO, *,
            engine: str) -> int:
    """The query of ``args`` (or the prompt's statements) through ``run``, printed."""
    if args.query is None:
        return interactive(run, args.format, stdin, out, err, engine=engine)
    try:
        columns, rows = run(args.query)
    except SqlError as exc:
        print(f"stockpile sql: error: {exc}", file=err)
        return EXIT_USAGE
    write_result(columns, rows, args.format, out)
    return EXIT_OK


# -- PostgreSQL ---------------------------------------------------------------------------------


class PostgresSql:
    """A read-only SQL session on a PostgreSQL ledger: its schema first on the search path,
    every statement in a transaction of its own (``REPEATABLE READ, READ ONLY``).

    Raises :class:`SqlError` (one line, the password never in it) when the server cannot
    be reached, refuses the login, or has no such ledger schema.
    """

    def __init__(self, url: str) -> None:
        # deferred: psycopg is in the [ledger] extra, and only a PostgreSQL ledger needs it
        try:
            import psycopg
            from ledger.postgres_sql import split_url
            from ledger.postgres_store import CONNECT_TIMEOUT_S
        except ImportError as exc:
            raise SqlError(f"a PostgreSQL ledger needs psycopg (pip install "
                           f"'stockpile-ledger[ledger]'): {one_line(exc)}") from None
        self._psycopg = psycopg
        self.name = describe_ledger(url)
        try:
            conninfo, self.schema = split_url(url)
        except ValueError as exc:
            raise SqlError(one_line(exc)) from None
        try:
            self.con = psycopg.connect(conninfo, connect_timeout=CONNECT_TIMEOUT_S,
                                       application_name="stockpile sql")
        except psycopg.Error as exc:
            raise SqlError(f"cannot connect to {self.name}: {_pg_line(exc)}") from None
        try:
            self._prepare()
        except BaseException:
            self.con.close()
            raise

    def _prepare(self) -> None:
        psycopg = self._psycopg
        self.con.isolation_level = psycopg.IsolationLevel.REPEATABLE_READ
        self.con.read_only = True
        try:
            found = self.con.execute("SELECT to_regclass(format('%%I.event_log', %s::text)), "
                                     "current_setting('server_version')",
                                     [self.schema]).fetchone()
            if found[0] is None:
                raise SqlError(f"no ledger schema {self.schema!r} in {self.name}")
            self.server_version = found[1]
            self.con.execute("SELECT set_config('search_path', format('%%I, public', "
                             "%s::text), false)", [self.schema])
            self.con.commit()
        except psycopg.Error as exc:
            raise SqlError(f"{self.name}: {_pg_line(exc)}") from None

    def run(self, query: str) -> tuple[list[str], list[tuple]]:
        """Column names and rows of ``query`` (the last statement's, for several), in one
        read-only snapshot; :class:`SqlError` with the server's words when it refuses."""
        psycopg = self._psycopg
        try:
            columns: list[str] = []
            rows: list[tuple] = []
            with self.con.cursor() as cur:
                cur.execute(query)
                while True:
                    if cur.description is not None:
                        columns, rows = [d.name for d in cur.description], cur.fetchall()
                    if not cur.nextset():
                        break
            return columns, rows
        except psycopg.Error as exc:
            raise SqlError(_pg_line(exc)) from None
        finally:
            self._end()

    def _end(self) -> None:
        try:
            self.con.rollback()   # read-only: nothing to keep; a failed statement's end
        except self._psycopg.Error:
            pass

    def close(self) -> None:
        self.con.close()


def _pg_line(exc: BaseException) -> str:
    """psycopg's message on one line (libpq puts the server's words after a newline)."""
    text = " ".join(part.strip() for part in str(exc).strip().splitlines() if part.strip())
    return text or type(exc).__name__


def _sql_postgres(args: argparse.Namespace, stdin: TextIO, out: TextIO, err: TextIO) -> int:
    try:
        session = PostgresSql(args.ledger)
    except SqlError as exc:
        print(f"stockpile sql: error: {exc}", file=err)
        return EXIT_USAGE
    try:
        return _answer(session.run, args, stdin, out, err,
                       engine=f"PostgreSQL {session.server_version} ({session.name})")
    finally:
        session.close()


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``sql`` to the ``stockpile`` parser."""
    p = subparsers.add_parser(
        "sql", help="query a ledger's SQL views (read-only): one query or a prompt",
        description="Run SQL on a ledger's views (events, assays, reclaim_cuts, stack_passes, "
        "lots) and tables (gaps, quarantine), read-only, with the DuckDB this program runs "
        "on, or on a PostgreSQL ledger's server (one read-only snapshot per statement). "
        "With QUERY, print its result; without, read statements ending in ';' from "
        "standard input until end of input.")
    add_ledger(p, help="opened read-only")
    p.add_argument("query", nargs="?", metavar="QUERY", help="one SQL query (default: read "
                   "statements from standard input)")
    p.add_argument("--format", choices=FORMATS, default="table",
                   help="table (aligned columns, the default), csv, or json (one object per "
                   "row, JSON lines)")
    p.set_defaults(func=cmd_sql)
