"""``stockpile service lab``: the laboratory's LIMS export files in, ``assay`` events out.

The service watches a drop folder (``--watch DIR``), turns each export file's rows into
``assay`` events with the LIMS map (``--map lims.toml``, :mod:`services.lims_map`) and
publishes them under one source (``--source``, default ``lab1``), signed with
``--signing-key FILE`` when given.

Which files it takes: regular files directly in DIR whose name ends in ``.csv`` (``.json``
for a JSON map) and does not start with a dot, once their size and modification time
have not changed for ``--settle`` seconds (default 1).  A writer that can rename should
write under a hidden or other name and rename into place (the simulator does); one that
cannot must not pause for longer than ``--settle`` while it writes.

Exactly once, through restarts, re-drops and crashes.  A file's identity is the sha256
of its bytes.  The journal ``DIR/.stockpile-lab/journal.jsonl`` (one JSON object a line,
each fsynced before the step it records) holds:

- ``stream``: the source and its epoch, chosen once, so the source stays one stream
  (one epoch, a dense sequence) across restarts;
- ``begun``: a file's hash and name, the sequence range given to its assays, the
  assays' payloads and the refused rows, written *before* the first is published;
- ``published``: all of the file's assays handed to Zenoh, and where it is archived;
- ``archived``: the file moved to ``DIR/archive/``.

On start, a file ``begun`` but not ``published`` is published again from the journal
with the same source, epoch and sequence numbers (the ledger keeps the first copy of an
identical event and counts the rest as duplicates); a file ``published`` but not
``archived`` is archived; a finished file is not published again, and a file whose hash
the journal holds is a duplicate: moved to ``DIR/archive/duplicates/`` and logged.
``--resend`` publishes every journaled assay again (after a ledger outage that outlived
the adapter's publisher cache).

A row whose assay (the same id and values) an earlier file published is not published
again (a cumulative export): it is listed with the refused rows as ``already published``.
Processed files go to ``DIR/archive/<name>`` (``<stem>.<hash12><suffix>`` when that name is
taken); the rows refused are listed in ``DIR/archive/<name>.refused.csv`` (``line,reason``).

Status counters (the ``status`` and ``stopped`` lines): ``files``, ``published``,
``refused_rows`` (error), ``repeated_rows``, ``duplicates``, ``republished``,
``unreadable`` (error).
The service exits 0 on SIGINT/SIGTERM and 2 with one line for a bad folder, journal,
key or Zenoh session.  For tests only, the environment variable :data:`HALT_ENV` set to
one of :data:`HALT_POINTS` makes it log ``halting`` at that step and wait there to be
killed.
"""

from __future__ import annotations

import argparse
import base64
import csv
import fcntl
import hashlib
import io
import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.options import add_signing_key
from ledger.head_file import fsync_directory
from schemas import pb
from security.event_keys import SigningKey, load_signing_key
from services.lims_map import LimsMap, RefusedRow, RowAssay, parse_map, rows_to_assays
from services.service import (
    DEFAULT_SITE,
    DEFAULT_STATUS_PERIOD_S,
    EventPublisher,
    ServiceRuntime,
    Stopper,
    ZenohOptions,
    log,
)
from schemas.events import is_valid_source

__all__ = ["SERVICE", "DEFAULT_SOURCE", "DEFAULT_POLL_S", "DEFAULT_SETTLE_S", "STATE_DIR",
           "JOURNAL_NAME", "ARCHIVE_DIR", "HALT_ENV", "HALT_POINTS", "ERROR_KEYS", "Config",
           "Journal", "FileEntry", "add_arguments", "config_from_args", "main"]

SERVICE = "lab"
DEFAULT_SOURCE = "lab1"
#: Seconds between two looks at the drop folder.
DEFAULT_POLL_S = 0.5
#: Seconds a file's size and modification time must stay unchanged before it is taken.
DEFAULT_SETTLE_S = 1.0
STATE_DIR = ".stockpile-lab"
JOURNAL_NAME = "journal.jsonl"
ARCHIVE_DIR = "archive"
#: Test hook: the step at which to log ``halting`` and wait to be killed.
HALT_ENV = "STOCKPILE_LAB_HALT_AT"
#: ``begun``: journaled, nothing published; ``publishing``: half the file's assays
#: published; ``published``: all published, not yet journaled; ``archiving``: journaled
#: published, not archived.
HALT_POINTS = ("begun", "publishing", "published", "archiving")
ERROR_KEYS = ("refused_rows", "unreadable")


# -- configuration ------------------------------------------------------------------------


@dataclass(frozen=True)
class Config:
    """Options of one lab adapter.

    Attributes
    ----------
    watch : str
        The drop folder.
    lims : LimsMap
        The parsed map.
    site, zenoh, status_period_s
        As every service.
    source : str
        Event source (also the name in the liveliness token).
    signing_key : str or None
        Ed25519 key file (PKCS#8 PEM) to sign every assay with.
    poll_s : float
        Seconds between two looks at the folder.
    settle_s : float
        Seconds a file must stay unchanged before it is taken (0: at first sight).
    resend : bool
        Publish every journaled assay again at start.
    """

    watch: str
    lims: LimsMap
    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    source: str = DEFAULT_SOURCE
    signing_key: str | None = None
    poll_s: float = DEFAULT_POLL_S
    settle_s: float = DEFAULT_SETTLE_S
    resend: bool = False

    def __post_init__(self) -> None:
        if not is_valid_source(self.source):
            raise ValueError(f"bad source name {self.source!r}")
        if not self.poll_s > 0:
            raise ValueError(f"--poll must be > 0 s, got {self.poll_s}")
        if not self.settle_s >= 0:
            raise ValueError(f"--settle must be >= 0 s, got {self.settle_s}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the lab adapter's own options (the shared ones come from ``service_cli``)."""
    parser.add_argument("--watch", required=True, metavar="DIR",
                        help="the drop folder the LIMS exports into")
    parser.add_argument("--map", required=True, metavar="FILE",
                        help="the LIMS map (lims.toml; see docs/lims.example.toml)")
    parser.add_argument("--source", default=DEFAULT_SOURCE,
                        help=f"event source (default {DEFAULT_SOURCE})")
    add_signing_key(parser, what="assay")
    parser.add_argument("--poll", type=float, default=DEFAULT_POLL_S, metavar="S",
                        help=f"seconds between looks at the folder (default {DEFAULT_POLL_S:g})")
    parser.add_argument("--settle", type=float, default=DEFAULT_SETTLE_S, metavar="S",
                        help="seconds a file's size and time must stay unchanged before it "
                        f"is taken (default {DEFAULT_SETTLE_S:g}; 0 for writers that rename)")
    parser.add_argument("--resend", action="store_true",
                        help="publish every journaled assay again at start (the ledger "
                        "drops the copies it holds)")


def config_from_args(args: argparse.Namespace) -> Config:
    """A :class:`Config` from parsed arguments (ValueError with one line on a bad map)."""
    try:
        text = Path(args.map).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--map {args.map}: cannot read it ({exc})") from None
    try:
        lims = parse_map(text)
    except ValueError as exc:
        raise ValueError(f"--map {args.map}: {exc}") from None
    return Config(watch=args.watch, lims=lims, site=args.site, zenoh=ZenohOptions.from_args(args),
                  status_period_s=args.status_period, source=args.source,
                  signing_key=args.signing_key, poll_s=args.poll, settle_s=args.settle,
                  resend=args.resend)


# -- the journal --------------------------------------------------------------------------


@dataclass
class FileEntry:
    """One file as the journal knows it."""

    sha256: str
    name: str
    first_seq: int
    payloads: list[bytes]
    refused: list[RefusedRow]
    archive: str = ""
    published: bool = False
    archived: bool = False


class Journal:
    """The adapter's durable record (module docstring): append-only JSON lines, each
    fsynced before the step it records.  A torn last line (a crash while writing it) is
    cut off when the journal is opened: the step it would have recorded never started."""

    def __init__(self, path: Path, source: str) -> None:
        self.path = path
        self.files: dict[str, FileEntry] = {}
        self.epoch: int | None = None
        self._origins: dict[bytes, str] = {}  # sha256 of a published payload -> file name
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists():
            self._load(source)
        if self.epoch is None:
            self.epoch = time.time_ns()
            self._write({"kind": "stream", "source": source, "epoch": self.epoch})

    def origin_of(self, payload: bytes) -> str | None:
        """The name of the file an identical assay payload was published from, or None."""
        return self._origins.get(hashlib.sha256(payload).digest())

    def _add(self, entry: FileEntry) -> None:
        self.files[entry.sha256] = entry
        for payload in entry.payloads:
            self._origins.setdefault(hashlib.sha256(payload).digest(), entry.name)

    @property
    def next_seq(self) -> int:
        """The first sequence number no file was given."""
        return max((e.first_seq + len(e.payloads) for e in self.files.values()), default=0)

    def _load(self, source: str) -> None:
        data = self.path.read_bytes()
        lines = data.split(b"\n")
        offset = 0
        for number, raw in enumerate(lines[:-1], 1):
            if raw.strip():
                try:
                    self._apply(json.loads(raw), source)
                except _ForeignJournal:
                    raise
                except (ValueError, KeyError, TypeError) as exc:
                    raise ValueError(f"journal {self.path} line {number} is damaged "
                                     f"({type(exc).__name__}: {exc})") from None
            offset += len(raw) + 1
        if lines[-1]:  # a line without its newline: torn by a crash, its step never started
            with open(self.path, "r+b") as f:
                f.truncate(offset)
                os.fsync(f.fileno())

    def _apply(self, record: dict, source: str) -> None:
        kind = record["kind"]
        if kind == "stream":
            if record["source"] != source:
                raise _ForeignJournal(f"journal {self.path} is source {record['source']!r}'s, "
                                      f"not {source!r}")
            self.epoch = int(record["epoch"])
        elif kind == "begun":
            self._add(FileEntry(
                record["sha256"], record["name"], int(record["first_seq"]),
                [base64.b64decode(p) for p in record["payloads"]],
                [RefusedRow(int(line), str(reason)) for line, reason in record["refused"]]))
        elif kind == "published":
            entry = self.files[record["sha256"]]
            entry.published, entry.archive = True, record["archive"]
        elif kind == "archived":
            self.files[record["sha256"]].archived = True
        else:
            raise ValueError(f"unknown record kind {kind!r}")

    def _write(self, record: dict) -> None:
        line = (json.dumps(record, separators=(",", ":")) + "\n").encode()
        new = not self.path.exists()
        with open(self.path, "ab") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
        if new:
            fsync_directory(self.path.parent)

    def begin(self, entry: FileEntry) -> None:
        """Record a file and the sequence range of its assays (before publishing them)."""
        self._write({"kind": "begun", "sha256": entry.sha256, "name": entry.name,
                     "first_seq": entry.first_seq,
                     "payloads": [base64.b64encode(p).decode() for p in entry.payloads],
                     "refused": [[r.line, r.reason] for r in entry.refused]})
        self._add(entry)

    def mark_published(self, entry: FileEntry, archive: str) -> None:
        self._write({"kind": "published", "sha256": entry.sha256, "archive": archive})
        entry.published, entry.archive = True, archive

    def mark_archived(self, entry: FileEntry) -> None:
        self._write({"kind": "archived", "sha256": entry.sha256})
        entry.archived = True


class _ForeignJournal(ValueError):
    """The journal belongs to another source (never a torn line)."""


# -- files in the folder ------------------------------------------------------------------


def _free_name(directory: Path, name: str, sha256: str) -> Path:
    """``directory/name``, or ``<stem>.<hash12>[.<n>]<suffix>`` when that is taken."""
    target = directory / name
    stem, suffix = Path(name).stem, Path(name).suffix
    n = 0
    while target.exists() or Path(f"{target}.refused.csv").exists():
        n += 1
        tail = f".{n}" if n > 1 else ""
        target = directory / f"{stem}.{sha256[:12]}{tail}{suffix}"
    return target


def _write_atomic(path: Path, text: str) -> None:
    temp = path.with_name(f".{path.name}.tmp")
    with open(temp, "w", encoding="utf-8", newline="") as out:
        out.write(text)
        out.flush()
        os.fsync(out.fileno())
    os.replace(temp, path)


def refused_csv(refused: list[RefusedRow]) -> str:
    """The ``<name>.refused.csv`` text: a ``line,reason`` header and one row per refusal."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["line", "reason"])
    writer.writerows([r.line, r.reason] for r in refused)
    return buffer.getvalue()


class _Folder:
    """The files of the drop folder that are ready: matching names, settled."""

    def __init__(self, directory: Path, suffix: str, settle_s: float,
                 clock=time.monotonic) -> None:
        self.directory, self.suffix, self.settle_s = directory, suffix, settle_s
        self.clock = clock  # seconds, monotonic
        self._seen: dict[str, tuple[tuple[int, int], float]] = {}

    def ready(self) -> list[Path]:
        """Names in name order whose size and mtime are unchanged for ``settle_s``."""
        now = self.clock()
        out, seen = [], {}
        for entry in sorted(os.scandir(self.directory), key=lambda e: e.name):
            if entry.name.startswith(".") or not entry.name.lower().endswith(self.suffix):
                continue
            try:
                if not entry.is_file(follow_symlinks=False):
                    continue
                stat = entry.stat(follow_symlinks=False)
            except OSError:
                continue  # gone between the listing and the look
            signature = (stat.st_size, stat.st_mtime_ns)
            before = self._seen.get(entry.name)
            since = before[1] if before and before[0] == signature else now
            seen[entry.name] = (signature, since)
            if now - since >= self.settle_s:
                out.append(Path(entry.path))
        self._seen = seen
        return out


# -- the adapter --------------------------------------------------------------------------


class LabAdapter:
    """The drop folder, the journal and the publisher of one running service."""

    def __init__(self, config: Config, runtime: ServiceRuntime, publisher: EventPublisher,
                 journal: Journal) -> None:
        self.config, self.runtime, self.publisher, self.journal = (config, runtime, publisher,
                                                                   journal)
        self.directory = Path(config.watch)
        self.archive_dir = self.directory / ARCHIVE_DIR
        self.folder = _Folder(self.directory, "." + config.lims.format, config.settle_s)
        self.status = runtime.status
        self._unreadable: set[str] = set()

    # recovery -------------------------------------------------------------------------

    def recover(self) -> None:
        """Finish what the journal says a previous run left unfinished (module docstring)."""
        for entry in list(self.journal.files.values()):
            if not entry.published or self.config.resend:
                self._publish(entry, again=True)
            if not entry.published:
                self._mark_published(entry)
            if not entry.archived:
                self._archive(entry, self.directory / entry.name)
        self.publisher.seq = self.journal.next_seq

    # one look at the folder -----------------------------------------------------------

    def poll(self) -> None:
        """Take every ready file once."""
        for path in self.folder.ready():
            if self.runtime.stopper.is_set():
                return
            self._take(path)

    def _take(self, path: Path) -> None:
        try:
            data = path.read_bytes()
        except OSError as exc:
            if path.name not in self._unreadable:
                self._unreadable.add(path.name)
                self.status.add("unreadable")
                self.runtime.log("cannot read file", level="warning", file=path.name,
                                 error=str(exc))
            return
        self._unreadable.discard(path.name)
        digest = hashlib.sha256(data).hexdigest()
        known = self.journal.files.get(digest)
        if known is not None:
            self._duplicate(path, digest, known)
            return
        assays, refused = rows_to_assays(data, self.config.lims)
        payloads, repeated = self._fresh(assays)
        entry = FileEntry(digest, path.name, self.journal.next_seq, payloads,
                          sorted(refused + repeated, key=lambda r: r.line))
        self.journal.begin(entry)
        _halt(self.runtime, "begun")
        self._publish(entry, again=False)
        self._mark_published(entry)
        self._archive(entry, path)
        self.status.add("files")
        if refused:
            self.status.add("refused_rows", len(refused))
        if repeated:
            self.status.add("repeated_rows", len(repeated))
        self.runtime.log("file done", file=path.name, sha256=digest[:16], assays=len(payloads),
                         refused=len(refused), repeated=len(repeated),
                         first_seq=entry.first_seq, archive=entry.archive)

    def _fresh(self, assays: list[RowAssay]) -> tuple[list[bytes], list[RefusedRow]]:
        """The payloads of the assays no earlier file published, and a row for each one an
        earlier file did (a cumulative export repeats the results it already gave)."""
        payloads, repeated = [], []
        for row in assays:
            payload = row.assay.SerializeToString(deterministic=True)
            origin = self.journal.origin_of(payload)
            if origin is None:
                payloads.append(payload)
            else:
                repeated.append(RefusedRow(row.line, f"already published from {origin} "
                                           "(the same result)"))
        return payloads, repeated

    def _publish(self, entry: FileEntry, *, again: bool) -> None:
        """Publish a file's assays with their journaled sequence numbers."""
        self.publisher.seq = entry.first_seq
        half = max(1, len(entry.payloads) // 2)
        for i, payload in enumerate(entry.payloads):
            self.publisher.publish(pb.Assay.FromString(payload))
            self.status.add("republished" if again else "published")
            if i + 1 == half and not again:
                _halt(self.runtime, "publishing")
        self.publisher.seq = max(self.publisher.seq, self.journal.next_seq)
        if again and entry.payloads:
            self.runtime.log("republished", file=entry.name, first_seq=entry.first_seq,
                             count=len(entry.payloads))
        _halt(self.runtime, "published")

    def _mark_published(self, entry: FileEntry) -> None:
        self.archive_dir.mkdir(exist_ok=True)
        target = _free_name(self.archive_dir, entry.name, entry.sha256)
        self.journal.mark_published(entry, str(target.relative_to(self.directory)))
        _halt(self.runtime, "archiving")

    def _archive(self, entry: FileEntry, path: Path) -> None:
        """Move the file to its journaled archive name, its refused rows beside it."""
        target = self.directory / entry.archive
        target.parent.mkdir(parents=True, exist_ok=True)
        if entry.refused:
            _write_atomic(Path(f"{target}.refused.csv"), refused_csv(entry.refused))
        if path.exists() and not target.exists() and _sha256_of(path) == entry.sha256:
            os.replace(path, target)
        elif not target.exists():
            self.runtime.log("file gone before archiving", level="warning", file=entry.name)
        fsync_directory(target.parent)
        fsync_directory(self.directory)
        self.journal.mark_archived(entry)

    def _duplicate(self, path: Path, digest: str, known: FileEntry) -> None:
        folder = self.archive_dir / "duplicates"
        folder.mkdir(parents=True, exist_ok=True)
        target = _free_name(folder, path.name, digest)
        os.replace(path, target)
        fsync_directory(folder)
        self.status.add("duplicates")
        self.runtime.log("duplicate file", level="warning", file=path.name, sha256=digest[:16],
                         first_name=known.name, archive=str(target.relative_to(self.directory)))


def _sha256_of(path: Path) -> str:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return ""


def _halt(runtime: ServiceRuntime, point: str) -> None:
    """The test hook: at the step named by :data:`HALT_ENV`, log and wait to be killed."""
    if os.environ.get(HALT_ENV) == point:
        runtime.log("halting", level="warning", at=point)
        threading.Event().wait()


# -- the service --------------------------------------------------------------------------


def _lock(state: Path) -> Any:
    """An exclusive lock on ``state/lock`` (one adapter per folder); OSError when held."""
    handle = open(state / "lock", "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        raise OSError(f"another lab adapter holds {state}") from None
    return handle


def _prepare(config: Config) -> tuple[Any, Journal, SigningKey | None]:
    """The folder's lock, its journal and the signing key (OSError / ValueError, one line)."""
    directory = Path(config.watch)
    if not directory.is_dir():
        raise OSError(f"--watch {directory}: no such folder")
    state = directory / STATE_DIR
    state.mkdir(exist_ok=True)
    lock = _lock(state)
    try:
        journal = Journal(state / JOURNAL_NAME, config.source)
        key = load_signing_key(config.signing_key) if config.signing_key else None
    except BaseException:
        lock.close()
        raise
    return lock, journal, key


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the lab adapter until SIGINT/SIGTERM.

    Returns
    -------
    int
        0 on a clean stop, 2 for a bad folder, journal or key, or a Zenoh session that
        cannot start (one ``cannot start`` line).
    """
    stopper = stopper or Stopper()  # installed first: SIGTERM during start-up stops cleanly
    try:
        lock, journal, key = _prepare(config)
    except (OSError, ValueError) as exc:
        log(SERVICE, "cannot start", level="error", error=str(exc).splitlines()[0])
        return 2
    with lock:
        runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=config.source,
                                 status_period_s=config.status_period_s, stopper=stopper)
        try:
            runtime.open(error_keys=ERROR_KEYS, announce=False)
        except OSError as exc:
            log(SERVICE, "cannot start", level="error", error=str(exc).splitlines()[0])
            return 2
        with runtime:
            publisher = runtime.publisher(config.source, epoch=journal.epoch, signing_key=key)
            publisher.declare("assay")
            adapter = LabAdapter(config, runtime, publisher, journal)
            runtime.log("watching", folder=config.watch, source=config.source,
                        epoch=journal.epoch, next_seq=journal.next_seq,
                        signed=key is not None, format=config.lims.format)
            adapter.recover()
            runtime.announce()
            while not stopper.is_set():
                adapter.poll()
                stopper.wait(config.poll_s)
    return 0
