"""NMEA 0183 GGA sentences, as GNSS receivers send them over serial (docs/domain.md §5).

::

    $GPGGA,hhmmss.ss,ddmm.mmmmmmm,N,dddmm.mmmmmmm,E,q,nn,h.h,alt,M,sep,M,,*CS\\r\\n

``q`` is the fix quality (0 = no fix, 1 = GPS, 2 = DGPS, 4 = RTK fixed, 5 = RTK float, ...),
``nn`` the satellites in use, ``h.h`` the HDOP, ``alt`` the altitude above mean sea level and
``sep`` the geoid separation, both metres. ``CS`` is the XOR of every character between ``$`` and
``*`` as two hex digits.

:func:`format_gga` writes 7 decimals of arc-minutes (1e-7 min = 1.7e-9 deg, about 0.2 mm), so a
sentence can exceed NMEA's 82-character limit, as high-precision receivers' sentences do;
:class:`NmeaReader` therefore accepts sentences up to :data:`MAX_LINE_LENGTH` = 128 characters
(``$`` through CR LF) by default.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from schemas.times import NS_PER_DAY

__all__ = ["NmeaError", "Gga", "NmeaReader", "nmea_checksum", "format_gga", "parse_gga",
           "MAX_LINE_LENGTH", "HDOP_RANGE", "ALTITUDE_RANGE_M", "GEOID_SEP_RANGE_M",
           "MAX_SATELLITES"]

#: Longest line :class:`NmeaReader` accepts by default, characters including ``$`` and CR LF.
MAX_LINE_LENGTH = 128

#: HDOP :func:`parse_gga` accepts: 0 up to receivers' "no geometry" value 99.99
HDOP_RANGE = (0.0, 99.99)
#: altitude above mean sea level :func:`parse_gga` accepts, metres (deepest open pit to well
#: above any mountain yard)
ALTITUDE_RANGE_M = (-1_000.0, 10_000.0)
#: geoid separation :func:`parse_gga` accepts, metres (the geoid lies within about -107 ..
#: +86 m of the WGS84 ellipsoid)
GEOID_SEP_RANGE_M = (-200.0, 200.0)
#: satellites in use :func:`parse_gga` accepts (the field has two digits)
MAX_SATELLITES = 99

_NS_PER_CS = 10**7  # nanoseconds per centisecond
_MINUTE_DECIMALS = 7
_TALKER_RE = re.compile(r"^[A-Z]{2}$")
_TIME_RE = re.compile(r"^([0-9]{2})([0-9]{2})([0-9]{2}(?:\.[0-9]+)?)$")
_LAT_RE = re.compile(r"^([0-9]{2})([0-9]{2}(?:\.[0-9]+)?)$")
_LON_RE = re.compile(r"^([0-9]{3})([0-9]{2}(?:\.[0-9]+)?)$")
_DECIMAL_RE = re.compile(r"^-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)$")
_INT_RE = re.compile(r"^[0-9]{1,9}$")
_CHECKSUM_RE = re.compile(r"^[0-9A-Fa-f]{2}$")


class NmeaError(ValueError):
    """A sentence is malformed: bad framing or checksum, wrong type, missing or bad fields."""


@dataclass(frozen=True)
class Gga:
    """One GGA fix.

    Attributes
    ----------
    time_of_day_s : float
        UTC time of day, seconds since midnight (NaN if the receiver sent none).
    lat_deg, lon_deg : float
        Latitude and longitude, degrees, north and east positive (NaN when quality is 0 and the
        fields are empty).
    quality : int
        Fix quality 0..8; 0 = no fix (returned as is: the caller decides).
    satellites : int
        Satellites in use.
    hdop : float
        Horizontal dilution of precision (NaN if empty with quality 0).
    altitude_m : float
        Antenna altitude above mean sea level, metres (NaN if empty with quality 0).
    geoid_sep_m : float
        Geoid separation (geoid above ellipsoid), metres; ellipsoidal height =
        altitude_m + geoid_sep_m. NaN if empty.
    talker : str
        Talker id, e.g. ``"GP"`` or ``"GN"``.
    """

    time_of_day_s: float
    lat_deg: float
    lon_deg: float
    quality: int
    satellites: int
    hdop: float
    altitude_m: float
    geoid_sep_m: float
    talker: str = "GP"


def nmea_checksum(body: str) -> str:
    """The NMEA checksum of a sentence body.

    Parameters
    ----------
    body : str
        The characters between ``$`` and ``*`` (exclusive), printable ASCII.

    Returns
    -------
    str
        XOR of the character codes as two uppercase hex digits.
    """
    if not body.isascii():
        raise ValueError("NMEA sentence body must be ASCII")
    if "$" in body or "*" in body:
        raise ValueError("body must exclude the '$' and '*' delimiters")
    cs = 0
    for ch in body.encode("ascii"):
        cs ^= ch
    return f"{cs:02X}"


def _format_angle(angle_deg: float, deg_digits: int) -> str:
    """|angle| as d..dmm.mmmmmmm with exact carry of rounded minutes into degrees."""
    scale = 60 * 10**_MINUTE_DECIMALS
    total = round(abs(angle_deg) * scale)  # units of 1e-7 arc-minute
    deg, rem = divmod(total, scale)
    minutes, frac = divmod(rem, 10**_MINUTE_DECIMALS)
    return f"{deg:0{deg_digits}d}{minutes:02d}.{frac:0{_MINUTE_DECIMALS}d}"


def _format_time(time_ns: int) -> str:
    """UTC nanoseconds -> hhmmss.ss (time of day, truncated to the centisecond)."""
    cs = (time_ns % NS_PER_DAY) // _NS_PER_CS
    s, cs = divmod(cs, 100)
    m, s = divmod(s, 60)
    h, m = divmod(m, 60)
    return f"{h:02d}{m:02d}{s:02d}.{cs:02d}"


def format_gga(time_ns: int, lat_deg: float, lon_deg: float, quality: int, satellites: int,
               hdop: float, altitude_m: float, geoid_sep_m: float = 0.0,
               talker: str = "GP") -> str:
    """Format a GGA sentence.

    Parameters
    ----------
    time_ns : int
        UTC time, nanoseconds since the Unix epoch; only the time of day is sent, truncated to
        the centisecond (leap seconds are ignored).
    lat_deg : float
        Latitude, degrees, -90..90, north positive.
    lon_deg : float
        Longitude, degrees, -180..180, east positive.
    quality : int
        Fix quality 0..8.  With 0 (no fix) and a NaN position, the position fields are
        sent empty, as receivers do.
    satellites : int
        Satellites in use, 0..99.
    hdop : float
        Horizontal dilution of precision, >= 0 (sent with 1 decimal).
    altitude_m : float
        Altitude above mean sea level, metres (sent with 3 decimals).
    geoid_sep_m : float
        Geoid separation, metres (sent with 3 decimals).
    talker : str
        Two uppercase letters, e.g. ``"GP"`` (GPS) or ``"GN"`` (multi-constellation).

    Returns
    -------
    str
        ``$<talker>GGA,...*CS\\r\\n``; positions carry 7 decimals of arc-minutes.
    """
    if not isinstance(time_ns, int) or isinstance(time_ns, bool):
        raise ValueError(f"time_ns must be an int, got {type(time_ns).__name__}")
    if quality == 0 and not all(math.isfinite(v) for v in (lat_deg, lon_deg, altitude_m)):
        # no fix: receivers send the sentence with empty position fields
        if not 0 <= satellites <= 99:
            raise ValueError(f"satellites must be 0..99, got {satellites}")
        if not _TALKER_RE.match(talker):
            raise ValueError(f"talker must be two uppercase letters, got {talker!r}")
        hdop_text = f"{hdop:.1f}" if math.isfinite(hdop) and hdop >= 0 else ""
        body = ",".join([f"{talker}GGA", _format_time(time_ns), "", "", "", "", "0",
                         f"{int(satellites):02d}", hdop_text, "", "M", "", "M", "", ""])
        return f"${body}*{nmea_checksum(body)}\r\n"
    for name, x in (("lat_deg", lat_deg), ("lon_deg", lon_deg), ("hdop", hdop),
                    ("altitude_m", altitude_m), ("geoid_sep_m", geoid_sep_m)):
        if not math.isfinite(x):
            raise ValueError(f"{name} must be finite, got {x}")
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"lat_deg must be in -90..90, got {lat_deg}")
    if not -180.0 <= lon_deg <= 180.0:
        raise ValueError(f"lon_deg must be in -180..180, got {lon_deg}")
    if not 0 <= quality <= 8:
        raise ValueError(f"quality must be 0..8, got {quality}")
    if not 0 <= satellites <= 99:
        raise ValueError(f"satellites must be 0..99, got {satellites}")
    if hdop < 0.0:
        raise ValueError(f"hdop must be >= 0, got {hdop}")
    if not _TALKER_RE.match(talker):
        raise ValueError(f"talker must be two uppercase letters, got {talker!r}")
    body = ",".join([
        f"{talker}GGA",
        _format_time(time_ns),
        _format_angle(lat_deg, 2), "N" if lat_deg >= 0.0 else "S",
        _format_angle(lon_deg, 3), "E" if lon_deg >= 0.0 else "W",
        str(int(quality)),
        f"{int(satellites):02d}",
        f"{hdop:.1f}",
        f"{altitude_m:.3f}", "M",
        f"{geoid_sep_m:.3f}", "M",
        "",  # age of differential corrections
        "",  # differential reference station id
    ])
    return f"${body}*{nmea_checksum(body)}\r\n"


def _split_checked(sentence: str) -> list[str]:
    """Check framing and checksum; return the comma-separated fields of the body."""
    s = sentence.rstrip("\r\n")
    if not s.startswith("$"):
        raise NmeaError(f"sentence must start with '$': {s[:20]!r}")
    star = s.rfind("*")
    if star < 0:
        raise NmeaError(f"sentence has no '*' checksum: {s[:20]!r}")
    body, given = s[1:star], s[star + 1:]
    if not _CHECKSUM_RE.match(given):
        raise NmeaError(f"malformed checksum {given!r}")
    try:
        expected = nmea_checksum(body)
    except ValueError as exc:
        raise NmeaError(str(exc)) from exc
    if given.upper() != expected:
        raise NmeaError(f"bad checksum: sentence has {given}, computed {expected}")
    return body.split(",")


def _parse_float(name: str, text: str, allow_empty: bool,
                 limits: tuple[float, float] | None = None) -> float:
    """A decimal field (plain digits, an optional '-' and '.'; no exponent, underscore or
    space) within ``limits`` (inclusive); NaN if empty and allowed."""
    if text == "":
        if allow_empty:
            return math.nan
        raise NmeaError(f"missing {name}")
    if not _DECIMAL_RE.match(text) or len(text) > 32:
        raise NmeaError(f"bad {name}: {text!r}")
    x = float(text)
    if limits is not None and not limits[0] <= x <= limits[1]:
        raise NmeaError(f"bad {name}: {text!r} outside {limits[0]:g}..{limits[1]:g}")
    return x


def _parse_angle(name: str, text: str, hemi: str, regex: re.Pattern, limit_deg: float,
                 signs: tuple[str, str], allow_empty: bool) -> float:
    """ddmm.mmmm + hemisphere letter -> signed degrees."""
    if text == "" and hemi == "":
        if allow_empty:
            return math.nan
        raise NmeaError(f"missing {name}")
    m = regex.match(text)
    if m is None:
        raise NmeaError(f"bad {name}: {text!r}")
    deg, minutes = int(m.group(1)), float(m.group(2))
    if minutes >= 60.0:
        raise NmeaError(f"bad {name}: minutes {minutes} >= 60")
    value = deg + minutes / 60.0
    if value > limit_deg:
        raise NmeaError(f"bad {name}: {value} deg exceeds {limit_deg}")
    if hemi == signs[0]:
        return value
    if hemi == signs[1]:
        return -value
    raise NmeaError(f"bad {name} hemisphere {hemi!r}")


def _parse_time(text: str, allow_empty: bool) -> float:
    """hhmmss.ss -> seconds since midnight (hh <= 23, mm <= 59, ss.ss < 60)."""
    if text == "":
        if allow_empty:
            return math.nan
        raise NmeaError("missing time")
    m = _TIME_RE.match(text)
    if m is None:
        raise NmeaError(f"bad time: {text!r}")
    h, mi, s = int(m.group(1)), int(m.group(2)), float(m.group(3))
    if h > 23 or mi > 59 or s >= 60.0:   # no leap second 60 (docs/domain.md §5)
        raise NmeaError(f"bad time: {text!r}")
    return h * 3600.0 + mi * 60.0 + s


def _parse_int(name: str, text: str, allow_empty: bool, limit: int | None = None) -> int:
    """A non-negative integer field of plain digits, at most ``limit``; 0 if empty and
    allowed."""
    if text == "" and allow_empty:
        return 0
    if not _INT_RE.match(text):
        raise NmeaError(f"bad {name}: {text!r}")
    value = int(text)
    if limit is not None and value > limit:
        raise NmeaError(f"bad {name}: {text!r} outside 0..{limit}")
    return value


def _check_unit(name: str, value: float, unit: str) -> None:
    """The unit field after a length must be 'M' (or empty when the value is)."""
    if unit != "M" and not (math.isnan(value) and unit == ""):
        raise NmeaError(f"{name} unit must be 'M', got {unit!r}")


def parse_gga(sentence: str) -> Gga:
    """Parse one GGA sentence.

    Parameters
    ----------
    sentence : str
        ``$..GGA,...*CS`` with or without the trailing CR LF; any talker id.

    Returns
    -------
    Gga
        With quality 0 (no fix) empty fields become NaN (satellites 0); with a fix every field
        through the geoid separation is required. The geoid separation may be empty (NaN).

    Raises
    ------
    NmeaError
        On bad framing or checksum, a sentence other than GGA, missing or malformed fields
        (numbers are plain ASCII digits), and values outside physical ranges: time of day
        beyond 23:59:59.99 (no leap second), latitude beyond 90 or longitude beyond 180
        degrees, minutes >= 60, more than :data:`MAX_SATELLITES` satellites, HDOP outside
        :data:`HDOP_RANGE`, altitude outside :data:`ALTITUDE_RANGE_M`, geoid separation
        outside :data:`GEOID_SEP_RANGE_M`.
    """
    fields = _split_checked(sentence)
    kind = fields[0]
    if len(kind) != 5 or not kind.endswith("GGA") or not _TALKER_RE.match(kind[:2]):
        raise NmeaError(f"not a GGA sentence: {kind!r}")
    if len(fields) < 13:
        raise NmeaError(f"GGA needs at least 12 fields after the type, got {len(fields) - 1}")
    (time_f, lat_f, ns_f, lon_f, ew_f, q_f, sats_f, hdop_f, alt_f, alt_u, sep_f,
     sep_u) = fields[1:13]
    quality = _parse_int("quality", q_f, allow_empty=False)
    if quality > 8:
        raise NmeaError(f"bad quality: {quality}")
    no_fix = quality == 0
    altitude_m = _parse_float("altitude", alt_f, no_fix, ALTITUDE_RANGE_M)
    geoid_sep_m = _parse_float("geoid separation", sep_f, True, GEOID_SEP_RANGE_M)
    _check_unit("altitude", altitude_m, alt_u)
    _check_unit("geoid separation", geoid_sep_m, sep_u)
    return Gga(
        time_of_day_s=_parse_time(time_f, no_fix),
        lat_deg=_parse_angle("latitude", lat_f, ns_f, _LAT_RE, 90.0, ("N", "S"), no_fix),
        lon_deg=_parse_angle("longitude", lon_f, ew_f, _LON_RE, 180.0, ("E", "W"), no_fix),
        quality=quality,
        satellites=_parse_int("satellites", sats_f, no_fix, MAX_SATELLITES),
        hdop=_parse_float("hdop", hdop_f, no_fix, HDOP_RANGE),
        altitude_m=altitude_m,
        geoid_sep_m=geoid_sep_m,
        talker=kind[:2],
    )


def _valid_sentence(line: bytes) -> str | None:
    """The line as a str if it is a framed, checksum-valid sentence, else None."""
    try:
        text = line.decode("ascii")
        _split_checked(text)
    except (UnicodeDecodeError, NmeaError):
        return None
    return text


class NmeaReader:
    """Incremental NMEA 0183 line parser: bytes in, checksum-valid sentences out.

    Lines end in LF (an optional CR before it is dropped). A sentence starts at the last ``$``
    of its line (``$`` is reserved and never occurs inside a sentence), so noise before a
    sentence on the same line does not lose it. Sentences of any type are returned; parse them
    with e.g. :func:`parse_gga`. The buffer never holds more than ``max_line_length`` bytes.

    Attributes
    ----------
    sentences : int
        Sentences returned so far.
    checksum_errors : int
        Candidate sentences (``$`` through the end of the line) whose checksum is wrong,
        missing or malformed, or which contain non-ASCII bytes. Their bytes are not counted in
        ``garbage_bytes``.
    garbage_bytes : int
        Bytes discarded for framing: bytes not preceded by a ``$`` on their line, and
        candidates longer than ``max_line_length`` bytes (``$`` through CR LF), e.g. a sentence
        whose line feed was lost.
    """

    def __init__(self, max_line_length: int = MAX_LINE_LENGTH) -> None:
        if max_line_length < 8:
            raise ValueError(f"max_line_length must be >= 8, got {max_line_length}")
        self.max_line_length = max_line_length
        self.sentences = 0
        self.checksum_errors = 0
        self.garbage_bytes = 0
        self._buf = bytearray()  # empty, or a partial candidate starting with b"$"

    @property
    def buffered_bytes(self) -> int:
        """Bytes of an incomplete sentence held back."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[str]:
        """Add bytes from the stream; return the sentences they complete, in order.

        Parameters
        ----------
        data : bytes
            The next bytes of the stream.

        Returns
        -------
        list of str
            Checksum-valid sentences, ``$`` through the checksum, without CR LF.
        """
        out: list[str] = []
        self._buf += data
        buf = self._buf
        pos = 0
        while True:
            lf = buf.find(b"\n", pos)
            if lf < 0:
                break
            self._take_line(bytes(buf[pos:lf + 1]), out)
            pos = lf + 1
        del buf[:pos]
        # keep only a candidate that can still become a sentence
        dollar = buf.rfind(b"$")
        if dollar < 0:
            self.garbage_bytes += len(buf)
            buf.clear()
        else:
            self.garbage_bytes += dollar
            del buf[:dollar]
            if len(buf) > self.max_line_length:
                self.garbage_bytes += len(buf)
                buf.clear()
        return out

    def _take_line(self, line: bytes, out: list[str]) -> None:
        """Classify one complete line (including its LF)."""
        dollar = line.rfind(b"$")
        if dollar < 0:
            self.garbage_bytes += len(line)
            return
        self.garbage_bytes += dollar
        candidate = line[dollar:]
        if len(candidate) > self.max_line_length:
            self.garbage_bytes += len(candidate)
            return
        text = _valid_sentence(candidate.rstrip(b"\r\n"))
        if text is None:
            self.checksum_errors += 1
        else:
            self.sentences += 1
            out.append(text)
