"""Tamper evidence: the payload hash and the hash chain over every stored row.

``chain[n] = sha256(chain[n-1] || global_seq, epoch, seq, valid_time_ns,
recorded_time_ns (little-endian i64) || len(type) type || len(source) source ||
sha256(payload) [|| b"S" || len(key id) key id || len(signature) signature, lengths
u16, for a signed row])`` with ``chain[-1]`` = 32 zero bytes.  Changing any stored field
of any row changes its chain value and every one after it; ``stockpile ledger
verify`` recomputes the chain and names the first row that disagrees.

Quarantine entries are links of the same chain, in arrival order between the rows
(an entry stored after row ``n`` and before row ``n+1`` records ``after_global_seq =
n``): ``link = sha256(previous link || b"Q" || quarantine_id, after_global_seq,
recorded_time_ns (i64) || epoch, seq, valid_time_ns, existing_global_seq (each a
presence byte then i64) || len(type) type || len(source) source || len(code) code ||
len(detail) detail (lengths u32) || sha256(raw))``, and the next row's ``chain[n-1]``
is the last link before it.  Deleting or editing an entry therefore breaks the chain
of every row after it.
"""

from __future__ import annotations

import hashlib
import struct
from functools import lru_cache

GENESIS = bytes(32)

_INTS = struct.Struct("<qqqqq")
_LEN = struct.Struct("<H")
_QINTS = struct.Struct("<qqq")
_LEN32 = struct.Struct("<I")
_OPT = struct.Struct("<Bq")


def payload_hash(payload: bytes) -> bytes:
    """sha256 of the payload bytes (32 bytes)."""
    return hashlib.sha256(payload).digest()


@lru_cache(maxsize=4096)
def _names(type_name: str, source: str) -> bytes:
    t = type_name.encode()
    s = source.encode()
    return _LEN.pack(len(t)) + t + _LEN.pack(len(s)) + s


def chain_hash(
    previous: bytes,
    global_seq: int,
    type_name: str,
    source: str,
    epoch: int,
    seq: int,
    valid_time_ns: int,
    recorded_time_ns: int,
    payload_sha256: bytes,
    signature_block: bytes = b"",
) -> bytes:
    """The chain value of one row given the previous row's (32 bytes); a signed row's
    ``signature_block`` (:func:`ledger.signing.signature_block`) goes last."""
    return hashlib.sha256(b"".join((
        previous,
        _INTS.pack(global_seq, epoch, seq, valid_time_ns, recorded_time_ns),
        _names(type_name, source),
        payload_sha256,
        signature_block,
    ))).digest()


def _optional(value: int | None) -> bytes:
    return _OPT.pack(0, 0) if value is None else _OPT.pack(1, value)


def _text(value: str) -> bytes:
    raw = value.encode("utf-8", "surrogatepass")
    return _LEN32.pack(len(raw)) + raw


def quarantine_hash(
    previous: bytes,
    quarantine_id: int,
    after_global_seq: int,
    recorded_time_ns: int,
    epoch: int | None,
    seq: int | None,
    valid_time_ns: int | None,
    existing_global_seq: int | None,
    type_name: str,
    source: str,
    code: str,
    detail: str,
    raw: bytes,
) -> bytes:
    """The chain value of one quarantine entry given the previous link (32 bytes)."""
    return hashlib.sha256(b"".join((
        previous,
        b"Q",
        _QINTS.pack(quarantine_id, after_global_seq, recorded_time_ns),
        _optional(epoch), _optional(seq), _optional(valid_time_ns),
        _optional(existing_global_seq),
        _text(type_name), _text(source), _text(code), _text(detail),
        hashlib.sha256(raw).digest(),
    ))).digest()
