"""The ledger's exception tree, and the one place backend errors are mapped into it.

::

    LedgerError                      base of everything the ledger raises
    ├── InterfaceError               misuse of the API: closed store, wrong argument types,
    │                                a second writer on one file in one process
    └── DatabaseError                the backend could not do what was asked
        ├── DataError                a value the backend cannot store
        ├── OperationalError         not now: missing file, disk full, I/O error
        │   ├── LedgerLocked         the file is open for writing by another process
        │   └── LedgerDiskFull       the ledger's disk (or quota) is full; retry once space returns
        ├── IntegrityError           stored data contradicts the ledger's invariants
        ├── InternalError            an unexpected backend failure
        ├── ProgrammingError         schema version or SQL mismatch (a bug or an old file)
        └── NotSupportedError        an operation this backend does not offer

Bad *events* are not exceptions: they are quarantined and reported per event in
:class:`~ledger.records.AppendResult`.  Exceptions are for the store itself.
"""

from __future__ import annotations

import contextlib
import errno
import re
from typing import Iterator, Sequence


class LedgerError(Exception):
    """Base class of every error the ledger raises."""


class InterfaceError(LedgerError):
    """The API was used wrongly (closed store, wrong argument types, second writer)."""


class DatabaseError(LedgerError):
    """The backend could not do what was asked."""


class DataError(DatabaseError):
    """A value the backend cannot store."""


class OperationalError(DatabaseError):
    """Not possible now: locked by another process, missing file, disk full, I/O."""


class LedgerLocked(OperationalError):
    """The ledger file is open for writing by another process.

    ``holder_pid`` is that process's id when the backend names it, else None.
    """

    def __init__(self, message: str, holder_pid: int | None = None) -> None:
        super().__init__(message)
        self.holder_pid = holder_pid


class IntegrityError(DatabaseError):
    """Stored data contradicts the ledger's invariants."""


class InternalError(DatabaseError):
    """An unexpected backend failure."""


class ProgrammingError(DatabaseError):
    """Schema version or SQL mismatch: a bug, or a ledger file from another version."""


class NotSupportedError(DatabaseError):
    """An operation this backend does not offer."""


def _duckdb_mapping() -> list[tuple[type[BaseException], type[LedgerError]]]:
    # deferred: duckdb is heavy and only a DuckDB store (which has imported it) raises its errors
    import duckdb

    mapping: list[tuple[type[BaseException], type[LedgerError]]] = []
    # most specific first: duckdb's exceptions subclass each other
    for name, ours in (
        ("ConstraintException", IntegrityError),
        ("IntegrityError", IntegrityError),
        ("ConversionException", DataError),
        ("OutOfRangeException", DataError),
        ("DataError", DataError),
        ("IOException", OperationalError),
        ("OutOfMemoryException", OperationalError),
        ("TransactionException", OperationalError),
        ("InterruptException", OperationalError),
        ("OperationalError", OperationalError),
        ("NotImplementedException", NotSupportedError),
        ("NotSupportedError", NotSupportedError),
        ("CatalogException", ProgrammingError),
        ("BinderException", ProgrammingError),
        ("ParserException", ProgrammingError),
        ("ProgrammingError", ProgrammingError),
        ("InternalException", InternalError),
        ("InternalError", InternalError),
        ("Error", DatabaseError),
    ):
        cls = getattr(duckdb, name, None)
        if isinstance(cls, type) and issubclass(cls, BaseException):
            mapping.append((cls, ours))
    return mapping


_MAPPING: list[tuple[type[BaseException], type[LedgerError]]] | None = None


def first_line(exc: BaseException) -> str:
    """A backend exception's message as one line (its class name when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0].strip() if text else type(exc).__name__


def class_for(exc: BaseException, mapping: Sequence[tuple[type[BaseException],
                                                          type[LedgerError]]]
              ) -> type[LedgerError] | None:
    """The :class:`LedgerError` subclass of the first ``(backend class, ours)`` pair of
    ``mapping`` that ``exc`` is an instance of (None when none is)."""
    for backend_cls, ours in mapping:
        if isinstance(exc, backend_cls):
            return ours
    return None


def map_backend_error(exc: BaseException) -> LedgerError:
    """The :class:`LedgerError` for a backend exception (DuckDB or OS)."""
    global _MAPPING
    if isinstance(exc, LedgerError):
        return exc
    if _MAPPING is None:
        _MAPPING = _duckdb_mapping()
    message = first_line(exc)
    os_error = disk_full_text(exc)
    if os_error is not None:
        return LedgerDiskFull(f"the ledger's disk is full: {message}", os_error=os_error)
    if isinstance(exc, OSError):
        return OperationalError(message)
    ours = class_for(exc, _MAPPING)
    if ours is OperationalError and "lock" in message.lower():
        pid = re.search(r"\(PID (\d+)\)", message)
        return LedgerLocked(
            "the ledger is open for writing by another process "
            f"(one writer or many readers, never both): {message}",
            int(pid.group(1)) if pid else None)
    return ours(message) if ours else InternalError(f"{type(exc).__name__}: {message}")


@contextlib.contextmanager
def backend_errors() -> Iterator[None]:
    """Re-raise backend exceptions inside the block as :class:`LedgerError` subclasses."""
    try:
        yield
    except LedgerError:
        raise
    except Exception as exc:
        raise map_backend_error(exc) from exc


class HeadWentBackwards(IntegrityError):
    """The ledger holds less than its head sidecar recorded as committed (a lost WAL tail,
    a stale copy), or another history: it is not opened for writing without
    ``accept_loss`` (:mod:`ledger.head_file`)."""


#: the operating system's words for a full disk or quota, as DuckDB passes them on
_DISK_FULL_TEXTS = ("No space left on device", "Disk quota exceeded")
_DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})


class LedgerDiskFull(OperationalError):
    """The ledger's disk (or the writer's quota) is full: nothing of the failed batch
    was committed, and the same batch can be appended again once space returns.

    ``os_error`` is the operating system's text (``No space left on device``).
    """

    def __init__(self, message: str, os_error: str = "No space left on device") -> None:
        super().__init__(message)
        self.os_error = os_error


def disk_full_text(exc: BaseException) -> str | None:
    """The OS error text when ``exc`` (an ``OSError`` or a backend error) says the disk
    or quota is full, else None."""
    if isinstance(exc, OSError) and exc.errno in _DISK_FULL_ERRNOS:
        return exc.strerror or _DISK_FULL_TEXTS[0]
    text = str(exc)
    for words in _DISK_FULL_TEXTS:
        if words in text:
            return words
    return None
