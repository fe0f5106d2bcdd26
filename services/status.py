"""The one-line status a service logs every few seconds: rate, backlog, errors, counters.

:class:`StatusReporter` holds a service's counters (thread-safe) and runs a thread
that logs them as a ``level=status`` line every ``period_s`` seconds, through the same
logger as every other line (:func:`services.logfmt.log`; the ``status`` level sits
between info and warning, so ``--quiet`` hides it).
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

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0) + n

    def get(self, name: str) -> int:
        with self._lock:
            return self.counters.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counters)

    def status_fields(self) -> dict[str, Any]:
        now = time.monotonic()
        counters = self.snapshot()
        count = counters.get(self.rate_of, 0)
        t0, c0 = self._last
        self._last = (now, count)
        rate = (count - c0) / (now - t0) if now > t0 else 0.0
        fields: dict[str, Any] = {f"{self.rate_of}_per_s": round(rate, 1)}
        if self.backlog is not None:
            fields["backlog"] = self.backlog()
        fields["errors"] = sum(counters.get(k, 0) for k in self.error_keys)
        fields.update(counters)
        return fields

    def start(self) -> StatusReporter:
        if self.period_s > 0 and self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"{self.service}-status",
                                            daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            log(self.service, "status", level="status", **self.status_fields())

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
