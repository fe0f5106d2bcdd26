"""LMS200 telegrams, NMEA GGA sentences and the pty serial emulation.

Known vectors come from published telegrams (SICK LMS2xx host commands) and the classic GGA
example; everything else is round trips, including through a real pseudo-terminal read with
pyserial. Random data is seeded
from the run's seed (``--seed N`` or ``STOCKPILE_TEST_SEED=N`` reproduces a run; the seed is
printed, and written into a failing test's report).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import serial

from devices import lms200 as L
from devices import nmea as N
from sim.pty import PtyDevice

from seeding import session_seed

SEED = session_seed()
#: the random tests here draw from the run's seed (tests/seeding.py)
pytestmark = pytest.mark.seeded
IO_DEADLINE_S = 20.0  # generous: a run normally takes well under a second


def _rng(test_name: str) -> np.random.Generator:
    print(f"{test_name}: seed {SEED} (--seed {SEED} reproduces it)")
    return np.random.default_rng(SEED)


# --------------------------------------------------------------------------- LMS200: CRC

# Published host -> scanner telegrams (SICK LMS2xx), last two bytes = CRC little-endian.
KNOWN_TELEGRAMS = {
    "status request": "02 00 01 00 31 15 12",
    "start continuous (mode 0x24)": "02 00 02 00 20 24 34 08",
    "stop continuous (mode 0x25)": "02 00 02 00 20 25 35 08",
    "38400 baud (mode 0x40)": "02 00 02 00 20 40 50 08",
    "9600 baud (mode 0x42)": "02 00 02 00 20 42 52 08",
}


@pytest.mark.parametrize("name", sorted(KNOWN_TELEGRAMS))
def test_crc16_known_telegrams(name):
    telegram = bytes.fromhex(KNOWN_TELEGRAMS[name])
    assert L.crc16(telegram[:-2]) == int.from_bytes(telegram[-2:], "little")
    frame = L.decode_frame(telegram)
    assert L.encode_frame(frame.address, frame.payload) == telegram


def test_crc16_status_request_value():
    assert L.crc16(bytes.fromhex("0200010031")) == 0x1215
    assert L.crc16(b"") == 0
    assert L.crc16(bytearray(b"\x02\x00\x01\x00\x31")) == 0x1215


def test_host_command_constants():
    assert L.START_CONTINUOUS == bytes.fromhex("0200020020243408")
    assert L.STOP_CONTINUOUS == bytes.fromhex("0200020020253508")
    assert L.STATUS_REQUEST == bytes.fromhex("02000100311512")
    frame = L.decode_frame(L.START_CONTINUOUS)
    assert (frame.address, frame.command, frame.from_scanner) == (0x00, 0x20, False)


def test_crc16_detects_every_single_bit_flip():
    rng = _rng("single bit flips")
    telegram = L.encode_measurement(rng.integers(0, 8192, 181))
    for i in range(len(telegram) - 2):
        for bit in range(8):
            bad = bytearray(telegram)
            bad[i] ^= 1 << bit
            with pytest.raises(L.TelegramError):
                L.decode_measurement(bytes(bad))


# --------------------------------------------------------------------------- LMS200: 0xB0

def test_measurement_layout_by_hand():
    t = L.encode_measurement([1, 2, 8191, 8182], flags=[0, 1, 7, 2], partial_index=2,
                             status=0x10)
    assert t[:5] == bytes([0x02, 0x80, 12, 0, 0xB0])  # length = 1 + 2 + 4*2 + 1
    header = int.from_bytes(t[5:7], "little")
    assert header == 4 | (2 << 11) | (1 << 14)
    words = [int.from_bytes(t[7 + 2 * i:9 + 2 * i], "little") for i in range(4)]
    assert words == [1, 2 | (1 << 13), 8191 | (7 << 13), 8182 | (2 << 13)]
    assert t[15] == 0x10
    assert L.crc16(t[:-2]) == int.from_bytes(t[-2:], "little")
    cm = L.encode_measurement([5], unit_mm=False)
    assert int.from_bytes(cm[5:7], "little") == 1  # unit bits 0 = cm


@pytest.mark.parametrize("unit_mm", [True, False])
def test_measurement_round_trip_random(unit_mm):
    rng = _rng(f"measurement round trip unit_mm={unit_mm}")
    unit_m = 0.001 if unit_mm else 0.01
    max_m = L.MAX_RANGE_VALUE * unit_m
    for trial in range(50):
        n = int(rng.integers(1, L.MAX_VALUES + 1))
        ranges_m = rng.uniform(0.0, 1.1 * max_m, n)
        ranges_m[rng.random(n) < 0.05] = np.nan
        flags = rng.integers(0, 8, n)
        partial = int(rng.integers(0, 4))
        status = int(rng.integers(0, 256))
        values = L.ranges_to_values(ranges_m, unit_mm)
        m = L.decode_measurement(L.encode_measurement(
            values, unit_mm=unit_mm, partial_index=partial, flags=flags, status=status))
        assert m.unit_mm is unit_mm and m.partial_index == partial and m.status == status
        assert m.address == 0x80 and m.count == n
        np.testing.assert_array_equal(m.values, values)
        np.testing.assert_array_equal(m.flags, flags)
        got = m.ranges_m
        nan = np.isnan(ranges_m)
        over = ranges_m > max_m + unit_m / 2
        inside = ~nan & ~over
        np.testing.assert_array_equal(np.isnan(got), nan | over)
        assert np.all(np.abs(got[inside] - ranges_m[inside]) <= unit_m / 2 + 1e-12)
        np.testing.assert_array_equal(values[nan], L.NO_RETURN)
        np.testing.assert_array_equal(values[over], L.OVER_RANGE)


def test_ranges_to_values_edges():
    v = L.ranges_to_values([0.0, 0.0004, 0.0016, 8.182, 8.1826, np.inf, np.nan])
    np.testing.assert_array_equal(v, [0, 0, 2, 8182, L.OVER_RANGE, L.OVER_RANGE, L.NO_RETURN])
    assert v.dtype == np.uint16
    v = L.ranges_to_values([81.82, 81.826, 1.234], unit_mm=False)
    np.testing.assert_array_equal(v, [8182, L.OVER_RANGE, 123])
    with pytest.raises(ValueError, match=">= 0"):
        L.ranges_to_values([1.0, -0.001])
    with pytest.raises(ValueError):
        L.ranges_to_values([-np.inf])


def test_values_to_ranges_error_codes_are_nan():
    codes = np.arange(L.ERROR_CODE_MIN, 8192)
    assert np.all(np.isnan(L.values_to_ranges_m(codes)))
    r = L.values_to_ranges_m([0, 1, 8182], unit_mm=False)
    np.testing.assert_allclose(r, [0.0, 0.01, 81.82])
    every = np.arange(0, L.MAX_RANGE_VALUE + 1)
    for unit_mm in (True, False):
        back = L.ranges_to_values(L.values_to_ranges_m(every, unit_mm), unit_mm)
        np.testing.assert_array_equal(back, every)
    with pytest.raises(ValueError):
        L.values_to_ranges_m([8192])
    with pytest.raises(ValueError):
        L.values_to_ranges_m([-1])
    with pytest.raises(ValueError):
        L.values_to_ranges_m([1.5])


def test_encode_measurement_validation():
    with pytest.raises(ValueError, match="1..1023"):
        L.encode_measurement(np.zeros(0, dtype=int))
    with pytest.raises(ValueError, match="1..1023"):
        L.encode_measurement(np.zeros(1024, dtype=int))
    with pytest.raises(ValueError, match="0..8191"):
        L.encode_measurement([8192])
    with pytest.raises(ValueError, match="integers"):
        L.encode_measurement([1.5])
    with pytest.raises(ValueError, match="flags"):
        L.encode_measurement([1, 2], flags=[8, 0])
    with pytest.raises(ValueError, match="flags"):
        L.encode_measurement([1, 2], flags=[1])
    with pytest.raises(ValueError, match="partial_index"):
        L.encode_measurement([1], partial_index=4)
    with pytest.raises(ValueError, match="status"):
        L.encode_measurement([1], status=256)
    with pytest.raises(ValueError, match="address"):
        L.encode_measurement([1], address=-1)
    # the largest telegram is still within MAX_LENGTH and decodes
    big = L.encode_measurement(np.full(1023, 8191), flags=7)
    assert len(big) == 4 + L.MAX_LENGTH + 2
    assert L.decode_measurement(big).count == 1023


def test_decode_measurement_errors():
    good = L.encode_measurement([100, 200, 300])
    with pytest.raises(L.TelegramError, match="CRC"):
        L.decode_measurement(good[:-1] + bytes([good[-1] ^ 0xFF]))
    with pytest.raises(L.TelegramError, match="0x02"):
        L.decode_measurement(b"\x03" + good[1:])
    with pytest.raises(L.TelegramError, match="implies"):
        L.decode_measurement(good + b"\x00")
    with pytest.raises(L.TelegramError, match="short"):
        L.decode_measurement(good[:5])
    with pytest.raises(L.TelegramError, match="command"):
        L.decode_measurement(L.START_CONTINUOUS)
    with pytest.raises(L.TelegramError, match="scanner"):
        L.decode_measurement(L.encode_measurement([1], address=0x00))
    # count in the header disagrees with the length (valid CRC)
    payload = bytearray(L.decode_frame(good).payload)
    payload[1] = 4
    with pytest.raises(L.TelegramError, match="values"):
        L.decode_measurement(L.encode_frame(0x80, bytes(payload)))
    payload[1] = 3
    payload[2] |= 0x80  # unit bits = 2
    with pytest.raises(L.TelegramError, match="unit"):
        L.decode_measurement(L.encode_frame(0x80, bytes(payload)))
    assert isinstance(L.TelegramError("x"), ValueError)


def test_measurement_arrays_are_read_only():
    m = L.decode_measurement(L.encode_measurement([1, 2, 3]))
    with pytest.raises(ValueError):
        m.values[0] = 5
    with pytest.raises(AttributeError):
        m.status = 0


def test_field_for_count():
    assert L.field_for_count(401) == (100.0, 0.25)
    assert L.field_for_count(361) == (180.0, 0.5)
    assert L.field_for_count(181) == (180.0, 1.0)
    assert L.field_for_count(201) == (100.0, 0.5)
    assert L.field_for_count(101) == (100.0, 1.0)
    assert L.field_for_count(np.int64(361)) == (180.0, 0.5)
    for fov_deg, step_deg in map(L.field_for_count, (401, 361, 181, 201, 101)):
        assert fov_deg / step_deg + 1 in (401, 361, 181, 201, 101)
    for bad in (0, 100, 180, 360, 400, 402, 1023, 361.0, "361", True):
        with pytest.raises(ValueError, match="values per scan"):
            L.field_for_count(bad)


# --------------------------------------------------------------------------- LMS200: reader

def _random_scan_telegrams(rng, count):
    """(values, unit_mm, partial, flags, telegram) for `count` random scans."""
    sizes = (401, 361, 181, 201, 101)
    scans = []
    for i in range(count):
        n = sizes[i % len(sizes)]
        unit_mm = i % 3 != 2
        max_m = L.MAX_RANGE_VALUE * (0.001 if unit_mm else 0.01)
        ranges_m = rng.uniform(0.0, 1.05 * max_m, n)
        ranges_m[rng.random(n) < 0.05] = np.nan
        values = L.ranges_to_values(ranges_m, unit_mm)
        flags = rng.integers(0, 8, n)
        partial = i % 4
        telegram = L.encode_measurement(values, unit_mm=unit_mm, partial_index=partial,
                                        flags=flags)
        scans.append((values, unit_mm, partial, flags, telegram))
    return scans


def _garbage(rng, max_len, forbidden):
    g = rng.integers(0, 256, int(rng.integers(0, max_len + 1))).astype(np.uint8)
    for b in forbidden:
        g[g == b] = (b + 1) % 256
    return g.tobytes()


def _assert_scans_equal(telegram, scan):
    values, unit_mm, partial, flags, _ = scan
    m = L.decode_measurement(telegram)
    np.testing.assert_array_equal(m.values, values)
    np.testing.assert_array_equal(m.flags, flags)
    assert (m.unit_mm, m.partial_index) == (unit_mm, partial)


def test_reader_byte_by_byte_and_random_chunks():
    rng = _rng("reader chunks")
    scans = _random_scan_telegrams(rng, 12)
    stream = b"".join(_garbage(rng, 30, [L.STX]) + s[-1] for s in scans)
    for chunking in ("bytes", "random"):
        reader = L.TelegramReader()
        got, pos = [], 0
        while pos < len(stream):
            step = 1 if chunking == "bytes" else int(rng.integers(1, 700))
            got += reader.feed(stream[pos:pos + step])
            pos += step
        assert got == [s[-1] for s in scans]
        assert reader.crc_errors == 0 and reader.telegrams == len(scans)
        assert sum(map(len, got)) + reader.garbage_bytes + reader.buffered_bytes == len(stream)


def test_reader_corrupt_length_does_not_swallow_following_telegrams():
    rng = _rng("corrupt length")
    scans = _random_scan_telegrams(rng, 6)
    bad = bytearray(scans[1][-1])
    bad[3] = 0x07  # claimed length grows by 7 * 256 bytes (still <= MAX_LENGTH)
    assert int.from_bytes(bad[2:4], "little") <= L.MAX_LENGTH
    stream = scans[0][-1] + bytes(bad) + b"".join(s[-1] for s in scans[2:])
    reader = L.TelegramReader()
    got = reader.feed(stream)
    assert got == [scans[0][-1]] + [s[-1] for s in scans[2:]]
    assert reader.crc_errors == 1


def test_reader_absurd_length_is_garbage():
    good = L.encode_measurement([1, 2, 3])
    absurd = b"\x02\x80\xff\xff\xb0"  # length 65535 > MAX_LENGTH
    zero = b"\x02\x80\x00\x00"  # length 0 < MIN_LENGTH
    reader = L.TelegramReader()
    assert reader.feed(absurd + zero + good) == [good]
    assert reader.crc_errors == 0
    assert reader.garbage_bytes == len(absurd) + len(zero)


def test_reader_garbage_containing_stx_still_recovers_everything():
    """0x02 in line noise makes false candidates (counted as CRC errors) but loses nothing."""
    rng = _rng("garbage with 0x02")
    scans = _random_scan_telegrams(rng, 10)
    stream = b""
    for s in scans:
        g = bytearray(_garbage(rng, 20, []))
        g[len(g) // 2:len(g) // 2] = b"\x02\x80\x03\x00"  # a plausible false header
        stream += bytes(g) + s[-1]
    reader = L.TelegramReader()
    got = []
    for i in range(0, len(stream), 97):
        got += reader.feed(stream[i:i + 97])
    # a false candidate near the end may claim more bytes than ever arrive: flush on idle
    got += reader.flush()
    assert got == [s[-1] for s in scans]
    assert reader.crc_errors >= 1
    assert reader.buffered_bytes == 0
    assert sum(map(len, got)) + reader.garbage_bytes == len(stream)


def test_reader_flush_releases_telegram_stuck_behind_a_false_candidate():
    good = L.encode_measurement([10, 20, 30])
    false_header = b"\x02\x80\x00\x08"  # claims 2048 bytes that never come
    reader = L.TelegramReader()
    assert reader.feed(false_header + good) == []
    assert reader.buffered_bytes == len(false_header) + len(good)
    assert reader.flush() == [good]
    assert reader.garbage_bytes == len(false_header) and reader.buffered_bytes == 0
    assert reader.flush() == []
    # flushing while a telegram is still in flight discards it: flush only on an idle line
    reader = L.TelegramReader()
    assert reader.feed(good[:5]) == [] and reader.flush() == []
    assert reader.garbage_bytes == 5
    assert reader.feed(good[5:]) == []


# --------------------------------------------------------------------------- pty

def _read_until(port, feed, want, deadline_s=IO_DEADLINE_S):
    """Read from a pyserial port into `feed` until `want` items or the deadline."""
    got = []
    deadline = time.monotonic() + deadline_s
    while len(got) < want and time.monotonic() < deadline:
        got += feed(port.read(port.in_waiting or 1))
    return got


def _write_in_thread(dev, chunks):
    def run():
        for c in chunks:
            dev.write(c)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_pty_is_binary_transparent():
    with PtyDevice(write_timeout_s=IO_DEADLINE_S) as dev:
        assert dev.path.startswith("/dev/")
        with serial.Serial(dev.path, 38400, timeout=0.2) as port:
            data = bytes(range(256)) * 8  # CR, LF, XON/XOFF, ^C, ^D, DEL, 0xFF ...
            writer = _write_in_thread(dev, [data])
            got = bytearray()
            deadline = time.monotonic() + IO_DEADLINE_S
            while len(got) < len(data) and time.monotonic() < deadline:
                got += port.read(port.in_waiting or 1)
            writer.join(IO_DEADLINE_S)
            assert bytes(got) == data
            # host -> device direction (e.g. the start-continuous request)
            port.write(L.START_CONTINUOUS)
            port.flush()
            back = b""
            deadline = time.monotonic() + IO_DEADLINE_S
            while len(back) < len(L.START_CONTINUOUS) and time.monotonic() < deadline:
                back += dev.read()
            assert back == L.START_CONTINUOUS
        assert dev.dropped_bytes == 0 and dev.written_bytes == len(data)


def test_pty_drops_instead_of_blocking_without_reader():
    with PtyDevice(write_timeout_s=0.05) as dev:
        t0 = time.monotonic()
        written = sum(dev.write(b"\xAA" * 65536) for _ in range(16))
        elapsed_s = time.monotonic() - t0
        assert dev.dropped_bytes > 0
        assert written + dev.dropped_bytes == 16 * 65536 == dev.written_bytes + dev.dropped_bytes
        assert elapsed_s < 16 * 0.05 + 2.0
    assert dev.closed
    dev.close()  # idempotent
    with pytest.raises(ValueError, match="closed"):
        dev.write(b"x")


def test_lms200_telegrams_through_pty():
    rng = _rng("lms200 through pty")
    scans = _random_scan_telegrams(rng, 40)
    corrupt = 17
    # make sure the corrupted telegram contains 0x02 bytes behind its header (false candidates)
    values, unit_mm, partial, flags, _ = scans[corrupt]
    values = values.copy()
    values[:3] = [0x0002, 0x0202, 0x1002]
    scans[corrupt] = (values, unit_mm, partial, flags,
                      L.encode_measurement(values, unit_mm=unit_mm, partial_index=partial,
                                           flags=flags))
    chunks = []
    for i, scan in enumerate(scans):
        chunks.append(_garbage(rng, 40, [L.STX]))
        telegram = bytearray(scan[-1])
        if i == corrupt:
            k = 7 + 6 + int(rng.integers(0, 2 * (len(values) - 3)))  # a data byte after those
            telegram[k] ^= 1 << int(rng.integers(0, 8))
        chunks.append(bytes(telegram))
    expected = [s for i, s in enumerate(scans) if i != corrupt]

    with PtyDevice(write_timeout_s=IO_DEADLINE_S) as dev:
        with serial.Serial(dev.path, 38400, timeout=0.2) as port:
            reader = L.TelegramReader()
            writer = _write_in_thread(dev, chunks)
            got = _read_until(port, reader.feed, len(expected))
            writer.join(IO_DEADLINE_S)
        assert dev.dropped_bytes == 0

    assert len(got) == len(expected), f"got {len(got)} of {len(expected)} before the deadline"
    for telegram, scan in zip(got, expected):
        _assert_scans_equal(telegram, scan)
    assert got[corrupt] == scans[corrupt + 1][-1]  # the telegram after the corrupt one
    assert reader.crc_errors == 1
    assert reader.telegrams == len(expected)
    assert reader.garbage_bytes >= sum(len(chunks[2 * i]) for i in range(len(scans)))


# --------------------------------------------------------------------------- NMEA

WIKI_GGA = "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"


def test_nmea_checksum_known_sentence():
    body = WIKI_GGA[1:WIKI_GGA.index("*")]
    assert N.nmea_checksum(body) == "47"
    g = N.parse_gga(WIKI_GGA + "\r\n")
    assert g.time_of_day_s == 12 * 3600 + 35 * 60 + 19
    assert g.lat_deg == pytest.approx(48 + 7.038 / 60, abs=1e-12)
    assert g.lon_deg == pytest.approx(11 + 31.0 / 60, abs=1e-12)
    assert (g.quality, g.satellites, g.hdop) == (1, 8, 0.9)
    assert (g.altitude_m, g.geoid_sep_m, g.talker) == (545.4, 46.9, "GP")
    with pytest.raises(ValueError):
        N.nmea_checksum("GPGGA*")
    with pytest.raises(ValueError):
        N.nmea_checksum("GPGGA,é")


def test_format_gga_layout():
    t_ns = ((12 * 60 + 35) * 60 + 19) * 10**9 + 987_654_321 + 3 * 86_400 * 10**9
    s = N.format_gga(t_ns, 48.1173, -11.5166666667, 4, 8, 0.9, 545.4, 46.9)
    assert s.endswith("\r\n")
    fields = s[1:s.index("*")].split(",")
    assert fields[:7] == ["GPGGA", "123519.98", "4807.0380000", "N", "01131.0000000", "W", "4"]
    assert fields[7:] == ["08", "0.9", "545.400", "M", "46.900", "M", "", ""]
    assert s[s.index("*") + 1:-2] == N.nmea_checksum(s[1:s.index("*")])
    # minute rounding carries into degrees; end of day
    s = N.format_gga(86_400 * 10**9 - 1, -0.9999999999999, 179.99999999999, 1, 5, 1.0, 0.0,
                     talker="GN")
    fields = s[1:s.index("*")].split(",")
    assert fields[:6] == ["GNGGA", "235959.99", "0100.0000000", "S", "18000.0000000", "E"]


def test_gga_round_trip_random():
    rng = _rng("gga round trip")
    for _ in range(2000):
        lat = float(rng.uniform(-90, 90))
        lon = float(rng.uniform(-180, 180))
        t_ns = int(rng.integers(0, 2**62))
        alt = float(rng.uniform(-100, 5000))
        sep = float(rng.uniform(-100, 100))
        q = int(rng.choice([0, 1, 2, 4, 5]))
        g = N.parse_gga(N.format_gga(t_ns, lat, lon, q, int(rng.integers(0, 40)),
                                     float(rng.uniform(0, 20)), alt, sep))
        assert abs(g.lat_deg - lat) < 1e-8 and abs(g.lon_deg - lon) < 1e-8
        assert abs(g.altitude_m - alt) <= 0.0005 + 1e-9
        assert abs(g.geoid_sep_m - sep) <= 0.0005 + 1e-9
        tod_s = (t_ns % (86_400 * 10**9)) / 1e9
        assert 0.0 <= tod_s - g.time_of_day_s < 0.01 + 1e-9
        assert g.quality == q


def test_format_gga_validation():
    ok = dict(time_ns=0, lat_deg=0.0, lon_deg=0.0, quality=1, satellites=8, hdop=1.0,
              altitude_m=0.0)
    N.format_gga(**ok)
    for key, bad in [("lat_deg", 90.1), ("lon_deg", -180.5), ("lat_deg", math.nan),
                     ("quality", 9), ("satellites", 100), ("hdop", -1.0),
                     ("altitude_m", math.inf), ("time_ns", 1.5)]:
        with pytest.raises(ValueError):
            N.format_gga(**{**ok, key: bad})
    with pytest.raises(ValueError, match="talker"):
        N.format_gga(**ok, talker="gp")


def _sentence(body):
    return f"${body}*{N.nmea_checksum(body)}"


def test_parse_gga_errors_and_no_fix():
    with pytest.raises(N.NmeaError, match="checksum"):
        N.parse_gga(WIKI_GGA.replace("*47", "*48"))
    with pytest.raises(N.NmeaError, match="checksum"):
        N.parse_gga(WIKI_GGA.replace("545.4", "545.5"))
    with pytest.raises(N.NmeaError, match="'\\*'"):
        N.parse_gga(WIKI_GGA[:WIKI_GGA.index("*")])
    with pytest.raises(N.NmeaError, match="'\\$'"):
        N.parse_gga(WIKI_GGA[1:])
    with pytest.raises(N.NmeaError, match="not a GGA"):
        N.parse_gga(_sentence("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W"))
    with pytest.raises(N.NmeaError, match="fields"):
        N.parse_gga(_sentence("GPGGA,123519,4807.038,N,01131.000,E,1,08"))
    with pytest.raises(N.NmeaError, match="missing latitude"):
        N.parse_gga(_sentence("GPGGA,123519,,,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"))
    with pytest.raises(N.NmeaError, match="latitude"):
        N.parse_gga(_sentence("GPGGA,123519,4860.000,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"))
    with pytest.raises(N.NmeaError, match="hemisphere"):
        N.parse_gga(_sentence("GPGGA,123519,4807.038,E,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"))
    with pytest.raises(N.NmeaError, match="time"):
        N.parse_gga(_sentence("GPGGA,253519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"))
    with pytest.raises(N.NmeaError, match="unit"):
        N.parse_gga(_sentence("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,F,46.9,M,,"))
    assert isinstance(N.NmeaError("x"), ValueError)
    # no fix: returned, with NaN for the empty fields
    g = N.parse_gga(_sentence("GPGGA,002153.00,,,,,0,00,,,,,,,"))
    assert g.quality == 0 and g.satellites == 0
    assert g.time_of_day_s == pytest.approx(21 * 60 + 53)
    assert all(math.isnan(x) for x in (g.lat_deg, g.lon_deg, g.hdop, g.altitude_m,
                                       g.geoid_sep_m))
    assert N.parse_gga(WIKI_GGA.replace("*47", "*47".lower())).quality == 1


def test_nmea_reader_framing():
    good = [N.format_gga(i * 10**9, 10.0 + i, 20.0 + i, 1, 9, 0.8, 100.0) for i in range(4)]
    bad = good[1].replace(",N,", ",S,")  # checksum no longer matches
    stream = ("noise without dollar\n" + good[0] + "xx\x7f" + good[2].rstrip("\r\n") + "\n"
              + bad + "$GPGGA,truncated" + good[3]).encode("ascii")
    stream += b"\xff\xfe$" + b"9" * 300 + b"\r\n" + good[0].encode("ascii")
    reader = N.NmeaReader()
    got = []
    for b in stream:  # byte by byte
        got += reader.feed(bytes([b]))
    assert got == [s.rstrip("\r\n") for s in (good[0], good[2], good[3], good[0])]
    assert reader.checksum_errors == 1 and reader.sentences == 4
    assert reader.buffered_bytes == 0
    expected_garbage = (len("noise without dollar\n") + 3 + len("$GPGGA,truncated") + 2
                        + 1 + 300 + 2)
    assert reader.garbage_bytes == expected_garbage
    assert reader.feed(b"") == []


def test_gga_sentences_through_pty():
    rng = _rng("gga through pty")
    n = 200
    fixes = []
    for i in range(n):
        fixes.append(dict(time_ns=1_700_000_000 * 10**9 + i * 10**8,
                          lat_deg=float(rng.uniform(-60, 60)),
                          lon_deg=float(rng.uniform(-180, 180)),
                          quality=int(rng.choice([1, 2, 4, 5])),
                          satellites=int(rng.integers(4, 30)),
                          hdop=float(rng.uniform(0.5, 3)),
                          altitude_m=float(rng.uniform(0, 900)),
                          geoid_sep_m=float(rng.uniform(-50, 50))))
    # the last sentence stays good: reading stops at the last expected sentence, so a corrupt
    # one after it might not have been read yet
    corrupt = set(int(i) for i in rng.choice(n - 1, size=7, replace=False))
    chunks = []
    for i, fix in enumerate(fixes):
        chunks.append(_garbage(rng, 30, [ord("$"), ord("\n")]))
        s = bytearray(N.format_gga(**fix).encode("ascii"))
        if i in corrupt:  # change one digit of the body to another digit
            digits = [k for k in range(1, s.index(b"*")) if chr(s[k]).isdigit()]
            k = digits[int(rng.integers(0, len(digits)))]
            s[k] = ord("0") + (s[k] - ord("0") + 1 + int(rng.integers(0, 9))) % 10
        chunks.append(bytes(s))
    expected = [f for i, f in enumerate(fixes) if i not in corrupt]

    with PtyDevice(write_timeout_s=IO_DEADLINE_S) as dev:
        with serial.Serial(dev.path, 38400, timeout=0.2) as port:
            reader = N.NmeaReader()
            writer = _write_in_thread(dev, chunks)
            got = _read_until(port, reader.feed, len(expected))
            writer.join(IO_DEADLINE_S)
        assert dev.dropped_bytes == 0

    assert len(got) == len(expected), f"got {len(got)} of {len(expected)} before the deadline"
    assert reader.checksum_errors == len(corrupt)
    assert reader.garbage_bytes > 0
    for sentence, fix in zip(got, expected):
        g = N.parse_gga(sentence)
        assert abs(g.lat_deg - fix["lat_deg"]) < 1e-8
        assert abs(g.lon_deg - fix["lon_deg"]) < 1e-8
        assert g.quality == fix["quality"] and g.satellites == fix["satellites"]
        assert abs(g.altitude_m - fix["altitude_m"]) <= 0.0005 + 1e-9
