"""The head sidecar: the ledger's committed head, recorded outside the database file.

Beside ``yard.duckdb`` the writer keeps ``yard.duckdb.head``, one JSON line::

    {"global_seq": 41999, "chain_sha256": "9f2c...", "recorded_time_ns": 1790000000000000000,
     "written_ns": 1790000000123456789}

``global_seq`` and ``chain_sha256`` are the head after the last committed batch,
``recorded_time_ns`` that row's recorded time (site clock, ns; null for an empty
ledger), ``written_ns`` the wall-clock UTC ns the sidecar was written.  It is written
after every batch that moved the head, atomically: a temporary file, fsync, rename over
the old one, fsync of the directory.

On opening a ledger for writing, :func:`reconcile` compares the database's head with
its sidecar:

- equal: fine;
- the database ahead of the sidecar, its row at the sidecar's ``global_seq`` carrying
  the sidecar's chain hash (a crash between a commit and the sidecar write): fine, the
  sidecar is brought forward;
- the database behind the sidecar, or its row there carrying another chain hash (a lost
  WAL tail, a stale copy, a rewritten history): :class:`~ledger.errors.HeadWentBackwards`,
  unless ``accept_loss``, which logs the loss and rewrites the sidecar;
- no sidecar: one is written (for an existing ledger with rows, with a log line).

:func:`compare` makes the same comparison read-only, for ``stockpile ledger verify``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from common.logs import emit

from ledger.chain import GENESIS
from ledger.errors import HeadWentBackwards
from ledger.records import Head

if TYPE_CHECKING:
    from ledger.store import LedgerStore

HEAD_SUFFIX = ".head"


@dataclass(frozen=True)
class SidecarHead:
    """What a head sidecar records."""

    global_seq: int  # -1 for an empty ledger
    chain_sha256: bytes
    recorded_time_ns: int | None  # the head row's recorded time (site clock), ns
    written_ns: int  # wall-clock UTC ns when the sidecar was written

    def describe(self) -> str:
        """``global_seq 41999 (chain 9f2c0a1b..., written 2026-11-29T02:30:00Z)``"""
        written = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.written_ns / 1e9))
        return (f"global_seq {self.global_seq} (chain {self.chain_sha256.hex()[:16]}..., "
                f"written {written})")


def head_path(ledger_path: str | os.PathLike[str]) -> Path:
    """The head sidecar of a ledger file (``<ledger>.head``)."""
    return Path(str(ledger_path) + HEAD_SUFFIX)


def fsync_directory(directory: Path) -> None:
    """fsync a directory, so that a rename inside it survives a power cut."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_head(ledger_path: str | os.PathLike[str], head: Head) -> Path:
    """Record ``head`` in the ledger's sidecar atomically (temp file, fsync, rename, fsync
    of the directory); return the sidecar's path.  Raises OSError."""
    path = head_path(ledger_path)
    data = {"global_seq": head.global_seq, "chain_sha256": head.chain_sha256.hex(),
            "recorded_time_ns": head.recorded_time_ns, "written_ns": time.time_ns()}
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w") as out:
        out.write(json.dumps(data) + "\n")
        out.flush()
        os.fsync(out.fileno())
    os.replace(tmp, path)
    fsync_directory(path.parent)
    return path


def read_head(ledger_path: str | os.PathLike[str]) -> SidecarHead | None:
    """The head a ledger's sidecar records; None when there is no sidecar.

    Raises
    ------
    HeadWentBackwards
        The sidecar exists but cannot be read (the database cannot be checked against it).
    """
    path = head_path(ledger_path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise HeadWentBackwards(f"cannot read the head sidecar {path}: {exc}") from None
    try:
        data = json.loads(text)
        recorded = data["recorded_time_ns"]
        return SidecarHead(int(data["global_seq"]), bytes.fromhex(data["chain_sha256"]),
                           None if recorded is None else int(recorded), int(data["written_ns"]))
    except (ValueError, KeyError, TypeError) as exc:
        raise HeadWentBackwards(
            f"the head sidecar {path} is damaged ({type(exc).__name__}: {exc}); the ledger "
            "cannot be checked for a lost tail: restore a backup, or after a human has "
            "looked, open it with --accept-loss") from None


def _chain_at(store: LedgerStore, global_seq: int) -> bytes | None:
    """The chain hash of the row ``global_seq`` (GENESIS for -1), None when not stored."""
    if global_seq < 0:
        return GENESIS
    for row in store.read(global_seq, global_seq + 1):
        return row.chain_sha256
    return None


def problem(sidecar: SidecarHead, store: LedgerStore, ledger_path: str | os.PathLike[str]
            ) -> str | None:
    """Why ``store``'s head contradicts its sidecar (one line with the numbers), or None."""
    db = store.head()
    if db.global_seq < sidecar.global_seq:
        missing = sidecar.global_seq - db.global_seq
        return (f"{ledger_path}: its head went backwards: the head sidecar records "
                f"{sidecar.describe()}, the database holds global_seq {db.global_seq} "
                f"({missing:,} committed events missing: a lost WAL tail or a stale copy)")
    if _chain_at(store, sidecar.global_seq) != sidecar.chain_sha256:
        return (f"{ledger_path}: its history was replaced: the head sidecar records "
                f"{sidecar.describe()}, the database's row global_seq {sidecar.global_seq} "
                f"has another chain hash (database head global_seq {db.global_seq})")
    return None


def reconcile(store: LedgerStore, ledger_path: str | os.PathLike[str], *,
              accept_loss: bool = False) -> Head:
    """Check a ledger opened for writing against its sidecar and bring the sidecar to
    the database's head; return the head recorded.

    Raises
    ------
    HeadWentBackwards
        The database is behind its sidecar or disagrees with it (the message has both
        heads and what to do), and ``accept_loss`` is false.
    OSError
        The sidecar cannot be written.
    """
    head = store.head()
    try:
        sidecar = read_head(ledger_path)
        found = None if sidecar is None else problem(sidecar, store, ledger_path)
    except HeadWentBackwards as exc:
        sidecar, found = None, str(exc)
    if found is not None:
        if not accept_loss:
            raise HeadWentBackwards(
                f"{found}; refusing to open it: restore a backup (stockpile ledger restore), "
                "or after a human has looked, open it with --accept-loss")
        emit("ledger", "warning", "ACCEPTING LOSS (--accept-loss): the head went backwards; "
             "the head sidecar is rewritten to the database's head", finding=found,
             sidecar_global_seq=None if sidecar is None else sidecar.global_seq,
             database_global_seq=head.global_seq)
    elif sidecar is None and head.global_seq >= 0:
        emit("ledger", "warning", "no head sidecar (a ledger from before sidecars): writing one",
             ledger=str(ledger_path), global_seq=head.global_seq)
    elif sidecar is not None and head.global_seq > sidecar.global_seq:
        emit("ledger", "info", "the database is ahead of its head sidecar (a stop between a "
             "commit and the sidecar write): bringing the sidecar forward",
             ledger=str(ledger_path), sidecar_global_seq=sidecar.global_seq,
             database_global_seq=head.global_seq)
    write_head(ledger_path, head)
    return head


def compare(store: LedgerStore, ledger_path: str | os.PathLike[str]) -> tuple[bool, str]:
    """``(ok, one line)``: ``store`` (a DuckDB file opened read-only) against its sidecar.
    A missing sidecar is ok, with a line saying nothing was checked; so is a ledger read
    through the service holding it (that service checked it when it opened the file)."""
    if store.backend != "duckdb":
        return True, (f"{ledger_path} is read through the {store.backend} store holding it, "
                      "which checked its head sidecar when it opened it")
    try:
        sidecar = read_head(ledger_path)   # read before the head: the sidecar never leads
    except HeadWentBackwards as exc:
        return False, str(exc)
    if sidecar is None:
        return True, (f"no head sidecar beside {ledger_path}: a lost tail cannot be detected "
                      "(the next write opening writes one)")
    found = problem(sidecar, store, ledger_path)
    if found is not None:
        return False, found
    return True, f"the head sidecar records {sidecar.describe()}, the database holds it"


class HeadRecorder:
    """Writes the sidecar after each committed batch that moved the head.

    A failed write is logged, not raised: the batch is committed, and a database ahead
    of its sidecar is brought forward on the next open.
    """

    def __init__(self, ledger_path: str | os.PathLike[str], head: Head) -> None:
        self.ledger_path = ledger_path
        self.last_seq = head.global_seq
        self.failing = False

    def record(self, head: Head) -> None:
        if head.global_seq == self.last_seq and not self.failing:
            return
        try:
            write_head(self.ledger_path, head)
        except OSError as exc:
            if not self.failing:
                emit("ledger", "warning", "cannot write the head sidecar (the batch is "
                     "committed; a lost tail after it would go undetected until it is written)",
                     ledger=str(self.ledger_path), error=str(exc))
            self.failing = True
            return
        self.failing = False
        self.last_seq = head.global_seq
