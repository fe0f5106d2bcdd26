"""Ed25519 keys that producers sign events with, and the roles that may sign each type.

A link certificate (:mod:`security.pki`) proves who is on the other end of one hop; an
event signature proves who wrote the event, through any relay, MCAP file or import.
Each producer of the events that move money holds a signing key; the site admin
declares its public key in the ledger (a ``source_key_declared`` event) with a role and
a validity period.  The key id is the first 32 hex digits of sha256 of the raw public
key.  Private keys are written 0600 and never printed or logged.

- :func:`new_signing_key` writes ``NAME.sign.key`` (PKCS#8 PEM, 0600) and
  ``NAME.sign.pub`` (the raw public key as hex) and returns the key id;
- :func:`load_signing_key` / :func:`load_public_key` read them back;
- :func:`sign` / :func:`signature_holds` sign and check a message.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

#: The event types each role may sign.  ``admin`` declares and revokes keys and the
#: site's configuration; a type not listed for a role is refused (``key_role``).
ROLE_TYPES: dict[str, frozenset[str]] = {
    "admin": frozenset({"source_key_declared", "source_key_revoked", "site_declared",
                        "pile_declared", "machine_declared", "lot_declared"}),
    "lab": frozenset({"assay", "lot_declared"}),
    "plc": frozenset({"stack_started", "stack_ended", "reclaim_cut", "joint_reading",
                      "lot_declared"}),
    "scanner": frozenset({"scan"}),
    "gnss": frozenset({"location_fix"}),
    "localizer": frozenset({"frame_transform", "joint_estimate"}),
}

#: The types a site signs by default (the events that move money).
MONEY_TYPES: frozenset[str] = frozenset({
    "assay", "lot_declared", "stack_started", "stack_ended", "reclaim_cut",
    "site_declared", "pile_declared", "machine_declared"})

_PUBLIC_KEY_BYTES = 32


@dataclass(frozen=True)
class SigningKey:
    """A producer's private key and its key id (the key never appears in ``repr``)."""

    key_id: str
    private: Ed25519PrivateKey

    def __repr__(self) -> str:
        return f"SigningKey(key_id={self.key_id!r})"

    @property
    def public_raw(self) -> bytes:
        return public_raw(self.private.public_key())


def public_raw(public: Ed25519PublicKey) -> bytes:
    """The 32 raw bytes of a public key."""
    return public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)


def key_id_of(public_key: bytes) -> str:
    """The key id of a raw public key: the first 32 hex digits of its sha256."""
    return hashlib.sha256(bytes(public_key)).hexdigest()[:32]


def new_signing_key(directory: str | Path, name: str) -> str:
    """Make a key pair: ``NAME.sign.key`` (0600) and ``NAME.sign.pub`` in ``directory``;
    return the key id.  Refuses to overwrite an existing key."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    key_path, pub_path = directory / f"{name}.sign.key", directory / f"{name}.sign.pub"
    if key_path.exists():
        raise FileExistsError(f"{key_path} exists: a signing key is never overwritten")
    private = Ed25519PrivateKey.generate()
    pem = private.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(pem)
    raw = public_raw(private.public_key())
    pub_path.write_text(raw.hex() + "\n")
    return key_id_of(raw)


def load_signing_key(path: str | Path) -> SigningKey:
    """A signing key from its PEM file; raises ValueError when it is not Ed25519."""
    try:
        private = serialization.load_pem_private_key(Path(path).read_bytes(), password=None)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: not a PEM private key ({exc})") from None
    if not isinstance(private, Ed25519PrivateKey):
        raise ValueError(f"{path}: not an Ed25519 signing key")
    return SigningKey(key_id_of(public_raw(private.public_key())), private)


def load_public_key(path: str | Path) -> bytes:
    """The raw public key from a ``.sign.pub`` file (hex) or a ``.sign.key`` file."""
    path = Path(path)
    if path.name.endswith(".key"):
        return load_signing_key(path).public_raw
    try:
        raw = bytes.fromhex(path.read_text().strip())
    except ValueError:
        raise ValueError(f"{path}: not a hex public key") from None
    if len(raw) != _PUBLIC_KEY_BYTES:
        raise ValueError(f"{path}: {len(raw)} bytes, an Ed25519 public key is 32")
    return raw


def sign(key: SigningKey, message: bytes) -> bytes:
    """The 64-byte Ed25519 signature of ``message``."""
    return key.private.sign(message)


def signature_holds(public_key: bytes, signature: bytes, message: bytes) -> bool:
    """Whether ``signature`` is the Ed25519 signature of ``message`` by ``public_key``."""
    try:
        Ed25519PublicKey.from_public_bytes(bytes(public_key)).verify(bytes(signature), message)
    except (InvalidSignature, ValueError):
        return False
    return True
