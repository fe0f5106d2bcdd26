"""Who holds a ledger file for writing, and how to read it while they do.

DuckDB lets one process open a file for writing *or* many read it, never both.  While
``stockpile service ledger`` holds ``yard.duckdb``, it leaves a holder file beside it,
``yard.duckdb.service.json``, naming its site, process id and the Zenoh endpoints
through which its queryables answer, and removes it when it stops::

    {"site": "demo", "pid": 4242, "host": "yard-box", "started_ns": 1790000000000000000,
     "endpoints": ["tcp/127.0.0.1:7447"]}

:func:`ledger.open_ledger` with ``read_only=True`` on a locked file calls
:func:`open_held`: when the holder file names the process that holds the lock, the
reader registered with :func:`set_remote_reader` opens a read-only store that reads
through that service.  The ledger package has no network code of its own; the
application (``stockpile``) registers the reader.  Without a holder file, or without a
registered reader, the lock stays a one-line :class:`~ledger.errors.LedgerLocked`.
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from ledger.errors import LedgerLocked

if TYPE_CHECKING:
    from ledger.store import LedgerStore

HOLDER_SUFFIX = ".service.json"


@dataclass(frozen=True)
class LedgerHolder:
    """A running ledger service that holds a ledger file for writing."""

    site: str
    pid: int
    endpoints: tuple[str, ...]  # Zenoh endpoints a reader on this machine connects to
    started_ns: int  # wall-clock UTC ns when the service opened the ledger
    host: str = ""

    def describe(self) -> str:
        """``the ledger service of site demo (pid 4242)``"""
        return f"the ledger service of site {self.site} (pid {self.pid})"


RemoteReader = Callable[[Path, LedgerHolder], "LedgerStore"]
_remote_reader: RemoteReader | None = None


def holder_path(ledger_path: str | os.PathLike[str]) -> Path:
    """The holder file of a ledger file (``<ledger>.service.json``)."""
    return Path(str(ledger_path) + HOLDER_SUFFIX)


def write_holder(ledger_path: str | os.PathLike[str], holder: LedgerHolder) -> Path:
    """Write the holder file atomically (a reader never sees half of it); return its path."""
    path = holder_path(ledger_path)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(asdict(holder)) + "\n")
    os.replace(tmp, path)
    return path


def read_holder(ledger_path: str | os.PathLike[str]) -> LedgerHolder | None:
    """The holder named beside a ledger file, or None when there is no readable one."""
    try:
        data = json.loads(holder_path(ledger_path).read_text())
        return LedgerHolder(site=str(data["site"]), pid=int(data["pid"]),
                            endpoints=tuple(str(e) for e in data["endpoints"]),
                            started_ns=int(data["started_ns"]), host=str(data.get("host", "")))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def remove_holder(ledger_path: str | os.PathLike[str], pid: int) -> None:
    """Remove the holder file if it still names ``pid`` (a newer holder's file stays)."""
    holder = read_holder(ledger_path)
    if holder is not None and holder.pid == pid:
        holder_path(ledger_path).unlink(missing_ok=True)


def this_host() -> str:
    return socket.gethostname()


def set_remote_reader(reader: RemoteReader | None) -> None:
    """Register how a locked ledger is read through its holder (None: not at all)."""
    global _remote_reader
    _remote_reader = reader


def open_held(path: Path, locked: LedgerLocked) -> LedgerStore:
    """A read-only store of a ledger that another process holds for writing.

    Raises
    ------
    LedgerLocked
        No holder file names the process that holds the lock, or no reader is
        registered; the message says who holds the file when it is known.
    """
    holder = read_holder(path)
    if holder is None or (locked.holder_pid is not None and holder.pid != locked.holder_pid):
        who = f"process {locked.holder_pid}" if locked.holder_pid is not None else "another process"
        raise LedgerLocked(f"{path} is open for writing by {who}, which serves no reads "
                           "(a DuckDB file has one writer or many readers, never both); "
                           "wait for it to finish, or read a backup (stockpile ledger backup)",
                           locked.holder_pid)
    if _remote_reader is None:
        raise LedgerLocked(f"{path} is held by {holder.describe()}; read it through the "
                           "service (stockpile does) or stop the service", holder.pid)
    return _remote_reader(path, holder)
