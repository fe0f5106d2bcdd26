"""``stockpile service scanner --tcp HOST:PORT --protocol cola-a|cola-b``: a SICK LMS1xx,
LMS5xx or TiM on Ethernet -> ``scan`` events.

The service connects to the scanner's CoLa port (TCP 2111 or 2112 on a real device),
sends ``sEN LMDscandata 1`` (:func:`devices.cola.start_scandata`), feeds every byte it
reads into the resynchronising :class:`devices.cola_reader.ColaReader` and publishes each
intact ``sSN LMDscandata`` telegram as one ``scan`` event (``foxglove.LaserScan``) on
``stockpile/<site>/@v1/scan/<source>`` through the shared
:class:`~services.service.EventPublisher`, like the serial LMS200 path
(:mod:`services.scanner`).

Geometry: from each telegram's DIST1 channel: ``start_angle`` = the device's start angle
- 90 deg (the device's 90 deg is straight ahead, the scanner frame's +x), the step as
sent (any step: 0.1667, 0.25, 0.333, 0.5, 1 deg ...), ``end_angle = start + (n - 1) *
step``; ranges = value x scale factor + offset, mm -> m; the reserved codes below 16
(no return, dazzled) are NaN.  ``--intensities`` adds RSSI1 (scaled) when the telegram
has it with as many values.

Valid time: the telegram's arrival (``time.monotonic()`` after the read that completed
it) mapped to site time as the serial path maps it (``--clock wall``: the machine's UTC
clock; ``--clock site``: between the simulator's clock ticks around it, waiting up to
``MAX_TICK_WAIT_S`` for the tick after it), less the device's own latency: ``time of
transmission - time since start-up`` (both on the device's microsecond counter; the
first is when the finished scan went to the output, the second the scan's zero index),
so the valid time is the scan's start.  A latency beyond ``MAX_LATENCY_US`` is not
believed (counted ``latency_ignored``, nothing subtracted).  The transfer time of a
telegram on Ethernet (a few kB at 10-100 Mbit/s: well under a millisecond) is not
subtracted.  The optional time block (the device's real-time clock) is decoded but not
used (docs/integration.md says why).

A cut (the scanner closes, a read fails) drops the bytes of the telegram in flight
(``garbage_bytes``) and reconnects, at once after a connection that delivered telegrams,
else after a backoff that doubles from ``--backoff-initial`` to ``--backoff-max``.  The
device's 16-bit scan counter tells what was lost (:class:`ScanGaps`).

Status counters (the periodic ``status`` line and the final ``stopped`` line):

=====================  ========================================================  ======
counter                meaning                                                   error?
=====================  ========================================================  ======
``telegrams``          intact telegrams of any kind                              no
``published``          scans published                                           no
``checksum_errors``    CoLa-B telegrams whose checksum failed (the reader's)     yes
``broken_frames``      CoLa-A frames broken by a stray STX or a control byte     yes
``garbage_bytes``      bytes discarded while resynchronising or at a cut         no
``bad_telegrams``      scan telegrams that do not decode, or without DIST1       yes
``other_telegrams``    telegrams that are neither scans nor the start answer     yes
``lost_scans``         scans the device made that never arrived intact           yes
``reconnects``         connections after the first                               no
``connect_failures``   connection attempts that failed                           no
``latency_ignored``    telegrams whose device latency was not believed           no
``waiting_for_clock``  scans dropped in ``--clock site`` before the first tick   no
=====================  ========================================================  ======
"""

from __future__ import annotations

import ipaddress
import math
import socket
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import zenoh

from devices import cola
from devices.cola_reader import ColaReader
from schemas.events import is_valid_source
from services.lms200_scans import ScanField, scan_message
from services.serial_device import DevicePipeline
from services.service import (
    DEFAULT_SITE,
    DEFAULT_STATUS_PERIOD_S,
    ServiceRuntime,
    SiteTime,
    Stopper,
    ZenohOptions,
    log,
)

__all__ = ["SERVICE", "DEFAULT_SOURCE", "ERROR_KEYS", "MAX_LATENCY_US", "TcpConfig",
           "ScanGaps", "parse_endpoint", "main"]

SERVICE = "scanner"
DEFAULT_SOURCE = "bwr1.scanner"
#: longest wait for a TCP connection, seconds
CONNECT_TIMEOUT_S = 5.0
#: longest wait of one read, seconds (then the pending clock ticks are looked at)
READ_TIMEOUT_S = 0.1
#: first and longest wait between failed connection attempts, seconds
BACKOFF_INITIAL_S, BACKOFF_MAX_S = 0.1, 5.0
#: site mode: the longest a telegram waits for the clock tick after its arrival (local s)
MAX_TICK_WAIT_S = 2.0
#: the longest device latency (transmission - scan start) believed, microseconds
MAX_LATENCY_US = 1_000_000
RECV_BYTES = 65_536
ERROR_KEYS = ("checksum_errors", "broken_frames", "bad_telegrams", "other_telegrams",
              "lost_scans")
_COUNTER_MOD = 1 << 16
_TIME_MOD = 1 << 32


def parse_endpoint(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT`` for an IPv6 address) -> (host, port); ValueError
    with the reason otherwise."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--tcp wants HOST:PORT with a port 1..65535, got {text!r}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
        ipaddress.IPv6Address(host)
    return host, int(port)


@dataclass(frozen=True)
class TcpConfig:
    """Options of the scanner service on Ethernet (module docstring).

    Attributes
    ----------
    host, port : str, int
        The scanner's address.
    protocol : str
        ``"cola-a"`` or ``"cola-b"`` (the port's framing, set in the device).
    site, zenoh, status_period_s, source, frame_id, clock
        As :class:`services.scanner.Config`.
    intensities : bool
        Publish RSSI1 as the scan's intensities.
    connect_timeout_s, read_timeout_s, backoff_initial_s, backoff_max_s : float
        Seconds (see the constants).
    """

    host: str
    port: int
    protocol: str = "cola-b"
    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    source: str = DEFAULT_SOURCE
    frame_id: str = ""
    clock: str = "wall"
    intensities: bool = False
    connect_timeout_s: float = CONNECT_TIMEOUT_S
    read_timeout_s: float = READ_TIMEOUT_S
    backoff_initial_s: float = BACKOFF_INITIAL_S
    backoff_max_s: float = BACKOFF_MAX_S

    def __post_init__(self) -> None:
        if not self.host or not 0 < int(self.port) < 65536:
            raise ValueError(f"bad scanner address {self.host!r}:{self.port!r}")
        cola.check_protocol(self.protocol)
        if not is_valid_source(self.source):
            raise ValueError(f"bad source name {self.source!r}")
        if self.clock not in ("wall", "site"):
            raise ValueError(f"clock must be 'wall' or 'site', got {self.clock!r}")
        for name in ("connect_timeout_s", "read_timeout_s", "backoff_initial_s",
                     "backoff_max_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        if not self.frame_id:
            object.__setattr__(self, "frame_id", self.source.replace(".", "/", 1))

    @property
    def endpoint(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"


class ScanGaps:
    """Scans lost between telegrams, from the device's scan counter (16 bits) and its
    microsecond counter (32 bits).

    The counter's gap is the count, modulo 2**16.  When the device time says more scans
    passed than half the counter's range (a long cut: over 5.5 min at 100 Hz), the time
    gives the count instead (``elapsed * frequency - 1``), up to half the microsecond
    counter's range (35 min).  A counter that repeats (a polled scan sent again) loses
    nothing; a device time that went back, or on by more than 35 min (the device
    restarted), is counted in :attr:`restarts` and loses nothing it can tell.
    """

    def __init__(self) -> None:
        self.restarts = 0
        self._last: tuple[int, int] | None = None  # (scan counter, time since start-up us)

    def seen(self, counter: int, start_us: int, frequency_hz: float) -> int:
        """Record one telegram's counter and start time; return the scans lost before it."""
        last, self._last = self._last, (int(counter), int(start_us))
        if last is None:
            return 0
        elapsed_us = (int(start_us) - last[1]) % _TIME_MOD
        if elapsed_us >= _TIME_MOD // 2:
            self.restarts += 1
            return 0
        by_counter = (int(counter) - last[0] - 1) % _COUNTER_MOD
        by_time = round(elapsed_us * frequency_hz / 1e6) - 1 if frequency_hz > 0 else -1
        if by_time >= _COUNTER_MOD // 2:
            return by_time
        return by_counter if by_counter < _COUNTER_MOD // 2 else 0


@dataclass(frozen=True, eq=False)
class _Scan:
    """A decoded scan waiting for its valid time."""

    ranges_m: np.ndarray
    geometry: ScanField
    intensities: np.ndarray | None
    latency_ns: int
    arrived_s: float
    arrived_ns: int | None      # the wall clock's reading of the arrival (wall mode)


class _TcpScanPipeline(DevicePipeline):
    """Bytes in, scans out: the reader, the scan counter, the clock and the counters."""

    def __init__(self, config: TcpConfig, runtime: ServiceRuntime, site_time: SiteTime) -> None:
        super().__init__(runtime, site_time, config.source, "scan")
        self.config = config
        self.reader = ColaReader(config.protocol)
        self.gaps = ScanGaps()
        self._waiting: deque[_Scan] = deque()
        self._logged: set[str] = set()

    def connected(self, sock: socket.socket) -> None:
        """A new connection: turn the scan output on."""
        sock.sendall(cola.start_scandata(self.config.protocol))
        self.runtime.log("connected", scanner=self.config.endpoint,
                         protocol=self.config.protocol, source=self.config.source,
                         frame_id=self.config.frame_id, epoch=self.publisher.epoch)

    def cut(self, reason: str) -> None:
        """The connection ended: the telegram in flight never completes."""
        dropped = self.reader.reset()
        self.sync_counters(self.reader, "garbage_bytes")
        self.runtime.log("connection lost", level="warning", scanner=self.config.endpoint,
                         reason=reason, bytes_dropped=dropped)

    def feed(self, data: bytes, arrived_s: float) -> None:
        payloads = self.reader.feed(data)
        self.sync_counters(self.reader, "checksum_errors", "broken_frames", "garbage_bytes")
        if payloads:
            self.status.add("telegrams", len(payloads))
        # the wall clock is read once a read: telegrams that arrived together share it
        arrived_ns = self.site_time.at(arrived_s) if self.site_time.mode == "wall" else None
        for payload in payloads:
            self._telegram(payload, arrived_s, arrived_ns)
        self._release()

    def idle(self) -> None:
        self.log_clock_when_ready()
        self._release()

    def finish(self) -> None:
        self._release(final=True)

    def _telegram(self, payload: bytes, arrived_s: float, arrived_ns: int | None) -> None:
        kind, name = cola.command_of(payload)
        if name == "LMDscandata" and kind == "sEA":
            self._log_once("sEA", "scan data output on", answer=payload.decode("latin-1")
                           if self.config.protocol == "cola-a" else payload.hex())
            return
        if name != "LMDscandata" or kind not in ("sSN", "sRA"):
            self._count("other_telegrams", "not a scan telegram", command=f"{kind} {name}")
            return
        try:
            scan = cola.decode_scandata(payload, self.config.protocol)
            ranges, start, step = scan.ranges_m, scan.start_bearing_rad, scan.step_rad
        except cola.ColaError as exc:
            self._count("bad_telegrams", "bad scan telegram", error=str(exc))
            return
        n = len(ranges)
        if n < 2 or not 0 < step * (n - 1) <= 2 * math.pi:
            self._count("bad_telegrams", "bad scan telegram",
                        error=f"{n} values at {math.degrees(step):g} deg steps")
            return
        lost = self.gaps.seen(scan.scan_counter, scan.time_since_startup_us,
                              scan.scan_frequency_hz)
        if lost:
            self.status.add("lost_scans", lost)
            self.runtime.log("scans lost", level="warning", lost=lost,
                             scan_counter=scan.scan_counter)
        if not self.site_time.ready.is_set():
            self.status.add("waiting_for_clock")
            return
        self.log_clock_when_ready()
        geometry = ScanField(start, start + step * (n - 1), n)
        self._waiting.append(_Scan(ranges, geometry, self._intensities(scan, n),
                                   self._latency_ns(scan), arrived_s, arrived_ns))

    def _latency_ns(self, scan: cola.ScanTelegram) -> int:
        if scan.latency_us <= MAX_LATENCY_US:
            return scan.latency_us * 1000
        self._count("latency_ignored", "device latency not believed",
                    latency_us=scan.latency_us)
        return 0

    def _intensities(self, scan: cola.ScanTelegram, n: int) -> np.ndarray | None:
        rssi = scan.rssi1 if self.config.intensities else None
        if rssi is None or len(rssi.values) != n:
            return None
        return rssi.values.astype(np.float64) * rssi.scale_factor + rssi.scale_offset

    def _release(self, final: bool = False) -> None:
        """Date and publish the waiting scans whose arrival has a clock tick after it (all
        at once on the wall clock); one that waited ``MAX_TICK_WAIT_S`` (or all, when
        ``final``) is dated by the clock's fitted line instead."""
        now_s = time.monotonic()
        while self._waiting:
            scan = self._waiting[0]
            arrived_ns = scan.arrived_ns
            if arrived_ns is None:
                arrived_ns = self.site_time.interpolate(scan.arrived_s)
            if arrived_ns is None:
                if not (final or now_s - scan.arrived_s > MAX_TICK_WAIT_S):
                    return
                arrived_ns = self.site_ns(scan.arrived_s)
            self._waiting.popleft()
            msg = scan_message(scan.ranges_m, arrived_ns - scan.latency_ns,
                               self.config.frame_id, scan.geometry)
            if scan.intensities is not None:
                msg.intensities.extend(scan.intensities.tolist())
            self.publisher.publish(msg)
            self.status.add("published")

    def _count(self, counter: str, msg: str, **fields) -> None:
        """Count an event; log the first of its kind."""
        self._log_once(counter, msg, level="warning", **fields)
        self.status.add(counter)

    def _log_once(self, key: str, msg: str, *, level: str = "info", **fields) -> None:
        if key not in self._logged:
            self._logged.add(key)
            self.runtime.log(msg, level=level, **fields)


def _connect(config: TcpConfig, runtime: ServiceRuntime, failures: int) -> socket.socket | None:
    """One connection attempt; None (logged on the first failure of a run, and every
    tenth) when the scanner cannot be reached."""
    try:
        sock = socket.create_connection((config.host, config.port),
                                        timeout=config.connect_timeout_s)
    except OSError as exc:
        runtime.status.add("connect_failures")
        if failures % 10 == 0:
            runtime.log("cannot connect", level="warning", scanner=config.endpoint,
                        error=str(exc) or type(exc).__name__, attempts=failures + 1)
        return None
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.settimeout(config.read_timeout_s)
    return sock


def _read(sock: socket.socket, pipeline: _TcpScanPipeline, stopper: Stopper) -> str | None:
    """Read one connection until it is cut (the reason) or a stop (None)."""
    try:
        pipeline.connected(sock)
    except OSError as exc:
        return f"cannot send the start command: {exc}"
    while not stopper.is_set():
        try:
            data = sock.recv(RECV_BYTES)
        except socket.timeout:
            pipeline.idle()
            continue
        except OSError as exc:
            return str(exc) or type(exc).__name__
        if not data:
            return "closed by the scanner"
        pipeline.feed(data, time.monotonic())
    try:                                        # a clean stop: turn the output off
        sock.sendall(cola.stop_scandata(pipeline.config.protocol))
    except OSError:
        pass
    return None


def _run(config: TcpConfig, runtime: ServiceRuntime, pipeline: _TcpScanPipeline) -> None:
    """Connect, read, reconnect after every cut, until a stop."""
    stopper = runtime.stopper
    failures, connections = 0, 0
    while not stopper.is_set():
        sock = _connect(config, runtime, failures)
        if sock is None:
            failures += 1
            delay_s = min(config.backoff_max_s,
                          config.backoff_initial_s * 2 ** min(failures - 1, 30))
            stopper.wait(delay_s)               # the backoff; a stop ends it at once
            continue
        connections += 1
        if connections > 1:
            runtime.status.add("reconnects")
        telegrams_before = pipeline.reader.telegrams
        with sock:
            reason = _read(sock, pipeline, stopper)
        if reason is None:
            break
        pipeline.cut(reason)
        failures = 0 if pipeline.reader.telegrams > telegrams_before else failures + 1
        if failures:
            stopper.wait(min(config.backoff_max_s,
                             config.backoff_initial_s * 2 ** min(failures - 1, 30)))
    pipeline.finish()


def main(config: TcpConfig, *, stopper: Stopper | None = None) -> int:
    """Run the scanner service on Ethernet until SIGINT/SIGTERM.

    Returns
    -------
    int
        0 on a clean stop, 2 if the Zenoh session cannot start.  An unreachable scanner
        is retried for ever (logged), never fatal.
    """
    stopper = stopper or Stopper()  # installed first: SIGTERM during start-up stops cleanly
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=config.source,
                             status_period_s=config.status_period_s, stopper=stopper)
    try:
        runtime.open(error_keys=ERROR_KEYS, announce=False)
    except (zenoh.ZError, OSError) as exc:
        log(SERVICE, "cannot open zenoh session", level="error", error=str(exc))
        return 2
    with runtime:
        site_time = SiteTime(config.clock)
        site_time.follow(runtime.session, config.site)
        try:
            pipeline = _TcpScanPipeline(config, runtime, site_time)
            runtime.announce()
            runtime.log("reading", scanner=config.endpoint, protocol=config.protocol,
                        clock=config.clock)
            _run(config, runtime, pipeline)
        finally:
            site_time.close()
    return 0
