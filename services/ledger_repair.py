"""The ledger service's gap repair: ask a source's publisher cache again for what it missed.

Split out of :mod:`services.ledger_service` (which imports :class:`GapRepair` from here).
"""

from __future__ import annotations

import queue
import threading
import time

import zenoh.ext as zext

from ledger.store import LedgerStore
from schemas.events import decode_attachment
from services.pump import SamplePump
from services.service import ServiceRuntime

__all__ = ["GapRepair"]

#: longest a repair sample waits for room in the full queue before it looks again
#: whether its subscriber is being retired, seconds
PUT_WAIT_S = 0.2


class GapRepair:
    """Asks a source's publisher cache again when its stream has open gaps.

    :meth:`check` (called by the writer when the number of missing events changes)
    logs every newly opened gap with its exact range and, for each source with
    missing events, declares a short-lived history subscriber on that source's keys
    (at most one per source at a time, for ``window_s``).  Its samples are queued
    only when their sequence lies in an open gap, so a cache replay costs almost
    nothing.

    While gaps stay open, :meth:`check` runs again every ``window_s`` on a timer of its
    own, so a gap whose repair window ended before the cache replay reached it is asked
    again even when no new event arrives.

    A repair subscriber is retired (undeclared) outside the lock, after telling its
    callback to stop waiting for room in the queue: the writer, the only one that
    drains the queue, is the thread that retires it.  A sample dropped that way
    leaves its gap open, and the next check asks again.
    """

    def __init__(self, session, site: str, store: LedgerStore, samples: queue.Queue,
                 runtime: ServiceRuntime, *, window_s: float = 10.0) -> None:
        self.session, self.site, self.store, self.samples = session, site, store, samples
        self.runtime = runtime
        self.window_s = window_s
        self._reported: set[int] = set()
        self._active: dict[str, tuple[object, threading.Event, float]] = {}
        self._open: dict[tuple[str, int], list[tuple[int, int]]] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._timer: threading.Timer | None = None

    def check(self) -> None:
        status = self.runtime.status
        gaps = self.store.gaps(open_only=True)
        open_ranges: dict[tuple[str, int], list[tuple[int, int]]] = {}
        for gap in gaps:
            open_ranges.setdefault((gap.source, gap.epoch), []).append((gap.first_seq, gap.last_seq))
            if gap.gap_id not in self._reported:
                self._reported.add(gap.gap_id)
                if status is not None:
                    status.add("gaps_opened")
                self.runtime.log("gap opened", level="warning", source=gap.source,
                                 epoch=gap.epoch, first_seq=gap.first_seq,
                                 last_seq=gap.last_seq, missing=gap.size)
        now = time.monotonic()
        retired = []
        with self._lock:
            if self._closed:
                return
            self._open = open_ranges
            for source, (sub, stop, since) in list(self._active.items()):
                if now - since > self.window_s or not any(k[0] == source for k in open_ranges):
                    retired.append((sub, stop))
                    del self._active[source]
            wanted = [source for source in {k[0] for k in open_ranges}
                      if source not in self._active]
        self._retire(retired)
        self._again_later(bool(open_ranges))
        for source in wanted:
            sub, stop = self._ask(source)
            with self._lock:
                if self._closed or source in self._active:
                    retired.append((sub, stop))
                    continue
                self._active[source] = (sub, stop, now)
            if status is not None:
                status.add("repairs_asked")
        self._retire(retired)

    def _again_later(self, gaps_open: bool) -> None:
        """Schedule one more :meth:`check` in ``window_s`` while gaps are open."""
        with self._lock:
            if self._closed or not gaps_open or (self._timer and self._timer.is_alive()):
                return
            self._timer = threading.Timer(self.window_s, self.check)
            self._timer.daemon = True
            self._timer.start()

    def _wanted(self, source: str, epoch: int, seq: int) -> bool:
        with self._lock:
            return any(first <= seq <= last for first, last in self._open.get((source, epoch), ()))

    def _ask(self, source: str):
        stop = threading.Event()

        def on_sample(sample) -> None:
            attachment = sample.attachment
            if attachment is None:
                return
            try:
                epoch, seq, _valid = decode_attachment(attachment.to_bytes())
            except ValueError:
                return
            if self._wanted(source, epoch, seq):
                item = (str(sample.key_expr), sample.payload.to_bytes(), attachment.to_bytes(),
                        time.monotonic())
                while not stop.is_set():
                    try:
                        self.samples.put(item, timeout=PUT_WAIT_S)
                        return
                    except queue.Full:
                        continue

        sub = SamplePump(lambda handler: zext.declare_advanced_subscriber(
            self.session, f"stockpile/{self.site}/@v1/*/{source}", handler,
            history=zext.HistoryConfig(detect_late_publishers=False)),
            on_sample, name=f"gap-repair-{source}")
        return sub, stop

    @staticmethod
    def _retire(subscribers) -> None:
        for sub, stop in subscribers:
            stop.set()
            sub.undeclare()
        subscribers.clear()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self._timer is not None:
                self._timer.cancel()
            retired = [(sub, stop) for sub, stop, _since in self._active.values()]
            self._active.clear()
        self._retire(retired)
