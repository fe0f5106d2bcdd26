"""The declarations a localizer takes from the ledger when no publisher's cache has them.

A localizer needs the site's datum (``site_declared``) and its machine's geometry
(``machine_declared``) before it can place anything.  Its subscribers ask the publishers'
caches for declarations made before it started, but a declaration the ledger holds may
have no live publisher any more: a yard whose configuration was imported, or a
configuration service that declared and exited.  :class:`LedgerDeclarations` asks the
ledger service (``events`` of those two types) on start, retrying while no ledger answers,
until one answer came or both declarations are known; it hands the latest of each to the
service loop, which applies one only when the localizer still lacks it (what the caches
or a live declaration gave is never replaced by an older record).
"""

from __future__ import annotations

import threading
from typing import Callable

from schemas.events import Event
from schemas.validate import InvalidEvent, check_event
from ledger.errors import LedgerError
from services.ledger_client import LedgerClient

#: the event types asked from the ledger
DECLARATION_TYPES = ("site_declared", "machine_declared")
#: seconds between attempts while no ledger service answers (the last one repeats)
RETRY_S = (0.5, 1.0, 2.0, 5.0)


class FromLedger:
    """A declaration read from the ledger, queued for the service loop."""

    __slots__ = ("event",)

    def __init__(self, event: Event) -> None:
        self.event = event


def latest_declarations(events, machine_id: str) -> list[Event]:
    """The last ``site_declared`` and the last ``machine_declared`` of ``machine_id``.

    ``events`` are in ledger order (the later record wins); a record that fails the
    event checks is skipped.  Returns 0-2 events, the site's first.
    """
    site = machine = None
    for event in events:
        try:
            message = check_event(event)
        except InvalidEvent:
            continue
        if event.type == "site_declared":
            site = event
        elif event.type == "machine_declared" and message.machine_id == machine_id:
            machine = event
    return [e for e in (site, machine) if e is not None]


class LedgerDeclarations(threading.Thread):
    """Ask the ledger for the declarations until it answers or they are known.

    Parameters
    ----------
    client : LedgerClient
    machine_id : str
    put : callable(FromLedger) -> None
        Queues a declaration for the service loop.
    needed : callable() -> bool
        True while the localizer lacks the site's or its machine's declaration.
    stop : threading.Event
        The service's stop: the thread ends at once when it is set.
    log : callable(msg, **fields) -> None
    """

    def __init__(self, client: LedgerClient, machine_id: str, put: Callable[[FromLedger], None],
                 needed: Callable[[], bool], stop: threading.Event, log) -> None:
        super().__init__(name="localizer-declarations", daemon=True)
        self.client, self.machine_id = client, machine_id
        self._put, self._needed, self._stop, self._log = put, needed, stop, log
        self.attempts = 0

    def run(self) -> None:
        waits = iter(RETRY_S)
        wait_s = RETRY_S[0]
        while self._needed() and not self._stop.is_set():
            self.attempts += 1
            try:
                records = self.client.read(types=DECLARATION_TYPES)
            except LedgerError as exc:
                if self.attempts == 1:
                    self._log("declarations not yet from the ledger", reason=str(exc))
                wait_s = next(waits, wait_s)
                self._stop.wait(wait_s)
                continue
            except Exception as exc:  # noqa: BLE001 - the session may be closing
                self._log("declarations from the ledger failed", level="warning",
                          error=f"{type(exc).__name__}: {exc}")
                return
            found = latest_declarations((r.to_event() for r in records), self.machine_id)
            for event in found:
                self._put(FromLedger(event))
            self._log("declarations from the ledger", found=len(found),
                      types=",".join(e.type for e in found) or "none",
                      attempts=self.attempts)
            return
