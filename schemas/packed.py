"""Packed ``repeated double`` fields read straight from a protobuf payload's wire bytes
(zero-copy numpy views), for checks that would otherwise walk a long repeated field
value by value (a scan's ranges)."""

from __future__ import annotations

import struct
from functools import lru_cache

import numpy as np


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7


def packed_doubles(payload: bytes, *field_numbers: int) -> list[np.ndarray] | None:
    """Packed ``repeated double`` fields read straight from wire bytes (zero-copy).

    Returns one array per requested field number, or ``None`` when one of them is
    encoded unpacked (legal but unusual), so the caller can fall back to the decoded
    message.  The payload must already have parsed successfully.
    """
    chunks: dict[int, list[np.ndarray]] = {n: [] for n in field_numbers}
    pos, end = 0, len(payload)
    while pos < end:
        tag, pos = _varint(payload, pos)
        number, wire_type = tag >> 3, tag & 7
        if wire_type == 2:
            length, pos = _varint(payload, pos)
            if number in chunks:
                chunks[number].append(np.frombuffer(payload, dtype="<f8", count=length // 8, offset=pos))
            pos += length
        elif wire_type == 0:
            _, pos = _varint(payload, pos)
        elif wire_type == 1:
            if number in chunks:
                return None
            pos += 8
        elif wire_type == 5:
            pos += 4
        else:  # groups do not occur in proto3
            return None
    return [
        (c[0] if len(c) == 1 else np.concatenate(c) if c else np.empty(0))
        for c in (chunks[n] for n in field_numbers)
    ]


def _varint_bytes(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


@lru_cache(maxsize=256)
def _packed_header(field_number: int, count: int) -> bytes:
    return _varint_bytes((field_number << 3) | 2) + _varint_bytes(8 * count)


_DOUBLE = struct.Struct("<d")
_F8 = np.dtype("<f8")


def packed_tail(payload: bytes, field_number: int, count: int, decoded) -> np.ndarray | None:
    """Fast path of :func:`packed_doubles` for one packed field written as one chunk.

    Finds the field's tag and length with one ``find`` (fields are written in field
    number order, so a scan's ranges come right after its header) and confirms the find against
    the decoded message's first and last values (bit for bit); returns ``None`` when
    unsure, so the caller falls back to the full wire walk.
    """
    header = _packed_header(field_number, count)
    start = payload.find(header)
    offset = start + len(header)
    if start < 0 or offset + 8 * count > len(payload):
        return None
    first = _DOUBLE.unpack_from(payload, offset)[0]
    last = _DOUBLE.unpack_from(payload, offset + 8 * (count - 1))[0]
    if not (_same(first, decoded[0]) and _same(last, decoded[count - 1])):
        return None
    return np.frombuffer(payload, dtype=_F8, count=count, offset=offset)


def _same(a: float, b: float) -> bool:
    return a == b or (a != a and b != b)
