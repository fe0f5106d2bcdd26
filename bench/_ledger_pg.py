"""The ledger benchmark's PostgreSQL columns (see ``bench/ledger.py``).

:class:`PgColumns` starts one throw-away local PostgreSQL server
(:class:`ledger.pg_local.LocalPostgres`, its defaults: fsync and synchronous commit on)
and, for each row of the append table, creates a fresh database for each system:
ours (:func:`ledger.open_ledger` on a ``postgresql://`` URL, the product's
``PostgresStore``) and ``eventsourcing``'s ``PostgresApplicationRecorder`` (its
``postgres`` extra: psycopg 3).  Both connect as the server's superuser over TCP on
127.0.0.1 and append the same pre-built events (same payload bytes, same batch sizes)
as the DuckDB and SQLite columns; a row's databases are dropped after it.

When PostgreSQL cannot run (no server binaries, psycopg missing, a server that does not
start, or ``--no-postgres``) :attr:`PgColumns.reason` says why and every PostgreSQL cell
is ``n/a``.
"""

from __future__ import annotations

import importlib.metadata
from dataclasses import dataclass

from bench._ledger_systems import Workload, batches, es_append, ours_append
from ledger.pg_local import LocalPostgres, PostgresFailed, PostgresNotFound

#: events of a batch-1 row on PostgreSQL, (full, --quick): each batch is a commit
#: waiting for its WAL flush, so the row is capped to take seconds
PG_BATCH1_EVENTS = (1_000, 100)

NO_BINARIES = "n/a (no PostgreSQL server binaries)"
SKIPPED = "n/a (skipped: --no-postgres)"


@dataclass(frozen=True)
class PgRates:
    """One row's PostgreSQL figures: events appended and each system's events/s."""

    events: int
    capped: bool
    ours_ev_s: float
    es_ev_s: float


def pg_events(n: int, batch: int, quick: bool) -> int:
    """Events of a PostgreSQL row: the DuckDB row's ``n``, capped at batch 1."""
    if batch != 1:
        return n
    return min(n, PG_BATCH1_EVENTS[1 if quick else 0])


def _rate(n: int, seconds: float) -> float:
    return n / seconds if seconds > 0 else float("inf")


class PgColumns:
    """The PostgreSQL side of the append table: one local server, fresh databases per row.

    Use :meth:`start`; when :attr:`reason` is not None the server is not running and
    the row methods must not be called.
    """

    def __init__(self, reason: str | None, server: LocalPostgres | None = None) -> None:
        self.reason = reason
        self.server = server
        self._admin = None
        self._psycopg = None
        self._es = None
        if server is not None:
            self._connect_admin()

    # -- starting and stopping ------------------------------------------------------------

    @classmethod
    def start(cls, *, enabled: bool = True, log=None) -> PgColumns:
        """Start the local server, or say why the PostgreSQL columns are ``n/a``."""
        if not enabled:
            return cls(SKIPPED)
        try:
            # deferred: psycopg and eventsourcing's PostgreSQL module are optional
            # (the dev extra); without them the columns are n/a, the rest still runs
            import eventsourcing.postgres  # noqa: F401
            import psycopg  # noqa: F401
        except ImportError as exc:
            return cls(f"n/a (psycopg not installed: {exc}; pip install -e '.[dev]')")
        try:
            server = LocalPostgres()
        except PostgresNotFound as exc:
            if log is not None:
                log(f"PostgreSQL columns n/a: {exc}")
            return cls(NO_BINARIES)
        except PostgresFailed as exc:
            return cls(f"n/a (the PostgreSQL server did not start: {exc})")
        try:
            return cls(None, server)
        except BaseException:
            server.stop()
            raise

    def _connect_admin(self) -> None:
        # deferred: optional dependencies (see start)
        import eventsourcing.postgres as es_postgres
        import psycopg

        self._psycopg, self._es = psycopg, es_postgres
        self._admin = psycopg.connect(self.server.url(database="postgres"), autocommit=True)

    def stop(self) -> None:
        """Close the admin connection and stop the server (its directory is removed)."""
        if self._admin is not None:
            self._admin.close()
            self._admin = None
        if self.server is not None:
            self.server.stop()
            self.server = None

    def __enter__(self) -> PgColumns:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    @property
    def available(self) -> bool:
        return self.reason is None

    def describe(self) -> str:
        """One header line: the server's version and settings, or why it is n/a."""
        if not self.available:
            return f"postgresql   : {self.reason}"
        version = self._admin.execute("SHOW server_version").fetchone()[0]
        settings = {name: self._admin.execute(f"SHOW {name}").fetchone()[0]
                    for name in ("fsync", "synchronous_commit", "shared_buffers")}
        return (f"postgresql   : {version} (LocalPostgres on 127.0.0.1, "
                + ", ".join(f"{k} {v}" for k, v in settings.items())
                + f"); psycopg {importlib.metadata.version('psycopg')} "
                f"({self._psycopg.pq.__impl__}), one fresh database per system and row")

    # -- databases --------------------------------------------------------------------------

    def _create(self, name: str) -> str:
        sql = self._psycopg.sql
        self._admin.execute(sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(
            sql.Identifier(name)))
        self._admin.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name)))
        return name

    def _drop(self, name: str) -> None:
        sql = self._psycopg.sql
        self._admin.execute(sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(
            sql.Identifier(name)))

    def _es_recorder(self, database: str):
        # its insert through a database function: the default path (a psycopg pipeline)
        # hung for good on a batch of 10,000 scans (33 MB), waiting on a server that
        # waited for the rest of the statement
        datastore = self._es.PostgresDatastore(
            database, "127.0.0.1", self.server.port, "postgres", self.server.password,
            enable_db_functions=True)
        recorder = self._es.PostgresApplicationRecorder(datastore)
        recorder.create_table()
        return datastore, recorder

    # -- one row ----------------------------------------------------------------------------

    def append_row(self, tag: str, work: Workload, stored: list, batch: int, *,
                   capped: bool, reappend_batch: int | None = None
                   ) -> tuple[PgRates, PgRates | None]:
        """Append ``work`` (and ``stored``, the same events) at ``batch`` into fresh
        databases; with ``reappend_batch``, then append them all again at that batch.

        Returns the row's rates and, with ``reappend_batch``, the re-append's.
        """
        n = len(work)
        ours_db, es_db = self._create(f"{tag}_ours"), self._create(f"{tag}_es")
        datastore = None
        try:
            url = self.server.url(database=ours_db)
            ours_s, counts = ours_append(url, work, batch)
            if counts["appended"] != n:
                raise RuntimeError(f"ours on PostgreSQL appended {counts} of {n}")
            datastore, recorder = self._es_recorder(es_db)
            es_s, _ = es_append(recorder, stored, batch)
            rates = PgRates(n, capped, _rate(n, ours_s), _rate(n, es_s))
            again = None
            if reappend_batch is not None:
                again = self._reappend(url, recorder, work, stored, reappend_batch)
            return rates, again
        finally:
            if datastore is not None:
                datastore.close()
            self._drop(ours_db)
            self._drop(es_db)

    def _reappend(self, url: str, recorder, work: Workload, stored: list, batch: int
                  ) -> PgRates:
        """Every event again: ours must call each a duplicate, eventsourcing refuse
        every batch."""
        n = len(work)
        dup_s, counts = ours_append(url, work, batch)
        if counts["duplicate"] != n:
            raise RuntimeError(f"re-append on PostgreSQL gave {counts}, expected {n} duplicates")
        es_s, refused = es_append(recorder, stored, batch, expect_duplicates=True)
        expected = len(batches(n, batch))
        if refused != expected:
            raise RuntimeError(f"eventsourcing on PostgreSQL accepted {expected - refused}"
                               " batches of duplicates")
        return PgRates(n, False, _rate(n, dup_s), _rate(n, es_s))

