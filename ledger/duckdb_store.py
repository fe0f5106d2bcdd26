"""DuckDB ledger store: the default backend, one file.

Tables (raw, append-only; the auditors' views are in :mod:`ledger.views`):

``event_log``
    one row per stored event: identity, valid and recorded time (ns), payload,
    sha256(payload), chain hash, flags, for domain events the JSON body, and for a
    signed event its signer's key id and signature.
``gaps``
    missing source sequence ranges, opened and closed.
``quarantine``
    everything refused, with its reason and raw bytes.
``ledger_meta``
    schema version; the declared analyte list and unknown-analyte policy
    (:func:`ledger.views.recorded_policy`).

Payloads and hashes are random-looking bytes: their columns are stored uncompressed,
because DuckDB's compression analysis of them made each checkpoint seconds long
(3.5x slower appends of scans, measured) for no saving.

Global sequence numbers are assigned by the writer inside its transaction (never a
DuckDB SEQUENCE, whose rolled-back values leave holes).  Every batch is one
transaction.

DuckDB allows one process to open a file for writing *or* many processes to open
it read-only, never both at once.  While a writer (the ledger service) runs, other
processes read through it (the ledger service's Zenoh queryables), or read a backup
(:mod:`ledger.backup`).
"""

from __future__ import annotations

import json
import os
import threading
from dataclasses import replace
from pathlib import Path
from typing import Iterator, Sequence

import duckdb
import pyarrow as pa

from schemas.analytes import AnalyteOptions, AnalytePolicy

from ledger import views
from ledger.bodies import body_problem
from ledger.chain import GENESIS
from ledger.clock import SiteClock
from ledger.duckdb_sql import (  # the schema and the SQL statements
    SCHEMA_VERSION, _DDL, _EVENT_SCHEMA, _FETCH_ROWS, _BEGIN, _COMMIT, _ROLLBACK,
    _SELECT_HEAD, _SELECT_STREAMS, _SELECT_OPEN_GAPS_BY_FIRST_SEQ, _SELECT_LATEST_CLOCK,
    _SELECT_KEY_ROWS, _SELECT_KNOWN_LOTS, _SELECT_NEXT_GAP_ID, _SELECT_NEXT_QUARANTINE_ID,
    _WANTED_KEYS, _KEYS_SCHEMA, _SELECT_WANTED_KEYS, _AND_VALID_IN, _NEW_EVENTS,
    _INSERT_NEW_EVENTS, _FLAG_SEPARATOR, _INSERT_QUARANTINE, _GAP_SCHEMA, _GAP_CHANGES,
    _INSERT_GAPS, _CLOSE_GAPS, _WHERE_TYPE_IN, _WHERE_SOURCE_IN, _WHERE_SEQ_FROM,
    _WHERE_SEQ_BEFORE, _WHERE_VALID_BY, _WHERE_KNOWN_BY, _WHERE_AFTER, _AND,
    _SELECT_ROWS_WHERE, _ORDER_BY_SEQ, _ORDER_BY_TIME, _SELECT_GAPS, _SELECT_OPEN_GAPS,
    _SELECT_QUARANTINE, _SELECT_LAST_QUARANTINE_LINK,
)
from ledger.errors import InterfaceError, OperationalError, ProgrammingError, backend_errors
from ledger.head_file import HeadRecorder, reconcile
from ledger.signing import SigningPolicy, registry_from_rows
from ledger.records import (EventTally, Gap, Head, LedgerStats, QuarantineEntry, RecordedEvent,
                            VerifyReport)
from ledger.store import LedgerStore
from ledger.writer_state import (BODY_TYPES, BatchPlan, Key, StoredKey, StreamState,
                                 WriterState)

# one writer per file per process: a second DuckDBStore on the same file would hold a
# stale copy of the writer state
_OPEN_WRITERS: set[str] = set()
_OPEN_WRITERS_LOCK = threading.Lock()


#: a writer's default cap on DuckDB's buffer pool, megabytes (docs/operations.md)
WRITER_MEMORY_LIMIT_MB = 256
#: how much write-ahead log a writer lets grow before DuckDB checkpoints it into the
#: database file, megabytes (docs/operations.md)
WRITER_CHECKPOINT_MB = 256
_SET_CHECKPOINT_THRESHOLD = f"SET checkpoint_threshold = '{WRITER_CHECKPOINT_MB}MB'"


class DuckDBStore(LedgerStore):
    """A ledger in one DuckDB file.

    Parameters
    ----------
    path : str or Path
        The ledger file; created (with its folder) when missing unless ``read_only``.
    clock : SiteClock, optional
        Source of recorded time (default: wall clock).
    read_only : bool
        Open for reading only; many read-only processes may share a file that no
        writer has open.
    signing : SigningPolicy, optional
        Types that must be signed and the admin key trusted (:mod:`ledger.signing`).
    memory_limit_mb : int or None
        A writer's cap on DuckDB's buffer pool, megabytes (None:
        :data:`WRITER_MEMORY_LIMIT_MB`).
        Without it a long-running writer keeps the pages it wrote cached and its memory
        grows with the file; larger work spills to a temporary directory.

    Raises
    ------
    OperationalError
        The file is missing (read-only) or locked by a writer in another process.
    InterfaceError
        This process already has a writer open on the file.
    ProgrammingError
        The file is not a ledger of this schema version.
    """

    backend = "duckdb"

    def __init__(self, path: str | os.PathLike[str], clock: SiteClock | None = None, *,
                 read_only: bool = False, signing: SigningPolicy | None = None,
                 accept_loss: bool = False,
                 analytes: AnalytePolicy | AnalyteOptions | None = None,
                 memory_limit_mb: int | None = None) -> None:
        super().__init__(clock, read_only=read_only, signing=signing)
        self._given_analytes = analytes
        self.path = Path(path)
        self._registered = False
        self._head_recorder: HeadRecorder | None = None
        self._tally: EventTally | None = None   # stats(): counts kept as batches commit
        resolved = str(self.path.resolve())
        if read_only and not self.path.exists():
            raise OperationalError(f"no ledger at {self.path}")
        if not read_only:
            with _OPEN_WRITERS_LOCK:
                if resolved in _OPEN_WRITERS:
                    raise InterfaceError(f"this process already has {self.path} open for writing")
                _OPEN_WRITERS.add(resolved)
                self._registered = True
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._resolved = resolved
        try:
            with backend_errors():
                self._con = duckdb.connect(str(self.path), read_only=read_only)
            try:
                with backend_errors():
                    if not read_only:
                        limit_mb = memory_limit_mb or WRITER_MEMORY_LIMIT_MB
                        self._con.execute(f"SET memory_limit = '{int(limit_mb)}MB'")
                        self._con.execute(_SET_CHECKPOINT_THRESHOLD)
                        self._create_schema()
                    self._check_schema()
                    self._state, self._analytes = self._load_state()
                if not read_only:
                    self._head_recorder = HeadRecorder(
                        self.path, reconcile(self, self.path, accept_loss=accept_loss))
            except BaseException:
                self._con.close()
                raise
        except BaseException:
            self._unregister()
            raise

    # -- opening ---------------------------------------------------------------------------

    def _create_schema(self) -> None:
        con = self._con
        con.execute("BEGIN TRANSACTION")
        try:
            for ddl in _DDL:
                con.execute(ddl)
            if not con.execute("SELECT count(*) FROM ledger_meta").fetchone()[0]:
                con.execute("INSERT INTO ledger_meta VALUES ('schema_version', ?)", [SCHEMA_VERSION])
            con.execute("COMMIT")
        except BaseException:
            con.execute("ROLLBACK")
            raise

    def _check_schema(self) -> None:
        try:
            row = self._con.execute(
                "SELECT value FROM ledger_meta WHERE key = 'schema_version'").fetchone()
        except duckdb.CatalogException:
            raise ProgrammingError(f"{self.path} is not a stockpile ledger") from None
        if row is None or row[0] != SCHEMA_VERSION:
            raise ProgrammingError(
                f"{self.path} has ledger schema version {row and row[0]!r}, "
                f"this program reads version {SCHEMA_VERSION!r}")

    def _load_state(self) -> tuple[WriterState, set[str]]:
        con = self._con
        state = WriterState()
        head = con.execute(_SELECT_HEAD).fetchone()
        if head is not None:
            state.head_seq, state.last_recorded_ns, state.head_chain = head[0], head[1], bytes(head[2])
        else:
            state.head_chain = GENESIS
        last_entry = con.execute(_SELECT_LAST_QUARANTINE_LINK).fetchone()
        after_head = last_entry is not None and last_entry[0] == state.head_seq
        state.link_chain = bytes(last_entry[1]) if after_head else state.head_chain
        for source, epoch, max_seq in con.execute(_SELECT_STREAMS).fetchall():
            state.streams[(source, epoch)] = StreamState(max_seq=max_seq)
        for values in con.execute(_SELECT_OPEN_GAPS_BY_FIRST_SEQ).fetchall():
            gap = Gap(*values)
            state.streams.setdefault((gap.source, gap.epoch), StreamState()).open_gaps.append(gap)
        state.latest_clock_event_ns = con.execute(_SELECT_LATEST_CLOCK).fetchone()[0]
        state.keys = registry_from_rows((t, bytes(p)) for t, p in
                                        con.execute(_SELECT_KEY_ROWS).fetchall())
        state.known_lots = {
            r[0] for r in con.execute(_SELECT_KNOWN_LOTS).fetchall() if r[0] is not None
        }
        state.next_gap_id = con.execute(_SELECT_NEXT_GAP_ID).fetchone()[0]
        state.next_quarantine_id = con.execute(_SELECT_NEXT_QUARANTINE_ID).fetchone()[0]
        analytes = views.stored_analytes(con)
        self.analytes = self._analyte_policy(analytes)
        return state, analytes

    def _analyte_policy(self, stored: set[str]) -> AnalytePolicy:
        """The declared analytes: the given options resolved against the list the ledger
        recorded (:meth:`AnalyteOptions.resolve`), recorded and the views made from it by
        a writer.  Raises ValueError for a name that collides with a
        fixed column of the views."""
        con = self._con
        recorded = views.recorded_policy(con)
        given = self._given_analytes
        policy = given.resolve(recorded) if given is not None else recorded or AnalytePolicy()
        views.check_declared(policy.declared)
        if not self.read_only:
            con.execute(_BEGIN)
            try:
                if policy != recorded:
                    views.record_policy(con, policy)
                views.create_views(con, policy.declared, stored)
                con.execute(_COMMIT)
            except BaseException:
                con.execute(_ROLLBACK)
                raise
        return policy

    # -- writing ---------------------------------------------------------------------------

    def _lookup(self, keys: Sequence[Key], valid_span_ns: tuple[int, int] | None = None
                ) -> dict[Key, StoredKey]:
        # a resent batch's rows lie in its valid-time span: a filter on it lets the scan skip
        # most of the log; what is not there (a conflict at another valid time) is looked
        # up again over the whole log
        found = self._lookup_in(keys, valid_span_ns) if valid_span_ns else {}
        missing = [k for k in keys if k not in found] if found else keys
        if missing:
            found.update(self._lookup_in(missing, None))
        return found

    def _lookup_in(self, keys: Sequence[Key], valid_span_ns: tuple[int, int] | None
                   ) -> dict[Key, StoredKey]:
        wanted = pa.Table.from_arrays([
            pa.array([k[0] for k in keys]),
            pa.array([k[1] for k in keys]),
            pa.array([k[2] for k in keys]),
        ], schema=_KEYS_SCHEMA)
        low = min(k[2] for k in keys)
        high = max(k[2] for k in keys)
        with backend_errors():
            cur = self._con.cursor()
            try:
                cur.register(_WANTED_KEYS, wanted)
                if valid_span_ns is None:
                    rows = cur.execute(_SELECT_WANTED_KEYS, [low, high]).fetchall()
                else:
                    rows = cur.execute(_SELECT_WANTED_KEYS + _AND_VALID_IN,
                                       [low, high, *valid_span_ns]).fetchall()
            finally:
                cur.close()
        return {(r[0], r[1], r[2]): (r[3], bytes(r[4]), r[5], r[6]) for r in rows}

    def _commit(self, plan: BatchPlan) -> None:
        new_analytes = self._new_analytes(plan)
        with backend_errors():
            self._con.execute(_BEGIN)
            try:
                if plan.rows:
                    self._insert_rows(plan.rows, plan.bodies)
                self._write_rest(plan, new_analytes)
                self._con.execute(_COMMIT)
            except BaseException:
                # a COMMIT that failed (disk full) has already ended the transaction, so
                # this ROLLBACK fails too: the error raised is the first one, never its own
                try:
                    self._con.execute(_ROLLBACK)
                except duckdb.Error:
                    pass
                raise
        self._analytes |= new_analytes
        if self._tally is not None:
            self._tally.add(plan.rows)
        if self._head_recorder is not None and plan.state is not None:
            s = plan.state
            self._head_recorder.record(Head(s.head_seq, s.last_recorded_ns, s.head_chain))

    def _insert_rows(self, rows: list[RecordedEvent], bodies: list[str | None]) -> None:
        """INSERT rows into event_log through Arrow (inside the open transaction)."""
        (global_seq, type_, source, epoch, seq, valid, recorded, payload, payload_sha256,
         chain_sha256, flags, signer, signature) = zip(*rows)   # one column per field
        batch = pa.Table.from_arrays([     # the types are _EVENT_SCHEMA's
            pa.array(global_seq, pa.int64()),
            pa.array(type_, pa.string()),
            pa.array(source, pa.string()),
            pa.array(epoch, pa.int64()),
            pa.array(seq, pa.int64()),
            pa.array(valid, pa.int64()),
            pa.array(recorded, pa.int64()),
            pa.array(payload, pa.binary()),
            pa.array(payload_sha256, pa.binary()),
            pa.array(chain_sha256, pa.binary()),
            pa.array([_FLAG_SEPARATOR.join(f) if f else None for f in flags], pa.string()),
            pa.array(bodies, pa.string()),
            pa.array(signer, pa.string()),
            pa.array(signature, pa.binary()),
        ], schema=_EVENT_SCHEMA)
        self._con.register(_NEW_EVENTS, batch)
        try:
            self._con.execute(_INSERT_NEW_EVENTS)
        finally:
            self._con.unregister(_NEW_EVENTS)

    def _write_rest(self, plan: BatchPlan, new_analytes: set[str]) -> None:
        """Quarantine, gaps and views of a batch (inside the open transaction)."""
        con = self._con
        if plan.quarantine:
            con.executemany(
                _INSERT_QUARANTINE,
                [[q.quarantine_id, q.recorded_time_ns, q.type, q.source, q.epoch, q.seq,
                  q.valid_time_ns, q.code, q.detail, q.raw, q.existing_global_seq,
                  q.after_global_seq, q.chain_sha256]
                 for q in plan.quarantine])
        for gaps, statement in ((plan.closed_gaps, _CLOSE_GAPS), (plan.opened_gaps, _INSERT_GAPS)):
            if gaps:
                self._with_gaps(gaps, statement)
        if new_analytes:
            views.create_views(con, self.analytes.declared, self._analytes | new_analytes)

    def _with_gaps(self, gaps: list[Gap], statement: str) -> None:
        """Run ``statement`` on ``gaps`` registered as the table ``gap_changes`` (one
        statement for a batch's gaps, however many: a backlog filled in order opens and
        closes one per event)."""
        table = pa.Table.from_arrays(
            [pa.array([getattr(g, name) for g in gaps], type=_GAP_SCHEMA.field(name).type)
             for name in _GAP_SCHEMA.names], schema=_GAP_SCHEMA)
        self._con.register(_GAP_CHANGES, table)
        try:
            self._con.execute(statement)
        finally:
            self._con.unregister(_GAP_CHANGES)

    def _new_analytes(self, plan: BatchPlan) -> set[str]:
        found: set[str] = set()
        for row, body in zip(plan.rows, plan.bodies):
            if row.type == "assay" and body:
                found.update(json.loads(body).get("analytes", {}))
        return found - self._analytes

    def checkpoint(self) -> Head:
        """Write everything committed into the database file (DuckDB's CHECKPOINT, which
        empties the WAL); return the head the file then holds."""
        with self._lock:
            self._check_writable()
            with backend_errors():
                self._con.execute("FORCE CHECKPOINT")
            return self.head()

    # -- verifying -------------------------------------------------------------------------

    def verify(self) -> VerifyReport:
        """The chain and flags (:meth:`LedgerStore.verify`), then every stored JSON ``body``
        (what the SQL views and the auditors read) against its row's payload."""
        report = super().verify()
        if not report.ok:
            return report
        with self._lock:
            self._check_open()
            with backend_errors():
                cur = self._con.cursor()
                reader = cur.sql("SELECT global_seq, type, payload, body FROM event_log "
                                 "WHERE body IS NOT NULL OR type IN (SELECT unnest(?)) "
                                 "ORDER BY global_seq", params=[sorted(BODY_TYPES)]
                                 ).to_arrow_reader(_FETCH_ROWS)
                for batch in reader:
                    for g, type_name, payload, body in zip(*(c.to_pylist() for c in batch.columns)):
                        problem = body_problem(type_name, payload, body, BODY_TYPES)
                        if problem:
                            return VerifyReport(False, report.rows_checked, g, problem)
        return report

    # -- reading ---------------------------------------------------------------------------

    def _query(self, sql: str, params: list) -> Iterator[RecordedEvent]:
        """Stream rows as records, fetched in Arrow batches on a cursor of its own."""
        with self._lock:
            self._check_open()
            with backend_errors():
                cur = self._con.cursor()
                reader = cur.sql(sql, params=params).to_arrow_reader(_FETCH_ROWS)
        make = RecordedEvent._make
        try:
            while True:
                with backend_errors():
                    try:
                        batch = reader.read_next_batch()
                    except StopIteration:
                        return
                columns = [column.to_pylist() for column in batch.columns]
                columns[10] = [() if f is None else tuple(f.split(_FLAG_SEPARATOR))
                               for f in columns[10]]
                yield from map(make, zip(*columns))
        finally:
            cur.close()

    @staticmethod
    def _filters(types: Sequence[str] | None, sources: Sequence[str] | None,
                 where: list[str], params: list) -> None:
        if types is not None:
            where.append(_WHERE_TYPE_IN)
            params.append(list(types))
        if sources is not None:
            where.append(_WHERE_SOURCE_IN)
            params.append(list(sources))

    def read(self, start_seq: int = 0, stop_seq: int | None = None, *,
             types: Sequence[str] | None = None,
             sources: Sequence[str] | None = None) -> Iterator[RecordedEvent]:
        where, params = [_WHERE_SEQ_FROM], [start_seq]
        if stop_seq is not None:
            where.append(_WHERE_SEQ_BEFORE)
            params.append(stop_seq)
        self._filters(types, sources, where, params)
        return self._query(_SELECT_ROWS_WHERE + _AND.join(where) + _ORDER_BY_SEQ, params)

    def as_of(self, valid_time_ns: int, known_time_ns: int, *,
              types: Sequence[str] | None = None,
              after: tuple[int, int] | None = None) -> Iterator[RecordedEvent]:
        where = [_WHERE_VALID_BY, _WHERE_KNOWN_BY]
        params: list = [valid_time_ns, known_time_ns]
        if after is not None:
            where.append(_WHERE_AFTER)
            params += [int(after[0]), int(after[0]), int(after[1])]
        self._filters(types, None, where, params)
        return self._query(_SELECT_ROWS_WHERE + _AND.join(where) + _ORDER_BY_TIME, params)

    def gaps(self, *, open_only: bool = False) -> list[Gap]:
        sql = _SELECT_OPEN_GAPS if open_only else _SELECT_GAPS
        with self._lock:
            self._check_open()
            with backend_errors():
                rows = self._con.execute(sql).fetchall()
        return [Gap(*r) for r in rows]

    def quarantine(self) -> list[QuarantineEntry]:
        with self._lock:
            self._check_open()
            with backend_errors():
                rows = self._con.execute(_SELECT_QUARANTINE).fetchall()
        return [QuarantineEntry(*r[:9], bytes(r[9]), r[10], r[11], bytes(r[12])) for r in rows]

    def stats(self) -> LedgerStats:
        """As :meth:`LedgerStore.stats`: the events' counts from a tally the store keeps as
        batches commit (the log is read once, at the first call), gaps and quarantine in
        SQL."""
        with self._lock:
            self._check_open()
            with backend_errors():
                con = self._con
                if self._tally is None:
                    self._tally = _tally_of_log(con)
                open_gaps, missing, closed_gaps = con.execute(
                    "SELECT count(*) FILTER (WHERE closed_recorded_ns IS NULL), "
                    "coalesce(sum(last_seq - first_seq + 1) FILTER (WHERE closed_recorded_ns IS NULL), 0), "
                    "count(*) FILTER (WHERE closed_recorded_ns IS NOT NULL) FROM gaps").fetchone()
                by_code = dict(con.execute(
                    "SELECT code, count(*) FROM quarantine GROUP BY code ORDER BY code").fetchall())
            counted = self._tally.stats(self.head(), [], [])
        return replace(counted, open_gaps=open_gaps, missing_events=int(missing),
                       closed_gaps=closed_gaps, quarantined=sum(by_code.values()),
                       quarantine_by_code=by_code)

    # -- closing ---------------------------------------------------------------------------

    def _close(self) -> None:
        try:
            with backend_errors():
                self._con.close()
        finally:
            self._unregister()

    def _unregister(self) -> None:
        if self._registered:
            with _OPEN_WRITERS_LOCK:
                _OPEN_WRITERS.discard(self._resolved)
            self._registered = False


def _tally_of_log(con) -> EventTally:
    """The :class:`EventTally` of every row of ``event_log``, counted in SQL."""
    tally = EventTally()
    tally.per_type.update(dict(con.execute(
        "SELECT type, count(*) FROM event_log GROUP BY type").fetchall()))
    tally.per_source.update(dict(con.execute(
        "SELECT source, count(*) FROM event_log GROUP BY source").fetchall()))
    vmin, vmax, rmin, rmax = con.execute(
        "SELECT min(valid_time_ns), max(valid_time_ns), min(recorded_time_ns), "
        "max(recorded_time_ns) FROM event_log").fetchone()
    if vmin is not None:
        tally.valid, tally.recorded = (vmin, vmax), (rmin, rmax)
    tally.flagged.update(dict(con.execute(
        "SELECT f, count(*) FROM (SELECT unnest(string_split(flags, ',')) AS f "
        "FROM event_log WHERE flags IS NOT NULL) GROUP BY f").fetchall()))
    return tally
