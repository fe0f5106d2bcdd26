"""Where a service gets "now" in site time: the wall clock, or the simulator's clock events.

:class:`SiteTime` maps the local monotonic clock onto site time (UTC ns): in a real
yard the machine's UTC clock, in the simulated yard a least-squares line through the
recent arrivals of the site's ``clock`` events that restarts at every change of the
simulator's pace (:func:`_pace_segment_start`), or the straight line between the two
ticks around a reading (:meth:`SiteTime.interpolate`).
"""

from __future__ import annotations

import bisect
import threading
import time

from schemas.events import decode_attachment

__all__ = ["TICKS_KEPT", "SiteTime"]

#: clock ticks :meth:`SiteTime.interpolate` keeps (see docs/design-notes.md)
TICKS_KEPT = 4096


def _pace_segment_start(pairs: list[tuple[float, int]], pace_change: float,
                        min_step_s: float = 0.0005) -> int:
    """Index of the first (arrival s, site ns) pair of the newest run of steps whose
    rates (site ns per local s) stay within a factor ``pace_change`` of the newest
    step's.  A step shorter than ``min_step_s`` of local time (events delivered in a
    burst) has no usable rate and neither ends a run nor sets the newest rate."""
    rates = [(i + 1, (sb - sa) / (mb - ma))
             for i, ((ma, sa), (mb, sb)) in enumerate(zip(pairs, pairs[1:]))
             if mb - ma >= min_step_s]
    if len(rates) < 2:
        return 0
    newest = rates[-1][1]
    for end, rate in reversed(rates[:-1]):
        if not newest / pace_change <= rate <= newest * pace_change:
            return end
    return 0


class SiteTime:
    """Where a service gets "now" in site time (UTC ns).

    ``mode="wall"`` (a real yard): the machine's UTC clock.  ``mode="site"`` (the
    simulated yard, which runs faster than real time): follow the ``clock`` events on
    ``stockpile/<site>/@v1/clock/**`` and map the local monotonic clock onto site
    time with a least-squares line through the recent (arrival, site time) pairs of
    the current pace.  The simulator changes pace (the demo's 40x while a machine
    moves, 2000x while none does, around every reclaim cut; slower when it falls
    behind): a pair whose step from the one before runs at more than ``pace_change``
    times, or less than 1 / ``pace_change`` of, the newest step's rate starts the
    segment the line is fitted to, so the line never spans a change of pace (see
    docs/design-notes.md).
    ``now_ns()`` before the first clock event raises :class:`LookupError`.

    A reading that already has a tick after it is better placed by :meth:`interpolate`:
    on the straight line between the ticks that arrived just before and just after it.
    That follows every change of pace, also one the line has not seen yet (a simulator
    that falls behind its schedule runs slower for a while), so a service that can wait
    for the next tick (the scanner) dates its readings that way.
    """

    def __init__(self, mode: str = "wall", *, window: int = 20,
                 pace_change: float = 1.5) -> None:
        if mode not in ("wall", "site"):
            raise ValueError(f"clock mode must be 'wall' or 'site', got {mode!r}")
        if not pace_change > 1.0:
            raise ValueError(f"pace_change must be > 1, got {pace_change!r}")
        self.mode = mode
        self.window = int(window)
        self.pace_change = float(pace_change)
        self._pairs: list[tuple[float, int]] = []  # (monotonic s, site ns)
        # every tick kept, in arrival order, for interpolate(): monotonic s, site ns
        self._ticks_s: list[float] = []
        self._ticks_ns: list[int] = []
        self._fit: tuple[float, float, int] | None = None  # (mono0, ns per s, site0)
        self._lock = threading.Lock()
        self._subscriber = None
        self.ready = threading.Event()
        if mode == "wall":
            self.ready.set()

    def follow(self, session, site: str) -> None:
        """Subscribe to the site's ``clock`` events (site mode only)."""
        if self.mode != "site":
            return
        def on_sample(sample) -> None:
            arrived = time.monotonic()
            try:
                _epoch, _seq, valid_ns = decode_attachment(bytes(sample.attachment.to_bytes()))
            except Exception:  # noqa: BLE001 - a malformed clock event is ignored
                return
            self.observe(arrived, valid_ns)

        self._subscriber = session.declare_subscriber(f"stockpile/{site}/@v1/clock/**",
                                                      on_sample)

    def observe(self, monotonic_s: float, site_ns: int) -> None:
        """Add one (arrival, site time) pair.  A tick no later in site time than the
        newest one (a repeat, or one delivered late) carries nothing new and is ignored."""
        with self._lock:
            if self._pairs and int(site_ns) <= self._pairs[-1][1]:
                return
            self._pairs.append((monotonic_s, int(site_ns)))
            if not self._ticks_s or monotonic_s >= self._ticks_s[-1]:
                self._ticks_s.append(monotonic_s)
                self._ticks_ns.append(int(site_ns))
                del self._ticks_s[:-TICKS_KEPT], self._ticks_ns[:-TICKS_KEPT]
            del self._pairs[:-self.window]
            del self._pairs[:_pace_segment_start(self._pairs, self.pace_change)]
            pairs = self._pairs
            m0, s0 = pairs[0]
            if len(pairs) >= 2 and pairs[-1][0] > m0:
                n = len(pairs)
                xs = [m - m0 for m, _ in pairs]
                ys = [float(s - s0) for _, s in pairs]
                mx, my = sum(xs) / n, sum(ys) / n
                sxx = sum((x - mx) ** 2 for x in xs)
                slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx if sxx > 0 else 1e9
                intercept = my - slope * mx
                self._fit = (m0, slope, s0 + int(intercept))
                speed_known = True
            else:
                self._fit = (m0, 1e9, s0)
                speed_known = False
        # Ready only once the site clock's speed is measured: with a single pair the
        # fit assumes real time, which is off by seconds when the site runs faster.
        if speed_known:
            self.ready.set()

    def at(self, monotonic_s: float) -> int:
        """Site time (ns) at a local ``time.monotonic()`` reading."""
        if self.mode == "wall":
            return time.time_ns() - int((time.monotonic() - monotonic_s) * 1e9)
        with self._lock:
            if self._fit is None:
                raise LookupError("no clock event received yet")
            m0, slope, s0 = self._fit
        return s0 + int((monotonic_s - m0) * slope)

    def interpolate(self, monotonic_s: float) -> int | None:
        """Site time (ns) at a local ``time.monotonic()`` reading, on the line between the
        ticks that arrived just before and just after it; None while no tick has arrived
        after it yet, or when it is older than the ticks kept (then use :meth:`at`).  In
        wall mode, :meth:`at`."""
        if self.mode == "wall":
            return self.at(monotonic_s)
        with self._lock:
            ticks_s, ticks_ns = self._ticks_s, self._ticks_ns
            if not ticks_s or not ticks_s[0] <= monotonic_s <= ticks_s[-1]:
                return None
            i = bisect.bisect_right(ticks_s, monotonic_s)
            if i == len(ticks_s):      # exactly at the newest tick's arrival
                return ticks_ns[-1]
            m0, m1, s0, s1 = ticks_s[i - 1], ticks_s[i], ticks_ns[i - 1], ticks_ns[i]
        return s0 + int(round((monotonic_s - m0) / (m1 - m0) * (s1 - s0)))

    def now_ns(self) -> int:
        return self.at(time.monotonic())

    @property
    def speed(self) -> float:
        """Site seconds per local second (1.0 in wall mode)."""
        if self.mode == "wall" or self._fit is None:
            return 1.0
        return self._fit[1] / 1e9

    def close(self) -> None:
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
