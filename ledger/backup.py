"""Consistent, verified backups of a DuckDB ledger, and their restore.

A backup directory holds three files::

    DIR/yard.duckdb        the database, as of one committed head
    DIR/yard.duckdb.head   its head sidecar (:mod:`ledger.head_file`)
    DIR/manifest.json      head, sha256 and size of the database, time taken, source

Taking one (:func:`take_copy` then :func:`finish`, or :func:`backup` for both):
DuckDB's CHECKPOINT writes everything committed into the database file and empties
the WAL; the file is then copied (sha256 computed on the way, fsynced) while no batch
is written, which makes the copy consistent with the head at the checkpoint.  The
ledger service runs :func:`take_copy` on its writer thread between two batches, and
:func:`finish` elsewhere, so that verifying does not hold up the writer.  :func:`finish`
opens the copy read-only, recomputes its chain from genesis, checks its head equals
the head copied, and only then writes the manifest: a directory without a manifest
is not a backup.

:func:`restore` checks a backup (manifest, sha256, chain, head) and installs it as a
ledger file with a matching head sidecar, removing the target's stale WAL; it refuses
to overwrite an existing ledger unless ``force``, and refuses while a process holds it.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from common.progress import Progress

from ledger.errors import IntegrityError, LedgerLocked, OperationalError
from ledger.head_file import fsync_directory, write_head
from ledger.holder import read_holder
from ledger.records import Head

if TYPE_CHECKING:
    from ledger.duckdb_store import DuckDBStore

MANIFEST = "manifest.json"
MANIFEST_FORMAT = 1
_CHUNK_BYTES = 4 << 20


@dataclass(frozen=True)
class Manifest:
    """What a backup directory's ``manifest.json`` records."""

    database: str  # the database file's name inside the backup directory
    global_seq: int  # the head copied (-1: an empty ledger)
    chain_sha256: str  # hex
    recorded_time_ns: int | None  # the head row's recorded time (site clock), ns
    sha256: str  # hex digest of the database file
    size_bytes: int
    rows_verified: int
    created_ns: int  # wall-clock UTC ns when the backup was finished
    source: str  # absolute path of the ledger backed up
    format: int = MANIFEST_FORMAT

    def head(self) -> Head:
        return Head(self.global_seq, self.recorded_time_ns, bytes.fromhex(self.chain_sha256))

    def describe(self) -> str:
        """``head global_seq 41999 (chain 9f2c...), sha256 ab12..., 12.3 MiB``"""
        return (f"head global_seq {self.global_seq} (chain {self.chain_sha256[:16]}...), "
                f"sha256 {self.sha256[:16]}..., {self.size_bytes / 2**20:.1f} MiB")


@dataclass(frozen=True)
class PendingBackup:
    """A database copied into a backup directory, not yet verified (no manifest)."""

    directory: Path
    database: str
    head: Head
    sha256: str
    size_bytes: int
    source: str


def _copy_file(source: Path, target: Path, progress: Progress | None) -> tuple[str, int]:
    """Copy ``source`` to ``target`` (fsynced); return (sha256 hex, size in bytes)."""
    digest = hashlib.sha256()
    size_bytes = 0
    with open(source, "rb") as inp, open(target, "wb") as out:
        while chunk := inp.read(_CHUNK_BYTES):
            digest.update(chunk)
            out.write(chunk)
            size_bytes += len(chunk)
            if progress is not None:
                progress.update_to(size_bytes)
        out.flush()
        os.fsync(out.fileno())
    return digest.hexdigest(), size_bytes


def file_sha256(path: Path, progress: Progress | None = None) -> str:
    """The sha256 hex digest of a file, read in chunks."""
    digest = hashlib.sha256()
    done = 0
    with open(path, "rb") as inp:
        while chunk := inp.read(_CHUNK_BYTES):
            digest.update(chunk)
            done += len(chunk)
            if progress is not None:
                progress.update_to(done)
    return digest.hexdigest()


def take_copy(store: DuckDBStore, target_dir: str | os.PathLike[str], *,
              progress: Progress | None = None) -> PendingBackup:
    """CHECKPOINT ``store`` and copy its database file with a head sidecar into
    ``target_dir``.  Call it where no batch is appended meanwhile (the writer's thread).

    Raises
    ------
    ValueError
        ``target_dir`` already holds a backup or a file of that name.
    OperationalError
        The WAL is not empty after the checkpoint (the copy would not be consistent).
    OSError
        The copy failed (the partial file is removed).
    """
    source = store.path.resolve()
    directory = Path(target_dir).resolve()
    name = source.name
    if (directory / MANIFEST).exists() or (directory / name).exists():
        raise ValueError(f"{directory} already holds a backup; give an empty or new directory")
    if directory == source.parent:
        raise ValueError(f"{directory} is the ledger's own directory; back up to another one")
    directory.mkdir(parents=True, exist_ok=True)
    head = store.checkpoint()
    wal = Path(str(source) + ".wal")
    if wal.exists() and wal.stat().st_size:
        raise OperationalError(f"{wal} still holds {wal.stat().st_size:,} bytes after a "
                               "CHECKPOINT: a copy of the file alone would not be consistent")
    if progress is not None:
        progress.total = source.stat().st_size
    partial = directory / (name + ".partial")
    try:
        sha256, size_bytes = _copy_file(source, partial, progress)
        os.replace(partial, directory / name)
        write_head(directory / name, head)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return PendingBackup(directory, name, head, sha256, size_bytes, str(source))


def _verified(database: Path, head: Head) -> int:
    """Open ``database`` read-only, verify its chain from genesis and its head; the rows
    verified.  Raises IntegrityError naming what does not hold."""
    from ledger.duckdb_store import DuckDBStore   # deferred: duckdb is heavy

    with DuckDBStore(database, read_only=True) as copy:
        report = copy.verify()
        found = copy.head()
    if not report.ok:
        where = "" if report.first_bad_seq is None else f" at global_seq {report.first_bad_seq}"
        raise IntegrityError(f"{database} does not verify{where}: {report.problem}")
    if (found.global_seq, found.chain_sha256) != (head.global_seq, head.chain_sha256):
        raise IntegrityError(f"{database} holds head global_seq {found.global_seq} (chain "
                             f"{found.chain_sha256.hex()[:16]}...) where global_seq "
                             f"{head.global_seq} (chain {head.chain_sha256.hex()[:16]}...) "
                             "was copied")
    return report.rows_checked


def finish(pending: PendingBackup) -> Manifest:
    """Verify a copy (chain from genesis, head equal to the head copied) and write its
    manifest; return it.  Raises IntegrityError when the copy does not verify."""
    rows = _verified(pending.directory / pending.database, pending.head)
    head = pending.head
    manifest = Manifest(pending.database, head.global_seq, head.chain_sha256.hex(),
                        head.recorded_time_ns, pending.sha256, pending.size_bytes, rows,
                        time.time_ns(), pending.source)
    path = pending.directory / MANIFEST
    tmp = path.with_name(MANIFEST + ".tmp")
    with open(tmp, "w") as out:
        out.write(json.dumps(asdict(manifest), indent=2) + "\n")
        out.flush()
        os.fsync(out.fileno())
    os.replace(tmp, path)
    fsync_directory(pending.directory)
    return manifest


def backup(store: DuckDBStore, target_dir: str | os.PathLike[str], *,
           progress: Progress | None = None) -> Manifest:
    """:func:`take_copy` then :func:`finish`, for a store this process writes."""
    return finish(take_copy(store, target_dir, progress=progress))


def read_manifest(backup_dir: str | os.PathLike[str]) -> Manifest:
    """The manifest of a backup directory.  Raises ValueError when there is none or it is
    damaged."""
    path = Path(backup_dir) / MANIFEST
    try:
        data = json.loads(path.read_text())
        manifest = Manifest(**data)
        manifest.head()
    except FileNotFoundError:
        raise ValueError(f"{backup_dir} is not a backup (no {MANIFEST}; an unfinished or "
                         "failed backup has none)") from None
    except (OSError, ValueError, TypeError) as exc:
        raise ValueError(f"{path} is damaged: {exc}") from None
    if manifest.format != MANIFEST_FORMAT or Path(manifest.database).name != manifest.database:
        raise ValueError(f"{path} is not a backup manifest this program reads")
    return manifest


def check_backup(backup_dir: str | os.PathLike[str], *,
                 progress: Progress | None = None) -> Manifest:
    """Check a backup: its manifest, the database's size and sha256, the chain from
    genesis and the head.  Raises ValueError (no manifest) or IntegrityError."""
    manifest = read_manifest(backup_dir)
    database = Path(backup_dir) / manifest.database
    if not database.is_file():
        raise IntegrityError(f"the backup {backup_dir} has no {manifest.database}")
    size_bytes = database.stat().st_size
    if size_bytes != manifest.size_bytes:
        raise IntegrityError(f"{database} has {size_bytes:,} bytes where the manifest records "
                             f"{manifest.size_bytes:,}: the backup is damaged")
    if progress is not None:
        progress.total = size_bytes
    sha256 = file_sha256(database, progress)
    if sha256 != manifest.sha256:
        raise IntegrityError(f"{database} has sha256 {sha256[:16]}... where the manifest "
                             f"records {manifest.sha256[:16]}...: the backup is damaged")
    _verified(database, manifest.head())
    return manifest


def _refuse_if_held(ledger_path: Path) -> None:
    """LedgerLocked when a live process holds the ledger (its holder file, or its lock)."""
    holder = read_holder(ledger_path)
    if holder is not None and _alive(holder.pid):
        raise LedgerLocked(f"{ledger_path} is held by {holder.describe()}: stop it before "
                           "restoring", holder.pid)
    if ledger_path.exists():
        from ledger.duckdb_store import DuckDBStore   # deferred: duckdb is heavy

        DuckDBStore(ledger_path, read_only=True).close()  # raises LedgerLocked when held


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def restore(backup_dir: str | os.PathLike[str], ledger_path: str | os.PathLike[str], *,
            force: bool = False, progress: Progress | None = None) -> Manifest:
    """Check a backup (:func:`check_backup`) and install it as ``ledger_path`` with a
    matching head sidecar; return its manifest.

    Raises
    ------
    ValueError
        Not a backup, or ``ledger_path`` exists and ``force`` is false.
    IntegrityError
        The backup is damaged.
    LedgerLocked
        A process holds ``ledger_path``.
    """
    target = Path(ledger_path)
    manifest = check_backup(backup_dir, progress=progress)
    _refuse_if_held(target)
    if target.exists() and not force:
        raise ValueError(f"{target} exists; give --force to replace it with the backup")
    target.parent.mkdir(parents=True, exist_ok=True)
    staged = target.with_name(target.name + ".restoring")
    try:
        shutil.copyfile(Path(backup_dir) / manifest.database, staged)
        with open(staged, "rb+") as out:
            os.fsync(out.fileno())
        if file_sha256(staged) != manifest.sha256:
            raise IntegrityError(f"the copy {staged} differs from the backup")
        # the replaced ledger's WAL would be replayed into the restored file
        Path(str(target) + ".wal").unlink(missing_ok=True)
        os.replace(staged, target)
    finally:
        staged.unlink(missing_ok=True)
    write_head(target, manifest.head())
    fsync_directory(target.parent)
    return manifest


__all__ = ["MANIFEST", "Manifest", "PendingBackup", "backup", "check_backup", "file_sha256",
           "finish", "read_manifest", "restore", "take_copy"]
