"""Time and number cells of a laboratory's export (``services.lims_map``): ISO 8601 or
strptime times to UTC ns, and numbers with either decimal mark to :class:`~decimal.Decimal`.
Pure functions; ValueError with a one-line reason on a bad cell.
"""

from __future__ import annotations

import re
from calendar import timegm
from datetime import datetime, timedelta, timezone
from decimal import Decimal, InvalidOperation
from typing import Any

from schemas.times import MAX_TIME_NS, MIN_TIME_NS, NS_PER_S

__all__ = ["ISO8601", "parse_time_ns", "parse_number"]

#: The time format name for ISO 8601 (``2026-11-22T14:03:00.5+08:00``, ``T`` or a space,
#: up to nanoseconds, offset optional).
ISO8601 = "iso8601"

_ISO_RE = re.compile(
    r"(\d{4})-(\d{2})-(\d{2})[T ](\d{2}):(\d{2})(?::(\d{2})(?:[.,](\d{1,9}))?)?"
    r"\s*(Z|[+-]\d{2}(?::?\d{2})?)?", re.IGNORECASE)
_NUMBER_RE = {".": re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?"),
              ",": re.compile(r"[+-]?(\d+(,\d*)?|,\d+)([eE][+-]?\d+)?")}

def _utc_ns(moment: datetime, frac_ns: int) -> int:
    """UTC ns of an aware datetime (whole seconds) plus ``frac_ns``."""
    return timegm(moment.utctimetuple()) * NS_PER_S + frac_ns


def parse_time_ns(text: str, time_format: str, tz) -> int:
    """A time cell -> UTC ns.

    ``time_format`` is :data:`ISO8601` (fraction up to nanoseconds, offset or ``Z``
    optional) or a strptime format (microseconds at most, ``%z`` optional); a time without
    an offset is local time in ``tz`` (an ambiguous local time takes its first occurrence).
    Raises ValueError with a one-line reason.
    """
    value = text.strip()
    if time_format == ISO8601:
        m = _ISO_RE.fullmatch(value)
        if not m:
            raise ValueError(f"time {value!r} is not ISO 8601")
        year, month, day, hour, minute = (int(m.group(i)) for i in range(1, 6))
        second = int(m.group(6) or 0)
        frac_ns = int((m.group(7) or "").ljust(9, "0") or 0)
        offset = m.group(8)
        try:
            moment = datetime(year, month, day, hour, minute, second)
        except ValueError as exc:
            raise ValueError(f"time {value!r}: {exc}") from None
        if offset is None:
            moment = moment.replace(tzinfo=tz)
        elif offset.upper() == "Z":
            moment = moment.replace(tzinfo=timezone.utc)
        else:
            digits = offset[1:].replace(":", "")
            delta = timedelta(hours=int(digits[:2]), minutes=int(digits[2:] or 0))
            moment = moment.replace(tzinfo=timezone(delta if offset[0] == "+" else -delta))
    else:
        try:
            moment = datetime.strptime(value, time_format)
        except ValueError:
            raise ValueError(f"time {value!r} does not match {time_format!r}") from None
        frac_ns = moment.microsecond * 1000
        moment = moment.replace(microsecond=0)
        if moment.tzinfo is None:
            moment = moment.replace(tzinfo=tz)
    ns = _utc_ns(moment, frac_ns)
    if not MIN_TIME_NS <= ns <= MAX_TIME_NS:
        raise ValueError(f"time {value!r} is out of range")
    return ns


def parse_number(value: Any, decimal: str) -> Decimal:
    """A number cell -> Decimal: text with ``decimal`` as the decimal mark, or a JSON number.

    Raises ValueError (empty, text that is not a plain number such as ``<0.01``, a boolean).
    """
    if isinstance(value, bool) or value is None:
        raise ValueError(f"{value!r} is not a number")
    if isinstance(value, (int, Decimal)):
        number = Decimal(value)
    else:
        text = str(value).strip()
        if not _NUMBER_RE[decimal].fullmatch(text):
            raise ValueError(f"{text!r} is not a number" if text else "empty")
        try:
            number = Decimal(text.replace(",", "."))
        except InvalidOperation:
            raise ValueError(f"{text!r} is not a number") from None
    if not number.is_finite():
        raise ValueError(f"{value!r} is not a finite number")
    return number
