"""Event types, the identity envelope, and how both travel on Zenoh.

Every event in the product is a protobuf payload plus an identity that travels
*outside* the payload, so Foxglove's well-known messages stay pure:

========================  ==========================================================
type                      snake_case name of the message (``scan``, ``assay`` ...)
source                    the producer, e.g. ``bwr1.scanner``
epoch                     integer chosen when the producer starts (never reused)
seq                       dense per (source, epoch), starting at 0
valid_time_ns             when it happened in the yard, UTC ns; equals the payload's
                          own timestamp (see :func:`payload_valid_time_ns`)
========================  ==========================================================

On Zenoh the key expression is ``stockpile/<site>/@v1/<type>/<source>`` and
``(epoch, seq, valid_time_ns)`` ride in the sample attachment
(:func:`encode_attachment`).  The ledger's idempotency key is ``(source, epoch, seq)``.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from google.protobuf.message import Message
from google.protobuf.timestamp_pb2 import Timestamp

from schemas.stockpile.v1 import events_pb2 as pb
from schemas.times import NS_PER_S

#: event type name -> protobuf message class.  Order is the documentation order.
EVENT_TYPES: dict[str, type[Message]] = {
    "scan": LaserScan,
    "location_fix": LocationFix,
    "frame_transform": FrameTransform,
    "joint_reading": pb.JointReading,
    "joint_estimate": pb.JointEstimate,
    "site_declared": pb.SiteDeclared,
    "pile_declared": pb.PileDeclared,
    "machine_declared": pb.MachineDeclared,
    "lot_declared": pb.LotDeclared,
    "stack_started": pb.StackStarted,
    "stack_ended": pb.StackEnded,
    "reclaim_cut": pb.ReclaimCut,
    "assay": pb.Assay,
    "clock": pb.Clock,
    "source_key_declared": pb.SourceKeyDeclared,
    "source_key_revoked": pb.SourceKeyRevoked,
    "survey": pb.Survey,
}

#: High-rate sensor streams; everything else is a low-rate domain event.
SENSOR_TYPES: frozenset[str] = frozenset(
    {"scan", "location_fix", "frame_transform", "joint_reading", "joint_estimate"}
)

#: Name of the payload field that holds each type's valid time.
VALID_TIME_FIELD: dict[str, str] = {
    name: ("timestamp" if name in ("scan", "location_fix", "frame_transform") else "time")
    for name in EVENT_TYPES
}
VALID_TIME_FIELD["reclaim_cut"] = "end_time"
VALID_TIME_FIELD["assay"] = "window_end"

KEY_PREFIX = "stockpile"
SCHEMA_VERSION = "@v1"

#: Largest epoch or sequence number (they are stored as signed 64-bit integers).
MAX_COUNTER = 2**63 - 1

_SOURCE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_SITE_RE = _SOURCE_RE


@dataclass(frozen=True, slots=True)
class Event:
    """One event as produced: identity, valid time and protobuf payload bytes.

    ``recorded_time_ns`` is normally ``None``: the ledger stamps recorded time from
    its site clock.  Imports that preserve history (JSON lines with
    ``recorded_time_ns``, MCAP ``log_time``) set it.
    """

    type: str
    source: str
    epoch: int
    seq: int
    valid_time_ns: int
    payload: bytes
    recorded_time_ns: int | None = None
    signer: str | None = None  # key id of the producer's signing key, when signed
    signature: bytes | None = None  # Ed25519 over signed_message(...), 64 bytes

    @property
    def key(self) -> tuple[str, int, int]:
        """The idempotency key ``(source, epoch, seq)``."""
        return (self.source, self.epoch, self.seq)


@dataclass(frozen=True, slots=True)
class Malformed:
    """Input that could not even be made into an :class:`Event` (bad JSON, bad body).

    It still goes to the ledger, which quarantines it with ``reason`` and ``raw``,
    so nothing that arrived is lost.  Identity fields are filled where they were
    readable.
    """

    raw: bytes
    reason: str
    type: str = ""
    source: str = ""
    epoch: int | None = None
    seq: int | None = None
    valid_time_ns: int | None = None


class UnknownEventType(ValueError):
    """An event type name that is not in :data:`EVENT_TYPES`."""


def message_class(type_name: str) -> type[Message]:
    """The protobuf class of an event type; raises :class:`UnknownEventType`."""
    try:
        return EVENT_TYPES[type_name]
    except KeyError:
        raise UnknownEventType(f"unknown event type {type_name!r}") from None


def type_of_message(message: Message) -> str:
    """The event type name of a protobuf message instance."""
    full_name = message.DESCRIPTOR.full_name
    for name, cls in EVENT_TYPES.items():
        if cls.DESCRIPTOR.full_name == full_name:
            return name
    raise UnknownEventType(f"{full_name} is not an event message")


def timestamp_ns(ts: Timestamp) -> int:
    """A protobuf Timestamp as integer UTC nanoseconds."""
    return ts.seconds * NS_PER_S + ts.nanos


def set_timestamp_ns(ts: Timestamp, time_ns: int) -> None:
    """Set a protobuf Timestamp from integer UTC nanoseconds (floor semantics)."""
    seconds, nanos = divmod(int(time_ns), NS_PER_S)
    ts.seconds = seconds
    ts.nanos = nanos


def payload_valid_time_ns(type_name: str, message: Message) -> int:
    """The valid time a payload carries itself, in UTC ns."""
    return timestamp_ns(getattr(message, VALID_TIME_FIELD[type_name]))


def make_event(
    message: Message,
    *,
    source: str,
    epoch: int,
    seq: int,
    recorded_time_ns: int | None = None,
    deterministic: bool = True,
) -> Event:
    """Wrap a protobuf message in an :class:`Event`, taking type and valid time from it."""
    type_name = type_of_message(message)
    return Event(
        type=type_name,
        source=source,
        epoch=epoch,
        seq=seq,
        valid_time_ns=payload_valid_time_ns(type_name, message),
        payload=message.SerializeToString(deterministic=deterministic),
        recorded_time_ns=recorded_time_ns,
    )


def decode_payload(type_name: str, payload: bytes) -> Message:
    """Parse payload bytes into the message of ``type_name`` (may raise DecodeError)."""
    return message_class(type_name).FromString(payload)


def is_valid_source(source: str) -> bool:
    """Sources are 1-128 chars of ``[A-Za-z0-9._-]``, starting alphanumeric."""
    return bool(_SOURCE_RE.match(source))


# --- Zenoh key expressions and attachments -------------------------------------------


def key_expr(site: str, type_name: str, source: str) -> str:
    """``stockpile/<site>/@v1/<type>/<source>``; raises ValueError on bad parts."""
    if not _SITE_RE.match(site):
        raise ValueError(f"bad site id {site!r}")
    message_class(type_name)
    if not is_valid_source(source):
        raise ValueError(f"bad source {source!r}")
    return f"{KEY_PREFIX}/{site}/{SCHEMA_VERSION}/{type_name}/{source}"


def site_key_expr(site: str) -> str:
    """The key expression covering every event of a site."""
    return f"{KEY_PREFIX}/{site}/{SCHEMA_VERSION}/**"


def parse_key_expr(key: str) -> tuple[str, str, str]:
    """Split a key expression into ``(site, type, source)``; raises ValueError."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != KEY_PREFIX or parts[2] != SCHEMA_VERSION:
        raise ValueError(f"not a stockpile event key: {key!r}")
    return parts[1], parts[3], parts[4]


# version byte, epoch u64, seq u64, valid_time_ns i64; little-endian.  Version 2 (a
# signed event) goes on with the signer's key id (u8 length, ASCII) and the signature
# (u8 length, bytes).
_ATTACHMENT = struct.Struct("<BQQq")
_ATTACHMENT_VERSION = 1
_SIGNED_ATTACHMENT_VERSION = 2


def encode_attachment(epoch: int, seq: int, valid_time_ns: int, signer: str | None = None,
                      signature: bytes | None = None) -> bytes:
    """Identity and valid time as the Zenoh sample attachment: 25 bytes, or with the
    signer's key id and signature after them when the event is signed."""
    if signer is None or signature is None:
        return _ATTACHMENT.pack(_ATTACHMENT_VERSION, epoch, seq, valid_time_ns)
    key_id = signer.encode("ascii")
    if len(key_id) > 255 or len(signature) > 255:
        raise ValueError("signer key id and signature must be at most 255 bytes each")
    return (_ATTACHMENT.pack(_SIGNED_ATTACHMENT_VERSION, epoch, seq, valid_time_ns)
            + bytes([len(key_id)]) + key_id + bytes([len(signature)]) + signature)


def decode_signed_attachment(data: bytes) -> tuple[int, int, int, str | None, bytes | None]:
    """Inverse of :func:`encode_attachment`: ``(epoch, seq, valid_time_ns, signer,
    signature)``, the last two None for an unsigned event; raises ValueError."""
    if len(data) < _ATTACHMENT.size:
        raise ValueError(f"attachment is {len(data)} bytes, expected {_ATTACHMENT.size}")
    version, epoch, seq, valid_time_ns = _ATTACHMENT.unpack_from(data)
    if version == _ATTACHMENT_VERSION:
        if len(data) != _ATTACHMENT.size:
            raise ValueError(f"attachment is {len(data)} bytes, expected {_ATTACHMENT.size}")
        return epoch, seq, valid_time_ns, None, None
    if version != _SIGNED_ATTACHMENT_VERSION:
        raise ValueError(f"attachment version {version} is not supported")
    pos = _ATTACHMENT.size
    parts = []
    for _ in range(2):
        if pos >= len(data) or pos + 1 + data[pos] > len(data):
            raise ValueError("signed attachment is cut short")
        parts.append(bytes(data[pos + 1:pos + 1 + data[pos]]))
        pos += 1 + data[pos]
    if pos != len(data):
        raise ValueError(f"signed attachment has {len(data) - pos} bytes too many")
    try:
        signer = parts[0].decode("ascii")
    except UnicodeDecodeError:
        raise ValueError("signer key id is not ASCII") from None
    return epoch, seq, valid_time_ns, signer, parts[1]


def decode_attachment(data: bytes) -> tuple[int, int, int]:
    """``(epoch, seq, valid_time_ns)`` of an attachment, signed or not."""
    return decode_signed_attachment(data)[:3]


def event_from_sample(key: str, payload: bytes, attachment: bytes | None) -> Event | Malformed:
    """Build an event from a Zenoh sample's key, payload and attachment.

    Anything unreadable becomes :class:`Malformed` (never an exception), so the
    ledger can quarantine it.
    """
    try:
        _site, type_name, source = parse_key_expr(key)
    except ValueError as exc:
        return Malformed(raw=bytes(payload), reason=f"bad_key: {exc}")
    if attachment is None:
        return Malformed(raw=bytes(payload), reason="bad_attachment: missing",
                         type=type_name, source=source)
    try:
        epoch, seq, valid_time_ns, signer, signature = decode_signed_attachment(bytes(attachment))
    except (ValueError, struct.error) as exc:
        return Malformed(raw=bytes(payload), reason=f"bad_attachment: {exc}",
                         type=type_name, source=source)
    return Event(type_name, source, epoch, seq, valid_time_ns, bytes(payload), None,
                 signer, signature)


def signed_message(type_name: str, source: str, epoch: int, seq: int, valid_time_ns: int,
                   payload_sha256: bytes) -> bytes:
    """The bytes a producer signs: the event's identity, valid time and payload hash, so
    a signature cannot be moved to another event."""
    names = b"\0".join(t.encode("utf-8", "surrogatepass") for t in (type_name, source))
    return (b"stockpile-event-v1\0" + names + b"\0"
            + struct.pack("<qqq", epoch, seq, valid_time_ns) + payload_sha256)

