"""Time in the product: integer UTC nanoseconds, its constants, and parsing and printing it.

- :data:`NS_PER_S`, :data:`NS_PER_MIN`, :data:`NS_PER_H`, :data:`NS_PER_DAY`: the one set of
  time constants every package uses
- :func:`parse_time_ns`, :func:`format_time_ns`: ISO-8601 or integer UTC nanoseconds, for people
"""

from __future__ import annotations

import re
from datetime import datetime, timedelta, timezone

_ISO = re.compile(
    r"^(?P<date>\d{4}-\d{2}-\d{2})(?:[T ](?P<h>\d{2}):(?P<m>\d{2})(?::(?P<s>\d{2})(?:[.,](?P<frac>\d{1,9}))?)?)?"
    r"(?P<tz>Z|[+-]\d{2}:?\d{2})?$"
)
_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)

NS_PER_S = 1_000_000_000
NS_PER_MIN = 60 * NS_PER_S
NS_PER_H = 3600 * NS_PER_S
NS_PER_DAY = 86_400 * NS_PER_S


def parse_time_ns(text: str) -> int:
    """``"2026-11-22T03:00:00.5Z"``, ``"2026-11-22"`` or ``"1763780400000000000"`` -> UTC ns.

    A time without a zone is UTC.  Raises ValueError with a clear message otherwise.
    """
    value = str(text).strip()
    if re.fullmatch(r"-?\d+", value):
        return int(value)
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
    whole = day + timedelta(hours=hours, minutes=minutes, seconds=seconds)
    tz = match["tz"]
    if tz and tz != "Z":
        sign = 1 if tz[0] == "+" else -1
        digits = tz[1:].replace(":", "")
        whole -= sign * timedelta(hours=int(digits[:2]), minutes=int(digits[2:]))
    delta = whole - _EPOCH
    ns = (delta.days * 86_400 + delta.seconds) * NS_PER_S
    frac = match["frac"]
    if frac:
        ns += int(frac.ljust(9, "0"))
    return ns


def format_time_ns(ns: int | None) -> str:
    """UTC nanoseconds as ISO-8601 with a 'Z' (fraction only when non-zero)."""
    if ns is None:
        return "-"
    seconds, frac = divmod(int(ns), NS_PER_S)
    text = (_EPOCH + timedelta(seconds=seconds)).strftime("%Y-%m-%dT%H:%M:%S")
    if frac:
        text += "." + f"{frac:09d}".rstrip("0")
    return text + "Z"
