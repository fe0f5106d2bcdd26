"""The ledger service's ``q/backup``: a consistent, verified backup taken between batches.

``stockpile ledger backup`` on a file a ledger service holds sends ``q/backup`` with the
payload ``{"to": "/abs/backup/dir"}``.  The queryable puts a :class:`BackupRequest` into
the writer's sample queue; the writer (:class:`services.ledger_service.Writer`) takes
its samples through :func:`next_sample`, which meets it between two batches and calls
:meth:`BackupRequest.copy` there, which checkpoints the store and copies its file
(:func:`ledger.backup.take_copy`): no batch is appended meanwhile, so the copy holds one
committed head.  Verifying the copy and writing its
manifest (:func:`ledger.backup.finish`) then run on a thread of their own, so the writer
goes back to its batches at once; the reply is the manifest as JSON, or one
``reply_err`` with the reason.
"""

from __future__ import annotations

import json
import queue
import threading
from dataclasses import asdict

from common.logs import emit
from ledger.backup import finish, take_copy
from ledger.errors import LedgerError
from ledger.store import LedgerStore

SERVICE = "ledger"


class BackupRequest:
    """One ``q/backup`` query, waiting in the writer's sample queue."""

    def __init__(self, query, key: str) -> None:
        self.query, self.key = query, key

    def _target(self) -> str:
        payload = self.query.payload
        params = json.loads(payload.to_bytes()) if payload is not None else {}
        target = params.get("to") if isinstance(params, dict) else None
        if not isinstance(target, str) or not target:
            raise ValueError('q/backup needs {"to": "/abs/backup/dir"}')
        return target

    def copy(self, store: LedgerStore) -> None:
        """On the writer's thread, between batches: take the copy, then hand verifying
        and replying to a thread of its own.  Never raises: a failure is the reply."""
        try:
            if store.backend == "postgresql":
                raise ValueError("this ledger service holds a PostgreSQL ledger: back it up "
                                 "with pg_basebackup or pg_dump, not through the service")
            if not hasattr(store, "checkpoint"):
                raise ValueError("this ledger service holds an in-memory ledger: nothing "
                                 "to back up")
            pending = take_copy(store, self._target())  # type: ignore[arg-type]
        except (LedgerError, OSError, ValueError) as exc:
            self._fail(exc)
            return
        emit(SERVICE, "info", "backup copied between batches", to=str(pending.directory),
             head=pending.head.global_seq, sha256=pending.sha256)
        threading.Thread(target=self._finish, args=(pending,), name="ledger-backup",
                         daemon=True).start()

    def _finish(self, pending) -> None:
        try:
            manifest = finish(pending)
        except (LedgerError, OSError, ValueError) as exc:
            self._fail(exc)
            return
        emit(SERVICE, "info", "backup verified", to=str(pending.directory),
             head=manifest.global_seq, rows=manifest.rows_verified)
        with self.query:
            self.query.reply(self.key, json.dumps(asdict(manifest)).encode())

    def _fail(self, exc: BaseException) -> None:
        message = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
        emit(SERVICE, "warning", "backup failed", error=message)
        with self.query:
            self.query.reply_err(message.encode())


def next_sample(samples: queue.Queue, store: LedgerStore, timeout_s: float | None = None):
    """The writer's next queue item (``timeout_s``: longest wait, seconds; queue.Empty
    after it); a backup request met on the way is served first, between batches (nothing
    of the batch being gathered is committed yet)."""
    while True:
        item = samples.get(timeout=timeout_s) if timeout_s is None or timeout_s > 0 \
            else samples.get_nowait()
        if not isinstance(item, BackupRequest):
            return item
        item.copy(store)
