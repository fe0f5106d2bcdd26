"""Pseudo-terminals the emulated serial devices write to (Linux).

A :class:`PtyDevice` is one end of an emulated serial line. The simulator writes the device's
bytes (LMS200 telegrams, NMEA sentences) to the pty master; a consumer opens the slave path
exactly as it would open the real port::

    with PtyDevice() as dev:
        port = serial.Serial(dev.path, 38400, timeout=0.1)
        dev.write(telegram)
        data = port.read(4096)

The slave is in raw mode (no echo, no CR/LF translation, no flow-control or signal
characters), so binary bytes pass unchanged; pyserial reconfigures it raw on open as well and
flushes whatever was written before it opened, as a real port would. The baud rate is not
emulated: the pty moves bytes as fast as the reader reads them, and a caller that wants
line-rate pacing must sleep between writes itself.
"""

from __future__ import annotations

import errno
import os
import select
import time
import tty

__all__ = ["PtyDevice"]


class PtyDevice:
    """A pseudo-terminal pair: write on the master, read from :attr:`path` (the slave).

    Parameters
    ----------
    write_timeout_s : float
        Longest time one :meth:`write` waits for the reader to drain the pty buffer, seconds.
        The bytes it could not write by then are dropped and counted in
        :attr:`dropped_bytes`, so a simulator never blocks on an absent reader.

    Attributes
    ----------
    path : str
        The slave device, e.g. ``/dev/pts/5``.
    written_bytes : int
        Bytes handed to the pty so far.
    dropped_bytes : int
        Bytes dropped because the buffer stayed full for ``write_timeout_s``.

    Notes
    -----
    The master (and a handle on the slave, so the line discipline keeps its raw settings and
    the master never sees a hang-up) stay open until :meth:`close`. Linux only.
    """

    def __init__(self, write_timeout_s: float = 0.5) -> None:
        if not write_timeout_s >= 0.0:
            raise ValueError(f"write_timeout_s must be >= 0, got {write_timeout_s}")
        self.write_timeout_s = float(write_timeout_s)
        self.written_bytes = 0
        self.dropped_bytes = 0
        self._master, self._slave = os.openpty()
        try:
            tty.setraw(self._slave)
            os.set_blocking(self._master, False)
            self.path = os.ttyname(self._slave)
        except BaseException:
            os.close(self._master)
            os.close(self._slave)
            raise
        self._closed = False

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._closed

    def fileno(self) -> int:
        """The master's file descriptor (for select/poll)."""
        self._check_open()
        return self._master

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError("PtyDevice is closed")

    def write(self, data: bytes) -> int:
        """Write bytes towards the reader, waiting at most ``write_timeout_s`` for room.

        Parameters
        ----------
        data : bytes
            Bytes to send.

        Returns
        -------
        int
            Bytes written; the rest (``len(data)`` minus this) were dropped and added to
            :attr:`dropped_bytes`.
        """
        self._check_open()
        view = memoryview(bytes(data))
        deadline = time.monotonic() + self.write_timeout_s
        done = 0
        while done < len(view):
            try:
                done += os.write(self._master, view[done:])
                continue
            except BlockingIOError:
                pass
            except OSError as exc:  # EIO: the line was hung up
                if exc.errno != errno.EIO:
                    raise
                break
            remaining_s = deadline - time.monotonic()
            if remaining_s <= 0.0:
                break
            select.select([], [self._master], [], remaining_s)
        self.written_bytes += done
        self.dropped_bytes += len(view) - done
        return done

    def read(self, max_bytes: int = 4096) -> bytes:
        """Bytes the reader wrote to the slave (host -> device commands), without waiting.

        Parameters
        ----------
        max_bytes : int
            Upper bound on the bytes returned.

        Returns
        -------
        bytes
            Possibly empty.
        """
        self._check_open()
        try:
            return os.read(self._master, max_bytes)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:
                return b""
            raise

    def close(self) -> None:
        """Close both ends; idempotent."""
        if self._closed:
            return
        self._closed = True
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyDevice:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            self.close()
