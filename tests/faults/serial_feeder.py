"""The yard's serial devices for a fault case: an LMS200 and a GNSS receiver on real ptys.

Run as ``python tests/faults/serial_feeder.py``: it opens two pseudo-terminals
(:class:`sim.pty.PtyDevice`), prints one JSON line ``{"scanner": PATH, "gnss": PATH}`` on
stdout, then writes, until SIGTERM, an LMS200 measured-values telegram (401 range codes,
0.25 deg over 100 deg) every 1/75 s and a GGA sentence (the current UTC time, a DGPS fix
near Cape Lambert) every 0.1 s, paced by the monotonic clock.  A telegram written while
the reading service is down (SIGKILLed, not yet restarted) is dropped by the pty after
its write timeout, as a real serial line drops bytes nobody reads.
"""

from __future__ import annotations

import json
import signal
import sys
import time

import numpy as np

from devices import lms200 as L
from devices.nmea import format_gga
from sim.pty import PtyDevice

SCAN_HZ = 75.0
GGA_HZ = 10.0
SCAN_VALUES = 401
#: near Cape Lambert, WA: degrees, metres
LAT_DEG, LON_DEG, ALT_M = -20.59, 117.18, 12.0


def main() -> int:
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    rng = np.random.default_rng(0)
    base = rng.integers(2_000, 40_000, SCAN_VALUES) // 10   # cm-scale codes in mm units
    with PtyDevice(write_timeout_s=0.05) as lms, PtyDevice(write_timeout_s=0.05) as gnss:
        print(json.dumps({"scanner": lms.path, "gnss": gnss.path}), flush=True)
        t0 = time.monotonic()
        n_scan = n_gga = 0
        while not stop:
            now = time.monotonic() - t0
            if now >= n_scan / SCAN_HZ:
                values = np.clip(base + (n_scan % 50), 0, L.MAX_RANGE_VALUE)
                lms.write(L.encode_measurement(values.astype(np.uint16)))
                n_scan += 1
            if now >= n_gga / GGA_HZ:
                line = format_gga(time.time_ns(), LAT_DEG, LON_DEG, 2, 12, 0.8, ALT_M)
                gnss.write(line.encode("ascii"))
                n_gga += 1
            wait_s = min(n_scan / SCAN_HZ, n_gga / GGA_HZ) - (time.monotonic() - t0)
            if wait_s > 0:
                time.sleep(wait_s)   # pacing the line rate, not synchronisation
    print(json.dumps({"telegrams": n_scan, "sentences": n_gga}), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
