"""The hand-over from Zenoh's callbacks to the one thread that handles what they bring.

:class:`Inbox` is a FIFO whose :meth:`Inbox.get` waits with a timeout that a signal
cannot turn into a wait without one, so a consumer loop still looks at its stopper in
time (the projector's and dashboard's committed heads, the localizer's samples, the
recorder's queue).
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Callable

__all__ = ["Inbox"]


class Inbox:
    """A FIFO from Zenoh's callbacks (:meth:`put`, cheap) to one consumer thread
    (:meth:`get` with a timeout).

    Not ``queue.SimpleQueue.get(timeout=...)``: in CPython 3.11, when a signal
    interrupts that wait and its handler returns after the deadline, the wait starts
    again with a negative timeout, which means none, and lasts until the next item.
    Here an empty queue is waited on with an :class:`threading.Event`, whose timeout
    holds through signals; the items still travel in a ``SimpleQueue``.
    """

    def __init__(self) -> None:
        self._items: queue.SimpleQueue = queue.SimpleQueue()
        self._bell = threading.Event()
        self._waiting = False
        #: the oldest item; :class:`queue.Empty` when there is none (the C method)
        self.get_nowait: Callable[[], Any] = self._items.get_nowait
        #: how many items wait (the C method)
        self.qsize: Callable[[], int] = self._items.qsize

    def put(self, item: object) -> None:
        self._items.put(item)
        if self._waiting:
            self._bell.set()

    def get(self, timeout_s: float) -> Any:
        """The oldest item, waiting up to ``timeout_s`` seconds for one;
        :class:`queue.Empty` when none came."""
        try:
            return self._items.get_nowait()
        except queue.Empty:
            if timeout_s <= 0:
                raise
        deadline = time.monotonic() + timeout_s
        self._waiting = True        # from here a put rings the bell
        try:
            while True:
                self._bell.clear()
                try:                # an item put before the bell was cleared
                    return self._items.get_nowait()
                except queue.Empty:
                    pass
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._bell.wait(remaining):
                    return self._items.get_nowait()
        finally:
            self._waiting = False
