"""The append-only event ledger: stores, records, errors, clocks.

>>> from ledger import open_ledger
>>> with open_ledger(":memory:") as store:
...     store.head().global_seq
-1

- :mod:`ledger.store`: the store interface and the shared append logic
- :mod:`ledger.duckdb_store`: the default backend (one DuckDB file)
- :mod:`ledger.memory`: the in-memory backend
- :mod:`ledger.postgres_store`: a PostgreSQL backend (one schema; readers while one writer
  appends); :mod:`ledger.postgres_sql` its schema, :mod:`ledger.pg_local` a throw-away
  local server
- :mod:`ledger.testing`: the contract test class every backend passes
- :mod:`ledger.errors`: the exception tree
- :mod:`ledger.records`: the immutable records the ledger returns
- :mod:`ledger.clock`: site clocks, where recorded time comes from
- :mod:`ledger.chain`: the payload hash and the hash chain
- :mod:`ledger.views`: SQL views for auditors
- :mod:`ledger.wire`: the forms reads take over the network (record chunks, JSON)
- :mod:`ledger.holder`: who holds a ledger file, and reading it through them
- :mod:`ledger.head_file`: the head sidecar, which detects a lost tail
- :mod:`ledger.backup`: consistent, verified backups and their restore
- :mod:`ledger.cli`: ``stockpile ledger import|export|verify|stats``
"""

from __future__ import annotations

import os
from pathlib import Path

from schemas.analytes import AnalyteOptions, AnalytePolicy

from ledger.clock import EventClock, ManualClock, SiteClock, WallClock, clock_by_name
from ledger.errors import (
    DatabaseError,
    DataError,
    HeadWentBackwards,
    IntegrityError,
    LedgerLocked,
    InterfaceError,
    InternalError,
    LedgerError,
    NotSupportedError,
    OperationalError,
    ProgrammingError,
)
from ledger.records import (
    AppendOutcome,
    AppendResult,
    Gap,
    Head,
    LedgerStats,
    QuarantineEntry,
    RecordedEvent,
    StreamInfo,
    VerifyReport,
)
from ledger.holder import open_held, read_holder
from ledger.memory import MemoryStore
from ledger.signing import SigningPolicy
from ledger.store import LedgerStore

MEMORY = ":memory:"
#: what a PostgreSQL ledger's URL starts with
POSTGRES_SCHEMES = ("postgresql://", "postgres://")


def is_postgres_url(text: object) -> bool:
    """Whether ``text`` names a PostgreSQL ledger (``postgresql://...`` or
    ``postgres://...``) rather than a DuckDB file."""
    return isinstance(text, str) and text.startswith(POSTGRES_SCHEMES)


def _open_postgres(url: str, clock: SiteClock | None, *, read_only: bool,
                   signing: SigningPolicy | None, accept_loss: bool,
                   analytes: AnalytePolicy | AnalyteOptions | None) -> LedgerStore:
    """A :class:`~ledger.postgres_store.PostgresStore`; options that only mean something
    for a DuckDB file are refused in one line."""
    if accept_loss:
        raise InterfaceError("accept_loss (--accept-loss) applies to a DuckDB file's head "
                             "sidecar; a PostgreSQL ledger keeps its committed head in the "
                             "server's WAL and has none")
    try:
        # deferred: psycopg is only needed by the processes that open a PostgreSQL ledger
        from ledger.postgres_store import PostgresStore
    except ImportError as exc:
        raise InterfaceError(f"a PostgreSQL ledger needs psycopg (pip install "
                             f"'stockpile-ledger[ledger]'): {exc}") from None
    return PostgresStore(url, clock, read_only=read_only, signing=signing, analytes=analytes)


def open_ledger(path: str | os.PathLike[str], clock: SiteClock | None = None, *,
                read_only: bool = False, signing: SigningPolicy | None = None,
                accept_loss: bool = False,
                analytes: AnalytePolicy | AnalyteOptions | None = None,
                memory_limit_mb: int | None = None) -> LedgerStore:
    """Open (or create) a ledger: a DuckDB file, a PostgreSQL URL
    (``postgresql://USER@HOST/DB?schema=NAME``, :mod:`ledger.postgres_store`), or
    ``":memory:"`` for the in-memory store.

    ``analytes`` is the site's declared analyte list and unknown-analyte policy; a DuckDB
    ledger records it and adds it to the list it recorded before (None: the recorded
    list, or the built-in one for a new ledger).

    Read-only, a file that a running ledger service holds is read through that service
    (:mod:`ledger.holder`) when the application registered a reader for it.

    For writing, a file is checked against its head sidecar (:mod:`ledger.head_file`):
    a ledger whose head went backwards raises :class:`HeadWentBackwards`, unless
    ``accept_loss`` (a human has looked), which logs the loss and rewrites the sidecar.
    A PostgreSQL ledger has no sidecar: ``accept_loss`` is refused for it, and
    ``memory_limit_mb`` (DuckDB's buffer pool cap) does not apply and is ignored.
    """
    if is_postgres_url(path):
        return _open_postgres(str(path), clock, read_only=read_only, signing=signing,
                              accept_loss=accept_loss, analytes=analytes)
    if str(path) == MEMORY:
        if read_only:
            raise InterfaceError("an in-memory ledger cannot be opened read-only")
        return MemoryStore(clock, signing=signing, analytes=analytes)
    # deferred: duckdb and pyarrow are heavy, and most processes that import the ledger
    # package (the edge services) never open a DuckDB file (see docs/design-notes.md)
    from ledger.duckdb_store import DuckDBStore

    try:
        return DuckDBStore(path, clock, read_only=read_only, signing=signing,
                           accept_loss=accept_loss, analytes=analytes,
                           memory_limit_mb=memory_limit_mb)
    except LedgerLocked as locked:
        if read_only:
            return open_held(Path(path), locked)
        holder = read_holder(path)
        if holder is not None and holder.pid == locked.holder_pid:
            raise LedgerLocked(f"{path} is held by {holder.describe()}: publish to it, "
                               "or stop it first", holder.pid) from None
        raise


__all__ = [
    "AppendOutcome", "AppendResult", "DataError", "DatabaseError", "EventClock", "Gap", "Head",
    "HeadWentBackwards",
    "IntegrityError", "InterfaceError", "InternalError", "LedgerError", "LedgerStats",
    "LedgerLocked", "LedgerStore", "MEMORY", "ManualClock", "NotSupportedError", "OperationalError",
    "ProgrammingError", "QuarantineEntry", "RecordedEvent", "SiteClock", "StreamInfo",
    "VerifyReport", "WallClock", "clock_by_name", "is_postgres_url", "open_ledger",
]
