"""SICK's CRC-16 of LMS200 telegrams (docs/domain.md §5), computed with one table look-up
per byte in numpy.

The byte-serial definition: start with crc = 0 and prev = 0; for each byte b, (prev, cur)
= (cur, b); crc = crc * x mod P (a one-bit left shift, xor 0x8005 when the top bit falls
out: P = x^16 + x^15 + x^2 + 1); then crc ^= cur | prev << 8.  Every step is linear over
GF(2), so the CRC of bytes d_0 .. d_{n-1} is the xor over i of a term that depends only
on the byte d_i and its distance k = n - 1 - i from the end:

    G[k][d] = d * x^k  xor  (d << 8) * x^(k-1)   (the second term for k >= 1)   mod P

:func:`crc16` looks the terms up in the table ``G`` (rows 0 .. the longest telegram
body, grown on demand) and xors them; short inputs take the byte-serial loop.  No CRC
library implements this variant (it shifts one bit a byte, not eight).
"""

from __future__ import annotations

import numpy as np

__all__ = ["crc16"]

_POLY = 0x8005
#: rows of the table built at first use: an LMS200 body with 1023 values (4 + 2050 bytes)
_INITIAL_ROWS = 4 + 1 + 2 + 2 * 1023 + 1

#: below this many bytes the byte-serial loop is faster than numpy's call overhead
_SERIAL_BELOW = 16

_table = np.zeros((0, 256), dtype=np.uint16)
_flat = _table.ravel()
_offsets = np.zeros(0, dtype=np.intp)   # [(rows-1)*256, ..., 256, 0]: row starts, last first


def _mulx(v: np.ndarray) -> np.ndarray:
    """``v * x mod P`` for an array of 16-bit CRC states."""
    v = v.astype(np.uint32)
    return (((v & 0x7FFF) << 1) ^ np.where(v & 0x8000, _POLY, 0)).astype(np.uint16)


def _grow(rows: int) -> None:
    """Make the table at least ``rows`` rows long (built or extended, then kept)."""
    global _table, _flat, _offsets
    have = len(_table)
    if have >= rows:
        return
    rows = max(rows, _INITIAL_ROWS, 2 * have)
    table = np.empty((rows, 256), dtype=np.uint16)
    table[:have] = _table
    d = np.arange(256, dtype=np.uint16)
    if have == 0:
        table[0] = d
        if rows > 1:
            table[1] = _mulx(d) ^ (d << 8)
        have = min(rows, 2)
    for k in range(have, rows):       # G[k] = G[k-1] * x for k >= 2
        table[k] = _mulx(table[k - 1])
    _table, _flat = table, table.ravel()
    _offsets = np.arange(rows - 1, -1, -1, dtype=np.intp) * 256


def crc16(data: bytes | bytearray | memoryview) -> int:
    """SICK's CRC-16 of ``data`` (every byte from the 0x02 through the last payload byte).

    Returns the CRC, 0..0xFFFF; it is sent little-endian after the payload.  E.g.
    ``crc16(bytes.fromhex("0200010031")) == 0x1215`` (the status request
    ``02 00 01 00 31 15 12``).
    """
    data = bytes(data)
    n = len(data)
    if n < _SERIAL_BELOW:
        crc = cur = 0
        for b in data:
            prev, cur = cur, b
            crc = (((crc & 0x7FFF) << 1) ^ _POLY if crc & 0x8000 else crc << 1) ^ cur ^ (prev << 8)
        return crc
    if n > len(_table):
        _grow(n)
    index = _offsets[len(_offsets) - n:] + np.frombuffer(data, dtype=np.uint8)
    return int(np.bitwise_xor.reduce(_flat.take(index)))
