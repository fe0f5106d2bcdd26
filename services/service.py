"""The shape every ``stockpile service NAME`` shares.

A service is one small process on the yard network.  Each one has:

- a typed ``main(config, ...)`` taking a frozen config dataclass (built from the
  command line by the module's ``config_from_args``), so tests and ``stockpile run``
  can start it without argparse;
- the shared Zenoh options (:func:`add_service_arguments`: ``--connect``,
  ``--listen``, ``--mode``, ``--config FILE``, ``--site``) and a session opened from
  them (:meth:`ServiceRuntime.open`);
- a liveliness token ``stockpile/<site>/@live/<service>/<name>`` while it runs;
- clean shutdown on SIGINT/SIGTERM (:class:`Stopper`);
- an :class:`Inbox` between Zenoh's callbacks and the thread that handles what they
  bring (a wait with a timeout that a signal cannot turn into one without);
- structured log lines on stderr in logfmt (:func:`log`), and a one-line status
  every few seconds (:class:`StatusReporter`: rate, backlog, errors);
- ledger-bound publishing through :class:`EventPublisher`: one source with its epoch
  and dense sequence, Zenoh ``AdvancedPublisher`` per key with a sample cache,
  sample-miss detection (heartbeat) and publisher detection, congestion control
  BLOCK, so a ledger that restarts can recover what it missed from the cache.

When it stops, a service logs one ``published`` line per source it published::

    ts=2026-11-22T10:00:00.000Z level=info service=scanner msg=published source=bwr1.scanner epoch=1795... count=1200

which the demo and the end-to-end tests compare with the ledger.
"""

from __future__ import annotations

import argparse
import bisect
import json
import math
import os
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Sequence, TextIO

from google.protobuf.message import Message

from schemas.events import (
    Event,
    encode_attachment,
    is_valid_source,
    key_expr,
    make_event,
)

#: Every service ``stockpile service NAME`` can start (module ``services.<module>``).
DEFAULT_SITE = "demo"
DEFAULT_STATUS_PERIOD_S = 5.0
#: samples each AdvancedPublisher keeps for late joiners and recovery (per key)
DEFAULT_CACHE_SAMPLES = 50_000
#: period of the AdvancedPublisher heartbeat that lets a subscriber detect a lost last sample, s
HEARTBEAT_PERIOD_S = 0.5


# -- options ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ZenohOptions:
    """The shared Zenoh options.  Defaults: peer mode, multicast scouting off."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    scouting: bool = False

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ZenohOptions:
        return cls(mode=args.mode, connect=tuple(args.connect or ()),
                   listen=tuple(args.listen or ()), config_file=args.zenoh_config,
                   scouting=bool(args.scouting))

    def to_config(self):
        """A ``zenoh.Config`` from these options."""
        from services.zenoh_config import zenoh_config

        return zenoh_config(mode=self.mode, connect=self.connect, listen=self.listen,
                            config_file=self.config_file, scouting=self.scouting)

    def to_argv(self) -> list[str]:
        """The same options as command-line arguments (to start a child process)."""
        argv = ["--mode", self.mode]
        for endpoint in self.connect:
            argv += ["--connect", endpoint]
        for endpoint in self.listen:
            argv += ["--listen", endpoint]
        if self.config_file:
            argv += ["--config", self.config_file]
        if self.scouting:
            argv.append("--scouting")
        return argv


def add_service_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options every service shares: Zenoh, ``--site``, ``--status-period``."""
    from services.zenoh_config import add_zenoh_arguments

    parser.add_argument("--site", default=DEFAULT_SITE,
                        help=f"site id: keys are stockpile/<site>/@v1/... (default {DEFAULT_SITE})")
    parser.add_argument("--status-period", type=float, default=DEFAULT_STATUS_PERIOD_S,
                        metavar="S", help="seconds between status lines on stderr (default 5)")
    add_zenoh_arguments(parser)


# -- logging ------------------------------------------------------------------------------

_log_lock = threading.Lock()


def _logfmt_value(value: Any) -> str:
    if isinstance(value, float):
        text = f"{value:.6g}"
    else:
        text = str(value)
    if text == "" or any(c in text for c in ' ="\\\n\t'):
        return json.dumps(text)
    return text


def format_log(service: str, level: str, msg: str, fields: dict[str, Any],
               now_ns: int | None = None) -> str:
    """One logfmt line: ``ts=... level=... service=... msg=... key=value ...``."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    secs, ns = divmod(now_ns, 1_000_000_000)
    ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(secs)) + f".{ns // 1_000_000:03d}Z"
    parts = [f"ts={ts}", f"level={level}", f"service={_logfmt_value(service)}",
             f"msg={_logfmt_value(msg)}"]
    parts += [f"{k}={_logfmt_value(v)}" for k, v in fields.items()]
    return " ".join(parts)


def log(service: str, msg: str, *, level: str = "info", stream: TextIO | None = None,
        **fields: Any) -> None:
    """Write one structured log line on stderr (thread-safe)."""
    line = format_log(service, level, msg, fields)
    with _log_lock:
        out = stream or sys.stderr
        out.write(line + "\n")
        out.flush()


def parse_logfmt(line: str) -> dict[str, str]:
    """Inverse of :func:`format_log` for one line (tests and the demo read logs back)."""
    out: dict[str, str] = {}
    i, n = 0, len(line)
    while i < n:
        while i < n and line[i] == " ":
            i += 1
        eq = line.find("=", i)
        if eq < 0:
            break
        key = line[i:eq]
        j = eq + 1
        if j < n and line[j] == '"':
            decoder = json.JSONDecoder()
            value, end = decoder.raw_decode(line, j)
            out[key] = value
            i = end
        else:
            end = line.find(" ", j)
            end = n if end < 0 else end
            out[key] = line[j:end]
            i = end
    return out


# -- shutdown -----------------------------------------------------------------------------


class Stopper:
    """Turns SIGINT/SIGTERM into a :class:`threading.Event` (main thread only).

    ``stop.wait(t)`` doubles as an interruptible sleep for service loops.

    The stop does not depend on Python running the signal handler.  Python runs a
    handler in the main thread between two bytecodes, which may be inside
    ``event.wait()`` while that holds the event's lock (``Event.set()`` there would
    wait for that lock forever: a projector that ignored SIGTERM), or not at all while
    the main thread waits inside C code that does not return.  So the process's
    signal wakeup fd (:func:`signal.set_wakeup_fd`) is a pipe: the C-level handler
    writes the signal's number to it at once, and one relay thread per process reads
    it and sets the event of the stopper installed last.  The Python handler, when it
    runs, writes to the same pipe (in case something replaced the wakeup fd); a stop
    relayed twice is harmless.  A loop that waits for items between two looks at the
    event waits on an :class:`Inbox`, whose timeout a signal cannot undo.
    """

    def __init__(self, install: bool = True) -> None:
        self.event = threading.Event()
        self.signal_name: str | None = None
        if install and threading.current_thread() is threading.main_thread():
            _signal_relay(self)
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, _handled_by_the_relay)

    def set(self) -> None:
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self.event.wait(timeout_s)


def _handled_by_the_relay(signum: int, _frame: object) -> None:
    """Python-level handler of SIGINT/SIGTERM: the relay's pipe (:class:`Stopper`);
    no lock is taken here."""
    if _relay_write_fd is not None:
        try:
            os.write(_relay_write_fd, bytes((signum,)))
        except BlockingIOError:       # the pipe is full of stops already on their way
            pass


_relay_lock = threading.Lock()
_relay_write_fd: int | None = None
_relay_target: Stopper | None = None


def _signal_relay(stopper: Stopper) -> None:
    """Make ``stopper`` the one the relay thread stops (the pipe, the wakeup fd and
    the thread are set up once per process, from the main thread)."""
    global _relay_write_fd, _relay_target
    with _relay_lock:
        _relay_target = stopper
        if _relay_write_fd is None:
            read_fd, write_fd = os.pipe()
            os.set_blocking(write_fd, False)
            signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
            threading.Thread(target=_relay, args=(read_fd,), name="signal-relay",
                             daemon=True).start()
            _relay_write_fd = write_fd


def _relay(read_fd: int) -> None:
    while chunk := os.read(read_fd, 64):
        target = _relay_target
        if target is None:
            continue
        for signum in chunk:
            if signum in (signal.SIGINT, signal.SIGTERM):
                target.signal_name = signal.Signals(signum).name
                target.event.set()


# -- inbox ------------------------------------------------------------------------------


class Inbox:
    """A FIFO from Zenoh's callbacks (:meth:`put`, cheap) to one consumer thread
    (:meth:`get` with a timeout).

    Not ``queue.SimpleQueue.get(timeout=...)``: in CPython 3.11, when a signal
    interrupts that wait and its handler returns after the deadline, the wait starts
    again with a negative timeout, which means none, and lasts until the next item
    (a live dashboard waited for a committed head that never came and so never saw
    SIGTERM's stop).  Here an empty queue is waited on with an :class:`threading.Event`,
    whose timeout holds through signals; the items still travel in a ``SimpleQueue``.
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


# -- status -------------------------------------------------------------------------------


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


# -- publishing ---------------------------------------------------------------------------


def declare_ledger_publisher(session, key: str, *, cache_samples: int = DEFAULT_CACHE_SAMPLES,
                             priority=None):
    """An AdvancedPublisher for ledger-bound events on ``key``.

    Congestion control BLOCK (never drops), reliable, a cache of ``cache_samples``
    whose replies also block rather than drop, sample-miss detection with a heartbeat,
    and publisher detection, so a ledger that (re)starts finds it and asks its cache.
    """
    import zenoh
    import zenoh.ext as zext

    priority = zenoh.Priority.DATA if priority is None else priority
    return zext.declare_advanced_publisher(
        session, key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        priority=priority,
        reliability=zenoh.Reliability.RELIABLE,
        cache=zext.CacheConfig(cache_samples, replies_config=zext.RepliesConfig(
            congestion_control=zenoh.CongestionControl.BLOCK, priority=priority)),
        sample_miss_detection=zext.MissDetectionConfig(
            heartbeat=HEARTBEAT_PERIOD_S, sporadic_heartbeat=None),
        publisher_detection=True,
    )


class EventPublisher:
    """One ledger-bound event source on Zenoh: epoch, dense sequence, reliable keys.

    Each event type gets its own ``AdvancedPublisher`` on
    ``stockpile/<site>/@v1/<type>/<source>`` with a cache of ``cache_samples``
    samples, sample-miss detection with a heartbeat, publisher detection, and
    congestion control BLOCK, so nothing is dropped on the way and a subscriber that
    joins late (a restarted ledger) can query what it missed.

    The sequence is shared by all types of the source (the ledger's identity is
    ``(source, epoch, seq)``).  Thread-safe.

    Parameters
    ----------
    session : zenoh.Session
    site, source : str
    epoch : int, optional
        Default: the wall clock in nanoseconds at construction (never reused).
    cache_samples : int
        Samples kept per key for recovery.
    priority : zenoh.Priority, optional
        Default ``Priority.DATA``.
    """

    def __init__(self, session, site: str, source: str, *, epoch: int | None = None,
                 cache_samples: int = DEFAULT_CACHE_SAMPLES, priority=None) -> None:
        import zenoh

        if not is_valid_source(source):
            raise ValueError(f"bad source name {source!r}")
        self.session, self.site, self.source = session, site, source
        self.epoch = time.time_ns() if epoch is None else int(epoch)
        self.cache_samples = int(cache_samples)
        self.priority = zenoh.Priority.DATA if priority is None else priority
        self.seq = 0
        self._publishers: dict[str, Any] = {}
        self._lock = threading.Lock()

    def _publisher(self, type_name: str):
        publisher = self._publishers.get(type_name)
        if publisher is None:
            publisher = declare_ledger_publisher(
                self.session, key_expr(self.site, type_name, self.source),
                cache_samples=self.cache_samples, priority=self.priority)
            self._publishers[type_name] = publisher
        return publisher

    def wait_matched(self, type_name: str, timeout_s: float) -> None:
        """Block until a subscriber matches this source's key for ``type_name``.

        An event published before any subscriber matched reaches it only through the
        publisher's cache (on the subscriber's next history query); waiting first makes
        the first event live.  Raises :class:`TimeoutError` after ``timeout_s``.
        """
        import zenoh

        key = self._publisher(type_name).key_expr
        plain = self.session.declare_publisher(key,
                                               congestion_control=zenoh.CongestionControl.BLOCK)
        matched = threading.Event()
        listener = plain.declare_matching_listener(lambda s: s.matching and matched.set())
        try:
            if not (plain.matching_status.matching or matched.wait(timeout_s)):
                raise TimeoutError(f"no subscriber matched {key} in {timeout_s:g} s")
        finally:
            listener.undeclare()
            plain.undeclare()

    def declare(self, *type_names: str) -> None:
        """Declare the keys up front (so subscribers can match before the first event)."""
        with self._lock:
            for name in type_names:
                self._publisher(name)

    def publish(self, message: Message) -> Event:
        """Publish one message as the next event of this source; return the event.

        The valid time is the message's own timestamp field.
        """
        with self._lock:
            event = make_event(message, source=self.source, epoch=self.epoch, seq=self.seq)
            self._publisher(event.type).put(
                event.payload,
                attachment=encode_attachment(event.epoch, event.seq, event.valid_time_ns))
            self.seq += 1
            return event

    @property
    def count(self) -> int:
        return self.seq

    def close(self) -> None:
        with self._lock:
            for publisher in self._publishers.values():
                try:
                    publisher.undeclare()
                except Exception:  # noqa: BLE001 - the session may already be closed
                    pass
            self._publishers.clear()


# -- the runtime --------------------------------------------------------------------------


@dataclass
class ServiceRuntime:
    """What a running service holds: its session, liveliness token, status and stopper.

    Use as a context manager; on exit the publishers log their ``published`` lines,
    the token is dropped and the session closed.
    """

    service: str
    site: str
    zenoh_options: ZenohOptions
    name: str = ""
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    stopper: Stopper | None = None
    session: Any = None
    status: StatusReporter | None = None
    publishers: list[EventPublisher] = field(default_factory=list)
    _token: Any = None

    def open(self, *, rate_of: str = "published", backlog: Callable[[], int] | None = None,
             error_keys: Sequence[str] = ("errors",), announce: bool = True) -> ServiceRuntime:
        """Open the session and start the status line.

        With ``announce`` (default) the liveliness token is declared at once; a
        service that must set up subscribers or queryables first passes
        ``announce=False`` and calls :meth:`announce` when it is ready, so that
        "token present" means "serving".
        """
        import zenoh

        self.stopper = self.stopper or Stopper()
        self.session = zenoh.open(self.zenoh_options.to_config())
        self.status = StatusReporter(self.service, period_s=self.status_period_s,
                                     rate_of=rate_of, backlog=backlog, error_keys=error_keys)
        self.log("started", site=self.site, pid=_pid(), zid=str(self.session.zid()))
        self.status.start()
        if announce:
            self.announce()
        return self

    @property
    def token_key(self) -> str:
        """``stockpile/<site>/@live/<service>/<name>``."""
        return f"stockpile/{self.site}/@live/{self.service}/{self.name or self.service}"

    def announce(self) -> None:
        """Declare the liveliness token (once)."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.token_key)
            self.log("ready", liveliness=self.token_key)

    def publisher(self, source: str, **kwargs: Any) -> EventPublisher:
        pub = EventPublisher(self.session, self.site, source, **kwargs)
        self.publishers.append(pub)
        return pub

    def log(self, msg: str, *, level: str = "info", **fields: Any) -> None:
        log(self.service, msg, level=level, **fields)

    def close(self) -> None:
        if self.status is not None:
            self.status.stop()
        for pub in self.publishers:
            self.log("published", source=pub.source, epoch=pub.epoch, count=pub.count)
            pub.close()
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:  # noqa: BLE001
                pass
            self._token = None
        if self.session is not None:
            self.session.close()
            self.session = None
        fields = dict(self.status.snapshot()) if self.status else {}
        reason = self.stopper.signal_name if self.stopper and self.stopper.signal_name else "done"
        self.log("stopped", reason=reason, **fields)

    def __enter__(self) -> ServiceRuntime:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _pid() -> int:
    import os

    return os.getpid()


# -- site time ----------------------------------------------------------------------------


#: clock ticks :meth:`SiteTime.interpolate` keeps (the demo's simulator ticks before
#: each telegram while a machine works, 200 a second at 40x: 20 s of local time)
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
    segment the line is fitted to, so the line never spans a change of pace (fitted
    across one it was off by seconds of site time for the next ``window`` pairs).
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
        from schemas.events import decode_attachment

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
