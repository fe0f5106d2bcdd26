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
from typing import Any

from google.protobuf import json_format
from google.protobuf.message import Message

from schemas.events import EVENT_TYPES, Event, Malformed, decode_payload

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


def decode_line(line: str | bytes, *, where: str = "") -> Event | Malformed:
    """Parse one JSON line into an :class:`Event`; anything unreadable becomes :class:`Malformed`.

    The payload is serialised deterministically, so the same body always gives the
    same payload bytes (re-importing a file is a no-op, not a conflict).
    """
    raw = line.encode() if isinstance(line, str) else bytes(line)
    prefix = f"{where}: " if where else ""
    try:
        record = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        return Malformed(raw=raw, reason=f"malformed: {prefix}not JSON ({exc.msg})")
    if not isinstance(record, dict):
        return Malformed(raw=raw, reason=f"malformed: {prefix}a line must be a JSON object")
    type_name = record.get("type")
    source = record.get("source")
    ident = {
        "type": type_name if isinstance(type_name, str) else "",
        "source": source if isinstance(source, str) else "",
    }
    for name in _ENVELOPE_INT_FIELDS:
        value = record.get(name)
        if isinstance(value, int) and not isinstance(value, bool):
            ident[name] = value
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
        return Malformed(raw=raw, reason=f"unknown_type: {prefix}unknown event type {type_name!r}",
                         **ident)
    body = record.get("body", {})
    if not isinstance(body, dict):
        return Malformed(raw=raw, reason=f"malformed: {prefix}body must be a JSON object", **ident)
    try:
        message = json_format.ParseDict(body, EVENT_TYPES[type_name]())
    except (json_format.ParseError, ValueError, TypeError) as exc:
        return Malformed(raw=raw, reason=f"undecodable: {prefix}body is not a {type_name}: {exc}",
                         **ident)
    return Event(
        type=type_name,
        source=source,
        epoch=ident["epoch"],
        seq=ident["seq"],
        valid_time_ns=ident["valid_time_ns"],
        payload=message.SerializeToString(deterministic=True),
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
