"""Serial parsers under garbage: LMS200 telegrams and NMEA GGA against the line rate.

    .venv/bin/python bench/parsers.py [--kib N] [--budget-s S] [--chunk BYTES] [--seed N]

Feeds each stream to the parser the services use (:class:`devices.lms200.TelegramReader`,
:class:`devices.nmea.NmeaReader`) in ``--chunk``-byte reads, as a serial port returns them,
then flushes, and prints one table: kB/s (1 kB = 1000 bytes) per stream and the ratio to
the 50 kB/s a 500 kbaud line delivers (10 bits a byte on the wire).  A ratio below 1 means
the reader falls behind the line on that stream.  A stream is cut short when ``--budget-s``
of wall time is spent; the table says how much of it was read.

Streams:

- ``0x02 flood`` / ``'$' flood``: one start byte repeated.
- ``random``: uniform random bytes.
- ``near-valid``: LMS200: a start byte, the scanner's address and the largest length
  (2,050), repeated every 4 bytes: a candidate as long as a telegram may be starts at
  every 4th byte and only its CRC rejects it; NMEA: GGA sentences with a wrong checksum.
- ``clean``: LMS200: 361-value 0xB0 telegrams back to back; NMEA: GGA sentences.
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from devices import lms200, nmea  # noqa: E402

#: bytes per second a 500 kbaud line delivers (8N1: 10 bits on the wire per byte)
LINE_RATE_BYTES_PER_S = 500_000 // 10


def _lms_streams(size_bytes: int, rng: random.Random) -> dict[str, bytes]:
    values = np.array([rng.randrange(0, lms200.MAX_RANGE_VALUE) for _ in range(361)])
    telegram = lms200.encode_measurement(values)
    # near-valid: 02 80 | length = MAX_LENGTH, repeated: every 4th byte starts a candidate
    # as long as a telegram may be
    length = lms200.MAX_LENGTH.to_bytes(2, "little")
    near = bytes([lms200.STX, lms200.ADDRESS_SCANNER]) + length
    return {
        "0x02 flood": bytes([lms200.STX]) * size_bytes,
        "random": rng.randbytes(size_bytes),
        "near-valid": (near * (size_bytes // len(near) + 1))[:size_bytes],
        "clean": telegram * (size_bytes // len(telegram) + 1),
    }


def _nmea_streams(size_bytes: int, rng: random.Random) -> dict[str, bytes]:
    sentences = []
    for i in range(200):
        sentences.append(nmea.format_gga(
            1_790_000_000_000_000_000 + i * 10**8, -20.3 + rng.uniform(-1e-4, 1e-4),
            118.6 + rng.uniform(-1e-4, 1e-4), 2, 9, 0.9, 12.5 + rng.uniform(-0.1, 0.1),
            -10.0).encode("ascii"))
    clean = b"".join(sentences)
    bad = b"".join(s[:-4] + (b"00" if not s.endswith(b"00\r\n") else b"11") + b"\r\n"
                   for s in sentences)
    return {
        "'$' flood": b"$" * size_bytes,
        "random": rng.randbytes(size_bytes),
        "near-valid": bad * (size_bytes // len(bad) + 1),
        "clean": clean * (size_bytes // len(clean) + 1),
    }


def _run(reader, stream: bytes, size_bytes: int, chunk_bytes: int,
         budget_s: float) -> tuple[int, float, int]:
    """(bytes read, wall seconds, messages out) of one stream, cut at the budget."""
    stream = stream[:size_bytes]
    found = 0
    start = time.perf_counter()
    fed = 0
    while fed < len(stream):
        found += len(reader.feed(stream[fed:fed + chunk_bytes]))
        fed += chunk_bytes
        if time.perf_counter() - start > budget_s:
            break
    if hasattr(reader, "flush"):
        found += len(reader.flush())
    return min(fed, len(stream)), time.perf_counter() - start, found


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kib", type=int, default=512, help="KiB per stream (default 512)")
    ap.add_argument("--budget-s", type=float, default=5.0,
                    help="wall seconds per stream at most (default 5)")
    ap.add_argument("--chunk", type=int, default=1024, help="bytes per read (default 1024)")
    ap.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    args = ap.parse_args(argv)
    size = args.kib * 1024
    rng = random.Random(args.seed)
    rows = []
    cases = [("LMS200", lms200.TelegramReader, _lms_streams(size, rng)),
             ("NMEA", nmea.NmeaReader, _nmea_streams(size, rng))]
    for parser, make, streams in cases:
        for name, stream in streams.items():
            read, wall_s, found = _run(make(), stream, size, args.chunk, args.budget_s)
            rate = read / wall_s if wall_s > 0 else float("inf")
            rows.append((parser, name, read, wall_s, found, rate))
    print(f"{'parser':<7} {'stream':<11} {'read kB':>8} {'wall s':>7} {'found':>6} "
          f"{'kB/s':>9} {'x line':>7}")
    for parser, name, read, wall_s, found, rate in rows:
        print(f"{parser:<7} {name:<11} {read / 1000:>8.1f} {wall_s:>7.2f} {found:>6} "
              f"{rate / 1000:>9.1f} {rate / LINE_RATE_BYTES_PER_S:>7.2f}")
    print(f"line rate: {LINE_RATE_BYTES_PER_S / 1000:.0f} kB/s (500 kbaud, 10 bits a byte); "
          f"x line = kB/s over the line rate")
    return 0


if __name__ == "__main__":
    sys.exit(main())
