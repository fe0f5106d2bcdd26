"""Site clocks: where the ledger's recorded time comes from.

Recorded time is "when the ledger learned it".  In production that is the wall
clock; in the simulated yard it is the time of the latest ``clock`` event, so that
"an assay 4 hours late" means 4 simulated hours.

A clock is asked for the time with the valid time of the latest ``clock`` event the
ledger has accepted (or ``None``), so it holds no state of its own and a rolled-back
batch leaves nothing behind.  Whatever a clock says, the ledger never lets recorded
time go backwards along the global sequence.
"""

from __future__ import annotations

import time
from typing import Protocol


class SiteClock(Protocol):
    """Anything with ``now_ns(latest_clock_event_ns) -> int`` (UTC nanoseconds)."""

    name: str

    def now_ns(self, latest_clock_event_ns: int | None) -> int: ...


class WallClock:
    """Production: recorded time is the machine's UTC wall clock."""

    name = "wall"

    def now_ns(self, latest_clock_event_ns: int | None) -> int:
        return time.time_ns()


class EventClock:
    """Simulated yard: recorded time is the valid time of the latest ``clock`` event.

    Before the first ``clock`` event it reads ``start_ns`` (default 0).
    """

    name = "events"

    def __init__(self, start_ns: int = 0) -> None:
        self.start_ns = start_ns

    def now_ns(self, latest_clock_event_ns: int | None) -> int:
        return self.start_ns if latest_clock_event_ns is None else latest_clock_event_ns


class ManualClock:
    """Tests: recorded time is whatever ``set_ns``/``advance_ns`` last made it."""

    name = "manual"

    def __init__(self, now_ns: int = 0) -> None:
        self._now_ns = now_ns

    def set_ns(self, now_ns: int) -> None:
        self._now_ns = now_ns

    def advance_ns(self, delta_ns: int) -> int:
        self._now_ns += delta_ns
        return self._now_ns

    def now_ns(self, latest_clock_event_ns: int | None) -> int:
        return self._now_ns


CLOCKS = {"wall": WallClock, "events": EventClock}


def clock_by_name(name: str) -> SiteClock:
    """``"wall"`` or ``"events"``; raises ValueError otherwise."""
    try:
        return CLOCKS[name]()
    except KeyError:
        raise ValueError(f"unknown clock {name!r}; choose one of {sorted(CLOCKS)}") from None
