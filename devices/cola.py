"""SICK CoLa-A / CoLa-B telegrams of the LMS1xx, LMS5xx and TiM: framing and ``LMDscandata``.

Framing (SICK Telegram Listing 8014631, §2.1 "Binary telegram (CoLa B)" and §2.2 "ASCII
telegram (CoLa A)"; docs/integration.md cites each section used)::

    CoLa-A:  0x02 | ASCII payload | 0x03                      (no checksum)
    CoLa-B:  02 02 02 02 | length u32 big-endian | payload | XOR of the payload bytes

A payload is a SOPAS command: ``sEN LMDscandata 1`` (start the scan data output),
``sRN LMDscandata`` (poll one scan), and the device's ``sEA`` (answer), ``sSN`` (one
scan, streamed) and ``sRA`` (one scan, polled).  In CoLa-A the parameters are
space-separated tokens: unsigned numbers in hexadecimal without leading zeros, signed
ones either as two's-complement hexadecimal or as decimal with a ``+``/``-`` sign, reals
as the hexadecimal of their IEEE-754 single bits; in CoLa-B they follow the command
name and one space, big-endian binary.

The scan telegram (``sSN``/``sRA LMDscandata``; the LMS500 operating instructions
8013796, §10.2.4 "Read scan data", and the Telegram Listing's "Send data permanently")::

    version u16 | device number u16 | serial number u32 | device status 2 x u8
    telegram counter u16 | scan counter u16 | time since start-up us u32
    time of transmission us u32 | inputs 2 x u8 | outputs 2 x u8 | reserved u16
    scan frequency u32 (1/100 Hz) | measurement frequency u32
    encoders u16, each: position u32, speed u16
    16-bit channels u16, each: content 5 chars (DIST1, RSSI1 ...) | scale factor real
        | scale offset real | start angle i32 (1/10000 deg) | step u16 (1/10000 deg)
        | count u16 | values u16 x count
    8-bit channels u16, each: the same header, values u8 x count
    [position u16 (1: 6 reals, rotation type u8)] [name u16 (1: length u8, text)]
    [comment u16 (1: length u8, text)]
    [time u16 (1: year u16, month, day, hour, minute, second u8, microsecond u32)]
    [event u16 (1: type 4 chars, encoder position u32, time u32, angle i32)]

The blocks in brackets are read when the telegram goes on that far.  A DIST value times
the scale factor plus the offset is millimetres; values below 16 are not distances (0:
no return, 1: dazzled; the LMS4000 instructions' "LMDscandata - reserved values") and
become NaN.  The device's angles count counter-clockwise with 90 deg straight ahead;
:attr:`ScanTelegram.start_bearing_rad` is the Foxglove ``LaserScan`` bearing about the
scanner frame's +z from +x, with +x straight ahead: device angle - 90 deg.

Everything here is pure; :mod:`devices.cola_reader` holds the stream reader.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

__all__ = ["PROTOCOLS", "STX", "ETX", "MAGIC", "DEFAULT_MAX_PAYLOAD", "MIN_DISTANCE_VALUE",
           "FORWARD_DEG", "ANGLE_UNITS_PER_DEG", "ColaError", "Channel", "DeviceTime",
           "ScanTelegram", "check_protocol", "xor_checksum", "frame", "command_of",
           "start_scandata", "stop_scandata", "poll_scandata", "decode_scandata",
           "encode_scandata", "encode_payload", "dist_values"]

#: the two framings, as the command line names them
PROTOCOLS = ("cola-a", "cola-b")
#: CoLa-A start and end of a telegram
STX, ETX = 0x02, 0x03
#: CoLa-B start of a telegram
MAGIC = b"\x02\x02\x02\x02"
#: longest payload accepted, bytes; a longer length field is garbage
DEFAULT_MAX_PAYLOAD = 65_536
#: DIST values below this are reserved codes, not distances
MIN_DISTANCE_VALUE = 16
#: the device angle, degrees, that points straight ahead (the scanner frame's +x)
FORWARD_DEG = 90.0
#: start angles and steps are in 1/10000 degree
ANGLE_UNITS_PER_DEG = 10_000
_SCAN_COMMANDS = ("sSN", "sRA")
_SCANDATA = "LMDscandata"


class ColaError(ValueError):
    """A telegram is malformed: framing, checksum, command or contents."""


def check_protocol(protocol: str) -> None:
    """ValueError unless ``protocol`` is one of :data:`PROTOCOLS`."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")


def xor_checksum(payload: bytes) -> int:
    """The CoLa-B checksum: the XOR of every payload byte (0 for an empty payload)."""
    if not payload:
        return 0
    return int(np.bitwise_xor.reduce(np.frombuffer(payload, dtype=np.uint8)))


def frame(payload: bytes, protocol: str) -> bytes:
    """Frame a payload as one CoLa-A or CoLa-B telegram.

    Raises
    ------
    ValueError
        On an unknown protocol, an empty payload, or a CoLa-A payload holding STX or ETX.
    """
    check_protocol(protocol)
    payload = bytes(payload)
    if not payload:
        raise ValueError("a telegram needs a payload")
    if protocol == "cola-a":
        if STX in payload or ETX in payload:
            raise ValueError("a CoLa-A payload cannot hold 0x02 or 0x03")
        return bytes([STX]) + payload + bytes([ETX])
    return MAGIC + len(payload).to_bytes(4, "big") + payload + bytes([xor_checksum(payload)])


def command_of(payload: bytes) -> tuple[str, str]:
    """The command type and name of a payload: ``(b"sEA LMDscandata ...")`` ->
    ``("sEA", "LMDscandata")``; empty strings where the payload has none."""
    parts = bytes(payload).split(b" ", 2)
    kind = parts[0].decode("latin-1")
    name = parts[1].decode("latin-1") if len(parts) > 1 else ""
    return kind, name


def encode_payload(kind: str, name: str, protocol: str, *params: int) -> bytes:
    """A command payload with one-byte parameters (``sEN LMDscandata 1``): CoLa-A tokens or
    CoLa-B bytes after the name and a space."""
    check_protocol(protocol)
    head = f"{kind} {name}".encode("ascii")
    if not params:
        return head
    if protocol == "cola-a":
        return head + b" " + b" ".join(f"{p:X}".encode("ascii") for p in params)
    return head + b" " + bytes(params)


def start_scandata(protocol: str) -> bytes:
    """The framed ``sEN LMDscandata 1``: start streaming scans."""
    return frame(encode_payload("sEN", _SCANDATA, protocol, 1), protocol)


def stop_scandata(protocol: str) -> bytes:
    """The framed ``sEN LMDscandata 0``: stop streaming scans."""
    return frame(encode_payload("sEN", _SCANDATA, protocol, 0), protocol)


def poll_scandata(protocol: str) -> bytes:
    """The framed ``sRN LMDscandata``: ask for the last scan once."""
    return frame(encode_payload("sRN", _SCANDATA, protocol), protocol)


# -- the scan telegram --------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Channel:
    """One output channel: ``content`` (``DIST1``, ``RSSI1`` ...); a value times
    ``scale_factor`` plus ``scale_offset`` is the measurement (mm for DIST); the first
    value's angle and the step (``start_angle_raw``, ``step_raw``) in 1/10000 degree
    (device angles); ``values`` uint16 (16-bit channels) or uint8 (8-bit channels)."""

    content: str
    scale_factor: float
    scale_offset: float
    start_angle_raw: int
    step_raw: int
    values: np.ndarray


@dataclass(frozen=True)
class DeviceTime:
    """The telegram's optional time block: the device's real-time clock (UTC by its set-up)."""

    year: int
    month: int
    day: int
    hour: int
    minute: int
    second: int
    microsecond: int


@dataclass(frozen=True, eq=False)
class ScanTelegram:
    """One decoded ``sSN`` / ``sRA LMDscandata`` (module docstring for the layout).

    Times are the device's microsecond counter since power-up (wrapping at 2**32):
    ``time_since_startup_us`` at the scan's zero index, ``time_of_transmission_us`` when
    the finished scan went to the output buffer.  ``scan_frequency_raw`` is 1/100 Hz.
    """

    command: str = "sSN"
    version: int = 1
    device_number: int = 1
    serial_number: int = 0
    device_status: tuple[int, int] = (0, 0)
    telegram_counter: int = 0
    scan_counter: int = 0
    time_since_startup_us: int = 0
    time_of_transmission_us: int = 0
    inputs: tuple[int, int] = (0, 0)
    outputs: tuple[int, int] = (0, 0)
    reserved: int = 0
    scan_frequency_raw: int = 2500
    measurement_frequency_raw: int = 0
    encoders: tuple[tuple[int, int], ...] = ()
    channels_16: tuple[Channel, ...] = ()
    channels_8: tuple[Channel, ...] = ()
    device_time: DeviceTime | None = None
    extra: dict = field(default_factory=dict)  # position, name, comment, event: as read

    @property
    def scan_frequency_hz(self) -> float:
        """Scans per second."""
        return self.scan_frequency_raw / 100.0

    def channel(self, content: str) -> Channel | None:
        """The first channel (16-bit first) with this content, or None."""
        for ch in self.channels_16 + self.channels_8:
            if ch.content == content:
                return ch
        return None

    @property
    def dist1(self) -> Channel:
        """The DIST1 channel (ColaError when the telegram has none)."""
        ch = self.channel("DIST1")
        if ch is None:
            raise ColaError("the telegram has no DIST1 channel")
        return ch

    @property
    def rssi1(self) -> Channel | None:
        """The RSSI1 channel, 16- or 8-bit, or None."""
        return self.channel("RSSI1")

    @property
    def ranges_m(self) -> np.ndarray:
        """DIST1 in metres (factor and offset applied); reserved codes (< 16) are NaN."""
        ch = self.dist1
        mm = ch.values.astype(np.float64) * ch.scale_factor + ch.scale_offset
        ranges = mm / 1000.0
        ranges[ch.values < MIN_DISTANCE_VALUE] = np.nan
        return ranges

    @property
    def step_rad(self) -> float:
        """DIST1's angular step, radians."""
        return math.radians(self.dist1.step_raw / ANGLE_UNITS_PER_DEG)

    @property
    def start_bearing_rad(self) -> float:
        """DIST1's first bearing in the ``LaserScan`` convention: device angle - 90 deg."""
        return math.radians(self.dist1.start_angle_raw / ANGLE_UNITS_PER_DEG - FORWARD_DEG)

    @property
    def latency_us(self) -> int:
        """Microseconds from the scan's zero index to its transmission (device counter,
        modulo 2**32)."""
        return (self.time_of_transmission_us - self.time_since_startup_us) % (1 << 32)


def dist_values(ranges_m, scale_factor: float = 1.0) -> np.ndarray:
    """DIST codes for ranges in metres: ``round(mm / scale_factor)``; NaN, infinities,
    ranges below :data:`MIN_DISTANCE_VALUE` codes and beyond 65535 codes -> 0 (no return)."""
    r = np.asarray(ranges_m, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        codes = np.rint(r * 1000.0 / scale_factor)
        bad = ~np.isfinite(codes) | (codes < MIN_DISTANCE_VALUE) | (codes > 0xFFFF)
    return np.where(bad, 0.0, codes).astype(np.uint16)


# -- the two encodings, behind one reader and one writer interface ------------------------


class _BinaryIn:
    """CoLa-B parameters: big-endian binary from ``pos``."""

    def __init__(self, data: bytes, pos: int) -> None:
        self.data, self.pos = data, pos

    def _take(self, size: int) -> bytes:
        if self.pos + size > len(self.data):
            raise ColaError(f"telegram ends at byte {len(self.data)}, wanted {size} more "
                            f"bytes at {self.pos}")
        chunk = self.data[self.pos:self.pos + size]
        self.pos += size
        return chunk

    def uint(self, size: int) -> int:
        return int.from_bytes(self._take(size), "big")

    def int32(self) -> int:
        return int.from_bytes(self._take(4), "big", signed=True)

    def real(self) -> float:
        return struct.unpack(">f", self._take(4))[0]

    def text(self, size: int) -> str:
        return self._take(size).decode("latin-1")

    def flex_text(self) -> str:
        return self.text(self.uint(1))

    def array(self, count: int, size: int) -> np.ndarray:
        return np.frombuffer(self._take(count * size), dtype=">u2" if size == 2 else "u1"
                             ).astype(np.uint16 if size == 2 else np.uint8)

    @property
    def at_end(self) -> bool:
        return self.pos >= len(self.data)


class _AsciiIn:
    """CoLa-A parameters: space-separated tokens."""

    def __init__(self, tokens: list[bytes]) -> None:
        self.tokens, self.pos = tokens, 0

    def _token(self) -> bytes:
        if self.pos >= len(self.tokens):
            raise ColaError(f"telegram ends after {len(self.tokens)} tokens")
        token = self.tokens[self.pos]
        self.pos += 1
        return token

    def _number(self, token: bytes) -> int:
        try:
            return int(token, 10) if token[:1] in (b"+", b"-") else int(token, 16)
        except ValueError:
            raise ColaError(f"not a number: {token[:20]!r}") from None

    def uint(self, size: int) -> int:
        value = self._number(self._token())
        if not 0 <= value < 1 << (8 * size):
            raise ColaError(f"{value} does not fit {size} unsigned bytes")
        return value

    def int32(self) -> int:
        token = self._token()
        value = self._number(token)
        if token[:1] not in (b"+", b"-") and value >= 1 << 31:
            value -= 1 << 32
        if not -(1 << 31) <= value < 1 << 31:
            raise ColaError(f"{value} does not fit a signed 32-bit integer")
        return value

    def real(self) -> float:
        return struct.unpack(">f", self.uint(4).to_bytes(4, "big"))[0]

    def text(self, size: int) -> str:
        token = self._token()
        if len(token) != size:
            raise ColaError(f"expected {size} characters, got {token[:20]!r}")
        return token.decode("latin-1")

    def flex_text(self) -> str:
        size = self.uint(1)
        return self.text(size) if size else ""

    def array(self, count: int, size: int) -> np.ndarray:
        return np.array([self.uint(size) for _ in range(count)],
                        dtype=np.uint16 if size == 2 else np.uint8)

    @property
    def at_end(self) -> bool:
        return self.pos >= len(self.tokens)


class _Out:
    """Parameters written as CoLa-A tokens (``ascii``) or CoLa-B big-endian bytes."""

    def __init__(self, ascii: bool) -> None:
        self.ascii, self.parts = ascii, []

    def uint(self, value: int, size: int) -> None:
        self.parts.append(f"{int(value):X}".encode("ascii") if self.ascii
                          else int(value).to_bytes(size, "big"))

    def int32(self, value: int) -> None:
        self.uint(int(value) & 0xFFFFFFFF, 4)      # two's complement, both encodings

    def real(self, value: float) -> None:
        self.uint(int.from_bytes(struct.pack(">f", value), "big"), 4)

    def text(self, value: str) -> None:
        self.parts.append(value.encode("latin-1"))

    def array(self, values: np.ndarray, size: int) -> None:
        v = np.asarray(values)
        if self.ascii:
            self.parts.extend(f"{x:X}".encode("ascii") for x in v.tolist())
        else:
            self.parts.append(v.astype(">u2" if size == 2 else "u1").tobytes())

    def payload(self, head: bytes) -> bytes:
        return head + b" " + (b" " if self.ascii else b"").join(self.parts)


# -- decode -------------------------------------------------------------------------------


def _params(payload: bytes, protocol: str) -> tuple[str, _BinaryIn | _AsciiIn]:
    """The command type of a scan telegram and a reader of its parameters."""
    kind, name = command_of(payload)
    if kind not in _SCAN_COMMANDS or name != _SCANDATA:
        raise ColaError(f"not a scan telegram: {bytes(payload[:24])!r}")
    head = len(kind) + 1 + len(name) + 1
    if protocol == "cola-a":
        return kind, _AsciiIn(bytes(payload[head:]).split())
    return kind, _BinaryIn(bytes(payload), head)


def _read_channel(r, size: int) -> Channel:
    content = r.text(5)
    factor, offset = r.real(), r.real()
    start, step, count = r.int32(), r.uint(2), r.uint(2)
    if not (math.isfinite(factor) and math.isfinite(offset)):
        raise ColaError(f"{content}: scale factor {factor} / offset {offset} not finite")
    values = r.array(count, size)
    values.setflags(write=False)
    return Channel(content, factor, offset, start, step, values)


#: the optional blocks after the channels, in order: each a u16 flag, then (when 1) this
_TAIL = {
    "position": lambda r: tuple(r.real() for _ in range(6)) + (r.uint(1),),
    "name": lambda r: r.flex_text(),
    "comment": lambda r: r.flex_text(),
    "time": lambda r: DeviceTime(r.uint(2), r.uint(1), r.uint(1), r.uint(1), r.uint(1),
                                 r.uint(1), r.uint(4)),
    "event": lambda r: (r.text(4), r.uint(4), r.uint(4), r.int32()),
}


def _read_tail(r, extra: dict) -> DeviceTime | None:
    """The optional blocks present (a telegram may end before any of them) into ``extra``;
    returns the time block, or None."""
    for block, read in _TAIL.items():
        if r.at_end:
            break
        if r.uint(2):
            extra[block] = read(r)
    return extra.pop("time", None)


def decode_scandata(payload: bytes, protocol: str) -> ScanTelegram:
    """Decode the payload of an ``sSN`` / ``sRA LMDscandata`` telegram (unframed).

    Raises
    ------
    ColaError
        On another command, a telegram that ends early, a token that is not a number,
        a value out of its type's range, or a non-finite scale factor.
    """
    check_protocol(protocol)
    kind, r = _params(payload, protocol)
    head = dict(command=kind, version=r.uint(2), device_number=r.uint(2),
                serial_number=r.uint(4), device_status=(r.uint(1), r.uint(1)),
                telegram_counter=r.uint(2), scan_counter=r.uint(2),
                time_since_startup_us=r.uint(4), time_of_transmission_us=r.uint(4),
                inputs=(r.uint(1), r.uint(1)), outputs=(r.uint(1), r.uint(1)),
                reserved=r.uint(2), scan_frequency_raw=r.uint(4),
                measurement_frequency_raw=r.uint(4))
    encoders = tuple((r.uint(4), r.uint(2)) for _ in range(r.uint(2)))
    channels_16 = tuple(_read_channel(r, 2) for _ in range(r.uint(2)))
    channels_8 = tuple(_read_channel(r, 1) for _ in range(r.uint(2)))
    extra: dict = {}
    device_time = _read_tail(r, extra)
    return ScanTelegram(**head, encoders=encoders, channels_16=channels_16,
                        channels_8=channels_8, device_time=device_time, extra=extra)


# -- encode (the simulator's LMS511) ------------------------------------------------------


def _write_channel(w, ch: Channel, size: int) -> None:
    if len(ch.content) != 5:
        raise ValueError(f"channel content must be 5 characters, got {ch.content!r}")
    w.text(ch.content)
    w.real(ch.scale_factor)
    w.real(ch.scale_offset)
    w.int32(ch.start_angle_raw)
    w.uint(ch.step_raw, 2)
    w.uint(len(ch.values), 2)
    w.array(ch.values, size)


def encode_scandata(scan: ScanTelegram, protocol: str) -> bytes:
    """Frame a scan as an ``sSN`` (or ``sRA``) ``LMDscandata`` telegram, in the layout
    :func:`decode_scandata` reads: no position, name or comment; the time block when
    ``scan.device_time`` is set."""
    check_protocol(protocol)
    w = _Out(ascii=protocol == "cola-a")
    for value, size in ((scan.version, 2), (scan.device_number, 2), (scan.serial_number, 4),
                        (scan.device_status[0], 1), (scan.device_status[1], 1),
                        (scan.telegram_counter, 2), (scan.scan_counter, 2),
                        (scan.time_since_startup_us, 4), (scan.time_of_transmission_us, 4),
                        (scan.inputs[0], 1), (scan.inputs[1], 1), (scan.outputs[0], 1),
                        (scan.outputs[1], 1), (scan.reserved, 2), (scan.scan_frequency_raw, 4),
                        (scan.measurement_frequency_raw, 4), (len(scan.encoders), 2)):
        w.uint(value, size)
    for position, speed in scan.encoders:
        w.uint(position, 4)
        w.uint(speed, 2)
    for channels, size in ((scan.channels_16, 2), (scan.channels_8, 1)):
        w.uint(len(channels), 2)
        for ch in channels:
            _write_channel(w, ch, size)
    for _block in ("position", "name", "comment"):
        w.uint(0, 2)
    t = scan.device_time
    w.uint(int(t is not None), 2)
    if t is not None:
        for value, size in ((t.year, 2), (t.month, 1), (t.day, 1), (t.hour, 1), (t.minute, 1),
                            (t.second, 1), (t.microsecond, 4)):
            w.uint(value, size)
    w.uint(0, 2)  # no event block
    return frame(w.payload(f"{scan.command} {_SCANDATA}".encode("ascii")), protocol)
