"""Event schemas of stockpile-ledger: the bottom layer, imported by every other package.

Nothing here does I/O (except :mod:`schemas.generate`, the code generator).

- :mod:`schemas.stockpile.v1.events_pb2`: generated from ``schemas/proto`` (the source of truth)
- :mod:`schemas.events`: event types, the identity envelope, Zenoh keys and attachments
- :mod:`schemas.validate`: checks applied at the ledger boundary
- :mod:`schemas.jsonl`: canonical JSON lines
- :mod:`schemas.times`: the time constants (``NS_PER_S`` ...) and ISO-8601 <-> UTC ns
- :mod:`schemas.generate`: regenerates ``events_pb2`` with protoc (``make schemas``)
"""

from schemas.events import (
    EVENT_TYPES,
    SENSOR_TYPES,
    Event,
    Malformed,
    UnknownEventType,
    decode_attachment,
    decode_payload,
    encode_attachment,
    event_from_sample,
    key_expr,
    make_event,
    message_class,
    parse_key_expr,
    payload_valid_time_ns,
    set_timestamp_ns,
    site_key_expr,
    timestamp_ns,
    type_of_message,
)
from schemas.stockpile.v1 import events_pb2 as pb

__all__ = [
    "EVENT_TYPES",
    "SENSOR_TYPES",
    "Event",
    "Malformed",
    "UnknownEventType",
    "decode_attachment",
    "decode_payload",
    "encode_attachment",
    "event_from_sample",
    "key_expr",
    "make_event",
    "message_class",
    "parse_key_expr",
    "payload_valid_time_ns",
    "pb",
    "set_timestamp_ns",
    "site_key_expr",
    "timestamp_ns",
    "type_of_message",
]
