"""SICK LMS200 binary telegrams (docs/domain.md §5, thesis §3.4 and Appendix A).

Framing (all integers little-endian)::

    0x02 | address | length u16 | command | data ... [| status] | crc u16

``length`` counts command + data (+ status). Telegrams *from* the scanner carry address
``0x80 + device address`` and end with a status byte; telegrams *to* the scanner (address
``0x00`` + device address) carry no status byte, e.g. the start-continuous request
``02 00 02 00 20 24 34 08``. The CRC-16 covers every byte from the 0x02 through the last
payload byte (:func:`crc16`, table-driven in :mod:`devices.sick_crc`).

Command 0xB0 (measured values) from the scanner::

    data = header u16 | value u16 * count

header bits 0-9 = number of values, bits 11-12 = partial-scan index, bits 14-15 = unit
(0 = cm, 1 = mm); each value: bits 0-12 = range in that unit, bits 13-15 = field flags.
Range codes at the top of the 13-bit scale (>= :data:`ERROR_CODE_MIN`) are error codes, not
distances. This module defines the codes the emulator emits:

===========================  ======  =============================================
constant                     code    meaning
===========================  ======  =============================================
:data:`OVER_RANGE`           8183    measured value > maximum measurable value
:data:`DAZZLE`               8190    dazzled (receiver saturated, e.g. by sunlight)
:data:`NO_RETURN`            8191    measurement not valid / no return (NaN)
===========================  ======  =============================================

every other code in 8183..8191 is also treated as an error by decoders. The largest distance is
therefore :data:`MAX_RANGE_VALUE` = 8182 units: 8.182 m in mm mode, 81.82 m in cm mode.

All functions are pure; :class:`TelegramReader` is the only stateful object (an incremental
stream parser that owns no I/O).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from devices.sick_crc import crc16

__all__ = [
    "STX", "ADDRESS_SCANNER", "ADDRESS_HOST", "CMD_MEASUREMENT", "CMD_MODE", "CMD_STATUS",
    "MODE_CONTINUOUS", "MODE_STOP_CONTINUOUS", "MIN_LENGTH", "MAX_VALUES", "MAX_LENGTH",
    "MAX_RANGE_VALUE", "ERROR_CODE_MIN", "OVER_RANGE", "DAZZLE", "NO_RETURN", "ERROR_CODES",
    "START_CONTINUOUS", "STOP_CONTINUOUS", "STATUS_REQUEST",
    "TelegramError", "Frame", "Measurement", "TelegramReader",
    "crc16", "encode_frame", "decode_frame", "encode_measurement", "decode_measurement",
    "ranges_to_values", "values_to_ranges_m", "field_for_count",
]

#: Start-of-telegram byte.
STX = 0x02
#: Address bit set on telegrams sent by the scanner (0x80 + device address 0).
ADDRESS_SCANNER = 0x80
#: Address of a host -> scanner telegram to the (single) scanner on the line.
ADDRESS_HOST = 0x00

#: Scanner -> host: measured values.
CMD_MEASUREMENT = 0xB0
#: Host -> scanner: change operating mode (one data byte: the mode).
CMD_MODE = 0x20
#: Host -> scanner: status request.
CMD_STATUS = 0x31
#: Operating mode: continuous output of all measured values.
MODE_CONTINUOUS = 0x24
#: Operating mode: stop continuous output (measured values on request only).
MODE_STOP_CONTINUOUS = 0x25

#: Smallest legal ``length`` field: a host telegram with a command and no data.
MIN_LENGTH = 1
#: Largest number of values in one 0xB0 telegram (10-bit count).
MAX_VALUES = 1023
#: Largest ``length`` field accepted: a 0xB0 telegram with :data:`MAX_VALUES` values
#: (command + header + values + status). Anything longer is treated as garbage.
MAX_LENGTH = 1 + 2 + 2 * MAX_VALUES + 1

#: Largest range code that is a distance (units of mm or cm).
MAX_RANGE_VALUE = 8182
#: Smallest range code that is an error code.
ERROR_CODE_MIN = 8183
#: Error code: the measured value exceeds the maximum measurable value.
OVER_RANGE = 8183
#: Error code: the receiver was dazzled.
DAZZLE = 8190
#: Error code: measurement not valid / no return.
NO_RETURN = 8191
#: Descriptions of the error codes the emulator emits.
ERROR_CODES = {
    OVER_RANGE: "measured value > maximum measurable value",
    DAZZLE: "dazzled",
    NO_RETURN: "measurement not valid / no return",
}

_CODE_MAX = 0x1FFF  # 13-bit range field
_FLAGS_MAX = 0x7  # 3-bit field flags
_HEADER_UNIT_SHIFT = 14
_HEADER_PARTIAL_SHIFT = 11

#: count -> (field of view deg, angular step deg) of the LMS200 scanning configurations.
_FIELDS = {
    401: (100.0, 0.25),
    361: (180.0, 0.5),
    181: (180.0, 1.0),
    201: (100.0, 0.5),
    101: (100.0, 1.0),
}


class TelegramError(ValueError):
    """A telegram is malformed: bad start byte, length, CRC, command or contents."""


def encode_frame(address: int, payload: bytes) -> bytes:
    """Frame a payload as an LMS200 telegram: ``0x02 | address | length | payload | crc``.

    Parameters
    ----------
    address : int
        0..255; 0x80 + device address for scanner -> host, device address for host -> scanner.
    payload : bytes
        Command + data (+ status for scanner -> host telegrams); 1..:data:`MAX_LENGTH` bytes.

    Returns
    -------
    bytes
        The complete telegram including the CRC.
    """
    if not 0 <= address <= 0xFF:
        raise ValueError(f"address must be 0..255, got {address}")
    if not MIN_LENGTH <= len(payload) <= MAX_LENGTH:
        raise ValueError(f"payload must be {MIN_LENGTH}..{MAX_LENGTH} bytes, got {len(payload)}")
    body = bytes([STX, address]) + len(payload).to_bytes(2, "little") + bytes(payload)
    return body + crc16(body).to_bytes(2, "little")


@dataclass(frozen=True)
class Frame:
    """A CRC-checked telegram split into its address and payload.

    Attributes
    ----------
    address : int
        The address byte.
    payload : bytes
        Command + data (+ status for scanner -> host telegrams).
    """

    address: int
    payload: bytes

    @property
    def command(self) -> int:
        """The command byte (first payload byte)."""
        return self.payload[0]

    @property
    def from_scanner(self) -> bool:
        """True for scanner -> host telegrams (address bit 0x80 set; they end with a status)."""
        return bool(self.address & ADDRESS_SCANNER)


def decode_frame(telegram: bytes) -> Frame:
    """Check a telegram's start byte, length and CRC and split it.

    Parameters
    ----------
    telegram : bytes
        Exactly one complete telegram.

    Returns
    -------
    Frame

    Raises
    ------
    TelegramError
        If the start byte, the length field (or the telegram's size) or the CRC is wrong.
    """
    telegram = bytes(telegram)
    if len(telegram) < 4 + MIN_LENGTH + 2:
        raise TelegramError(f"telegram too short: {len(telegram)} bytes")
    if telegram[0] != STX:
        raise TelegramError(f"telegram must start with 0x02, got 0x{telegram[0]:02x}")
    length = int.from_bytes(telegram[2:4], "little")
    if not MIN_LENGTH <= length <= MAX_LENGTH:
        raise TelegramError(f"length field {length} outside {MIN_LENGTH}..{MAX_LENGTH}")
    if len(telegram) != 4 + length + 2:
        raise TelegramError(
            f"length field {length} implies {4 + length + 2} bytes, got {len(telegram)}")
    expected = crc16(telegram[:-2])
    got = int.from_bytes(telegram[-2:], "little")
    if got != expected:
        raise TelegramError(f"bad CRC: telegram has 0x{got:04x}, computed 0x{expected:04x}")
    return Frame(address=telegram[1], payload=telegram[4:-2])


#: Host -> scanner: start continuous output of all measured values (``02 00 02 00 20 24 34 08``).
START_CONTINUOUS = encode_frame(ADDRESS_HOST, bytes([CMD_MODE, MODE_CONTINUOUS]))
#: Host -> scanner: stop continuous output (``02 00 02 00 20 25 35 08``).
STOP_CONTINUOUS = encode_frame(ADDRESS_HOST, bytes([CMD_MODE, MODE_STOP_CONTINUOUS]))
#: Host -> scanner: status request (``02 00 01 00 31 15 12``).
STATUS_REQUEST = encode_frame(ADDRESS_HOST, bytes([CMD_STATUS]))


def _unit_m(unit_mm: bool) -> float:
    """Size of one range unit in metres."""
    return 0.001 if unit_mm else 0.01


def ranges_to_values(ranges_m: np.ndarray, unit_mm: bool = True) -> np.ndarray:
    """Convert ranges in metres to LMS200 range codes.

    Parameters
    ----------
    ranges_m : array_like of float
        Ranges, metres, >= 0. NaN means no return.
    unit_mm : bool
        True for millimetre units (max 8.182 m), False for centimetres (max 81.82 m).

    Returns
    -------
    numpy.ndarray of uint16, same shape
        Ranges rounded to the nearest unit; NaN -> :data:`NO_RETURN`; ranges that round above
        :data:`MAX_RANGE_VALUE` (including +inf) -> :data:`OVER_RANGE`.

    Raises
    ------
    ValueError
        If any range is negative (or -inf).
    """
    r = np.asarray(ranges_m, dtype=np.float64)
    if np.any(r < 0.0):
        raise ValueError("ranges_m must be >= 0 (NaN for no return)")
    nan = np.isnan(r)
    with np.errstate(invalid="ignore", over="ignore"):
        units = np.rint(np.where(nan, 0.0, r) / _unit_m(unit_mm))
    over = units > MAX_RANGE_VALUE  # +inf included
    values = np.where(over, 0.0, units).astype(np.uint16)
    values[over] = OVER_RANGE
    values[nan] = NO_RETURN
    return values


def values_to_ranges_m(values: np.ndarray, unit_mm: bool = True) -> np.ndarray:
    """Convert LMS200 range codes to metres; error codes become NaN.

    Parameters
    ----------
    values : array_like of int
        Range codes 0..8191 (without the field flags).
    unit_mm : bool
        True for millimetre units, False for centimetres.

    Returns
    -------
    numpy.ndarray of float64, same shape
        Ranges, metres; NaN where the code is >= :data:`ERROR_CODE_MIN`.

    Raises
    ------
    ValueError
        If a code is outside 0..8191.
    """
    v = np.asarray(values)
    if v.size and (not np.issubdtype(v.dtype, np.integer) or v.min() < 0 or v.max() > _CODE_MAX):
        raise ValueError(f"values must be integer range codes 0..{_CODE_MAX}")
    divisor = 1000.0 if unit_mm else 100.0
    ranges_m = v.astype(np.float64) / divisor
    ranges_m[v >= ERROR_CODE_MIN] = np.nan
    return ranges_m


def _as_codes(name: str, x, upper: int, n: int | None = None) -> np.ndarray:
    """Validate a 1-D array of integers in 0..upper (optionally of length n)."""
    a = np.asarray(x)
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        shape = f"({n},)" if n is not None else "1-D"
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must be integers, got dtype {a.dtype}")
    if a.size and (a.min() < 0 or a.max() > upper):
        raise ValueError(f"{name} must be in 0..{upper}, got {a.min()}..{a.max()}")
    return a.astype(np.uint16)


def encode_measurement(values, *, unit_mm: bool = True, partial_index: int = 0, flags=None,
                       status: int = 0x10, address: int = ADDRESS_SCANNER) -> bytes:
    """Encode one scan as a 0xB0 (measured values) telegram.

    Parameters
    ----------
    values : array_like of int, shape (n,)
        Range codes in the unit, 0..8191, 1 <= n <= 1023 (see :func:`ranges_to_values`);
        codes >= :data:`ERROR_CODE_MIN` are error codes.
    unit_mm : bool
        True: values are millimetres; False: centimetres.
    partial_index : int
        Partial-scan index 0..3 (0 for a full scan).
    flags : int or array_like of int, shape (n,), optional
        Field flags 0..7 per value (bits 13-15); default 0.
    status : int
        Status byte 0..255.
    address : int
        Address byte, default 0x80 (scanner, device address 0).

    Returns
    -------
    bytes
        The complete telegram.
    """
    v = _as_codes("values", values, _CODE_MAX)
    n = v.shape[0]
    if not 1 <= n <= MAX_VALUES:
        raise ValueError(f"number of values must be 1..{MAX_VALUES}, got {n}")
    if flags is None:
        f = np.zeros(n, dtype=np.uint16)
    elif np.ndim(flags) == 0:
        f = _as_codes("flags", np.full(n, flags), _FLAGS_MAX, n)
    else:
        f = _as_codes("flags", flags, _FLAGS_MAX, n)
    if not 0 <= partial_index <= 3:
        raise ValueError(f"partial_index must be 0..3, got {partial_index}")
    if not 0 <= status <= 0xFF:
        raise ValueError(f"status must be 0..255, got {status}")
    header = n | (partial_index << _HEADER_PARTIAL_SHIFT) | (int(unit_mm) << _HEADER_UNIT_SHIFT)
    words = (v | (f << 13)).astype("<u2")
    payload = (bytes([CMD_MEASUREMENT]) + header.to_bytes(2, "little") + words.tobytes()
               + bytes([status]))
    return encode_frame(address, payload)


@dataclass(frozen=True, eq=False)
class Measurement:
    """One decoded 0xB0 telegram. Arrays are read-only; compare fields, not instances.

    Attributes
    ----------
    values : numpy.ndarray of uint16, shape (n,)
        Range codes 0..8191 in the unit (flags stripped).
    unit_mm : bool
        True if the values are millimetres, False if centimetres.
    partial_index : int
        Partial-scan index 0..3.
    flags : numpy.ndarray of uint8, shape (n,)
        Field flags 0..7 (bits 13-15 of each value).
    status : int
        The status byte.
    address : int
        The address byte (0x80 + device address).
    """

    values: np.ndarray
    unit_mm: bool
    partial_index: int
    flags: np.ndarray
    status: int
    address: int

    @property
    def count(self) -> int:
        """Number of values."""
        return int(self.values.shape[0])

    @property
    def ranges_m(self) -> np.ndarray:
        """Ranges in metres; NaN for error codes."""
        return values_to_ranges_m(self.values, self.unit_mm)


def decode_measurement(telegram: bytes) -> Measurement:
    """Decode a 0xB0 (measured values) telegram.

    Parameters
    ----------
    telegram : bytes
        Exactly one complete telegram from the scanner.

    Returns
    -------
    Measurement

    Raises
    ------
    TelegramError
        On a bad start byte, length or CRC, a command other than 0xB0, a telegram not from the
        scanner (address bit 0x80 clear), a value count of 0 or one that disagrees with the
        length, or an undefined unit (header bits 14-15 not 0 or 1). Header bits 10 and 13
        are ignored.
    """
    frame = decode_frame(telegram)
    if frame.command != CMD_MEASUREMENT:
        raise TelegramError(f"expected command 0xb0, got 0x{frame.command:02x}")
    if not frame.from_scanner:
        raise TelegramError(f"address 0x{frame.address:02x} is not from a scanner (bit 0x80)")
    payload = frame.payload
    if len(payload) < 4:
        raise TelegramError(f"0xb0 payload too short: {len(payload)} bytes")
    header = int.from_bytes(payload[1:3], "little")
    n = header & 0x3FF
    unit = header >> _HEADER_UNIT_SHIFT
    if n == 0:
        raise TelegramError("0xb0 telegram with 0 values")
    if len(payload) != 1 + 2 + 2 * n + 1:
        raise TelegramError(
            f"header says {n} values ({1 + 2 + 2 * n + 1} payload bytes), "
            f"payload has {len(payload)} bytes")
    if unit not in (0, 1):
        raise TelegramError(f"undefined unit {unit} in header 0x{header:04x}")
    words = np.frombuffer(payload, dtype="<u2", count=n, offset=3)
    values = (words & _CODE_MAX).astype(np.uint16)
    flags = (words >> 13).astype(np.uint8)
    values.setflags(write=False)
    flags.setflags(write=False)
    return Measurement(values=values, unit_mm=bool(unit), partial_index=(header >> 11) & 0x3,
                       flags=flags, status=payload[-1], address=frame.address)


def field_for_count(n: int) -> tuple[float, float]:
    """The LMS200 scanning configuration that produces n values per scan.

    Parameters
    ----------
    n : int
        Values per scan: 401, 361, 181, 201 or 101.

    Returns
    -------
    (fov_deg, step_deg) : tuple of float
        Field of view and angular step, degrees: 401 -> (100, 0.25), 361 -> (180, 0.5),
        181 -> (180, 1), 201 -> (100, 0.5), 101 -> (100, 1).

    Raises
    ------
    ValueError
        For any other count.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or int(n) not in _FIELDS:
        raise ValueError(
            f"no LMS200 configuration yields {n!r} values per scan; expected one of "
            f"{sorted(_FIELDS)}")
    return _FIELDS[int(n)]


def _bad_measurement_header(buf: bytearray, pos: int, n: int, length: int) -> bool:
    """Whether the candidate at ``buf[pos]`` (``n`` bytes buffered) is a measured-values
    telegram from the scanner whose length cannot match its header's value count (False
    while the header has not arrived)."""
    if n - pos < 7 or not buf[pos + 1] & ADDRESS_SCANNER or buf[pos + 4] != CMD_MEASUREMENT:
        return False
    return length != 4 + 2 * ((buf[pos + 5] | (buf[pos + 6] << 8)) & 0x3FF)


class TelegramReader:
    """Incremental LMS200 stream parser: bytes in, CRC-valid telegrams out.

    Feed it whatever a serial port returns; it returns every complete telegram whose CRC is
    right, of any address and command (filter with :func:`decode_frame` /
    :func:`decode_measurement`; both directions share the framing).

    Resynchronisation: bytes before a 0x02 are skipped (``bytearray.find``). A candidate whose
    length field lies outside ``1..max_length`` is not a telegram: its 0x02 is skipped; so is
    a measured-values candidate (scanner address, command 0xB0) whose length disagrees with
    the value count in its header, as soon as the header has arrived and before any CRC.
    When a complete candidate fails its CRC, the search restarts at the byte *after its
    0x02* (not after its claimed length), so a corrupt length field cannot swallow the good
    telegrams behind it. A corrupt or spurious length only delays output until that many
    bytes have arrived (or until :meth:`flush`, which a caller should invoke when the line
    goes idle: a telegram in flight arrives back to back, so an idle line means the pending
    candidate is dead). Work per byte is bounded: each 0x02 costs at most one table-driven
    CRC over at most ``max_length + 4`` bytes (bench/parsers.py measures it).

    Attributes
    ----------
    telegrams : int
        Telegrams returned so far.
    crc_errors : int
        Corruption events: complete candidates whose CRC failed (or measured-values candidates
        whose length disagrees with their header), not counting candidates that
        start inside the span of an earlier failed candidate (0x02 bytes inside a corrupted
        telegram are echoes of the same event). A 0x02 in line noise followed by a plausible
        length also counts. A candidate passes a wrong CRC with probability 2**-16.
    garbage_bytes : int
        Bytes discarded (not part of a returned telegram), including the bytes of failed
        candidates. Invariant: bytes fed = bytes of returned telegrams + garbage_bytes +
        :attr:`buffered_bytes`.
    """

    def __init__(self, max_length: int = MAX_LENGTH) -> None:
        if not MIN_LENGTH <= max_length <= 0xFFFF:
            raise ValueError(f"max_length must be {MIN_LENGTH}..65535, got {max_length}")
        self.max_length = max_length
        self.telegrams = 0
        self.crc_errors = 0
        self.garbage_bytes = 0
        self._buf = bytearray()
        self._reject_end = 0  # buffer offset where the last failed candidate's span ends

    @property
    def buffered_bytes(self) -> int:
        """Bytes held back waiting for the rest of a telegram."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes from the stream; return the telegrams they complete, in order.

        Parameters
        ----------
        data : bytes
            The next bytes of the stream (any size, possibly empty).

        Returns
        -------
        list of bytes
            Complete, CRC-valid telegrams (0x02 through the CRC).
        """
        buf = self._buf
        buf += data
        n = len(buf)
        out: list[bytes] = []
        pos = 0
        while pos < n:
            start = buf.find(STX, pos)
            if start < 0:
                self.garbage_bytes += n - pos
                pos = n
                break
            self.garbage_bytes += start - pos
            pos = start
            if n - pos < 4:
                break
            length = buf[pos + 2] | (buf[pos + 3] << 8)
            if not MIN_LENGTH <= length <= self.max_length:
                self.garbage_bytes += 1
                pos += 1
                continue
            end = pos + 4 + length + 2
            if _bad_measurement_header(buf, pos, n, length):
                good = False
            elif end > n:
                break
            else:
                good = crc16(buf[pos:end - 2]) == buf[end - 2] | (buf[end - 1] << 8)
            if good:
                out.append(bytes(buf[pos:end]))
                self.telegrams += 1
                pos = end
            else:
                if pos >= self._reject_end:
                    self.crc_errors += 1
                self._reject_end = max(self._reject_end, end)
                self.garbage_bytes += 1
                pos += 1
        del buf[:pos]
        self._reject_end = max(0, self._reject_end - pos)
        return out

    def flush(self) -> list[bytes]:
        """Give up on the pending candidate; return telegrams found behind it.

        Call when the line has been idle for longer than the gap between bytes of one
        telegram (e.g. a serial read timed out with no data): the held-back bytes then cannot
        be waiting for the rest of a telegram still in flight. The pending candidate's 0x02 is
        skipped and the rest rescanned, repeatedly, until nothing is held back. Discarded
        bytes count as garbage (a truncated telegram is not a CRC error).

        Returns
        -------
        list of bytes
            CRC-valid telegrams that were stuck behind a truncated or spurious candidate.
        """
        out: list[bytes] = []
        while self._buf:
            self.garbage_bytes += 1
            del self._buf[:1]
            self._reject_end = max(0, self._reject_end - 1)
            out += self.feed(b"")
        return out
