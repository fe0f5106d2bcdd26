"""The one-line status a service logs every few seconds: rate, backlog, errors, counters.

:class:`StatusReporter` holds a service's counters (thread-safe) and runs a thread
that logs them as a ``level=status`` line every ``period_s`` seconds, through the same
logger as every other line (:func:`services.logfmt.log`; the ``status`` level sits
between info and warning, so ``--quiet`` hides it).

An **alarm** (:meth:`StatusReporter.raise_alarm`) is a condition an operator must see
now, e.g. the ledger's disk below its watermark.  While it stands, every status line
carries ``alarm=<name>[,<name>...]`` and the alarm's fields; raising or clearing one logs
its own line at once, and ``on_status`` (when set: a service that publishes its status
on Zenoh) receives the same fields as a status line, at every status line and at
every alarm change.  Example::

    ts=... level=status service=ledger msg=status appended_per_s=0.0 backlog=200000 errors=0 ... alarm=disk_full free_bytes=0 error="No space left on device"
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Iterable

from services.logfmt import log

__all__ = ["DEFAULT_STATUS_PERIOD_S", "StatusReporter"]

#: seconds between two status lines unless ``--status-period`` says otherwise
DEFAULT_STATUS_PERIOD_S = 5.0


class StatusReporter:
    """Counters plus a thread that logs a one-line status every ``period_s``.

    ``rate_of`` names the counter whose rate per second is shown; ``backlog`` is a
    callable returning the current backlog (queue length).  Errors are the counters
    named in ``error_keys``.
    """

    def __init__(self, service: str, *, period_s: float = DEFAULT_STATUS_PERIOD_S,
                 rate_of: str = "published", backlog: Callable[[], int] | None = None,
                 error_keys: Iterable[str] = ("errors",)) -> None:
        self.service = service
        self.period_s = float(period_s)
        self.rate_of = rate_of
        self.backlog = backlog
        self.error_keys = tuple(error_keys)
        self.counters: dict[str, int] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last = (time.monotonic(), 0)
        self.alarms: dict[str, dict[str, Any]] = {}
        #: called with the status fields at every status line and alarm change
        self.on_status: Callable[[dict[str, Any]], None] | None = None

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0) + n

    def get(self, name: str) -> int:
        with self._lock:
            return self.counters.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counters)

    def status_fields(self, *, advance_rate: bool = True) -> dict[str, Any]:
        """The fields of one status line; ``advance_rate=False`` leaves the rate's
        reference point where it was (an alarm published between two lines)."""
        now = time.monotonic()
        counters = self.snapshot()
        count = counters.get(self.rate_of, 0)
        t0, c0 = self._last
        if advance_rate:
            self._last = (now, count)
        rate = (count - c0) / (now - t0) if now > t0 else 0.0
        fields: dict[str, Any] = {f"{self.rate_of}_per_s": round(rate, 1)}
        if self.backlog is not None:
            fields["backlog"] = self.backlog()
        fields["errors"] = sum(counters.get(k, 0) for k in self.error_keys)
        fields.update(counters)
        with self._lock:
            alarms = {name: dict(extra) for name, extra in self.alarms.items()}
        if alarms:
            fields["alarm"] = ",".join(sorted(alarms))
            for extra in alarms.values():
                fields.update(extra)
        return fields

    def raise_alarm(self, name: str, message: str, **fields: Any) -> None:
        """Raise (or update) alarm ``name``: a warning line ``message`` with ``fields``
        when it is new, and ``on_status`` at once whenever its fields changed."""
        with self._lock:
            new = name not in self.alarms
            changed = self.alarms.get(name) != fields
            self.alarms[name] = dict(fields)
        if new:
            log(self.service, message, level="warning", alarm=name, **fields)
        if changed:
            self._publish(advance_rate=False)

    def clear_alarm(self, name: str, message: str, **fields: Any) -> None:
        """Clear alarm ``name`` if it stands: an info line ``message``, ``on_status`` at once."""
        with self._lock:
            stood = self.alarms.pop(name, None) is not None
        if stood:
            log(self.service, message, alarm_cleared=name, **fields)
            self._publish(advance_rate=False)

    def _publish(self, *, advance_rate: bool, fields: dict[str, Any] | None = None) -> None:
        if self.on_status is None:
            return
        try:
            self.on_status(fields if fields is not None
                           else self.status_fields(advance_rate=advance_rate))
        except Exception as exc:  # noqa: BLE001 - a closed session must not stop the line
            log(self.service, "cannot publish the status", level="warning", error=str(exc))

    def start(self) -> StatusReporter:
        if self.period_s > 0 and self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"{self.service}-status",
                                            daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            fields = self.status_fields()
            log(self.service, "status", level="status", **fields)
            self._publish(advance_rate=False, fields=fields)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
