"""Canonical JSON lines: one event per line, for import, export and people.

::

    {"type": ..., "source": ..., "epoch": ..., "seq": ..., "valid_time_ns": ...,
     "recorded_time_ns": ..., "signer": ..., "signature": ..., "body": {...}}

``body`` is the protobuf JSON mapping of the payload.  Field names are emitted as
written in the ``.proto`` (``window_end``); on input camelCase (``windowEnd``) is
accepted too.  ``recorded_time_ns`` is optional on input: when present the ledger
keeps it instead of stamping its own.  A signed event carries its signer's key id and
its signature (base64); the payload is the deterministic serialisation of ``body``, the
bytes producers sign (:func:`schemas.events.make_event`), so a signature survives
export and import.

The encoding is canonical: the same event always gives the same line (keys of
``body`` sorted, no insignificant white space), so ``export -> import -> export``
gives identical lines.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import re
from typing import Any

from google.protobuf import json_format
from google.protobuf.message import Message

from schemas.events import EVENT_TYPES, Event, Malformed, decode_payload
from schemas.json_body import parse_body
from schemas.validate import shown

_ENVELOPE_INT_FIELDS = ("epoch", "seq", "valid_time_ns")


def body_to_dict(message: Message) -> dict[str, Any]:
    """The protobuf JSON mapping of a message, proto field names."""
    return json_format.MessageToDict(message, preserving_proto_field_name=True)


def body_json(message: Message) -> str:
    """Canonical JSON text of a message body (sorted keys, compact)."""
    return json.dumps(body_to_dict(message), sort_keys=True, separators=(",", ":"),
                      ensure_ascii=False)


def encode_line(
    type_name: str,
    source: str,
    epoch: int,
    seq: int,
    valid_time_ns: int,
    payload: bytes,
    recorded_time_ns: int | None = None,
    signer: str | None = None,
    signature: bytes | None = None,
) -> str:
    """One canonical JSON line (without the newline) for an event."""
    body = body_json(decode_payload(type_name, payload))
    head = {"type": type_name, "source": source, "epoch": epoch, "seq": seq,
            "valid_time_ns": valid_time_ns}
    if recorded_time_ns is not None:
        head["recorded_time_ns"] = recorded_time_ns
    if signer is not None and signature is not None:
        head["signer"] = signer
        head["signature"] = base64.b64encode(signature).decode("ascii")
    text = json.dumps(head, separators=(",", ":"), ensure_ascii=False)
    return f'{text[:-1]},"body":{body}}}'


def event_line(event) -> str:
    """:func:`encode_line` of an :class:`Event`, or of anything with its fields (a ledger
    row): recorded time and signature included when it has them."""
    return encode_line(event.type, event.source, event.epoch, event.seq, event.valid_time_ns,
                       event.payload, event.recorded_time_ns, event.signer, event.signature)


def storable_text(text: str) -> str:
    """``text`` with lone surrogates (which no UTF-8 store can hold) written as backslash
    escapes (``\\ud800``); any other text is returned unchanged."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return text


#: a ``\u`` escape of a UTF-16 surrogate: only a line holding one can decode to a lone one
_SURROGATE_ESCAPE = re.compile(rb"\\u[dD][89abcdefABCDEF]")


def _int64(value: object) -> int | None:
    """``value`` if it is an integer in signed 64 bits (what the store holds), else None."""
    if isinstance(value, int) and not isinstance(value, bool) and -(2**63) <= value < 2**63:
        return value
    return None


def decode_line(line: str | bytes, *, where: str = "") -> Event | Malformed:
    """Parse one JSON line into an :class:`Event`; anything unreadable becomes :class:`Malformed`.

    It never raises: bytes that are not UTF-8 (``not_utf8``), a lone surrogate escape
    anywhere (``lone_surrogate``), an integer too long to parse (``too_large``), nesting too
    deep to parse (``too_deep``), a body protobuf refuses (``undecodable``) each become a
    :class:`Malformed` whose reason starts with its code (:data:`schemas.validate.REASON_CODES`).
    Its identity fields are those that were readable; text is made storable
    (:func:`storable_text`) and integers outside signed 64 bits are left out.

    The payload is serialised deterministically, so the same body always gives the
    same payload bytes (re-importing a file is a no-op, not a conflict).
    """
    if isinstance(line, str):
        line = line.encode("utf-8", "surrogatepass")
    raw = bytes(line)
    prefix = f"{storable_text(where)}: " if where else ""
    try:
        return _decode(raw, prefix)
    except RecursionError:
        return Malformed(raw=raw, reason=f"too_deep: {prefix}nested too deeply to decode")
    except Exception as exc:  # noqa: BLE001 - the promise is "never raises"; the reason says what
        return Malformed(raw=raw, reason=f"malformed: {prefix}cannot decode "
                         f"({type(exc).__name__}: {storable_text(str(exc))[:200]})")


def _decode(raw: bytes, prefix: str) -> Event | Malformed:
    try:
        record = json.loads(raw)
    except UnicodeDecodeError as exc:
        return Malformed(raw=raw, reason=f"not_utf8: {prefix}byte 0x{raw[exc.start]:02x} at "
                         f"offset {exc.start} is not UTF-8 ({exc.reason})")
    except json.JSONDecodeError as exc:
        return Malformed(raw=raw, reason=f"malformed: {prefix}not JSON ({exc.msg} at offset "
                         f"{exc.pos})")
    except RecursionError:
        return Malformed(raw=raw, reason=f"too_deep: {prefix}JSON nested too deeply to parse")
    except ValueError as exc:  # an integer longer than sys.get_int_max_str_digits()
        return Malformed(raw=raw, reason=f"too_large: {prefix}{storable_text(str(exc))[:200]}")
    if not isinstance(record, dict):
        return Malformed(raw=raw, reason=f"malformed: {prefix}a line must be a JSON object")
    type_name = record.get("type")
    source = record.get("source")
    ident: dict[str, Any] = {
        "type": storable_text(type_name) if isinstance(type_name, str) else "",
        "source": storable_text(source) if isinstance(source, str) else "",
    }
    for name in _ENVELOPE_INT_FIELDS:
        value = _int64(record.get(name))
        if value is not None:
            ident[name] = value
    if _SURROGATE_ESCAPE.search(raw):
        try:
            json.dumps(record, ensure_ascii=False).encode("utf-8")
        except UnicodeEncodeError as exc:
            return Malformed(raw=raw, reason=f"lone_surrogate: {prefix}"
                             f"{exc.object[exc.start]!r} (half a surrogate pair) in the line",
                             **ident)
    too_big = [n for n in (*_ENVELOPE_INT_FIELDS, "recorded_time_ns")
               if isinstance(record.get(n), int) and not isinstance(record.get(n), bool)
               and _int64(record.get(n)) is None]
    if too_big:
        return Malformed(raw=raw, reason=f"bad_identity: {prefix}{', '.join(too_big)} outside "
                         "signed 64 bits", **ident)
    missing = [n for n in ("type", "source", *_ENVELOPE_INT_FIELDS) if n not in ident]
    if missing or not ident["type"] or not ident["source"]:
        missing = missing or [n for n in ("type", "source") if not ident[n]]
        return Malformed(raw=raw, reason=f"malformed: {prefix}missing or non-integer {', '.join(missing)}",
                         **ident)
    recorded = record.get("recorded_time_ns")
    if recorded is not None and (not isinstance(recorded, int) or isinstance(recorded, bool)):
        return Malformed(raw=raw, reason=f"malformed: {prefix}recorded_time_ns must be an integer",
                         **ident)
    signer, signature = record.get("signer"), record.get("signature")
    if signer is not None or signature is not None:
        try:
            if not isinstance(signer, str) or not isinstance(signature, str):
                raise ValueError("signer and signature must both be strings")
            signature = base64.b64decode(signature, validate=True)
        except (ValueError, binascii.Error) as exc:
            return Malformed(raw=raw, reason=f"malformed: {prefix}bad signature ({exc})", **ident)
    if type_name not in EVENT_TYPES:
        return Malformed(raw=raw, reason=f"unknown_type: {prefix}unknown event type "
                         f"{shown(ident['type'])}", **ident)
    body = record.get("body", {})
    if not isinstance(body, dict):
        return Malformed(raw=raw, reason=f"malformed: {prefix}body must be a JSON object", **ident)
    try:
        cls = EVENT_TYPES[type_name]
        message = parse_body(body, cls)
        if message is None:     # a shape the fast path leaves to json_format
            message = json_format.ParseDict(body, cls())
        payload = message.SerializeToString(deterministic=True)
    except RecursionError:
        return Malformed(raw=raw, reason=f"too_deep: {prefix}body nested too deeply", **ident)
    except Exception as exc:  # noqa: BLE001 - protobuf raises ParseError, ValueError, SystemError...
        return Malformed(raw=raw, reason=f"undecodable: {prefix}body is not a {type_name}: "
                         f"{storable_text(str(exc))[:300]}", **ident)
    return Event(
        type=type_name,
        source=source,
        epoch=ident["epoch"],
        seq=ident["seq"],
        valid_time_ns=ident["valid_time_ns"],
        payload=payload,
        recorded_time_ns=recorded,
        signer=signer,
        signature=signature,
    )


def json_safe(value):
    """NaN and inf -> None, tuples -> lists, keys -> str, recursively (strict JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value
