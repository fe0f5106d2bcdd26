"""Importing canonical JSON lines into a store, so that no line is lost and nothing raises
for bad input.

Every non-blank line ends up in exactly one place: appended, a duplicate of a stored
event, quarantined with its reason (a line that does not decode is quarantined with its
raw bytes, file name and line number, :func:`schemas.jsonl.decode_line`), or, as a last
resort, in a *reject file* (:class:`RejectFile`) when the store refuses even its
quarantine entry.  A batch the store refuses for a reason that lies in its data is
split in halves until the refused line is found; that line is then quarantined as raw
bytes only (``unstorable``) and, if the store refuses that too, written to the reject
file.  The good lines of the batch are appended.  Errors that are not the data's fault
(disk, I/O, a locked or closed store: :class:`~ledger.errors.OperationalError`,
:class:`~ledger.errors.InterfaceError`) are raised unchanged.
"""

from __future__ import annotations

import base64
import json
import os
import re
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit
from typing import Callable, Iterable, Iterator

from common.options import DEFAULT_BATCH_SIZE, is_ledger_url
from common.progress import Progress
from schemas.events import Event, Malformed
from schemas.jsonl import decode_line, storable_text

from ledger.errors import InterfaceError, OperationalError
from ledger.records import STATUSES
from ledger.store import LedgerStore

#: the count of lines written to the reject file, beside the statuses of ``STATUSES``
TO_REJECT_FILE = "to_reject_file"

#: the longest part of a store's error message kept in a reason (characters)
_ERROR_CHARS = 300


def default_rejects_path(ledger: str | os.PathLike[str]) -> Path:
    """Where an import into ``ledger`` writes lines no store would hold:
    ``<ledger>.rejects.jsonl`` beside a ledger file; for a PostgreSQL ledger (a URL)
    ``<database>[.<schema>].rejects.jsonl`` in the working directory."""
    if is_ledger_url(ledger):
        return Path(url_rejects_name(str(ledger)))
    path = Path(ledger)
    return path.with_name(path.name + ".rejects.jsonl")


def url_rejects_name(url: str) -> str:
    """``<database>[.<schema>].rejects.jsonl`` of a ``postgresql://`` URL (no host, user or
    password in it), each part reduced to letters, digits, ``_``, ``-`` and ``.``."""
    parts = urlsplit(url)
    database = unquote(parts.path.lstrip("/")) or "postgres"
    schema = parse_qs(parts.query).get("schema", [""])[0]
    stem = ".".join(p for p in (database, schema) if p)
    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem) + ".rejects.jsonl"


class RejectFile:
    """A JSON-lines file of the input lines a store refused even to quarantine.

    Each record is ``{"file", "line", "reason", "raw_base64"}`` (``line`` counts from 1).
    The file is created (or appended to) at the first record only; :meth:`close` flushes
    and fsyncs it.  ``written`` counts the records of this import.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.written = 0
        self._handle = None

    def write(self, file: str, line: int, reason: str, raw: bytes) -> None:
        if self._handle is None:
            self._handle = open(self.path, "a", encoding="utf-8")
        record = {"file": storable_text(file), "line": line, "reason": storable_text(reason),
                  "raw_base64": base64.b64encode(raw).decode("ascii")}
        self._handle.write(json.dumps(record, ensure_ascii=True) + "\n")
        self._handle.flush()
        self.written += 1

    def close(self) -> None:
        if self._handle is not None:
            os.fsync(self._handle.fileno())
            self._handle.close()
            self._handle = None

    def __enter__(self) -> RejectFile:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


Line = tuple[int, bytes, "Event | Malformed"]  # (line number from 1, raw bytes, decoded)


def _batches(items: Iterable[Line], size: int) -> Iterator[list[Line]]:
    batch: list[Line] = []
    for item in items:
        batch.append(item)
        if len(batch) >= size:
            yield batch
            batch = []
    if batch:
        yield batch


class _Importer:
    """Appends batches of decoded lines, isolating the lines a store refuses."""

    def __init__(self, store: LedgerStore, name: str, rejects: RejectFile | None) -> None:
        self.store = store
        self.name = name
        self.rejects = rejects
        self.counts = dict.fromkeys(STATUSES, 0)
        self.counts["lines"] = 0
        self.counts[TO_REJECT_FILE] = 0

    def append(self, batch: list[Line]) -> None:
        try:
            result = self.store.append([item for _, _, item in batch],
                                       origins=[f"{self.name}:{n}" for n, _, _ in batch])
        except (OperationalError, InterfaceError):
            raise  # not the data's fault: disk, I/O, lock, closed store
        except Exception as exc:  # noqa: BLE001 - a line the store cannot take; find it
            if len(batch) > 1:
                middle = len(batch) // 2
                self.append(batch[:middle])
                self.append(batch[middle:])
            else:
                self._unstorable(*batch[0], exc)
            return
        for status, n in result.counts.items():
            self.counts[status] += n

    def _unstorable(self, number: int, raw: bytes, _item: Event | Malformed,
                    exc: Exception) -> None:
        """Quarantine one refused line as raw bytes only; else write it to the reject file."""
        where = f"{self.name}:{number}"
        error = storable_text(f"{type(exc).__name__}: {exc}")[:_ERROR_CHARS]
        reason = f"unstorable: {where}: the store refused the line ({error})"
        try:
            result = self.store.append([Malformed(raw=raw, reason=reason)])
        except (OperationalError, InterfaceError):
            raise
        except Exception as again:  # noqa: BLE001 - even its raw bytes refused
            reason = (f"{reason}; its raw bytes were refused too "
                      f"({storable_text(str(again))[:_ERROR_CHARS]})")
        else:
            for status, n in result.counts.items():
                self.counts[status] += n
            return
        if self.rejects is None:
            raise OperationalError(f"{where} cannot be stored even in the quarantine and no "
                                   f"reject file was given: {reason}")
        self.rejects.write(self.name, number, reason, raw)
        self.counts[TO_REJECT_FILE] += 1


def import_lines(store: LedgerStore, lines: Iterable[str | bytes], *, name: str = "<input>",
                 batch_size: int = DEFAULT_BATCH_SIZE, progress: Progress | None = None,
                 fraction: Callable[[], float] | None = None,
                 rejects: RejectFile | None = None) -> dict[str, int]:
    """Append canonical JSON lines to a store in batches; return counts per status.

    Blank lines are skipped; every other line ends up appended, a duplicate, in
    quarantine with its reason, or (counted as ``to_reject_file``) in ``rejects``; the
    counts add up to ``lines``.  Without ``rejects`` a line the store refuses even to
    quarantine raises :class:`~ledger.errors.OperationalError` (after the lines before it
    were stored).  ``progress`` counts lines after each batch; ``fraction()`` (0..1, the
    part of the input read) lets it estimate the total.
    """
    importer = _Importer(store, name, rejects)
    counts = importer.counts

    def decoded() -> Iterator[Line]:
        for number, line in enumerate(lines, 1):
            stripped = line.strip()
            if not stripped:
                continue
            counts["lines"] += 1
            raw = (stripped.encode("utf-8", "surrogatepass") if isinstance(stripped, str)
                   else bytes(stripped))
            yield number, raw, decode_line(raw, where=f"{name}:{number}")

    for batch in _batches(decoded(), batch_size):
        importer.append(batch)
        if progress is not None:
            progress.set_postfix(f"{counts['appended']:,} appended")
            progress.update_to(counts["lines"], fraction=fraction() if fraction else None)
    return counts
