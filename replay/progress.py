"""A progress bar on stderr for replays and exports: percentage and messages/s.

On a terminal it redraws one line (``\\r``) a few times a second; otherwise (a log
file, a pipe) it writes a plain line every few seconds, so logs stay readable.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

BAR_WIDTH = 24


class ProgressBar:
    """Progress of one job of ``total`` messages (or of a fraction given per update).

    Parameters
    ----------
    what : str
        A short label (``replay``, ``export``).
    total : int or None
        Messages expected; without it the caller passes ``fraction`` to :meth:`update`.
    enabled : bool
        False prints nothing (``--no-progress``).
    """

    def __init__(self, what: str, total: int | None = None, *, stream: TextIO | None = None,
                 enabled: bool = True, every_s: float | None = None) -> None:
        self.what, self.total = what, total
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s if every_s is not None else (0.2 if self.tty else 2.0)
        self.started = time.monotonic()
        self._last = self.started
        self._drawn = False

    def line(self, done: int, fraction: float | None = None) -> str:
        """The progress text for ``done`` messages."""
        elapsed_s = max(time.monotonic() - self.started, 1e-9)
        if fraction is None and self.total:
            fraction = done / self.total
        rate = done / elapsed_s
        if fraction is None:
            return f"{self.what}: {done:,} msgs, {rate:,.0f} msgs/s"
        fraction = min(max(fraction, 0.0), 1.0)
        filled = int(round(fraction * BAR_WIDTH))
        bar = "#" * filled + "." * (BAR_WIDTH - filled)
        of = f"/{self.total:,}" if self.total else ""
        return f"{self.what}: [{bar}] {fraction * 100:5.1f} % {done:,}{of} msgs, {rate:,.0f} msgs/s"

    def update(self, done: int, fraction: float | None = None) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self._last < self.every_s:
            return
        self._last = now
        self._write(self.line(done, fraction))

    def finish(self, done: int) -> None:
        """The final state (100 % when the total was reached), ending the line."""
        if not self.enabled:
            return
        fraction = 1.0 if self.total is None or done >= self.total else None
        self._write(self.line(done, fraction))
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()

    def _write(self, text: str) -> None:
        if self.tty:
            self.stream.write("\r" + text.ljust(78))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
        self._drawn = True
