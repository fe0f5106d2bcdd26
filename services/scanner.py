"""``stockpile service scanner``: read a SICK LMS200 from a serial port, publish scans.

With ``--tcp HOST:PORT --protocol cola-a|cola-b`` instead of ``--device`` it reads a SICK
LMS1xx, LMS5xx or TiM on Ethernet: :mod:`services.scanner_tcp`.  This module parses both
command lines and runs the serial path.

The service opens the scanner's serial port with pyserial (a real RS-232/RS-422 line, or the
simulator's pseudo-terminal), feeds every byte into the resynchronising
:class:`devices.lms200.TelegramReader` and publishes each intact 0xB0 (measured
values) telegram as one ``scan`` event (``foxglove.LaserScan``) on
``stockpile/<site>/@v1/scan/<source>``, through the shared :class:`~services.service.EventPublisher`
(one epoch, dense sequence, cached ``AdvancedPublisher``, congestion control BLOCK).

Bad bytes never stop it.  Everything that is not published is counted in the status
counters (the periodic ``status`` line and the final ``stopped`` line):

=====================  ==========================================================  =======
counter                meaning                                                     error?
=====================  ==========================================================  =======
``telegrams``          CRC-valid telegrams of any kind                             no
``published``          scans published                                             no
``crc_errors``         corruption events (the reader's count; see its docs)        yes
``garbage_bytes``      bytes discarded while resynchronising (a byte count)        no [1]_
``other_telegrams``    CRC-valid telegrams that are not 0xB0 from the scanner      yes
                       (e.g. the acknowledgement of ``--send-start``, or host
                       commands seen by a read-only tap)
``bad_telegrams``      0xB0 telegrams whose contents do not decode                 yes
``partial_scans``      0xB0 telegrams with a partial-scan index other than 0       yes
                       (interlaced output is not supported; dropped)
``field_mismatch``     value counts that do not fit ``--fov-deg`` /                yes
                       ``--resolution-deg`` (or any LMS200 field, without them)
``waiting_for_clock``  scans dropped in ``--clock site`` mode before the first     no
                       ``clock`` event (their valid time is unknown)
=====================  ==========================================================  =======

.. [1] ``garbage_bytes`` is reported but not summed into the status line's ``errors``,
   which counts events: one corrupted telegram is one CRC error but hundreds of bytes.

Scan geometry (matches :mod:`sim.scanner`, the Foxglove ``LaserScan`` / ROS
convention): beam ``k`` has bearing ``-fov/2 + k * step`` about the scanner's +z axis from
+x, so ``start_angle = -fov/2`` and ``end_angle = -fov/2 + (n - 1) * step`` (= ``+fov/2``
for every LMS200 field), radians.  The field of view and step come from the value count of
each telegram (401 -> 100 deg / 0.25 deg, 361 -> 180 / 0.5, 181 -> 180 / 1,
201 -> 100 / 0.5, 101 -> 100 / 1) unless ``--fov-deg`` / ``--resolution-deg`` fix them.
Ranges are metres; no-return and error codes are NaN; intensities are empty.
(:mod:`services.lms200_scans` holds these pure parts: field, valid time, message.)

Valid time (:func:`~services.lms200_scans.scan_valid_time_ns`): the moment the telegram's last byte arrived minus
its serial transfer time (``bytes * 10 bits / baud``).  The arrival is
``time.monotonic()`` right after the read that completed the telegram, mapped to site time
through :class:`~services.service.SiteTime`.  When one read returns more than the
telegram (the service fell behind and several telegrams, or trailing bytes, arrived
together), the bytes behind it are taken to have followed it at line rate, so their
transfer time is subtracted too, but never back past the previous read (those bytes were
not there yet).  That is exact on a real, busy serial line.  A pseudo-terminal delivers
each write at once, faster than any line rate, so when the service falls behind the
simulator the scans of one burst get estimated times, off by up to the burst's line
time; they stay in order while the telegrams have one size (one field; a longer telegram
behind a shorter one in the same burst can get the earlier time).  When the service keeps
up (one telegram per read) the time is exact.  Line time is subtracted as site time,
after the mapping, so a simulator that writes each telegram at scan time + transfer time
(site time) gets its scan time back at any speed.

``--clock site``: until the first ``clock`` event arrives, scans cannot be given a site
time; they are dropped and counted as ``waiting_for_clock`` (a short blind spell at
start-up rather than scans with invented times).  The service logs ``site clock ready``
once the clock is known.  After that a telegram waits for the clock tick that arrives
after it (up to ``MAX_TICK_WAIT_S``, else the clock's fitted line dates it) and its
arrival is placed on the line between the ticks around it
(:meth:`~services.service.SiteTime.interpolate`).  The simulator's pace is not steady:
it changes around every cut, and on a loaded machine it falls behind.  A line fitted
to the ticks lags such a change; placed between ticks (the simulator ticks where its
pace changes, every site second while a machine works and right before each telegram
it writes to the pty) a scan follows it (see docs/design-notes.md).

The service stops on SIGINT/SIGTERM (exit 0), when the device goes away (the pty master
closed, a USB adapter unplugged: logged as ``device closed``, exit 0), and exits 2 with one
``cannot open device`` line when the port cannot be opened.
"""

from __future__ import annotations

import argparse
import math
import time
from collections import deque
from dataclasses import dataclass, field

import serial

from common.options import add_clock
from devices import cola, lms200
from schemas.events import is_valid_source
from services.lms200_scans import (
    BITS_PER_BYTE,
    ScanField,
    scan_field,
    scan_message,
    scan_valid_time_ns,
    telegram_end_offsets,
    transfer_time_ns,
)
from services import scanner_tcp
from services.serial_device import DevicePipeline, run_serial_service
from services.service import (
    DEFAULT_SITE,
    DEFAULT_STATUS_PERIOD_S,
    ServiceRuntime,
    SiteTime,
    Stopper,
    ZenohOptions,
)

__all__ = [
    "SERVICE", "DEFAULT_BAUD", "DEFAULT_SOURCE", "BITS_PER_BYTE", "READ_TIMEOUT_S", "ERROR_KEYS",
    "Config", "ScanField", "default_frame_id", "scan_field", "transfer_time_ns",
    "telegram_end_offsets", "scan_valid_time_ns", "scan_message", "add_arguments",
    "config_from_args", "main",
]

SERVICE = "scanner"
#: site mode: the longest a telegram waits for the clock tick after its arrival (local
#: seconds) before the clock's line dates it
MAX_TICK_WAIT_S = 2.0
#: site mode: telegrams published per read at most, per telegram the read brought (the
#: rest after the next reads, or when the line is idle), so a tick's backlog drains
RELEASE_PER_READ = 2
#: LMS200 default line rate for continuous output, baud (bits per second).
DEFAULT_BAUD = 500_000
DEFAULT_SOURCE = "bwr1.scanner"
#: Longest wait of one serial read, seconds.  A read that times out with nothing means an
#: idle line: a pending partial candidate is then given up (``TelegramReader.flush``).
READ_TIMEOUT_S = 0.1
#: Status counters summed into the status line's ``errors``.
ERROR_KEYS = ("crc_errors", "other_telegrams", "bad_telegrams", "partial_scans",
              "field_mismatch")


# -- configuration ------------------------------------------------------------------------


def default_frame_id(source: str) -> str:
    """The frame id for a source: its first ``.`` becomes ``/``.

    ``bwr1.scanner`` -> ``bwr1/scanner``.
    """
    return source.replace(".", "/", 1)


@dataclass(frozen=True)
class Config:
    """Options of one scanner service.

    Attributes
    ----------
    device : str
        Serial port, e.g. ``/dev/ttyUSB0`` or a simulator pty.
    site : str
        Site id: keys are ``stockpile/<site>/@v1/...``.
    zenoh : ZenohOptions
        Session options.
    status_period_s : float
        Seconds between status lines (0: none).
    baud : int
        Line rate, baud (bits per second); also sets the transfer time subtracted from the
        arrival time.
    source : str
        Event source, e.g. ``bwr1.scanner``.
    frame_id : str
        ``LaserScan.frame_id``; empty: :func:`default_frame_id` of the source.
    fov_deg, resolution_deg : float or None
        Field of view and angular step, degrees; None: from each telegram's value count.
    send_start : bool
        Send the start-continuous-output command once after opening the port (never waits
        for an answer).
    clock : str
        ``"wall"`` (the machine's UTC clock) or ``"site"`` (follow the ``clock`` events).
    read_timeout_s : float
        Longest wait of one serial read, seconds (also the idle-line threshold).
    """

    device: str
    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    baud: int = DEFAULT_BAUD
    source: str = DEFAULT_SOURCE
    frame_id: str = ""
    fov_deg: float | None = None
    resolution_deg: float | None = None
    send_start: bool = False
    clock: str = "wall"
    read_timeout_s: float = READ_TIMEOUT_S

    def __post_init__(self) -> None:
        if not self.device:
            raise ValueError("a device is required (--device PATH)")
        if not isinstance(self.baud, int) or self.baud <= 0:
            raise ValueError(f"baud must be a positive integer, got {self.baud!r}")
        if not is_valid_source(self.source):
            raise ValueError(f"bad source name {self.source!r}")
        if self.clock not in ("wall", "site"):
            raise ValueError(f"clock must be 'wall' or 'site', got {self.clock!r}")
        for name in ("fov_deg", "resolution_deg"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        if self.fov_deg is not None and self.fov_deg > 360.0:
            raise ValueError(f"fov_deg must be <= 360, got {self.fov_deg}")
        if not self.read_timeout_s > 0:
            raise ValueError(f"read_timeout_s must be > 0, got {self.read_timeout_s}")
        if not self.frame_id:
            object.__setattr__(self, "frame_id", default_frame_id(self.source))


# -- command line -------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the scanner's own options (the shared ones come from ``service_cli``)."""
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--device", metavar="PATH",
                       help="serial port of the LMS200, e.g. /dev/ttyUSB0 or a simulator pty")
    where.add_argument("--tcp", metavar="HOST:PORT",
                       help="a SICK LMS1xx/LMS5xx/TiM on Ethernet: its CoLa port, e.g. "
                       "192.168.0.1:2112 ([v6]:PORT for IPv6)")
    parser.add_argument("--protocol", choices=cola.PROTOCOLS, default=None,
                        help="with --tcp: the port's framing, CoLa-A (ASCII) or CoLa-B "
                        "(binary) (default cola-b)")
    parser.add_argument("--intensities", action="store_true",
                        help="with --tcp: publish RSSI1 as the scans' intensities")
    parser.add_argument("--baud", type=int, default=DEFAULT_BAUD,
                        help=f"line rate, baud (default {DEFAULT_BAUD})")
    parser.add_argument("--source", default=DEFAULT_SOURCE,
                        help=f"event source (default {DEFAULT_SOURCE})")
    parser.add_argument("--frame-id", default="",
                        help="LaserScan frame id (default: the source with its first '.' "
                        "replaced by '/', e.g. bwr1/scanner)")
    parser.add_argument("--fov-deg", type=float, default=None, metavar="DEG",
                        help="field of view, degrees (default: from each telegram's value "
                        "count: 401/201/101 -> 100, 361/181 -> 180)")
    parser.add_argument("--resolution-deg", type=float, default=None, metavar="DEG",
                        help="angular step, degrees (default: from the value count: 401 -> "
                        "0.25, 361/201 -> 0.5, 181/101 -> 1)")
    parser.add_argument("--send-start", action="store_true",
                        help="send the start-continuous-output command once on start (not "
                        "for a scanner already streaming or a read-only tap)")
    add_clock(parser, events_as="site",
              help="site time: the machine's UTC clock (wall) or the simulator's clock events")


def config_from_args(args: argparse.Namespace) -> Config | scanner_tcp.TcpConfig:
    """A :class:`Config` (``--device``) or a :class:`services.scanner_tcp.TcpConfig`
    (``--tcp``) from parsed arguments (raises ValueError on bad values, and on options of
    the other path)."""
    if args.tcp:
        serial_only = [name for name, given in (
            ("--fov-deg", args.fov_deg is not None),
            ("--resolution-deg", args.resolution_deg is not None),
            ("--send-start", args.send_start), ("--baud", args.baud != DEFAULT_BAUD)) if given]
        if serial_only:
            raise ValueError(f"{', '.join(serial_only)}: for --device only (a scanner on "
                             "Ethernet states its field in each telegram)")
        host, port = scanner_tcp.parse_endpoint(args.tcp)
        return scanner_tcp.TcpConfig(
            host=host, port=port, protocol=args.protocol or "cola-b", site=args.site,
            zenoh=ZenohOptions.from_args(args), status_period_s=args.status_period,
            source=args.source, frame_id=args.frame_id, clock=args.clock,
            intensities=args.intensities)
    if args.protocol is not None or args.intensities:
        raise ValueError("--protocol and --intensities are for --tcp only")
    return Config(device=args.device, site=args.site, zenoh=ZenohOptions.from_args(args),
                  status_period_s=args.status_period, baud=args.baud, source=args.source,
                  frame_id=args.frame_id, fov_deg=args.fov_deg,
                  resolution_deg=args.resolution_deg, send_start=args.send_start,
                  clock=args.clock)


# -- the service --------------------------------------------------------------------------


class _ScanPipeline(DevicePipeline):
    """Bytes in, scans out: the reader, the arrival bookkeeping and the counters."""

    def __init__(self, config: Config, runtime: ServiceRuntime, site_time: SiteTime) -> None:
        super().__init__(runtime, site_time, config.source, "scan")
        self.config = config
        self.reader = lms200.TelegramReader()
        self._pending = b""  # the reader's unconsumed bytes (tail of the stream)
        self._window_end_s = time.monotonic()  # monotonic time the last byte arrived
        self._previous_read_s = self._window_end_s  # ... and the read before that one
        self._fields: dict[int, ScanField | None] = {}
        # site mode: telegrams waiting for the clock tick after their arrival
        # (telegram, arrived s, bytes behind it, the read before s)
        self._waiting: deque[tuple[bytes, float, int, float]] = deque()

    def start(self, port: serial.Serial) -> None:
        config = self.config
        self.runtime.log("reading", device=config.device, baud=config.baud, source=config.source,
                         frame_id=config.frame_id, clock=config.clock, epoch=self.publisher.epoch)
        if config.send_start:
            _send_start(port, self.runtime)

    def feed(self, data: bytes, arrived_s: float) -> None:
        """Bytes that arrived at local monotonic time ``arrived_s``."""
        window = self._pending + data
        self._previous_read_s, self._window_end_s = self._window_end_s, arrived_s
        waiting = len(self._waiting)
        self._handle(window, self.reader.feed(data))
        # a few per read: publishing a whole tick's worth at once would hold up the reads
        # behind it, and their arrival times with them
        self._release(at_most=RELEASE_PER_READ * max(1, len(self._waiting) - waiting))

    def idle(self) -> None:
        """The line was idle for a whole read timeout: give up a pending candidate.

        Also logs ``site clock ready`` as soon as the clock is known, scans or not.
        """
        if self.reader.buffered_bytes:
            self._handle(self._pending, self.reader.flush())
        self.log_clock_when_ready()
        self._release()

    def finish(self) -> None:
        """Reading ended: the telegrams still waiting for a clock tick are dated now."""
        self._release(final=True)

    def _handle(self, window: bytes, telegrams: list[bytes]) -> None:
        buffered = self.reader.buffered_bytes
        self._pending = window[len(window) - buffered:] if buffered else b""
        self.sync_counters(self.reader, "crc_errors", "garbage_bytes")
        if not telegrams:
            return
        self.status.add("telegrams", len(telegrams))
        ends = telegram_end_offsets(window, telegrams)
        if not self.site_time.ready.is_set():
            for telegram in telegrams:          # counted as waiting for the clock
                self._telegram(telegram, None, 0, None)
            return
        # dated by :meth:`_release`: at once on the wall clock, on the site clock once the
        # tick after the arrival is in
        self.log_clock_when_ready()
        for telegram, end in zip(telegrams, ends):
            self._waiting.append((telegram, self._window_end_s, len(window) - end,
                                  self._previous_read_s))

    def _release(self, final: bool = False, at_most: int | None = None) -> None:
        """Date and publish the waiting telegrams whose arrival has a clock tick after it
        (``at_most`` of them): on the line between the ticks around it
        (:meth:`SiteTime.interpolate`; the wall clock has every reading at once).  One
        that waited ``MAX_TICK_WAIT_S`` (or all, when ``final``) is dated by the clock's
        line instead."""
        now_s = time.monotonic()
        budget = len(self._waiting) if at_most is None else at_most
        while self._waiting and budget > 0:
            budget -= 1
            telegram, arrived_s, bytes_behind, previous_s = self._waiting[0]
            window_end_ns = self.site_time.interpolate(arrived_s)
            if window_end_ns is None:
                if not (final or now_s - arrived_s > MAX_TICK_WAIT_S):
                    return
                window_end_ns = self.site_ns(arrived_s)
            self._waiting.popleft()
            self._telegram(telegram, window_end_ns, bytes_behind, self._placed_ns(previous_s))

    def _placed_ns(self, monotonic_s: float) -> int | None:
        """Site time of a local reading: between the ticks around it, else the clock's line."""
        placed = self.site_time.interpolate(monotonic_s)
        return placed if placed is not None else self.site_ns(monotonic_s)

    def _telegram(self, telegram: bytes, window_end_ns: int | None, bytes_behind: int,
                  not_before_ns: int | None) -> None:
        frame = lms200.decode_frame(telegram)
        if frame.command != lms200.CMD_MEASUREMENT or not frame.from_scanner:
            self.status.add("other_telegrams")
            return
        try:
            measurement = lms200.decode_measurement(telegram)
        except lms200.TelegramError as exc:
            self._count_once("bad_telegrams", "bad 0xb0 telegram", error=str(exc))
            return
        if measurement.partial_index != 0:
            self._count_once("partial_scans", "partial scans are not supported",
                             partial_index=measurement.partial_index)
            return
        geometry = self._field(measurement.count)
        if geometry is None:
            self.status.add("field_mismatch")
            return
        if window_end_ns is None:
            self.status.add("waiting_for_clock")
            return
        valid_ns = scan_valid_time_ns(window_end_ns, bytes_behind, len(telegram),
                                      self.config.baud, not_before_ns)
        self.publisher.publish(scan_message(measurement.ranges_m, valid_ns,
                                            self.config.frame_id, geometry))
        self.status.add("published")

    def _field(self, count: int) -> ScanField | None:
        """The scan geometry for a value count (cached); None (logged once) if it does not fit."""
        if count not in self._fields:
            try:
                self._fields[count] = scan_field(count, self.config.fov_deg,
                                                 self.config.resolution_deg)
            except ValueError as exc:
                self._fields[count] = None
                self.runtime.log("value count does not fit the field; these scans are "
                                 "dropped", level="warning", count=count, error=str(exc))
        return self._fields[count]

    def _count_once(self, counter: str, msg: str, **fields) -> None:
        """Count a dropped telegram; log the first of its kind."""
        if self.status.get(counter) == 0:
            self.runtime.log(msg, level="warning", **fields)
        self.status.add(counter)


def _send_start(port: serial.Serial, runtime: ServiceRuntime) -> None:
    """Send the start-continuous-output command once; never wait for its answer.

    A port that cannot be written (a read-only tap) is logged, not fatal.
    """
    try:
        port.write(lms200.START_CONTINUOUS)
        port.flush()
    except (serial.SerialException, OSError) as exc:
        runtime.log("could not send start continuous output", level="warning", error=str(exc))
        return
    runtime.log("sent start continuous output", command=lms200.START_CONTINUOUS.hex())


def main(config: Config | scanner_tcp.TcpConfig, *, stopper: Stopper | None = None) -> int:
    """Run the scanner service until the device ends or SIGINT/SIGTERM (a
    :class:`~services.scanner_tcp.TcpConfig`: :func:`services.scanner_tcp.main`).

    Returns
    -------
    int
        0 on a clean stop (signal or device closed), 2 if the device cannot be opened or
        the Zenoh session cannot start.
    """
    if isinstance(config, scanner_tcp.TcpConfig):
        return scanner_tcp.main(config, stopper=stopper)
    return run_serial_service(SERVICE, config, error_keys=ERROR_KEYS, stopper=stopper,
                              make_pipeline=lambda runtime, site_time:
                              _ScanPipeline(config, runtime, site_time))
