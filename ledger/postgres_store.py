"""PostgreSQL ledger store: one PostgreSQL schema, many readers while one writer appends.

The schema, its triggers, roles and views are in :mod:`ledger.postgres_sql`.  A ledger
is named by a URL: ``postgresql://USER[:PASSWORD]@HOST[:PORT]/DATABASE[?schema=NAME]``
(``postgres://`` too); ``schema`` is this product's own parameter (default
``stockpile``), stripped before libpq sees the URL.  Messages name a ledger without its
password (:func:`describe_url`).

One writer per ledger: the writer holds a session advisory lock keyed on the schema; a
second writer gets :class:`~ledger.errors.LedgerLocked` naming the holder (pid,
application name, client address, start).  Each batch is one transaction: its event
rows go in by binary ``COPY``, its quarantine entries by executemany, its gap changes by
one ``COPY`` and one ``UPDATE``; the global sequence is assigned by the writer
(:mod:`ledger.store`).

A read-only store holds one ``REPEATABLE READ, READ ONLY`` transaction for its whole life:
everything it reads (its head, streams, rows, gaps) comes from one snapshot, which shows
whole batches only and never blocks the writer.  Reads stream in pages by key (global
seq, or valid time and global seq), never fetching a whole table at once.

The DuckDB-only parts (the head sidecar file, the holder file, backups of a file) do
not apply: PostgreSQL's WAL keeps the committed head.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
from typing import Any, Iterator, Sequence
from urllib.parse import parse_qsl, urlsplit

import psycopg
from psycopg import errors as pg_errors
from psycopg.types.json import Jsonb

from schemas.analytes import AnalyteOptions, AnalytePolicy

from ledger import postgres_sql as ddl
from ledger.postgres_sql import describe_url, split_url
from ledger.bodies import body_problem
from ledger.chain import GENESIS
from ledger.clock import SiteClock
from ledger.errors import (DatabaseError, DataError, IntegrityError, InterfaceError,
                           InternalError, LedgerDiskFull, LedgerError, LedgerLocked,
                           NotSupportedError, OperationalError, ProgrammingError,
                           class_for, disk_full_text, first_line)
from ledger.records import Gap, LedgerStats, QuarantineEntry, RecordedEvent, VerifyReport
from ledger.signing import SigningPolicy, registry_from_rows
from ledger.store import LedgerStore
from ledger.writer_state import (BODY_TYPES, BatchPlan, Key, StoredKey, StreamState,
                                 WriterState)

#: rows fetched per page of a streamed read
PAGE_ROWS = 4_096
#: how long a writer waits for readers of the ``assays`` view when re-creating it, ms
VIEW_LOCK_TIMEOUT_MS = 5_000
#: how long a connection attempt may take, seconds
CONNECT_TIMEOUT_S = 10

_ROW_COLUMNS = ("global_seq, type, source, epoch, seq, valid_time_ns, recorded_time_ns, "
                "payload, payload_sha256, chain_sha256, flags, signer, signature")
_COPY_COLUMNS = _ROW_COLUMNS + ", body"
_COPY_TYPES = ["int8", "text", "text", "int8", "int8", "int8", "int8", "bytea", "bytea",
               "bytea", "text", "text", "bytea", "jsonb"]
_GAP_COLUMNS = ("gap_id, source, epoch, first_seq, last_seq, opened_recorded_ns, "
                "closed_recorded_ns")
_QUARANTINE_COLUMNS = ("quarantine_id, recorded_time_ns, type, source, epoch, seq, "
                       "valid_time_ns, code, detail, raw, existing_global_seq, "
                       "after_global_seq, chain_sha256")
_FLAG_SEPARATOR = ","
_INT64_MIN = -(2**63)


# -- errors: the one place psycopg's exceptions become the ledger's ------------------------------

def _lost_connection(exc: psycopg.Error) -> bool:
    state = exc.sqlstate or ""
    return isinstance(exc, psycopg.OperationalError) and (
        not state or state.startswith(("08", "57P")))


#: psycopg's exception classes -> ours, the first that matches wins
_PG_MAPPING: tuple[tuple[type[BaseException], type[LedgerError]], ...] = (
    (psycopg.IntegrityError, IntegrityError), (psycopg.DataError, DataError),
    (psycopg.OperationalError, OperationalError), (psycopg.ProgrammingError, ProgrammingError),
    (psycopg.NotSupportedError, NotSupportedError), (psycopg.InternalError, InternalError),
    (psycopg.InterfaceError, InterfaceError), (OSError, OperationalError),
    (psycopg.Error, DatabaseError))


def map_postgres_error(exc: BaseException) -> LedgerError:
    """The :class:`LedgerError` for a psycopg (or OS) exception, with a one-line message."""
    if isinstance(exc, LedgerError):
        return exc
    message = first_line(exc)
    if isinstance(exc, pg_errors.DiskFull):
        return LedgerDiskFull(f"the ledger's disk is full: {message}",
                              os_error=disk_full_text(exc) or "No space left on device")
    if isinstance(exc, pg_errors.ReadOnlySqlTransaction):   # 25006: a standby, or read-only
        return OperationalError(f"the PostgreSQL ledger is read-only here: {message}")
    if isinstance(exc, psycopg.Error) and _lost_connection(exc):
        return OperationalError(f"the connection to the PostgreSQL ledger was lost: {message}")
    ours = class_for(exc, _PG_MAPPING)
    return ours(message) if ours else InternalError(f"{type(exc).__name__}: {message}")


@contextlib.contextmanager
def postgres_errors() -> Iterator[None]:
    """Re-raise psycopg exceptions inside the block as :class:`LedgerError` subclasses."""
    try:
        yield
    except LedgerError:
        raise
    except (psycopg.Error, OSError) as exc:
        raise map_postgres_error(exc) from exc


# -- connecting and installing -------------------------------------------------------------------

def application_name(role: str) -> str:
    """What a connection calls itself in ``pg_stat_activity``: program, role, pid, host
    (PostgreSQL keeps 63 bytes)."""
    program = os.path.basename(sys.argv[0] or "python") or "python"
    return f"{program[:20]} {role} pid {os.getpid()} on {socket.gethostname()}"[:63]


def _connect(conninfo: str, role: str, **kwargs: Any) -> psycopg.Connection:
    params = dict(parse_qsl(urlsplit(conninfo).query))
    options: dict[str, Any] = {"connect_timeout": CONNECT_TIMEOUT_S}
    if "application_name" not in params:
        options["application_name"] = application_name(role)
    try:
        with postgres_errors():
            return psycopg.connect(conninfo, **options, **kwargs)
    except LedgerError as exc:
        password = urlsplit(conninfo).password
        if password and password in str(exc):  # never repeat a password in a message
            raise OperationalError(str(exc).replace(password, "***")) from None
        raise


def install(admin_conninfo: str, schema: str | None = None) -> None:
    """Install a ledger schema (tables, triggers, functions, views) and the
    ``stockpile_writer`` / ``stockpile_reader`` roles with their grants; idempotent.

    ``admin_conninfo`` is a URL of a user who may create roles and schemas (a
    superuser); ``schema`` defaults to the URL's ``schema`` parameter, else
    ``stockpile``.  Raises a :class:`~ledger.errors.DatabaseError` subclass on failure.
    """
    conninfo, url_schema = split_url(admin_conninfo)
    with _connect(conninfo, "install", autocommit=True) as con, postgres_errors():
        ddl.install_on(con, ddl.check_schema_name(schema or url_schema))


def _raw_json(text: str) -> str:
    return text


class PostgresStore(LedgerStore):
    """A ledger in one schema of a PostgreSQL database.

    Parameters
    ----------
    url : str
        ``postgresql://USER[:PASSWORD]@HOST[:PORT]/DATABASE[?schema=NAME]``.  A missing
        schema is installed (:func:`install`) when the user may do so, as a DuckDB
        file is created; otherwise it is a one-line error saying how to install it.
    clock : SiteClock, optional
        Source of recorded time (default: wall clock).
    read_only : bool
        Read one snapshot for the store's whole life (no lock, any number at once).
    signing : SigningPolicy, optional
        Types that must be signed and the admin key trusted (:mod:`ledger.signing`).
    analytes : AnalytePolicy or AnalyteOptions, optional
        As for :class:`~ledger.duckdb_store.DuckDBStore`: resolved against the list the
        ledger recorded; a writer records it and re-creates ``assays`` when it grows.

    Raises
    ------
    LedgerLocked
        Another writer holds the ledger (the message names it).
    OperationalError
        The server cannot be reached, or the schema is missing and cannot be installed.
    ProgrammingError
        The schema is not a ledger of this version.
    """

    backend = "postgresql"

    def __init__(self, url: str, clock: SiteClock | None = None, *, read_only: bool = False,
                 signing: SigningPolicy | None = None,
                 analytes: AnalytePolicy | AnalyteOptions | None = None) -> None:
        super().__init__(clock, read_only=read_only, signing=signing)
        try:
            self._conninfo, self.schema = split_url(url)
        except ValueError as exc:
            raise InterfaceError(str(exc)) from None
        self.url = url
        self.name = describe_url(url)
        self._given_analytes = analytes
        self._s = ddl.quoted(self.schema)
        self._con = _connect(self._conninfo, "reader" if read_only else "writer",
                             autocommit=not read_only)
        try:
            with postgres_errors():
                if read_only:
                    self._con.isolation_level = psycopg.IsolationLevel.REPEATABLE_READ
                    self._con.read_only = True
                self._open()
        except BaseException:
            self._con.close()
            raise

    def __repr__(self) -> str:
        return f"PostgresStore({self.name!r}, read_only={self.read_only})"

    # -- opening ---------------------------------------------------------------------------

    def _open(self) -> None:
        # pages are read by key in index order: without these, a table not yet analysed
        # (a fresh or fast-growing ledger) gets plans that scan and sort every row left
        # for every page.  The penalty they add to a plan that must sort would switch on
        # JIT compilation, which costs more than any of these short queries: off.
        self._con.execute("SET enable_sort = off; SET enable_bitmapscan = off; SET jit = off")
        oid = ddl.schema_oid(self._con, self.schema)
        if oid is None:
            oid = self._install_missing()
        if not self.read_only:
            if self._con.execute("SELECT pg_is_in_recovery()").fetchone()[0]:
                raise OperationalError(f"{self.name} is a hot standby (in recovery, "
                                       "read-only): write to the primary")
            self._take_lock(oid)
        self._check_schema()
        self._state = self._load_state()
        self.analytes = self._analyte_policy()

    def _install_missing(self) -> int:
        where = f"ledger schema {self.schema!r} in {self.name}"
        if self.read_only:
            raise OperationalError(f"no {where}")
        if not ddl.may_install(self._con):
            raise OperationalError(
                f"no {where}, and this user may not create it: install it as a database "
                f"administrator with ledger.postgres_store.install(ADMIN_URL, {self.schema!r})")
        ddl.install_on(self._con, self.schema)
        oid = ddl.schema_oid(self._con, self.schema)
        assert oid is not None
        return oid

    def _take_lock(self, oid: int) -> None:
        key = (ddl.LOCK_CLASS << 32) | oid
        if self._con.execute("SELECT pg_try_advisory_lock(%s)", [key]).fetchone()[0]:
            return
        holder = self._con.execute(
            "SELECT a.pid, a.application_name, host(a.client_addr), a.backend_start "
            "FROM pg_locks l JOIN pg_stat_activity a ON a.pid = l.pid "
            "WHERE l.locktype = 'advisory' AND l.granted AND l.classid = %s::bigint::oid "
            "AND l.objid = %s::bigint::oid AND l.objsubid = 1 AND l.database = "
            "(SELECT oid FROM pg_database WHERE datname = current_database())",
            [ddl.LOCK_CLASS, oid]).fetchone()
        if holder is None:
            described = "a writer that is going away"
            pid = None
        else:
            pid, app, addr, started = holder
            described = (f"pid {pid} ({app or 'no application name'}) from "
                         f"{addr or 'a local socket or a hidden address'}"
                         + (f" since {started:%Y-%m-%dT%H:%M:%S%z}" if started else ""))
        raise LedgerLocked(f"{self.name} is held by another writer: {described}; stop it "
                           "first, or read it read-only", pid)

    def _check_schema(self) -> None:
        try:
            row = self._con.execute(f"SELECT value FROM {self._s}.ledger_meta "
                                    "WHERE key = 'schema_version'").fetchone()
        except pg_errors.UndefinedTable:
            raise ProgrammingError(f"schema {self.schema!r} of {self.name} is not a "
                                   "stockpile ledger") from None
        if row is None or row[0] != ddl.SCHEMA_VERSION:
            raise ProgrammingError(
                f"{self.name} has ledger schema version {row and row[0]!r}, this program "
                f"reads version {ddl.SCHEMA_VERSION!r}")

    def _one(self, sql: str, params: Sequence[Any] = ()) -> tuple:
        return self._con.execute(sql.replace("{s}", self._s), params).fetchone()

    def _all(self, sql: str, params: Sequence[Any] = ()) -> list[tuple]:
        return self._con.execute(sql.replace("{s}", self._s), params).fetchall()

    def _load_state(self) -> WriterState:
        state = WriterState()
        head = self._one("SELECT global_seq, recorded_time_ns, chain_sha256 FROM {s}.event_log "
                         "ORDER BY global_seq DESC LIMIT 1")
        if head is not None:
            state.head_seq, state.last_recorded_ns, state.head_chain = head[0], head[1], head[2]
        else:
            state.head_chain = GENESIS
        last_entry = self._one("SELECT after_global_seq, chain_sha256 FROM {s}.quarantine "
                               "ORDER BY quarantine_id DESC LIMIT 1")
        after_head = last_entry is not None and last_entry[0] == state.head_seq
        state.link_chain = bytes(last_entry[1]) if after_head else state.head_chain
        for source, epoch, max_seq in self._all(
                "SELECT source, epoch, max(seq) FROM {s}.event_log GROUP BY source, epoch"):
            state.streams[(source, epoch)] = StreamState(max_seq=max_seq)
        for values in self._all(f"SELECT {_GAP_COLUMNS} FROM {{s}}.gaps "
                                "WHERE closed_recorded_ns IS NULL ORDER BY first_seq"):
            gap = Gap(*values)
            state.streams.setdefault((gap.source, gap.epoch), StreamState()).open_gaps.append(gap)
        state.latest_clock_event_ns = self._one(
            "SELECT max(valid_time_ns) FROM {s}.event_log WHERE type = 'clock'")[0]
        state.keys = registry_from_rows((t, bytes(p)) for t, p in self._all(
            "SELECT type, payload FROM {s}.event_log WHERE type IN "
            "('source_key_declared', 'source_key_revoked') ORDER BY global_seq"))
        state.known_lots = {r[0] for r in self._all(
            "SELECT DISTINCT body->>'lot_id' FROM {s}.event_log WHERE type = 'lot_declared'")
            if r[0] is not None}
        state.next_gap_id = self._one("SELECT coalesce(max(gap_id) + 1, 0) FROM {s}.gaps")[0]
        state.next_quarantine_id = self._one(
            "SELECT coalesce(max(quarantine_id) + 1, 0) FROM {s}.quarantine")[0]
        return state

    def _recorded_policy(self) -> AnalytePolicy | None:
        rows = dict(self._all("SELECT key, value FROM {s}.ledger_meta WHERE key IN "
                              "('analytes', 'unknown_analyte')"))
        if "analytes" not in rows:
            return None
        try:
            names = json.loads(rows["analytes"])
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise ValueError("not a JSON list of names")
            return AnalytePolicy(tuple(names), rows.get("unknown_analyte", "flag"))
        except ValueError as exc:
            raise ValueError(f"the ledger's recorded analyte list (ledger_meta) is damaged: "
                             f"{exc}") from None

    def _analyte_policy(self) -> AnalytePolicy:
        """The declared analytes (as :meth:`DuckDBStore._analyte_policy`); a writer records
        them and re-creates ``assays`` when its list differs from the view's."""
        recorded = self._recorded_policy()
        given = self._given_analytes
        policy = given.resolve(recorded) if given is not None else recorded or AnalytePolicy()
        ddl.views.check_declared(policy.declared)
        if self.read_only:
            return policy
        with self._con.transaction():
            if policy != recorded:
                self._con.execute(
                    f"INSERT INTO {self._s}.ledger_meta VALUES ('analytes', %s), "
                    "('unknown_analyte', %s) ON CONFLICT (key) DO UPDATE SET value = "
                    "excluded.value", [json.dumps(list(policy.declared)), policy.unknown])
            if ddl.views_analytes(self._con, self.schema) != policy.declared:
                self._con.execute(f"SET LOCAL lock_timeout = {VIEW_LOCK_TIMEOUT_MS}")
                try:
                    for statement in ddl.assays_statements(self.schema, policy.declared):
                        self._con.execute(statement)
                except pg_errors.LockNotAvailable:
                    raise OperationalError(
                        f"the declared analytes of {self.name} grew, and its assays view "
                        f"is in use by a reader (waited {VIEW_LOCK_TIMEOUT_MS} ms): open the "
                        "writer again once that reader is done") from None
                self._con.execute(
                    f"INSERT INTO {self._s}.ledger_meta VALUES (%s, %s) ON CONFLICT (key) "
                    "DO UPDATE SET value = excluded.value",
                    [ddl.META_VIEWS_ANALYTES, json.dumps(list(policy.declared))])
        return policy

    # -- writing ---------------------------------------------------------------------------

    def _lookup(self, keys: Sequence[Key], valid_span_ns: tuple[int, int] | None = None
                ) -> dict[Key, StoredKey]:
        if not keys:
            return {}
        with postgres_errors():
            rows = self._all(
                "SELECT e.source, e.epoch, e.seq, e.global_seq, e.payload_sha256, e.type, "
                "e.valid_time_ns "
                "FROM {s}.event_log e JOIN unnest(%s::text[], %s::bigint[], %s::bigint[]) "
                "AS w(source, epoch, seq) USING (source, epoch, seq)",
                [[k[0] for k in keys], [k[1] for k in keys], [k[2] for k in keys]])
        return {(r[0], r[1], r[2]): (r[3], bytes(r[4]), r[5], r[6]) for r in rows}

    def _commit(self, plan: BatchPlan) -> None:
        with postgres_errors(), self._con.transaction():
            if plan.rows:
                self._copy_rows(plan.rows, plan.bodies)
            self._write_rest(plan)

    def _copy_rows(self, rows: list[RecordedEvent], bodies: list[str | None]) -> None:
        """The batch's rows into event_log by binary COPY (inside the open transaction)."""
        sep = _FLAG_SEPARATOR
        with self._con.cursor() as cur:
            with cur.copy(f"COPY {self._s}.event_log ({_COPY_COLUMNS}) FROM STDIN "
                          "(FORMAT BINARY)") as copy:
                copy.set_types(_COPY_TYPES)
                for r, body in zip(rows, bodies):
                    copy.write_row((
                        r.global_seq, r.type, r.source, r.epoch, r.seq, r.valid_time_ns,
                        r.recorded_time_ns, r.payload, r.payload_sha256, r.chain_sha256,
                        sep.join(r.flags) if r.flags else None, r.signer, r.signature,
                        None if body is None else Jsonb(body, dumps=_raw_json)))

    def _write_rest(self, plan: BatchPlan) -> None:
        """Quarantine entries and gap changes of a batch (inside the open transaction)."""
        with self._con.cursor() as cur:
            if plan.quarantine:
                cur.executemany(
                    f"INSERT INTO {self._s}.quarantine ({_QUARANTINE_COLUMNS}) VALUES "
                    "(%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s)",
                    [(q.quarantine_id, q.recorded_time_ns, q.type, q.source, q.epoch, q.seq,
                      q.valid_time_ns, q.code, q.detail, q.raw, q.existing_global_seq,
                      q.after_global_seq, q.chain_sha256) for q in plan.quarantine])
            # one statement each, however many gaps: a backlog filled in order opens and
            # closes one per event
            if plan.closed_gaps:
                cur.execute(
                    f"UPDATE {self._s}.gaps g SET closed_recorded_ns = c.closed FROM "
                    "unnest(%s::bigint[], %s::bigint[]) AS c(gap_id, closed) "
                    "WHERE g.gap_id = c.gap_id",
                    [[g.gap_id for g in plan.closed_gaps],
                     [g.closed_recorded_ns for g in plan.closed_gaps]])
            if plan.opened_gaps:
                with cur.copy(f"COPY {self._s}.gaps ({_GAP_COLUMNS}) FROM STDIN") as copy:
                    for g in plan.opened_gaps:
                        copy.write_row((g.gap_id, g.source, g.epoch, g.first_seq, g.last_seq,
                                        g.opened_recorded_ns, g.closed_recorded_ns))

    # -- reading ---------------------------------------------------------------------------

    def _page(self, sql: str, params: Sequence[Any]) -> list[tuple]:
        with self._lock:
            self._check_open()
            with postgres_errors(), self._con.cursor(binary=True) as cur:
                # planned for each page's own bounds, never a generic plan
                return cur.execute(sql.replace("{s}", self._s), params,
                                   prepare=False).fetchall()

    @staticmethod
    def _record(row: tuple) -> RecordedEvent:
        flags = row[10]
        return RecordedEvent(*row[:10], () if flags is None else tuple(flags.split(_FLAG_SEPARATOR)),
                             row[11], row[12])

    @staticmethod
    def _filters(types: Sequence[str] | None, sources: Sequence[str] | None) -> tuple[str, list]:
        where, params = "", []
        if types is not None:
            where += " AND type = ANY(%s::text[])"
            params.append(list(types))
        if sources is not None:
            where += " AND source = ANY(%s::text[])"
            params.append(list(sources))
        return where, params

    def read(self, start_seq: int = 0, stop_seq: int | None = None, *,
             types: Sequence[str] | None = None,
             sources: Sequence[str] | None = None) -> Iterator[RecordedEvent]:
        self._check_open()
        # pinned to the head at the call: rows are immutable, so pages by key are one answer
        stop = self.head().global_seq + 1 if stop_seq is None else min(stop_seq,
                                                                      self.head().global_seq + 1)
        where, params = self._filters(types, sources)
        sql = (f"SELECT {_ROW_COLUMNS} FROM {{s}}.event_log WHERE global_seq >= %s "
               f"AND global_seq < %s{where} ORDER BY global_seq LIMIT {PAGE_ROWS}")
        return self._read_pages(sql, params, max(start_seq, 0), stop)

    def _read_pages(self, sql: str, params: list, start: int,
                    stop: int) -> Iterator[RecordedEvent]:
        record = self._record
        while start < stop:
            rows = self._page(sql, [start, stop, *params])
            yield from map(record, rows)
            if len(rows) < PAGE_ROWS:
                return
            start = rows[-1][0] + 1

    def as_of(self, valid_time_ns: int, known_time_ns: int, *,
              types: Sequence[str] | None = None,
              after: tuple[int, int] | None = None) -> Iterator[RecordedEvent]:
        self._check_open()
        where, params = self._filters(types, None)
        sql = (f"SELECT {_ROW_COLUMNS} FROM {{s}}.event_log WHERE valid_time_ns <= %s "
               "AND recorded_time_ns <= %s AND global_seq <= %s "
               f"AND (valid_time_ns, global_seq) > (%s, %s){where} "
               f"ORDER BY valid_time_ns, global_seq LIMIT {PAGE_ROWS}")
        mark = (int(after[0]), int(after[1])) if after is not None else (_INT64_MIN, -1)
        return self._as_of_pages(sql, [int(valid_time_ns), int(known_time_ns),
                                       self.head().global_seq], params, mark)

    def _as_of_pages(self, sql: str, bounds: list, params: list,
                     mark: tuple[int, int]) -> Iterator[RecordedEvent]:
        record = self._record
        while True:
            rows = self._page(sql, [*bounds, *mark, *params])
            yield from map(record, rows)
            if len(rows) < PAGE_ROWS:
                return
            mark = (rows[-1][5], rows[-1][0])

    def gaps(self, *, open_only: bool = False) -> list[Gap]:
        where = " WHERE closed_recorded_ns IS NULL" if open_only else ""
        return [Gap(*r) for r in self._page(
            f"SELECT {_GAP_COLUMNS} FROM {{s}}.gaps{where} ORDER BY gap_id", [])]

    def quarantine(self) -> list[QuarantineEntry]:
        rows = self._page(f"SELECT {_QUARANTINE_COLUMNS} FROM {{s}}.quarantine "
                          "ORDER BY quarantine_id", [])
        return [QuarantineEntry(*r) for r in rows]

    def verify(self) -> VerifyReport:
        """The chain and flags (:meth:`LedgerStore.verify`), then every stored JSON ``body``
        (what the SQL views and the auditors read) against its row's payload."""
        report = super().verify()
        if not report.ok:
            return report
        sql = ("SELECT global_seq, type, payload, body FROM {s}.event_log WHERE global_seq >= %s "
               "AND (body IS NOT NULL OR type = ANY(%s::text[])) AND global_seq < %s "
               f"ORDER BY global_seq LIMIT {PAGE_ROWS}")
        start, stop, types = 0, self.head().global_seq + 1, sorted(BODY_TYPES)
        while start < stop:
            rows = self._page(sql, [start, types, stop])
            for g, type_name, payload, body in rows:
                problem = body_problem(type_name, payload, body, BODY_TYPES)
                if problem:
                    return VerifyReport(False, report.rows_checked, g, problem)
            if len(rows) < PAGE_ROWS:
                break
            start = rows[-1][0] + 1
        return report

    def stats(self) -> LedgerStats:
        """As :meth:`LedgerStore.stats`, computed in SQL (no payloads are read)."""
        with self._lock:
            self._check_open()
            with postgres_errors():
                per_type = dict(self._all("SELECT type, count(*) FROM {s}.event_log "
                                          "GROUP BY type ORDER BY type"))
                per_source = dict(self._all("SELECT source, count(*) FROM {s}.event_log "
                                            "GROUP BY source ORDER BY source"))
                vmin, vmax, rmin, rmax = self._one(
                    "SELECT min(valid_time_ns), max(valid_time_ns), min(recorded_time_ns), "
                    "max(recorded_time_ns) FROM {s}.event_log")
                flagged = dict(self._all(
                    "SELECT f, count(*) FROM {s}.event_log, "
                    "unnest(string_to_array(flags, ',')) AS f WHERE flags IS NOT NULL "
                    "GROUP BY f ORDER BY f"))
                open_gaps, missing, closed_gaps = self._one(
                    "SELECT count(*) FILTER (WHERE closed_recorded_ns IS NULL), "
                    "coalesce(sum(last_seq - first_seq + 1) FILTER "
                    "(WHERE closed_recorded_ns IS NULL), 0), "
                    "count(*) FILTER (WHERE closed_recorded_ns IS NOT NULL) FROM {s}.gaps")
                by_code = dict(self._all("SELECT code, count(*) FROM {s}.quarantine "
                                         "GROUP BY code ORDER BY code"))
            return LedgerStats(
                events=sum(per_type.values()), head=self.head(), per_type=per_type,
                per_source=per_source,
                valid_time_range_ns=None if vmin is None else (vmin, vmax),
                recorded_time_range_ns=None if rmin is None else (rmin, rmax),
                open_gaps=open_gaps, missing_events=int(missing), closed_gaps=closed_gaps,
                quarantined=sum(by_code.values()), quarantine_by_code=by_code,
                flagged=flagged)

    # -- closing ---------------------------------------------------------------------------

    def _close(self) -> None:
        # closing the session releases the advisory lock and ends a reader's snapshot
        with contextlib.suppress(psycopg.Error):
            self._con.close()
