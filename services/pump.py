"""Take samples off Zenoh's receive threads: a FIFO channel and a thread that drains it.

A Python callback given to a subscriber runs on Zenoh's receive thread and takes the
GIL for every sample, so the link is read only as fast as the rest of the process lets
that thread in.  :class:`SamplePump` gives the subscriber a Rust-side bounded FIFO
channel instead (``zenoh.handlers.FifoChannel``): Zenoh's threads push into it without
the GIL and wait only when it is full (the backpressure of a bounded queue), and one
thread of the pump's own takes each sample out and calls ``on_sample``.
docs/operations.md "Backpressure" says why this matters under congestion control BLOCK.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

import zenoh

from services.logfmt import log

#: samples that may wait in a channel for ``on_sample``, by default
DEFAULT_CAPACITY = 100_000
#: how long close() waits for the pump's thread after undeclaring, s
CLOSE_WAIT_S = 5.0


class SamplePump:
    """Declares a subscriber on a FIFO channel of ``capacity`` samples and calls
    ``on_sample(sample)`` for each on a thread named ``name``.

    ``declare(handler)`` declares the subscriber with the given handler and returns it
    (e.g. ``lambda h: zenoh.ext.declare_advanced_subscriber(session, key, h, ...)``).
    :attr:`subscriber` is what it returned.  ``on_sample`` may block (a full queue
    downstream): the channel then fills and Zenoh holds back.  An exception from
    ``on_sample`` is passed to ``on_error(exc)`` (default: one error line naming the
    pump) and the pump goes on with the next sample.
    :meth:`close` undeclares the subscriber, which ends the thread.
    """

    def __init__(self, declare: Callable[[Any], Any], on_sample: Callable[[Any], None], *,
                 capacity: int = DEFAULT_CAPACITY, name: str = "sample-pump",
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.on_sample, self.name = on_sample, name
        self.on_error = on_error if on_error is not None else self._log_error
        self.subscriber = declare(zenoh.handlers.FifoChannel(capacity))
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for sample in self.subscriber:   # ends when the subscriber is undeclared
            try:
                self.on_sample(sample)
            except Exception as exc:   # noqa: BLE001 - one bad sample must not stop the pump
                self.on_error(exc)

    def _log_error(self, exc: BaseException) -> None:
        log("pump", "sample handler failed", level="error", pump=self.name,
            error=f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        """Undeclare the subscriber and wait (at most ``CLOSE_WAIT_S``) for the thread."""
        if self._closed:
            return
        self._closed = True
        try:
            self.subscriber.undeclare()
        except zenoh.ZError:
            pass   # the session is closed already
        if threading.current_thread() is not self._thread:
            self._thread.join(CLOSE_WAIT_S)

    def undeclare(self) -> None:
        """The same as :meth:`close` (so a pump stands in for a subscriber)."""
        self.close()

