"""Signed events: the site's signing policy, the registry of declared source keys, and the
check the writer (and ``verify``) makes of each signed or must-be-signed event.

The registry is built from the ledger's own ``source_key_declared`` and
``source_key_revoked`` rows, in global order, so it is the same for the writer and for
anyone re-checking the ledger later.  Rules (docs/security.md, "Signed events"):

- a signature, when present, must hold for :func:`schemas.events.signed_message` of the
  event with a declared key, valid at the event's valid time, not revoked from a time at
  or before it, whose role (:data:`security.event_keys.ROLE_TYPES`) may produce the type;
- a type in :attr:`SigningPolicy.signed_types` must be signed (``unsigned`` otherwise);
- key declarations and revocations are always signed by an admin key; the first admin
  key is a self-signed ``admin`` declaration, accepted when its key id is the policy's
  ``admin_key_id`` (or, with no pinned admin key, when no admin key is declared yet).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace

from schemas import pb
from schemas.events import Event, decode_payload, make_event, set_timestamp_ns, signed_message
from schemas.events import timestamp_ns
from security.event_keys import (MONEY_TYPES, ROLE_TYPES, SigningKey, key_id_of,
                                 load_public_key, sign, signature_holds)

KEY_TYPES = frozenset({"source_key_declared", "source_key_revoked"})

#: the source and epoch of the site admin's key declarations and revocations
ADMIN_SOURCE = "site-admin"
ADMIN_EPOCH = 1


@dataclass(frozen=True)
class SigningPolicy:
    """What a site requires: the types that must be signed, and the admin key it trusts
    (the key id of the site admin's public key; None: the first self-declared one)."""

    signed_types: frozenset[str] = frozenset()
    admin_key_id: str | None = None


@dataclass(frozen=True)
class KeyRecord:
    """A declared source key (times in ns, ``revoked_from_ns`` None while trusted)."""

    key_id: str
    public_key: bytes
    role: str
    name: str
    valid_from_ns: int
    valid_until_ns: int
    revoked_from_ns: int | None = None


@dataclass
class KeyRegistry:
    """Declared keys by key id; the writer copies it before a batch changes it."""

    keys: dict[str, KeyRecord] = field(default_factory=dict)

    def copy(self) -> KeyRegistry:
        return KeyRegistry(dict(self.keys))

    def describe(self, key_id: str | None) -> str:
        """``name (role)`` of a key id, for reports."""
        record = self.keys.get(key_id or "")
        return "" if record is None else f"{record.name} ({record.role})"

    def problem(self, type_name: str, source: str, epoch: int, seq: int, valid_time_ns: int,
                payload_sha256: bytes, message, signer: str | None, signature: bytes | None,
                policy: SigningPolicy | None) -> tuple[str, str] | None:
        """``(code, detail)`` when the event may not be stored as it is signed, else None.

        ``message`` is the decoded payload (read for a key declaration)."""
        if signer is None or signature is None:
            if type_name in KEY_TYPES:
                return "unsigned", f"a {type_name} must be signed by an admin key"
            if policy is not None and type_name in policy.signed_types:
                return "unsigned", f"this site requires {type_name} to be signed"
            return None
        record = self.keys.get(signer)
        if record is None and type_name == "source_key_declared" and message.key_id == signer:
            record = self._anchor(message, policy)
            if isinstance(record, tuple):
                return record
        if record is None:
            return "unknown_key", f"key {signer} was never declared by an admin"
        signed = signed_message(type_name, source, epoch, seq, valid_time_ns, payload_sha256)
        if not signature_holds(record.public_key, signature, signed):
            return "bad_signature", f"the signature does not hold for key {signer} ({record.name})"
        if record.revoked_from_ns is not None and valid_time_ns >= record.revoked_from_ns:
            return "revoked_key", (f"key {signer} ({record.name}) is revoked from "
                                   f"{record.revoked_from_ns} ns")
        if not record.valid_from_ns <= valid_time_ns < record.valid_until_ns:
            return "key_not_valid", (f"valid time {valid_time_ns} ns is outside key {signer}'s "
                                     f"period {record.valid_from_ns}..{record.valid_until_ns} ns")
        if type_name not in ROLE_TYPES.get(record.role, frozenset()):
            return "key_role", f"a {record.role} key ({record.name}) may not sign {type_name}"
        return None

    def _anchor(self, message, policy: SigningPolicy | None) -> KeyRecord | tuple[str, str] | None:
        """The record of a self-signed admin declaration, if it may be the trust anchor."""
        if message.role != "admin" or key_id_of(message.public_key) != message.key_id:
            return None
        pinned = None if policy is None else policy.admin_key_id
        if pinned is not None and pinned != message.key_id:
            return "unknown_key", (f"self-declared admin key {message.key_id} is not the "
                                   f"site's admin key {pinned}")
        if pinned is None and any(r.role == "admin" for r in self.keys.values()):
            return "unknown_key", (f"self-declared admin key {message.key_id}: this ledger "
                                   "already has an admin key")
        return _record(message)

    def learn(self, type_name: str, message) -> None:
        """Take in a stored key declaration or revocation."""
        if type_name == "source_key_declared":
            old = self.keys.get(message.key_id)
            revoked = None if old is None else old.revoked_from_ns  # a revocation stays
            self.keys[message.key_id] = replace(_record(message), revoked_from_ns=revoked)
        elif type_name == "source_key_revoked" and message.key_id in self.keys:
            revoked = timestamp_ns(message.time)
            old = self.keys[message.key_id]
            if old.revoked_from_ns is None or revoked < old.revoked_from_ns:
                self.keys[message.key_id] = replace(old, revoked_from_ns=revoked)


def sign_event(event: Event, key: SigningKey) -> Event:
    """``event`` signed by ``key``: its signer and signature set."""
    message = signed_message(event.type, event.source, event.epoch, event.seq,
                             event.valid_time_ns, hashlib.sha256(event.payload).digest())
    return replace(event, signer=key.key_id, signature=sign(key, message))


def key_declaration(admin: SigningKey, public_key: bytes, role: str, name: str, seq: int,
                    time_ns: int, valid_from_ns: int, valid_until_ns: int) -> Event:
    """The admin's signed ``source_key_declared`` event for a raw public key, number
    ``seq`` of the admin's source (times in UTC ns)."""
    m = pb.SourceKeyDeclared(key_id=key_id_of(public_key), public_key=bytes(public_key),
                             role=role, name=name)
    set_timestamp_ns(m.time, time_ns)
    set_timestamp_ns(m.valid_from, valid_from_ns)
    set_timestamp_ns(m.valid_until, valid_until_ns)
    return sign_event(make_event(m, source=ADMIN_SOURCE, epoch=ADMIN_EPOCH, seq=seq), admin)


def key_revocation(admin: SigningKey, key_id: str, seq: int, from_ns: int,
                   reason: str = "") -> Event:
    """The admin's signed ``source_key_revoked`` event: ``key_id`` untrusted from
    ``from_ns`` (UTC ns)."""
    m = pb.SourceKeyRevoked(key_id=key_id, reason=reason)
    set_timestamp_ns(m.time, from_ns)
    return sign_event(make_event(m, source=ADMIN_SOURCE, epoch=ADMIN_EPOCH, seq=seq), admin)


def add_signing_options(parser) -> None:
    """``--admin-key FILE`` and ``--signed-types T,...``: the site's signing policy."""
    parser.add_argument("--admin-key", metavar="FILE",
                        help="the site admin's public signing key (NAME.sign.pub): the trust "
                        "anchor of the source keys declared in the ledger")
    parser.add_argument("--signed-types", metavar="T,...",
                        help="event types that must be signed (default with --admin-key: "
                        f"{','.join(sorted(MONEY_TYPES))}; 'none' for none)")


def policy_from_args(args) -> SigningPolicy | None:
    """The policy of :func:`add_signing_options`' arguments (None when neither is given);
    raises ValueError on an unreadable key."""
    admin_key, types = getattr(args, "admin_key", None), getattr(args, "signed_types", None)
    if admin_key is None and types is None:
        return None
    admin_id = None if admin_key is None else key_id_of(load_public_key(admin_key))
    if types is None:
        signed = MONEY_TYPES
    elif types.strip() in ("", "none"):
        signed = frozenset()
    else:
        signed = frozenset(t.strip() for t in types.split(",") if t.strip())
    return SigningPolicy(signed, admin_id)


def _record(message) -> KeyRecord:
    return KeyRecord(message.key_id, bytes(message.public_key), message.role, message.name,
                     timestamp_ns(message.valid_from), timestamp_ns(message.valid_until))


def registry_from_rows(rows) -> KeyRegistry:
    """The registry of a ledger's stored key rows (``(type, payload)`` pairs in order)."""
    registry = KeyRegistry()
    for type_name, payload in rows:
        registry.learn(type_name, decode_payload(type_name, payload))
    return registry


def signature_block(signer: str | None, signature: bytes | None) -> bytes:
    """What a signed row adds to its chain value (empty for an unsigned row)."""
    if signer is None or signature is None:
        return b""
    key_id = signer.encode("ascii")
    return b"S" + len(key_id).to_bytes(2, "little") + key_id + \
        len(signature).to_bytes(2, "little") + bytes(signature)
