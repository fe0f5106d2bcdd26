"""The parts the recorder (:mod:`replay.record`) is built from, each independent of Zenoh.

- :class:`FileNamer`: the files of one recording, ``out`` itself or numbered parts
  when splitting;
- :class:`SampleQueue`: the bounded queue between Zenoh's callbacks and the writer
  thread (``put`` blocks while full; :data:`WAKE` wakes a waiting consumer);
- :class:`StreamTracker`: per (source, epoch), the highest sequence seen and the
  missing ranges (:data:`NEW`, :data:`DUPLICATE`);
- :class:`Counters`: a counter sink for a recorder run without a status line.
"""

from __future__ import annotations

import queue
import threading
from pathlib import Path
from typing import Any

from services.service import Inbox

__all__ = ["DRAIN_BATCH", "DUPLICATE", "NEW", "WAKE", "Counters", "FileNamer", "SampleQueue",
           "StreamTracker"]

#: most samples the writer takes from the queue at once
DRAIN_BATCH = 10_000


# -- files --------------------------------------------------------------------------------


class FileNamer:
    """The files of one recording: ``out`` itself, or numbered parts when splitting.

    A one-file recording whose file is already there (a recorder restarted by
    ``stockpile run`` after a crash) continues in the first free numbered part instead:
    nothing is overwritten, and the recording goes on.
    """

    def __init__(self, out: str, split: bool) -> None:
        self.out, self.split = Path(out), split
        self.continues = not split and self.out.exists()
        self.next_index = self._first_free() if split or self.continues else 0

    def _part(self, index: int) -> Path:
        return self.out.with_name(f"{self.out.stem}-{index:04d}{self.out.suffix or '.mcap'}")

    def _first_free(self) -> int:
        index = 0
        pattern = f"{self.out.stem}-[0-9][0-9][0-9][0-9]{self.out.suffix or '.mcap'}"
        for path in self.out.parent.glob(pattern):
            index = max(index, int(path.stem.rsplit("-", 1)[1]) + 1)
        return index

    def check(self) -> Path | None:
        """Create the output's directory (OSError if it cannot be); return the part a
        one-file recording continues in when its file is already there, else None."""
        self.out.parent.mkdir(parents=True, exist_ok=True)
        return self._part(self.next_index) if self.continues else None

    def next(self) -> Path:
        if not self.split and not self.continues:
            return self.out
        path = self._part(self.next_index)
        self.next_index += 1
        return path


# -- the queue between Zenoh and the writer -------------------------------------------------


class SampleQueue:
    """A bounded FIFO: ``put`` blocks while full; ``drain`` takes many at once.

    An :class:`services.inbox.Inbox` carries the items (the Zenoh callback pays one
    cheap put; the writer's wait for them keeps its timeout through signals); a
    producer that finds it full waits on a condition the consumer signals after
    draining.  :meth:`close` wakes a waiting consumer at once.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self._q = Inbox()
        self._space = threading.Condition()
        self._blocked = 0
        self._closed = False

    def put(self, item: object) -> None:
        if self._q.qsize() >= self.capacity and not self._closed:
            self._wait_for_space()
        self._q.put(item)

    def _wait_for_space(self) -> None:
        with self._space:
            self._blocked += 1
            try:
                while self._q.qsize() >= self.capacity and not self._closed:
                    self._space.wait(0.05)
            finally:
                self._blocked -= 1

    def drain(self, timeout_s: float, limit: int = DRAIN_BATCH) -> list:
        """Up to ``limit`` items (and :data:`WAKE` markers); waits up to ``timeout_s``
        when there are none."""
        q = self._q
        try:                          # a closed queue is drained without waiting
            out = [q.get(0.0 if self._closed else timeout_s)]
        except queue.Empty:
            return []
        get = q.get_nowait
        try:
            for _ in range(limit - 1):
                out.append(get())
        except queue.Empty:
            pass
        if self._blocked:
            with self._space:
                self._space.notify_all()
        return out

    def close(self) -> None:
        self._closed = True
        self._q.put(WAKE)
        with self._space:
            self._space.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        return self._q.qsize()


#: put by :meth:`SampleQueue.close` so a waiting consumer wakes at once
WAKE = object()


# -- sequence bookkeeping ------------------------------------------------------------------

NEW, DUPLICATE = 0, 1


class StreamTracker:
    """Per (source, epoch): the highest sequence seen and the missing ranges.

    :meth:`observe` returns ``NEW`` or ``DUPLICATE`` and, for a jump, the gap it
    opened as ``(first_seq, last_seq)``.  :meth:`cell` gives a stream's one-item list
    ``[highest seq]``, which the recorder's hot loop advances in place for the next
    sequence number.
    """

    def __init__(self) -> None:
        self._tops: dict[tuple[str, int], list[int]] = {}
        self._gaps: dict[tuple[str, int], list[list[int]]] = {}

    def cell(self, source: str, epoch: int) -> list[int]:
        stream = (source, epoch)
        cell = self._tops.get(stream)
        if cell is None:
            cell = self._tops[stream] = [-1]
        return cell

    def observe(self, source: str, epoch: int, seq: int) -> tuple[int, tuple[int, int] | None]:
        stream = (source, epoch)
        cell = self.cell(source, epoch)
        top = cell[0]
        if seq == top + 1:
            cell[0] = seq
            return NEW, None
        if seq > top:
            cell[0] = seq
            gap = (top + 1, seq - 1)
            self._gaps.setdefault(stream, []).append([gap[0], gap[1]])
            return NEW, gap
        return (NEW if self._fill(stream, seq) else DUPLICATE), None

    def _fill(self, stream: tuple[str, int], seq: int) -> bool:
        gaps = self._gaps.get(stream, ())
        for i, (first, last) in enumerate(gaps):
            if first <= seq <= last:
                parts = [[a, b] for a, b in ((first, seq - 1), (seq + 1, last)) if a <= b]
                gaps[i:i + 1] = parts  # type: ignore[index]
                return True
        return False

    def open_gaps(self) -> list[dict[str, Any]]:
        return [{"source": s, "epoch": e, "first_seq": a, "last_seq": b}
                for (s, e), gaps in sorted(self._gaps.items()) for a, b in gaps]


class Counters:
    """Counter sink when no :class:`services.status.StatusReporter` is used (tests, bench)."""

    def __init__(self) -> None:
        self.counters: dict[str, int] = {}

    def add(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def get(self, name: str) -> int:
        return self.counters.get(name, 0)
