"""What the serial-device services (scanner, GNSS) share: open, read loop, site clock.

A device service is a *pipeline* (bytes in, events out) run by :func:`run_serial_service`:

1. open the port (one ``cannot open device`` line and exit 2 on failure);
2. open the service runtime (Zenoh session; exit 2 if it cannot start);
3. follow the site clock (:class:`services.service.SiteTime`);
4. build the pipeline, announce the liveliness token ("token present" means "reading"),
   call ``pipeline.start(port)``;
5. read chunks until SIGINT/SIGTERM or the device goes away (``device closed``, exit 0):
   ``pipeline.feed(data, arrived_s)`` for bytes, ``pipeline.idle()`` after a silent timeout,
   ``pipeline.finish()`` once at the end.
"""

from __future__ import annotations

import time
from typing import Callable

import serial
import zenoh

from services.service import ServiceRuntime, SiteTime, Stopper, log

__all__ = ["DevicePipeline", "read_chunk", "run_serial_service"]


class DevicePipeline:
    """Base of a device pipeline: the runtime, the site clock, the publisher of its
    ``source`` (``type_name`` declared up front), reader counters.

    Subclasses implement :meth:`feed` and may extend :meth:`start` and :meth:`idle`.
    """

    def __init__(self, runtime: ServiceRuntime, site_time: SiteTime, source: str,
                 type_name: str) -> None:
        self.runtime = runtime
        self.publisher = runtime.publisher(source)
        self.publisher.declare(type_name)
        self.status = runtime.status
        self.site_time = site_time
        self._clock_logged = False
        self._seen: dict[str, int] = {}

    def start(self, port: serial.Serial) -> None:
        """Called once, after the token is announced and before the first read."""

    def feed(self, data: bytes, arrived_s: float) -> None:
        """Bytes that arrived at local monotonic time ``arrived_s``."""
        raise NotImplementedError

    def idle(self) -> None:
        """The line was silent for a whole read timeout."""
        self.log_clock_when_ready()

    def finish(self) -> None:
        """Called once when reading ends (device closed or a stop): publish what waits."""

    def site_ns(self, monotonic_s: float) -> int | None:
        """Site time of a local monotonic reading, or None before the site clock is known."""
        if not self.site_time.ready.is_set():
            return None
        if not self._clock_logged and self.site_time.mode == "site":
            self._clock_logged = True
            self.runtime.log("site clock ready", speed=self.site_time.speed)
        return self.site_time.at(monotonic_s)

    def log_clock_when_ready(self) -> None:
        """Log ``site clock ready`` as soon as the clock is known (also while idle)."""
        if not self._clock_logged and self.site_time.ready.is_set():
            self.site_ns(time.monotonic())

    def sync_counters(self, reader, *names: str) -> None:
        """Add the growth of the reader's counters ``names`` to the status (same keys)."""
        for name in names:
            value = getattr(reader, name)
            grown = value - self._seen.get(name, 0)
            if grown:
                self.status.add(name, grown)
                self._seen[name] = value


def read_chunk(port: serial.Serial) -> bytes:
    """Wait up to the port's timeout for a byte, then take everything already waiting."""
    data = port.read(1)
    if data:
        waiting = port.in_waiting
        if waiting:
            data += port.read(waiting)
    return data


def run_serial_service(service: str, config, *, error_keys: tuple[str, ...],
                       make_pipeline: Callable[[ServiceRuntime, SiteTime], DevicePipeline],
                       stopper: Stopper | None = None) -> int:
    """Run a device service until the device ends or SIGINT/SIGTERM (module docstring).

    ``config`` needs ``device``, ``baud``, ``read_timeout_s``, ``site``, ``zenoh``,
    ``source``, ``status_period_s`` and ``clock``.  Returns 0 on a clean stop, 2 if the
    device cannot be opened or the Zenoh session cannot start.
    """
    stopper = stopper or Stopper()  # installed first: SIGTERM during start-up stops cleanly
    try:
        port = serial.Serial(config.device, config.baud, timeout=config.read_timeout_s)
    except (serial.SerialException, OSError, ValueError) as exc:
        log(service, "cannot open device", level="error", device=config.device,
            error=str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
        return 2
    with port:
        runtime = ServiceRuntime(service, config.site, config.zenoh, name=config.source,
                                 status_period_s=config.status_period_s, stopper=stopper)
        try:
            runtime.open(error_keys=error_keys, announce=False)
        except zenoh.ZError as exc:
            log(service, "cannot open zenoh session", level="error", error=str(exc))
            return 2
        with runtime:
            site_time = SiteTime(config.clock)
            site_time.follow(runtime.session, config.site)
            try:
                _read_loop(config, port, runtime, make_pipeline(runtime, site_time))
            finally:
                site_time.close()
    return 0


def _read_loop(config, port: serial.Serial, runtime: ServiceRuntime,
               pipeline: DevicePipeline) -> None:
    runtime.announce()
    pipeline.start(port)
    stopper = runtime.stopper
    while not stopper.is_set():
        try:
            data = read_chunk(port)
        except (serial.SerialException, OSError) as exc:
            runtime.log("device closed", device=config.device, error=str(exc))
            break
        if data:
            pipeline.feed(data, time.monotonic())
        else:
            pipeline.idle()
    pipeline.finish()
