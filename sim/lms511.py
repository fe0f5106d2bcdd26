"""The simulated SICK LMS511 on Ethernet: a CoLa-A or CoLa-B TCP server on loopback.

:class:`Lms511Server` listens on a loopback port (the emulator never listens beyond it: a
real LMS5xx has no TLS), accepts one client at a time, answers ``sEN LMDscandata 1`` /
``0`` with ``sEA LMDscandata 1`` / ``0`` and ``sRN LMDscandata`` with the last scan as
``sRA``, and while the client has the output on, writes one ``sSN LMDscandata``
telegram (:func:`devices.cola.encode_scandata`) per scan the simulator hands it
(:meth:`Lms511Server.send_scan`).  Like the device, it counts every scan (the scan counter
runs whether anyone listens or not) and every telegram it gives to the interface.

Each telegram's device times: ``time since start-up`` is the scan's time on the device's
microsecond counter (started :data:`BOOT_LEAD_S` before the first scan), ``time of
transmission`` is that plus :attr:`Lms511Server.latency_ns` (one scan period by default:
the scan is complete after one turn of the mirror).  A runner that wants the service to
date each scan at its true time calls :meth:`~Lms511Server.send_scan` when its clock
reaches ``t_ns + latency_ns`` (the service subtracts the latency from the arrival).

Faults, seeded (``corrupt_rate``, ``rng``): a corrupted telegram either has one bit of its
DIST data flipped (CoLa-B: a bad checksum; CoLa-A, which has no checksum: one byte made a
control byte, a broken frame), so the scan is lost, or arrives intact behind a few
garbage bytes (never 0x02, so the bytes are garbage and nothing else).  A cut
(:meth:`~Lms511Server.suspend`) closes the listening socket and the client, optionally
half-way through a telegram; :meth:`~Lms511Server.resume` listens again on the same port.

``python -m sim.lms511`` runs a scripted session for the tests (:func:`main`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import sys
import threading
from dataclasses import dataclass

import numpy as np

from devices import cola
from devices.cola_reader import ColaReader

__all__ = ["LOOPBACK", "BOOT_LEAD_S", "SCAN_FREQUENCIES_HZ", "Lms511Server", "SentScan",
           "profile_ranges_m", "main"]

#: hosts the emulator may listen on
LOOPBACK = ("127.0.0.1", "::1", "localhost")
#: the device counter's start before the first scan, seconds
BOOT_LEAD_S = 30.0
#: scan frequencies an LMS511 runs at, Hz
SCAN_FREQUENCIES_HZ = (25.0, 35.0, 50.0, 75.0, 100.0)
_MIN_STEP_DEG, _MAX_STEP_DEG = 0.1667, 1.0
_SERIAL = 0x1234567


@dataclass(frozen=True)
class SentScan:
    """What :meth:`Lms511Server.send_scan` did with one scan (``fault``: ``""``,
    ``"flipped"`` or ``"garbage"``; ``sent``: written to a client; ``wire_bytes``: bytes
    written, garbage included)."""

    scan_counter: int
    sent: bool
    fault: str
    dist: np.ndarray
    telegram_bytes: int
    wire_bytes: int


class Lms511Server:
    """The emulated LMS511 (module docstring).  Use as a context manager or call
    :meth:`start` and :meth:`close`.

    Parameters
    ----------
    host, port : str, int
        Loopback address to listen on (port 0: any free port, see :attr:`port`).
    protocol : str
        ``"cola-a"`` or ``"cola-b"``.
    scan_frequency_hz : float
        One of :data:`SCAN_FREQUENCIES_HZ` (written into each telegram).
    corrupt_rate : float
        Probability that a telegram is corrupted (0..1); needs ``rng`` when > 0.
    rng : numpy.random.Generator, optional
        The fault stream.
    latency_ns : int, optional
        Time of transmission minus time since start-up; default one scan period.
    scale_factor : float
        The DIST1 scale factor (mm per code).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, protocol: str = "cola-b", *,
                 scan_frequency_hz: float = 25.0, corrupt_rate: float = 0.0,
                 rng: np.random.Generator | None = None, latency_ns: int | None = None,
                 scale_factor: float = 1.0) -> None:
        if host not in LOOPBACK:
            raise ValueError(f"the emulator listens on loopback only, not {host!r}")
        cola.check_protocol(protocol)
        if scan_frequency_hz not in SCAN_FREQUENCIES_HZ:
            raise ValueError(f"scan frequency must be one of {SCAN_FREQUENCIES_HZ} Hz, "
                             f"got {scan_frequency_hz}")
        if not 0.0 <= corrupt_rate <= 1.0 or (corrupt_rate > 0 and rng is None):
            raise ValueError("corrupt_rate must be in [0, 1], with an rng when > 0")
        self.host, self._port, self.protocol = host, int(port), protocol
        self.scan_frequency_hz = float(scan_frequency_hz)
        self.corrupt_rate, self.rng, self.scale_factor = corrupt_rate, rng, scale_factor
        period_ns = int(round(1e9 / scan_frequency_hz))
        self.latency_ns = period_ns if latency_ns is None else int(latency_ns)
        self.scans = self.telegrams = self.faults = 0
        self._boot_ns: int | None = None
        self._lock = threading.Lock()
        self._streaming = threading.Condition(self._lock)
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._output_on = False
        self._last_telegram: bytes | None = None
        self._closed = False

    # -- sockets ------------------------------------------------------------------------

    @property
    def port(self) -> int:
        """The port listened on (known once started)."""
        return self._port

    def start(self) -> Lms511Server:
        """Listen and accept clients in a thread."""
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        listener = socket.socket(family, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((self.host, self._port))
        listener.listen(1)
        self._port = listener.getsockname()[1]
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), name="lms511-accept",
                         daemon=True).start()
        return self

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return                          # the listener was closed
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                if self._listener is not listener:   # cut while this one connected
                    client.close()
                    return
                old, self._client, self._output_on = self._client, client, False
            if old is not None:
                old.close()
            threading.Thread(target=self._serve, args=(client,), name="lms511-client",
                             daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        """Read the client's commands and answer them, until it goes away."""
        reader = ColaReader(self.protocol)
        while True:
            try:
                data = client.recv(4096)
            except OSError:
                data = b""
            if not data:
                self._forget(client)
                return
            for payload in reader.feed(data):
                self._command(client, payload)

    def _command(self, client: socket.socket, payload: bytes) -> None:
        kind, name = cola.command_of(payload)
        if kind == "sEN" and name == "LMDscandata":
            on = payload.rstrip().endswith(b"1" if self.protocol == "cola-a" else b"\x01")
            answer = cola.frame(cola.encode_payload("sEA", name, self.protocol, int(on)),
                                self.protocol)
            with self._lock:
                if self._client is not client:
                    return
                self._write(client, answer)
                self._output_on = on
                self._streaming.notify_all()
        elif kind == "sRN" and name == "LMDscandata":
            with self._lock:
                if self._client is client and self._last_telegram is not None:
                    self._write(client, self._last_telegram.replace(b"sSN", b"sRA", 1))

    def _write(self, client: socket.socket, data: bytes) -> bool:
        """Write under the lock; a client that is gone is dropped."""
        try:
            client.sendall(data)
            return True
        except OSError:
            if self._client is client:
                self._client, self._output_on = None, False
            client.close()
            return False

    def _forget(self, client: socket.socket) -> None:
        with self._lock:
            if self._client is client:
                self._client, self._output_on = None, False
        client.close()

    def wait_streaming(self, timeout_s: float) -> bool:
        """Block until a client has the scan output on (True), or ``timeout_s`` passed."""
        with self._streaming:
            return self._streaming.wait_for(lambda: self._output_on or self._closed,
                                            timeout_s) and not self._closed

    def suspend(self, partial: bytes = b"") -> None:
        """A network cut: stop listening, then close the client (after writing ``partial``,
        e.g. the first half of a telegram), so the client cannot reconnect before
        :meth:`resume`.  Scans keep being counted."""
        with self._lock:
            listener, client = self._listener, self._client
            self._listener, self._client, self._output_on = None, None, False
            _close(listener)
            if client is not None and partial:
                try:
                    client.sendall(partial)
                except OSError:
                    pass
            _close(client)

    def resume(self) -> None:
        """Listen again on the same port after :meth:`suspend`."""
        self.start()

    def close(self) -> None:
        self.suspend()
        with self._streaming:
            self._closed = True
            self._streaming.notify_all()

    def __enter__(self) -> Lms511Server:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- scans --------------------------------------------------------------------------

    def telegram(self, t_ns: int, ranges_m, start_rad: float, step_rad: float) -> tuple[
            cola.ScanTelegram, bytes]:
        """Count one scan and encode it (no I/O): the device's telegram for it."""
        ranges_m = np.asarray(ranges_m, dtype=np.float64)
        step_raw = int(round(math.degrees(step_rad) * cola.ANGLE_UNITS_PER_DEG))
        if not (_MIN_STEP_DEG * cola.ANGLE_UNITS_PER_DEG <= step_raw
                <= _MAX_STEP_DEG * cola.ANGLE_UNITS_PER_DEG) or ranges_m.ndim != 1:
            raise ValueError(f"an LMS511 steps 0.1667-1 deg and sends 1-D ranges, got "
                             f"{math.degrees(step_rad):.5f} deg, shape {ranges_m.shape}")
        if self._boot_ns is None:
            self._boot_ns = int(t_ns) - int(BOOT_LEAD_S * 1e9)
        start_us = (int(t_ns) - self._boot_ns) // 1000
        start_raw = int(round((math.degrees(start_rad) + cola.FORWARD_DEG)
                              * cola.ANGLE_UNITS_PER_DEG))
        dist = cola.Channel("DIST1", self.scale_factor, 0.0, start_raw, step_raw,
                            cola.dist_values(ranges_m, self.scale_factor))
        scan = cola.ScanTelegram(
            serial_number=_SERIAL, telegram_counter=self.telegrams % 65536,
            scan_counter=self.scans % 65536, time_since_startup_us=start_us % (1 << 32),
            time_of_transmission_us=(start_us + self.latency_ns // 1000) % (1 << 32),
            scan_frequency_raw=int(round(self.scan_frequency_hz * 100)),
            measurement_frequency_raw=int(round(self.scan_frequency_hz * len(ranges_m) / 100)),
            channels_16=(dist,))
        self.scans += 1
        return scan, cola.encode_scandata(scan, self.protocol)

    def send_scan(self, t_ns: int, ranges_m, start_rad: float, step_rad: float, *,
                  fault: str | None = None) -> SentScan:
        """One scan at site time ``t_ns`` (UTC ns): ranges in metres (NaN: no return),
        beam ``k`` at bearing ``start_rad + k * step_rad`` (the ``LaserScan`` convention;
        the device's angles are 90 deg more).  Written to the client when its output is
        on, corrupted at the seeded rate (or as ``fault`` says: ``""``, ``"flipped"``,
        ``"garbage"``); counted either way."""
        scan, telegram = self.telegram(t_ns, ranges_m, start_rad, step_rad)
        if fault is None:
            fault = self._fault()
        elif fault not in ("", "flipped", "garbage") or (fault and self.rng is None):
            raise ValueError(f"fault must be '', 'flipped' or 'garbage' (with an rng), "
                             f"got {fault!r}")
        wire = self._corrupt(telegram, fault)
        with self._lock:
            self._last_telegram = telegram
            client = self._client if self._output_on else None
            sent = client is not None and self._write(client, wire)
            if sent:
                self.telegrams += 1
                self.faults += bool(fault)
        return SentScan(scan.scan_counter, sent, fault if sent else "", scan.dist1.values,
                        len(telegram), len(wire) if sent else 0)

    def _fault(self) -> str:
        if not self.corrupt_rate or self.rng.random() >= self.corrupt_rate:
            return ""
        return "flipped" if self.rng.random() < 0.5 else "garbage"

    def _corrupt(self, telegram: bytes, fault: str) -> bytes:
        if fault == "garbage":
            noise = self.rng.integers(0, 256, size=int(self.rng.integers(1, 40)), dtype=np.uint8)
            noise[noise == cola.STX] = 0x55
            return noise.tobytes() + telegram
        if fault != "flipped":
            return telegram
        data = bytearray(telegram)
        lo = len(telegram) // 2                 # inside the DIST data
        k = lo + int(self.rng.integers(0, len(telegram) // 4))
        if self.protocol == "cola-a":
            data[k] = 0x01                      # a control byte: a broken frame
        else:
            data[k] ^= 1 << int(self.rng.integers(0, 8))
            if cola.MAGIC in bytes(data[4:]):   # never fake a telegram start
                data[k] ^= 0xFF
        return bytes(data)


def _close(sock: socket.socket | None) -> None:
    """Shut a socket down (which also wakes a thread blocked in its accept) and close it."""
    if sock is None:
        return
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()


def profile_ranges_m(rng: np.random.Generator, count: int) -> np.ndarray:
    """A seeded bank profile, metres: 8-60 m, smooth, with about 1 % no-return beams."""
    x = np.linspace(0.0, 1.0, count)
    ranges = 20.0 + 15.0 * np.sin(3.0 * x + rng.uniform(0, 6)) + rng.normal(0, 0.02, count)
    ranges = np.clip(ranges, 8.0, 60.0)
    ranges[rng.random(count) < 0.01] = np.nan
    return ranges


# -- a scripted session for the tests ------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m sim.lms511",
                                description="serve a scripted LMS511 session on loopback")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--protocol", choices=cola.PROTOCOLS, default="cola-b")
    p.add_argument("--frequency-hz", type=float, default=25.0)
    p.add_argument("--step-deg", type=float, default=0.1667)
    p.add_argument("--fov-deg", type=float, default=190.0)
    p.add_argument("--scans", type=int, default=20, help="scans in all")
    p.add_argument("--cut-after", type=int, default=-1,
                   help="cut the connection half-way through this scan's telegram")
    p.add_argument("--scans-during-cut", type=int, default=0,
                   help="scans the device makes while nobody can connect")
    p.add_argument("--corrupt-rate", type=float, default=0.0)
    p.add_argument("--flip", default="", help="comma-separated scans sent with a bit flipped")
    p.add_argument("--garbage", default="", help="comma-separated scans sent behind garbage")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--report", required=True, help="JSON file of what was sent")
    p.add_argument("--t0-ns", type=int, default=1_790_000_000 * 10**9)
    return p


def _session(args: argparse.Namespace, server: Lms511Server, stop: threading.Event) -> dict:
    rng = np.random.default_rng(args.seed)
    count = int(math.floor(args.fov_deg / args.step_deg + 1e-9)) + 1
    start_rad, step_rad = math.radians(-args.fov_deg / 2), math.radians(args.step_deg)
    period_ns = int(round(1e9 / args.frequency_hz))
    planned = {int(i): "flipped" for i in args.flip.split(",") if i}
    planned.update({int(i): "garbage" for i in args.garbage.split(",") if i})
    sent, missed, partial_bytes = [], [], 0
    scan = 0
    while scan < args.scans and not stop.is_set():
        if not server.wait_streaming(60.0):
            raise SystemExit("no client turned the scan output on within 60 s")
        t_ns = args.t0_ns + scan * period_ns
        ranges = profile_ranges_m(rng, count)
        if scan == args.cut_after:
            _, telegram = server.telegram(t_ns, ranges, start_rad, step_rad)
            partial_bytes = len(telegram) // 2
            server.suspend(partial=telegram[:partial_bytes])
            missed.append(scan)
            for extra in range(1, args.scans_during_cut + 1):
                stop.wait(1.0 / args.frequency_hz)   # the device scans on, unheard
                server.telegram(t_ns + extra * period_ns, ranges, start_rad, step_rad)
                missed.append(scan + extra)
            scan += args.scans_during_cut + 1
            server.resume()
            continue
        result = server.send_scan(t_ns, ranges, start_rad, step_rad, fault=planned.get(scan))
        sent.append({"scan_counter": result.scan_counter, "t_ns": t_ns, "sent": result.sent,
                     "fault": result.fault, "telegram_bytes": result.telegram_bytes,
                     "wire_bytes": result.wire_bytes, "dist": result.dist.tolist()})
        scan += 1
        stop.wait(1.0 / args.frequency_hz)      # the device's scan period
    return {"protocol": args.protocol, "count": count, "start_rad": start_rad,
            "step_rad": step_rad, "step_raw": int(round(args.step_deg * 10_000)),
            "scale_factor": server.scale_factor, "latency_ns": server.latency_ns,
            "scans": sent, "missed": missed, "partial_bytes": partial_bytes}


def main(argv: list[str] | None = None) -> int:
    """Serve ``--scans`` scans to the first client, with an optional cut and seeded
    corruption; write the report; keep listening until SIGTERM/SIGINT."""
    args = _parser().parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    rng = np.random.default_rng(args.seed + 1)
    with Lms511Server("127.0.0.1", args.port, args.protocol,
                      scan_frequency_hz=args.frequency_hz, corrupt_rate=args.corrupt_rate,
                      rng=rng) as server:
        report = _session(args, server, stop)
        tmp = args.report + ".tmp"
        with open(tmp, "w") as f:
            json.dump(report, f)
        os.replace(tmp, args.report)
        print(f"sent {sum(s['sent'] for s in report['scans'])} scans", file=sys.stderr)
        while not stop.wait(0.5):            # until SIGTERM / SIGINT
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
