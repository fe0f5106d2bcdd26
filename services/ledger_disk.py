"""The ledger service's disk guard: a free-space watermark, and a pause when the disk is full.

- **Watermark.** After batches, at most once per ``check_period_s``, the writer asks
  the free space of the ledger's file system (:func:`common.disk.free_bytes`).  Below
  ``min_free_bytes`` the alarm ``low_disk`` stands (a warning line, the status line's
  ``alarm=low_disk free_bytes=...``, and the status published on Zenoh); it clears when
  the space is back above the watermark.
- **Pause.** When a commit fails because the disk is full
  (:class:`ledger.errors.LedgerDiskFull`), :meth:`DiskGuard.append` keeps the batch and
  tries it again every ``retry_period_s`` until it commits, raising the alarm
  ``disk_full`` with the operating system's words.  Meanwhile the writer takes no new
  batch: the service's bounded queue fills, the Zenoh callback blocks, and the
  publishers (congestion control BLOCK, :mod:`services.publishing`) hold back with their
  caches, for up to Zenoh's block budget; after it the router drops the link and the
  publishers go on into their caches, from which :mod:`services.ledger_repair` takes
  the missing range once the ledger resumes.  When space returns the held batch
  commits first, the alarm clears, and the writer goes on by itself.

A retry is a plain :meth:`LedgerStore.append` of the same items on the same store (the
store's writer state moves only when a commit succeeds; ``docs/operations.md``, "The
disk watermark", says what DuckDB leaves behind a COMMIT that failed).
"""

from __future__ import annotations

import json
import time
from typing import Sequence

from common.disk import BYTES_PER_MB, free_bytes
from ledger.errors import LedgerDiskFull
from ledger.records import AppendResult
from ledger.store import LedgerStore
from services.status import StatusReporter
from services.stopping import Stopper

__all__ = ["CHECK_PERIOD_S", "DEFAULT_MIN_FREE_MB", "DISK_FULL", "LOW_DISK", "RETRY_PERIOD_S",
           "DiskGuard", "publish_status", "status_key"]

#: default free-space watermark of the ledger's file system, MiB
DEFAULT_MIN_FREE_MB = 512.0
#: shortest time between two free-space checks after batches, seconds
CHECK_PERIOD_S = 1.0
#: time between two attempts to commit the held batch while the disk is full, seconds
RETRY_PERIOD_S = 1.0
#: alarm names on the status line and the status key
LOW_DISK, DISK_FULL = "low_disk", "disk_full"


def status_key(site: str) -> str:
    """Where the ledger service publishes its status (JSON: the status line's fields,
    alarms included, and ``service``)."""
    return f"stockpile/{site}/@ledger/status"


def publish_status(session, site: str, service: str, status: StatusReporter):
    """Declare the publisher of :func:`status_key` and make ``status`` publish on it at
    every status line and alarm change; return the publisher (undeclare it after
    setting ``status.on_status`` back to None)."""
    publisher = session.declare_publisher(status_key(site))
    status.on_status = lambda fields: publisher.put(
        json.dumps({"service": service, **fields}, default=str).encode())
    return publisher


class DiskGuard:
    """The watermark check and the disk-full pause of one ledger file.

    Parameters
    ----------
    ledger_path : str or None
        The ledger file (None or ``:memory:``: no file system to watch, as for a
        PostgreSQL ledger, whose server watches its own disk; a full disk, which the
        PostgreSQL store reports as :class:`LedgerDiskFull` from SQLSTATE 53100, is still
        held and retried).
    min_free_mb : float
        The watermark, MiB free on the ledger's file system.
    status : StatusReporter
        Where the alarms and counters go.
    stopper : Stopper
        A stop (SIGTERM) ends a pause: the held batch's error is raised.
    """

    def __init__(self, ledger_path: str | None, min_free_mb: float, status: StatusReporter,
                 stopper: Stopper, *, check_period_s: float = CHECK_PERIOD_S,
                 retry_period_s: float = RETRY_PERIOD_S) -> None:
        self.path = None if ledger_path in (None, ":memory:") else ledger_path
        self.min_free_bytes = int(min_free_mb * BYTES_PER_MB)
        self.status, self.stopper = status, stopper
        self.check_period_s, self.retry_period_s = check_period_s, retry_period_s
        self._checked_at = -float("inf")

    def free_bytes(self) -> int | None:
        """Free bytes on the ledger's file system, None without a file or when it cannot be
        asked."""
        if self.path is None:
            return None
        try:
            return free_bytes(self.path)
        except OSError:
            return None

    def check(self, *, now: float | None = None, force: bool = False) -> None:
        """Raise or clear ``low_disk`` from the free space, at most once per
        ``check_period_s`` unless ``force``."""
        now = time.monotonic() if now is None else now
        if not force and now - self._checked_at < self.check_period_s:
            return
        self._checked_at = now
        free = self.free_bytes()
        if free is None:
            return
        if free < self.min_free_bytes:
            self.status.raise_alarm(
                LOW_DISK, "ledger disk below its free-space watermark", free_bytes=free,
                min_free_bytes=self.min_free_bytes, ledger=self.path)
        else:
            self.status.clear_alarm(LOW_DISK, "ledger disk above its free-space watermark again",
                                    free_bytes=free)

    def append(self, store: LedgerStore, items: Sequence) -> AppendResult:
        """``store.append(items)``, holding the batch while the disk is full: retried every
        ``retry_period_s`` until it commits.  Raises :class:`LedgerDiskFull` if the
        service is stopped during the pause (nothing of the batch committed)."""
        paused_at: float | None = None
        while True:
            try:
                result = store.append(items)
            except LedgerDiskFull as exc:
                if paused_at is None:
                    paused_at = time.monotonic()
                    self.status.add("disk_full_pauses")
                    self.check(force=True)
                self.status.raise_alarm(
                    DISK_FULL, "ledger paused: the disk is full; the batch is held and no new "
                    "batch is taken until space returns (publishers hold back)",
                    error=exc.os_error, free_bytes=self.free_bytes(), held_events=len(items),
                    detail=str(exc))
                if self.stopper.wait(self.retry_period_s):
                    raise
                self.status.add("disk_full_retries")
                continue
            if paused_at is not None:
                paused_s = time.monotonic() - paused_at
                self.status.clear_alarm(DISK_FULL, "ledger resumed: the held batch is committed",
                                        paused_s=round(paused_s, 3), held_events=len(items))
                self.check(force=True)
            return result
