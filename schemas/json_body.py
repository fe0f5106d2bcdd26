"""A JSON line's body decoded without ``json_format`` for the high-rate sensor types.

``google.protobuf.json_format.ParseDict`` walks a body value by value in Python and
parses every timestamp with ``strptime``; for a scan of 401 ranges that is most of what
importing a line costs.  :func:`parse_body` fills the message straight from the body
for the shapes those types have (doubles, lists of doubles, ASCII strings, nested
messages, RFC 3339 timestamps in UTC), and gives up on anything else.

The rule it keeps: whenever it returns a message, ``ParseDict`` would have returned
one that serialises to the same bytes; whenever ``ParseDict`` would refuse the body, it
returns None.  The caller then runs ``ParseDict``, which gives the message or the error,
so a body decodes to the same payload, or the same refusal, on either path
(``tests/test_json_body.py`` checks both against ``ParseDict``).
"""

from __future__ import annotations

import datetime
import math
import re
from functools import lru_cache

from google.protobuf.descriptor import Descriptor, FieldDescriptor
from google.protobuf.message import Message

#: what each field of a message is, for the fill: a double, a list of doubles, a string,
#: a timestamp, or a nested message (with its own plan)
_DOUBLE, _DOUBLES, _STRING, _TIMESTAMP, _MESSAGE = range(5)

Plan = dict[str, tuple[int, "Plan | None"]]

_TIMESTAMP_NAME = "google.protobuf.Timestamp"
# the UTC form MessageToDict writes; other forms (offsets, other digit counts) go to ParseDict
_UTC_TIME = re.compile(r"(\d{4})-(\d\d)-(\d\d)T(\d\d):(\d\d):([0-5]\d)(?:\.(\d{1,9}))?Z")
_EPOCH = datetime.datetime(1970, 1, 1)
_SECONDS_PER_DAY = 86_400


class _NotTaken(Exception):
    """The body has a shape :func:`parse_body` leaves to ``ParseDict``."""


def parse_body(body: dict, cls: type[Message]) -> Message | None:
    """``cls`` filled from the JSON object ``body``, or None where ``ParseDict`` must decide.

    Returns None for a type outside the shapes above (oneofs, enums, integers, bytes,
    maps, repeated messages) and for any value other than a finite JSON number or a
    numeric string for a double, a list of those for a repeated double, an ASCII string
    for a string, an object for a message and ``YYYY-MM-DDTHH:MM:SS[.f{1,9}]Z`` for a
    timestamp.
    """
    plan = _plan(cls.DESCRIPTOR)
    if plan is None:
        return None
    message = cls()
    try:
        _fill(message, body, plan)
    except Exception:  # noqa: BLE001 - any refusal is ParseDict's to word
        return None
    return message


@lru_cache(maxsize=None)
def _plan(descriptor: Descriptor) -> Plan | None:
    """Each field's kind by its proto name; None when a field has a kind not taken."""
    if descriptor.oneofs:
        return None
    plan: Plan = {}
    for field in descriptor.fields:
        repeated = field.is_repeated
        if field.type == FieldDescriptor.TYPE_DOUBLE:
            plan[field.name] = (_DOUBLES if repeated else _DOUBLE, None)
        elif field.type == FieldDescriptor.TYPE_STRING and not repeated:
            plan[field.name] = (_STRING, None)
        elif field.type == FieldDescriptor.TYPE_MESSAGE and not repeated:
            if field.message_type.full_name == _TIMESTAMP_NAME:
                plan[field.name] = (_TIMESTAMP, None)
            else:
                sub = _plan(field.message_type)
                if sub is None:
                    return None
                plan[field.name] = (_MESSAGE, sub)
        else:
            return None
    return plan


def _fill(message: Message, body: dict, plan: Plan) -> None:
    if type(body) is not dict:
        raise _NotTaken
    for name, value in body.items():
        kind, sub = plan[name]              # KeyError: a json_name or unknown key
        if kind == _DOUBLE:
            setattr(message, name, _double(value))
        elif kind == _DOUBLES:
            getattr(message, name).extend(_doubles(value))
        elif kind == _STRING:
            if type(value) is not str or not value.isascii():
                raise _NotTaken
            setattr(message, name, value)
        elif kind == _TIMESTAMP:
            seconds, nanos = _utc_time(value)
            stamp = getattr(message, name)
            stamp.SetInParent()
            stamp.seconds, stamp.nanos = seconds, nanos
        else:
            nested = getattr(message, name)
            nested.SetInParent()
            _fill(nested, value, sub)


def _double(value) -> float:
    """A double as ParseDict reads it: a finite JSON number, or a numeric string."""
    if type(value) is float:
        if value - value == 0.0:            # finite (inf - inf and nan - nan are nan)
            return value
        raise _NotTaken                     # ParseDict refuses a bare NaN or Infinity
    if type(value) is str and value != "nan":
        return float(value)                 # ParseDict's float(); "nan" it refuses
    raise _NotTaken


def _doubles(values) -> list[float]:
    """A repeated double's list, each item as :func:`_double` reads it."""
    if type(values) is not list or not set(map(type, values)) <= {float, str}:
        raise _NotTaken
    floats = list(map(float, values))
    if not all(map(math.isfinite, floats)):     # a NaN or an infinity: from where?
        for value, number in zip(values, floats):
            if number - number != 0.0 and (type(value) is not str or value == "nan"):
                raise _NotTaken
    return floats


def _utc_time(value) -> tuple[int, int]:
    """(seconds, nanos) of a UTC RFC 3339 string, computed as Timestamp.FromJsonString
    computes them."""
    found = _UTC_TIME.fullmatch(value) if type(value) is str else None
    if found is None:
        raise _NotTaken
    year, month, day, hour, minute, second, fraction = found.groups()
    elapsed = datetime.datetime(int(year), int(month), int(day), int(hour), int(minute),
                                int(second)) - _EPOCH
    nanos = round(float("0." + fraction) * 1e9) if fraction else 0
    return elapsed.days * _SECONDS_PER_DAY + elapsed.seconds, nanos
