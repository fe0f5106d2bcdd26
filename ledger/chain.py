"""Tamper evidence: the payload hash and the hash chain over every stored row.

``chain[n] = sha256(chain[n-1] || global_seq, epoch, seq, valid_time_ns,
recorded_time_ns (little-endian i64) || len(type) type || len(source) source ||
sha256(payload))`` with ``chain[-1]`` = 32 zero bytes.  Changing any stored field
of any row changes its chain value and every one after it; ``stockpile ledger
verify`` recomputes the chain and names the first row that disagrees.
"""

from __future__ import annotations

import hashlib
import struct
from functools import lru_cache

GENESIS = bytes(32)

_INTS = struct.Struct("<qqqqq")
_LEN = struct.Struct("<H")


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
) -> bytes:
    """The chain value of one row given the previous row's (32 bytes)."""
    return hashlib.sha256(b"".join((
        previous,
        _INTS.pack(global_seq, epoch, seq, valid_time_ns, recorded_time_ns),
        _names(type_name, source),
        payload_sha256,
    ))).digest()
