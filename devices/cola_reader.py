"""The CoLa stream reader: bytes from a TCP connection in, intact telegram payloads out.

:class:`ColaReader` resynchronises on the CoLa-A STX/ETX or the CoLa-B magic after
garbage and counts what it discards; the framing itself is :mod:`devices.cola`'s.  It owns
no I/O: the scanner service feeds it whatever each socket read returned.
"""

from __future__ import annotations

from devices.cola import DEFAULT_MAX_PAYLOAD, ETX, MAGIC, STX, check_protocol, xor_checksum

__all__ = ["ColaReader"]

_CONTROL = bytes(range(0x20))  # bytes a CoLa-A payload never holds


class ColaReader:
    """Incremental CoLa stream parser: bytes in, payloads of intact telegrams out.

    Feed it whatever a socket read returned (any split); it returns the payload of every
    complete telegram, framing removed.  Resynchronisation:

    - CoLa-B: bytes before the magic ``02 02 02 02`` are skipped.  A candidate whose
      length lies outside ``1..max_payload``, or whose payload does not start with
      ``s`` (every SOPAS command does), is not a telegram: its first byte is skipped.
      When a complete candidate fails its checksum the search restarts one byte after
      its start, so a corrupt length cannot swallow the telegrams behind it.
    - CoLa-A: bytes before an STX are skipped.  An STX followed by another STX before
      any ETX, or a payload holding a control byte, is a broken frame and skipped up to
      the next STX (or past its ETX); an STX with no ETX within ``max_payload`` bytes is
      skipped.  CoLa-A has no checksum: a corrupted digit that is still a digit passes.

    Attributes
    ----------
    telegrams : int
        Payloads returned.
    checksum_errors : int
        CoLa-B candidates whose checksum failed, not counting candidates that start inside
        an earlier failed one (echoes of the same corruption).
    broken_frames : int
        CoLa-A frames broken by a stray STX, a control byte or a missing ETX.
    garbage_bytes : int
        Bytes discarded.  Invariant: bytes fed = framed bytes of the telegrams returned +
        ``garbage_bytes`` + :attr:`buffered_bytes`.
    """

    def __init__(self, protocol: str, max_payload: int = DEFAULT_MAX_PAYLOAD) -> None:
        check_protocol(protocol)
        if not 1 <= max_payload <= 1 << 31:
            raise ValueError(f"max_payload must be 1..2**31, got {max_payload}")
        self.protocol, self.max_payload = protocol, max_payload
        self.telegrams = self.checksum_errors = self.broken_frames = self.garbage_bytes = 0
        self._buf = bytearray()
        self._reject_end = 0

    @property
    def buffered_bytes(self) -> int:
        """Bytes held back waiting for the rest of a telegram."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes from the stream; return the payloads they complete, in order."""
        self._buf += data
        if self.protocol == "cola-b":
            out, pos = self._scan_binary()
        else:
            out, pos = self._scan_ascii()
        del self._buf[:pos]
        self._reject_end = max(0, self._reject_end - pos)
        self.telegrams += len(out)
        return out

    def reset(self) -> int:
        """Drop the bytes held back (a connection was cut: they never complete); they count
        as garbage.  Returns how many there were."""
        dropped = len(self._buf)
        self.garbage_bytes += dropped
        self._buf.clear()
        self._reject_end = 0
        return dropped

    def _scan_binary(self) -> tuple[list[bytes], int]:
        buf, n, pos, out = self._buf, len(self._buf), 0, []
        while True:
            start = buf.find(MAGIC, pos)
            if start < 0:
                keep = min(3, n - pos)      # a magic may be arriving: keep its first bytes
                while keep and any(b != STX for b in buf[n - keep:]):
                    keep -= 1
                self.garbage_bytes += n - keep - pos
                return out, n - keep
            self.garbage_bytes += start - pos
            pos = start
            if n - pos < 9:
                return out, pos
            length = int.from_bytes(buf[pos + 4:pos + 8], "big")
            if not 1 <= length <= self.max_payload or buf[pos + 8] != 0x73:  # "s"
                self.garbage_bytes += 1
                pos += 1
                continue
            end = pos + 8 + length + 1
            if end > n:
                return out, pos
            payload = bytes(buf[pos + 8:end - 1])
            if xor_checksum(payload) == buf[end - 1]:
                out.append(payload)
                pos = end
                continue
            if pos >= self._reject_end:
                self.checksum_errors += 1
            self._reject_end = max(self._reject_end, end)
            self.garbage_bytes += 1
            pos += 1

    def _scan_ascii(self) -> tuple[list[bytes], int]:
        buf, n, pos, out = self._buf, len(self._buf), 0, []
        while True:
            start = buf.find(STX, pos)
            if start < 0:
                self.garbage_bytes += n - pos
                return out, n
            self.garbage_bytes += start - pos
            pos = start
            limit = min(n, pos + 2 + self.max_payload)
            etx = buf.find(ETX, pos + 1, limit)
            stray = buf.find(STX, pos + 1, etx if etx >= 0 else limit)
            if stray >= 0:                      # a new telegram starts before this one ends
                self.broken_frames += 1
                self.garbage_bytes += stray - pos
                pos = stray
                continue
            if etx < 0:
                if limit < pos + 2 + self.max_payload:
                    return out, pos             # the ETX may still come
                self.broken_frames += 1         # too long: not a telegram
                self.garbage_bytes += 1
                pos += 1
                continue
            payload = bytes(buf[pos + 1:etx])
            if not payload or payload.translate(None, _CONTROL) != payload:
                self.broken_frames += 1
                self.garbage_bytes += etx + 1 - pos
            else:
                out.append(payload)
            pos = etx + 1
