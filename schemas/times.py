"""Time in the product: integer UTC nanoseconds, its constants, and parsing and printing it.

- :data:`NS_PER_S`, :data:`NS_PER_MIN`, :data:`NS_PER_H`, :data:`NS_PER_DAY`: the one set of
  time constants every package uses
- :data:`MIN_TIME_NS`, :data:`MAX_TIME_NS`: the representable range (int64 UTC ns,
  1677-09-21 .. 2262-04-11)
- :func:`parse_time_ns`, :func:`format_time_ns`: ISO-8601 or integer UTC nanoseconds, for people
"""

from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone

_ISO = re.compile(
    r"^(?P<date>\d{4}-\d{2}-\d{2})(?:[T ](?P<h>\d{2}):(?P<m>\d{2})(?::(?P<s>\d{2})(?:[.,](?P<frac>\d{1,9}))?)?)?"
    r"(?P<tz>Z|[+-]\d{2}:?\d{2})?$", re.ASCII
)
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)

NS_PER_S = 1_000_000_000
NS_PER_MIN = 60 * NS_PER_S
NS_PER_H = 3600 * NS_PER_S
NS_PER_DAY = 86_400 * NS_PER_S

#: the earliest and latest representable time (UTC ns): the int64 range every store uses
MIN_TIME_NS = -(2**63)
MAX_TIME_NS = 2**63 - 1

#: digits of the longest integer nanoseconds worth converting (int64 has at most 19)
_MAX_INT_DIGITS = 20


def _range_error(text: str) -> ValueError:
    return ValueError(f"time {text!r} is outside the representable range "
                      f"{format_time_ns(MIN_TIME_NS)} .. {format_time_ns(MAX_TIME_NS)} "
                      f"(int64 UTC ns)")


def parse_time_ns(text: str) -> int:
    """``"2026-11-22T03:00:00.5Z"``, ``"2026-11-22"`` or ``"1763780400000000000"`` -> UTC ns.

    A time without a zone is UTC.  Integers are plain ASCII digits with an optional sign.
    Raises ValueError with a clear message otherwise, and for times outside
    :data:`MIN_TIME_NS` .. :data:`MAX_TIME_NS`.
    """
    value = str(text).strip()
    if re.fullmatch(r"[-+]?[0-9]+", value):
        if len(value.lstrip("+-").lstrip("0")) > _MAX_INT_DIGITS:
            raise _range_error(str(text))
        ns = int(value)
        if not MIN_TIME_NS <= ns <= MAX_TIME_NS:
            raise _range_error(str(text))
        return ns
    match = _ISO.match(value)
    if not match:
        raise ValueError(f"not an ISO-8601 time or integer nanoseconds: {text!r}")
    try:
        day = datetime.strptime(match["date"], "%Y-%m-%d").replace(tzinfo=timezone.utc)
    except ValueError:
        raise ValueError(f"not a valid date: {text!r}") from None
    hours, minutes, seconds = int(match["h"] or 0), int(match["m"] or 0), int(match["s"] or 0)
    if hours > 23 or minutes > 59 or seconds > 59:
        raise ValueError(f"not a valid time of day: {text!r}")
    seconds_total = ((day - _EPOCH).days * 86_400 + hours * 3600 + minutes * 60 + seconds)
    tz = match["tz"]
    if tz and tz != "Z":
        sign = 1 if tz[0] == "+" else -1
        digits = tz[1:].replace(":", "")
        seconds_total -= sign * (int(digits[:2]) * 3600 + int(digits[2:]) * 60)
    ns = seconds_total * NS_PER_S
    frac = match["frac"]
    if frac:
        ns += int(frac.ljust(9, "0"))
    if not MIN_TIME_NS <= ns <= MAX_TIME_NS:
        raise _range_error(str(text))
    return ns


def format_time_ns(ns: int | None) -> str:
    """UTC nanoseconds as ISO-8601 with a 'Z' (fraction only when non-zero); ``"-"`` for None.

    Never raises for an int: a time outside the calendar's years 1..9999 is printed as its
    integer nanoseconds (which :func:`parse_time_ns` refuses as outside the range).
    """
    if ns is None:
        return "-"
    ns = int(ns)
    seconds, frac = divmod(ns, NS_PER_S)
    try:
        text = (_EPOCH + timedelta(seconds=seconds)).replace(tzinfo=None).isoformat()
    except OverflowError:
        return str(ns)
    if frac:
        text += "." + f"{frac:09d}".rstrip("0")
    return text + "Z"
