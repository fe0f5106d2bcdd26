"""The serial parsers' limits: the table-driven SICK CRC, the LMS200 reader under
pathological garbage, and NMEA GGA values outside physical ranges.

The CRC is checked against the byte-serial definition of docs/domain.md §5, kept here as
the reference.  Speed is shown by bench/parsers.py, not here.  Random data draws from the
run's seed (tests/seeding.py).
"""

from __future__ import annotations

import pytest

from devices import lms200 as L
from devices import nmea as N
from devices.sick_crc import crc16
from seeding import rng
from test_protocols import _garbage, _random_scan_telegrams

pytestmark = pytest.mark.seeded


def reference_crc16(data: bytes) -> int:
    """SICK's CRC-16, byte by byte, as docs/domain.md §5 defines it."""
    crc = 0
    cur = 0
    for b in bytes(data):
        prev, cur = cur, b
        if crc & 0x8000:
            crc = ((crc & 0x7FFF) << 1) ^ 0x8005
        else:
            crc = (crc << 1) & 0xFFFF
        crc ^= cur | (prev << 8)
    return crc


# -- CRC -------------------------------------------------------------------------------------


def test_crc16_equals_the_reference_on_random_data():
    gen = rng(61)
    lengths = list(range(0, 70)) + [L.MAX_LENGTH + 3, L.MAX_LENGTH + 4, L.MAX_LENGTH + 5]
    lengths += [int(n) for n in gen.integers(0, 3 * L.MAX_LENGTH, 300)]
    for n in lengths:
        data = gen.integers(0, 256, n).astype("u1").tobytes()
        assert crc16(data) == reference_crc16(data), n
        assert crc16(bytearray(data)) == crc16(memoryview(data)) == reference_crc16(data)


def test_crc16_equals_the_reference_on_telegram_like_data():
    gen = rng(62)
    for data in (b"\x02" * 600, b"\xff" * 2100, b"\x00" * 100, bytes(range(256)) * 9):
        assert crc16(data) == reference_crc16(data)
    for _, _, _, _, telegram in _random_scan_telegrams(gen, 10):
        assert crc16(telegram[:-2]) == reference_crc16(telegram[:-2])
        assert int.from_bytes(telegram[-2:], "little") == reference_crc16(telegram[:-2])
    assert crc16(bytes.fromhex("0200010031")) == 0x1215


# -- LMS200 reader ---------------------------------------------------------------------------


def _pathological(gen, kind: str) -> bytes:
    """Garbage that makes false candidates: 0x02 floods, near-valid headers, or noise."""
    size = int(gen.integers(0, 400))
    if kind == "flood":
        return b"\x02" * size
    if kind == "near-valid":
        # start byte, scanner address, the longest length, command 0xB0: a plausible header
        head = bytes([L.STX, L.ADDRESS_SCANNER]) + L.MAX_LENGTH.to_bytes(2, "little")
        return (head + bytes([L.CMD_MEASUREMENT])) * (size // 5 + 1)
    if kind == "other-address":
        # a host telegram's address, the longest length: only its CRC can reject it
        return (bytes([L.STX, 0x00]) + L.MAX_LENGTH.to_bytes(2, "little")) * (size // 4 + 1)
    return _garbage(gen, size, [])


def reference_frames(stream: bytes) -> list[tuple[int, bytes]]:
    """(offset, telegram) of the telegrams in a whole stream by the reader's rules (its
    docstring), one candidate at a time with :func:`reference_crc16`, every candidate left
    at the end given up as :meth:`~devices.lms200.TelegramReader.flush` does."""
    out, pos = [], 0
    while (pos := stream.find(bytes([L.STX]), pos)) >= 0:
        length = int.from_bytes(stream[pos + 2:pos + 4], "little")
        end = pos + 4 + length + 2
        head = stream[pos:pos + 7]
        bad_header = (len(head) == 7 and head[1] & L.ADDRESS_SCANNER
                      and head[4] == L.CMD_MEASUREMENT
                      and length != 4 + 2 * (int.from_bytes(head[5:7], "little") & 0x3FF))
        if (len(head) >= 4 and 1 <= length <= L.MAX_LENGTH and not bad_header
                and end <= len(stream)
                and reference_crc16(stream[pos:end - 2]) == int.from_bytes(stream[end - 2:end],
                                                                            "little")):
            out.append((pos, stream[pos:end]))
            pos = end
        else:
            pos += 1
    return out


@pytest.mark.parametrize("kind", ["flood", "near-valid", "other-address", "noise"])
def test_reader_finds_every_telegram_between_pathological_garbage(kind):
    """Every telegram comes out, in any chunking, exactly as the byte-serial reference finds
    them.  A false candidate passes the 16-bit CRC with probability 2**-16; garbage full of
    plausible headers makes thousands, so now and then one passes (in both) and hides the
    telegrams it overlaps: every telegram not found must lie under such a false frame."""
    gen = rng(63, ["flood", "near-valid", "other-address", "noise"].index(kind))
    scans = _random_scan_telegrams(gen, 12)
    stream, offsets = b"", []
    for s in scans:
        stream += _pathological(gen, kind)
        offsets.append(len(stream))
        stream += s[-1]
    stream += _pathological(gen, kind)
    reader = L.TelegramReader()
    got, pos = [], 0
    while pos < len(stream):
        step = int(gen.integers(1, 1500))
        got += reader.feed(stream[pos:pos + step])
        pos += step
    got += reader.flush()
    expected = reference_frames(stream)
    assert got == [frame for _, frame in expected]
    found = {at for at, _ in expected}
    false = [(at, at + len(frame)) for at, frame in expected if at not in offsets]
    for at, s in zip(offsets, scans):
        assert at in found or any(lo < at + len(s[-1]) and at < hi for lo, hi in false)
    assert reader.telegrams == len(got) and reader.buffered_bytes == 0
    assert sum(map(len, got)) + reader.garbage_bytes == len(stream)


def test_a_measurement_header_that_disagrees_with_its_length_is_skipped_at_once():
    """A false 0xB0 header claiming 2,048 bytes is dropped as soon as its value count has
    arrived: the good telegram behind it comes out without waiting for those bytes or for
    an idle line (flush)."""
    good = L.encode_measurement([10, 20, 30])
    false_header = bytes([L.STX, L.ADDRESS_SCANNER, 0x00, 0x08, L.CMD_MEASUREMENT, 0x03, 0x00])
    reader = L.TelegramReader()
    assert reader.feed(false_header + good) == [good]
    assert reader.buffered_bytes == 0
    assert reader.garbage_bytes == len(false_header)
    assert reader.crc_errors == 1


def test_a_real_telegram_with_a_corrupt_count_is_one_corruption_event():
    gen = rng(64)
    scans = _random_scan_telegrams(gen, 4)
    bad = bytearray(scans[1][-1])
    bad[5] ^= 0x01       # the value count no longer matches the length
    stream = scans[0][-1] + bytes(bad) + scans[2][-1] + scans[3][-1]
    reader = L.TelegramReader()
    # a 0x02 inside the damaged telegram may claim more bytes than follow: flush on idle
    got = reader.feed(stream) + reader.flush()
    assert got == [scans[0][-1], scans[2][-1], scans[3][-1]]
    assert reader.crc_errors == 1
    assert reader.garbage_bytes == len(bad)


# -- NMEA ------------------------------------------------------------------------------------


def _gga(time="123519.00", lat="4807.038", ns="N", lon="01131.000", ew="E", quality="1",
         sats="08", hdop="0.9", alt="545.4", sep="46.9") -> str:
    body = f"GPGGA,{time},{lat},{ns},{lon},{ew},{quality},{sats},{hdop},{alt},M,{sep},M,,"
    return f"${body}*{N.nmea_checksum(body)}"


@pytest.mark.parametrize("field, text, message", [
    ("hdop", "-0.5", "bad hdop"),
    ("hdop", "100.0", "bad hdop"),
    ("hdop", "1_0", "bad hdop"),
    ("alt", "1e308", "bad altitude"),
    ("alt", "1_000", "bad altitude"),
    ("alt", "10000.1", "bad altitude"),
    ("alt", "-1000.5", "bad altitude"),
    ("alt", " 545.4", "bad altitude"),
    ("alt", "+545.4", "bad altitude"),
    ("alt", "inf", "bad altitude"),
    ("alt", "nan", "bad altitude"),
    ("sep", "1e2", "bad geoid separation"),
    ("sep", "-250.0", "bad geoid separation"),
    ("sats", "1_0", "bad satellites"),
    ("sats", "100", "bad satellites"),
    ("quality", "1_0", "bad quality"),
    ("time", "235960.99", "bad time"),
    ("time", "235960", "bad time"),
    ("time", "240000.00", "bad time"),
    ("time", "236000.00", "bad time"),
    ("time", "12_519.00", "bad time"),
    ("lat", "9000.0001", "bad latitude"),
    ("lat", "4860.000", "bad latitude"),
    ("lat", "48_7.038", "bad latitude"),
    ("lon", "18000.0001", "bad longitude"),
    ("lon", "-1131.000", "bad longitude"),
])
def test_gga_values_outside_physical_ranges_are_refused(field, text, message):
    with pytest.raises(N.NmeaError, match=message):
        N.parse_gga(_gga(**{field: text}))


@pytest.mark.parametrize("field, text, value", [
    ("hdop", "0.0", 0.0), ("hdop", "99.99", 99.99),
    ("alt", "-1000", -1000.0), ("alt", "10000.0", 10000.0), ("alt", "-12.5", -12.5),
    ("alt", ".5", 0.5), ("alt", "7.", 7.0),
    ("sep", "-107.0", -107.0), ("sats", "99", 99),
    ("time", "235959.99", 86399.99), ("time", "000000", 0.0),
    ("lat", "9000.0000", 90.0), ("lon", "18000.0000", 180.0),
])
def test_gga_values_at_the_edges_of_the_ranges_are_accepted(field, text, value):
    fix = N.parse_gga(_gga(**{field: text}))
    got = {"hdop": fix.hdop, "alt": fix.altitude_m, "sep": fix.geoid_sep_m,
           "sats": fix.satellites, "time": fix.time_of_day_s, "lat": fix.lat_deg,
           "lon": fix.lon_deg}[field]
    assert got == pytest.approx(value)


def test_refused_gga_sentences_are_still_checksum_valid_lines_for_the_reader():
    """The reader passes framing-valid sentences on; the range checks are parse_gga's, so a
    service counts them as bad fixes, not as line noise."""
    line = _gga(hdop="-0.5")
    reader = N.NmeaReader()
    assert reader.feed((line + "\r\n").encode("ascii")) == [line]
    with pytest.raises(N.NmeaError, match="bad hdop"):
        N.parse_gga(line)
