"""SICK CoLa-A / CoLa-B: the decoder and the stream reader against telegrams built here.

Every telegram is built in this file from the published layout (the Telegram Listing
8014631's framing, the LMS500 instructions' "Read scan data" message; the module
docstring of devices/cola.py and docs/integration.md cite them) with ``struct`` and
string formatting, never with :func:`devices.cola.encode_scandata`; that encoder (the
simulator's) is itself checked against these bytes.  Random values come from the run's
seed (``--seed N`` reproduces a run; tests/seeding.py).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from functools import reduce

import numpy as np
import pytest

from devices import cola as C
from devices.cola_reader import ColaReader
from seeding import rng as seeded_rng

pytestmark = pytest.mark.seeded

MAGIC = b"\x02\x02\x02\x02"


# -- telegrams built from the published layout --------------------------------------------


@dataclass
class Chan:
    content: str
    factor: float
    offset: float
    start: int          # 1/10000 deg, signed
    step: int           # 1/10000 deg
    values: list[int]


@dataclass
class Fields:
    """The values of one scan telegram, in the listing's order."""

    version: int = 1
    device: int = 1
    serial: int = 0x10959BF
    status: tuple[int, int] = (0, 0)
    telegram_counter: int = 0x347F
    scan_counter: int = 0xCABC
    start_us: int = 0x1687D5AD
    transmit_us: int = 0x16884966
    inputs: tuple[int, int] = (0, 0)
    outputs: tuple[int, int] = (0, 0)
    reserved: int = 0
    frequency: int = 2500           # 1/100 Hz
    measurement_frequency: int = 36
    encoders: list[tuple[int, int]] = field(default_factory=list)
    ch16: list[Chan] = field(default_factory=list)
    ch8: list[Chan] = field(default_factory=list)
    name: str | None = None
    time: tuple[int, ...] | None = None   # year, month, day, hour, minute, second, us


def _xor(data: bytes) -> int:
    return reduce(lambda a, b: a ^ b, data, 0)


def binary_telegram(f: Fields, command: bytes = b"sSN") -> bytes:
    """CoLa-B: 4 x STX, length u32, payload, XOR; payload big-endian after the name."""
    p = [command + b" LMDscandata ",
         struct.pack(">HHIBBHHIIBBBBHII", f.version, f.device, f.serial, *f.status,
                     f.telegram_counter, f.scan_counter, f.start_us, f.transmit_us,
                     *f.inputs, *f.outputs, f.reserved, f.frequency,
                     f.measurement_frequency),
         struct.pack(">H", len(f.encoders))]
    p += [struct.pack(">IH", pos, speed) for pos, speed in f.encoders]
    for chans, fmt in ((f.ch16, "H"), (f.ch8, "B")):
        p.append(struct.pack(">H", len(chans)))
        for c in chans:
            p.append(c.content.encode() + struct.pack(">ffiHH", c.factor, c.offset, c.start,
                                                      c.step, len(c.values)))
            p.append(struct.pack(f">{len(c.values)}{fmt}", *c.values))
    p.append(struct.pack(">H", 0))                                   # no position
    p.append(struct.pack(">H", 0) if f.name is None else
             struct.pack(">HB", 1, len(f.name)) + f.name.encode())
    p.append(struct.pack(">H", 0))                                   # no comment
    p.append(struct.pack(">H", 0) if f.time is None else
             struct.pack(">HHBBBBBI", 1, *f.time))
    p.append(struct.pack(">H", 0))                                   # no event
    payload = b"".join(p)
    return MAGIC + struct.pack(">I", len(payload)) + payload + bytes([_xor(payload)])


def _hex(v: int) -> str:
    return f"{v:X}"


def _real(x: float) -> str:
    return _hex(struct.unpack(">I", struct.pack(">f", x))[0])


def ascii_telegram(f: Fields, *, signed_decimal: bool = False) -> bytes:
    """CoLa-A: STX, space-separated tokens, ETX; hex without leading zeros, a signed
    angle as two's complement hex (or ``+``/``-`` decimal), reals as their IEEE bits."""
    t = ["sSN", "LMDscandata", _hex(f.version), _hex(f.device), _hex(f.serial),
         *map(_hex, f.status), _hex(f.telegram_counter), _hex(f.scan_counter),
         _hex(f.start_us), _hex(f.transmit_us), *map(_hex, f.inputs), *map(_hex, f.outputs),
         _hex(f.reserved), _hex(f.frequency), _hex(f.measurement_frequency),
         _hex(len(f.encoders))]
    for pos, speed in f.encoders:
        t += [_hex(pos), _hex(speed)]
    for chans in (f.ch16, f.ch8):
        t.append(_hex(len(chans)))
        for c in chans:
            start = f"{c.start:+d}" if signed_decimal else _hex(c.start & 0xFFFFFFFF)
            t += [c.content, _real(c.factor), _real(c.offset), start, _hex(c.step),
                  _hex(len(c.values)), *map(_hex, c.values)]
    t.append("0")
    t += ["0"] if f.name is None else ["1", _hex(len(f.name)), f.name]
    t.append("0")
    t += ["0"] if f.time is None else ["1", *map(_hex, f.time)]
    t.append("0")
    return b"\x02" + " ".join(t).encode() + b"\x03"


def build(f: Fields, protocol: str, **kwargs) -> bytes:
    return binary_telegram(f) if protocol == "cola-b" else ascii_telegram(f, **kwargs)


def payload_of(telegram: bytes, protocol: str) -> bytes:
    return telegram[8:-1] if protocol == "cola-b" else telegram[1:-1]


def lms511_fields(rng: np.random.Generator, count: int = 1141, step: int = 1667,
                  start: int = -50_000, factor: float = 1.0, rssi8: bool = True,
                  time: bool = True) -> Fields:
    """An LMS511-like scan: DIST1 from 0.7 to 65 m with a few reserved codes, RSSI1."""
    dist = rng.integers(700, 65_000, count)
    dist[rng.random(count) < 0.03] = 0           # no return
    dist[rng.random(count) < 0.01] = 1           # dazzled
    f = Fields(telegram_counter=int(rng.integers(0, 65536)),
               scan_counter=int(rng.integers(0, 65536)),
               start_us=int(rng.integers(0, 2**32 - 100_000)), frequency=2500,
               encoders=[(int(rng.integers(0, 2**32)), int(rng.integers(0, 65536)))],
               ch16=[Chan("DIST1", factor, 0.0, start, step, dist.tolist())])
    f.transmit_us = f.start_us + 40_000
    if rssi8:
        f.ch8 = [Chan("RSSI1", 1.0, 0.0, start, step, rng.integers(0, 256, count).tolist())]
    if time:
        f.time = (2026, 11, 29, 9, 41, 7, int(rng.integers(0, 1_000_000)))
    return f


# -- commands: the published examples ------------------------------------------------------


def test_start_and_poll_commands_are_the_published_bytes():
    """The LMS4000/TiM instructions' examples of ``sEN LMDscandata 1`` and ``sRN
    LMDscandata`` (CoLa-B ends with the XOR 0x33 / 0x05)."""
    assert C.start_scandata("cola-b") == bytes.fromhex(
        "02020202 00000011 73454E20 4C4D4473 63616E64 61746120 01 33".replace(" ", ""))
    assert C.start_scandata("cola-a") == bytes.fromhex(
        "02 73454E20 4C4D4473 63616E64 61746120 31 03".replace(" ", ""))
    assert C.poll_scandata("cola-b") == bytes.fromhex(
        "02020202 0000000F 73524E20 4C4D4473 63616E64 617461 05".replace(" ", ""))
    assert C.poll_scandata("cola-a") == b"\x02sRN LMDscandata\x03"
    assert C.stop_scandata("cola-b")[-2:] == bytes([0x00, 0x32])


# -- decoding ------------------------------------------------------------------------------


def _assert_decoded(scan: C.ScanTelegram, f: Fields) -> None:
    assert (scan.version, scan.device_number, scan.serial_number) == (f.version, f.device,
                                                                     f.serial)
    assert scan.device_status == f.status
    assert (scan.telegram_counter, scan.scan_counter) == (f.telegram_counter, f.scan_counter)
    assert (scan.time_since_startup_us, scan.time_of_transmission_us) == (f.start_us,
                                                                          f.transmit_us)
    assert (scan.inputs, scan.outputs, scan.reserved) == (f.inputs, f.outputs, f.reserved)
    assert scan.scan_frequency_hz == f.frequency / 100
    assert scan.measurement_frequency_raw == f.measurement_frequency
    assert list(scan.encoders) == f.encoders
    for got, want in zip(scan.channels_16 + scan.channels_8, f.ch16 + f.ch8, strict=True):
        assert (got.content, got.start_angle_raw, got.step_raw) == (want.content, want.start,
                                                                   want.step)
        assert got.scale_factor == np.float32(want.factor)
        assert got.values.tolist() == want.values
    dist = np.asarray(f.ch16[0].values, dtype=np.float64)
    expected = dist * np.float32(f.ch16[0].factor) / 1000.0
    expected[dist < 16] = np.nan
    np.testing.assert_array_equal(scan.ranges_m, expected)
    assert scan.step_rad == math.radians(f.ch16[0].step / 10_000)
    assert scan.start_bearing_rad == math.radians(f.ch16[0].start / 10_000 - 90.0)
    assert scan.latency_us == (f.transmit_us - f.start_us) % 2**32
    if f.time is None:
        assert scan.device_time is None
    else:
        t = scan.device_time
        assert (t.year, t.month, t.day, t.hour, t.minute, t.second, t.microsecond) == f.time
    assert scan.extra.get("name") == f.name


SCANS = {
    "lms511-0.1667-rssi8-time": dict(count=1141, step=1667, start=-50_000),
    "lms511-0.25-scale2": dict(count=761, step=2500, start=-50_000, factor=2.0, time=False),
    "lms1xx-0.5-no-rssi": dict(count=541, step=5000, start=-450_000, rssi8=False),
    "tim-0.3333": dict(count=811, step=3333, start=-450_000),
    "lms511-1-deg": dict(count=191, step=10_000, start=-50_000, time=False),
}


@pytest.mark.parametrize("protocol", C.PROTOCOLS)
@pytest.mark.parametrize("case", list(SCANS))
def test_a_scan_telegram_decodes_every_field(protocol, case):
    f = lms511_fields(seeded_rng(1, len(case)), **SCANS[case])
    telegram = build(f, protocol)
    scan = C.decode_scandata(payload_of(telegram, protocol), protocol)
    _assert_decoded(scan, f)
    assert scan.command == "sSN"
    assert (scan.rssi1 is None) == (not f.ch8)


def test_ascii_accepts_signed_decimal_angles_and_a_device_name():
    f = lms511_fields(seeded_rng(2), count=271, step=3333, start=-450_000)
    f.name = "LMS511_1"
    for protocol, telegram in (("cola-a", ascii_telegram(f, signed_decimal=True)),
                               ("cola-b", binary_telegram(f))):
        _assert_decoded(C.decode_scandata(payload_of(telegram, protocol), protocol), f)


def test_a_polled_scan_sra_decodes_like_a_streamed_one():
    f = lms511_fields(seeded_rng(3), count=101, step=10_000)
    scan = C.decode_scandata(binary_telegram(f, b"sRA")[8:-1], "cola-b")
    assert scan.command == "sRA"
    _assert_decoded(scan, f)


def test_the_encoder_writes_the_published_layout():
    """The simulator's encoder gives the same bytes as the layout built here."""
    f = lms511_fields(seeded_rng(4), count=301, step=1667)
    ch = [C.Channel(c.content, c.factor, c.offset, c.start, c.step,
                    np.asarray(c.values, np.uint16 if i == 0 else np.uint8))
          for i, c in enumerate(f.ch16 + f.ch8)]
    scan = C.ScanTelegram(
        serial_number=f.serial, telegram_counter=f.telegram_counter,
        scan_counter=f.scan_counter, time_since_startup_us=f.start_us,
        time_of_transmission_us=f.transmit_us, scan_frequency_raw=f.frequency,
        measurement_frequency_raw=f.measurement_frequency, encoders=tuple(f.encoders),
        channels_16=(ch[0],), channels_8=(ch[1],), device_time=C.DeviceTime(*f.time))
    assert C.encode_scandata(scan, "cola-b") == binary_telegram(f)
    assert C.encode_scandata(scan, "cola-a") == ascii_telegram(f)


def test_dist_values_round_to_the_scale_and_mark_no_return():
    codes = C.dist_values([1.0, 0.0155, np.nan, np.inf, 70.0, 12.3456], scale_factor=1.0)
    assert codes.tolist() == [1000, 16, 0, 0, 0, 12346]
    assert C.dist_values([100.0], scale_factor=2.0).tolist() == [50_000]


@pytest.mark.parametrize("payload, match", [
    (b"sSN LMDscandata 1 1", "ends after"),
    (b"sSN LMDscandata 1 1 XYZ", "not a number"),
    (b"sSN LMDscandata 1 10000 0", "does not fit 2"),
    (b"sEA LMDscandata 1", "not a scan telegram"),
    (b"sSN LMDscandatb 1", "not a scan telegram"),
])
def test_a_bad_ascii_scan_is_one_clear_error(payload, match):
    with pytest.raises(C.ColaError, match=match):
        C.decode_scandata(payload, "cola-a")


def test_a_truncated_binary_scan_is_one_clear_error():
    payload = binary_telegram(lms511_fields(seeded_rng(5), count=11, step=10_000))[8:-1]
    with pytest.raises(C.ColaError, match="telegram ends at byte"):
        C.decode_scandata(payload[:60], "cola-b")
    no_dist = Fields(ch16=[Chan("RSSI1", 1.0, 0.0, 0, 10_000, [1, 2, 3])])
    scan = C.decode_scandata(binary_telegram(no_dist)[8:-1], "cola-b")
    with pytest.raises(C.ColaError, match="no DIST1"):
        scan.ranges_m


# -- the stream reader ---------------------------------------------------------------------


def _noise(rng: np.random.Generator, n: int) -> bytes:
    """Random bytes without 0x02 (so every error in a stream is one the test planted)."""
    b = rng.integers(0, 256, n, dtype=np.uint8)
    b[b == 0x02] = 0x55
    return b.tobytes()


def _stream(protocol: str, rng: np.random.Generator):
    """garbage, T0, garbage, T1 corrupted, T2, garbage, T3 (the last one intact).

    Returns (stream, intact payloads, corrupted telegrams, intact framed bytes)."""
    telegrams = [build(lms511_fields(rng, count=61, step=10_000, start=-50_000 + 100 * i),
                       protocol) for i in range(4)]
    bad = bytearray(telegrams[1])
    k = len(bad) // 2
    if protocol == "cola-b":
        bad[k] ^= 0x10                           # the checksum fails
    else:
        bad[k] = 0x07                            # a control byte: a broken frame
    parts = [_noise(rng, 17), telegrams[0], _noise(rng, 5), bytes(bad), telegrams[2],
             _noise(rng, 33), telegrams[3]]
    intact = [telegrams[0], telegrams[2], telegrams[3]]
    return b"".join(parts), [payload_of(t, protocol) for t in intact], sum(map(len, intact))


def _counts(reader: ColaReader) -> tuple[int, int, int, int, int]:
    return (reader.telegrams, reader.checksum_errors, reader.broken_frames,
            reader.garbage_bytes, reader.buffered_bytes)


@pytest.mark.parametrize("protocol", C.PROTOCOLS)
def test_the_reader_gives_the_same_telegrams_split_at_every_byte_boundary(protocol):
    stream, payloads, intact_bytes = _stream(protocol, seeded_rng(6))
    error = (1, 0) if protocol == "cola-b" else (0, 1)
    expected = (3, *error, len(stream) - intact_bytes, 0)
    for cut in range(len(stream) + 1):
        reader = ColaReader(protocol)
        got = reader.feed(stream[:cut]) + reader.feed(stream[cut:])
        assert got == payloads, f"split at byte {cut}"
        assert _counts(reader) == expected, f"split at byte {cut}"
    reader = ColaReader(protocol)
    got = [p for i in range(len(stream)) for p in reader.feed(stream[i:i + 1])]
    assert got == payloads and _counts(reader) == expected
    for payload, i in zip(got, (0, 2, 3)):
        scan = C.decode_scandata(payload, protocol)
        assert scan.dist1.start_angle_raw == -50_000 + 100 * i


def test_a_wrong_checksum_is_counted_once_and_the_next_telegram_is_found():
    rng = seeded_rng(7)
    good = binary_telegram(lms511_fields(rng, count=31, step=10_000))
    wrong = good[:-1] + bytes([good[-1] ^ 0xFF])
    reader = ColaReader("cola-b")
    assert reader.feed(wrong) == []
    assert reader.checksum_errors == 1
    # a last byte 0x02 is held back: it may start the next telegram's magic
    assert reader.garbage_bytes + reader.buffered_bytes == len(wrong)
    assert reader.buffered_bytes == (1 if wrong[-1] == 0x02 else 0)
    assert reader.feed(good) == [good[8:-1]]
    assert _counts(reader) == (1, 1, 0, len(wrong), 0)


def test_a_corrupt_length_does_not_swallow_the_telegrams_behind_it():
    good = binary_telegram(lms511_fields(seeded_rng(8), count=31, step=10_000))
    huge = MAGIC + struct.pack(">I", 10**9) + b"sSN"       # longer than any telegram
    reader = ColaReader("cola-b")
    assert reader.feed(huge + good) == [good[8:-1]]
    assert (reader.checksum_errors, reader.garbage_bytes) == (0, len(huge))
    # a plausible length: held until that many bytes are in, then its checksum fails and
    # the search goes on inside it
    rest = good + good + good
    length = len(good) + 20
    while True:             # a length whose checksum byte does not happen to match
        plausible = MAGIC + struct.pack(">I", length) + b"sSN x"
        stream = plausible + rest
        if _xor(stream[8:8 + length]) != stream[8 + length]:
            break
        length += 1
    reader = ColaReader("cola-b")
    assert reader.feed(plausible + good) == []
    assert reader.feed(good + good) == [good[8:-1]] * 3
    assert _counts(reader) == (3, 1, 0, len(plausible), 0)


def test_cola_a_frames_broken_by_a_stray_stx_or_no_etx_are_skipped():
    f = lms511_fields(seeded_rng(9), count=21, step=10_000)
    good = ascii_telegram(f)
    truncated = good[:len(good) // 2]
    reader = ColaReader("cola-a", max_payload=len(good))
    assert reader.feed(truncated + good) == [good[1:-1]]
    assert (reader.broken_frames, reader.garbage_bytes) == (1, len(truncated))
    never_ends = b"\x02" + b"x" * (len(good) + 5)
    assert reader.feed(never_ends + good) == [good[1:-1]]
    assert reader.broken_frames == 2
    assert reader.garbage_bytes == len(truncated) + len(never_ends)


@pytest.mark.parametrize("protocol", C.PROTOCOLS)
def test_a_cut_drops_the_telegram_in_flight_as_garbage(protocol):
    telegram = build(lms511_fields(seeded_rng(10), count=41, step=10_000), protocol)
    reader = ColaReader(protocol)
    assert reader.feed(telegram[:100]) == []
    assert reader.buffered_bytes == 100
    assert reader.reset() == 100
    assert reader.feed(telegram) == [payload_of(telegram, protocol)]
    assert _counts(reader) == (1, 0, 0, 100, 0)
