"""Progress of a long command on stderr: the one implementation every command uses.

- stderr is a terminal: a tqdm bar redrawn in place (``\\r``) with the count, the
  percentage when the total is known or estimated, the rate and the ETA;
- stderr is not a terminal (a CI log, a pipe, a file): a plain line at most every
  ``every_s`` seconds (5 s by default) and one final line with the count, the time and the
  rate, so logs stay readable and carry no ``\\r``;
- progress off (``enabled=False``, ``--no-progress``): nothing at all.

A job whose total is not known up front may pass ``fraction`` (0..1, e.g. the part of a
file read so far) with each update; the total is then estimated as ``done / fraction``,
which gives a percentage and an ETA too.

    with progress(total=n, unit="events", desc="export") as bar:
        for row in rows:
            ...
            bar.update(1)
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import TextIO

from tqdm import tqdm

#: seconds between two redraws of the bar on a terminal
TERMINAL_EVERY_S = 0.2
#: seconds between two plain lines when stderr is not a terminal
PLAIN_EVERY_S = 5.0


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def _screen(stream: TextIO) -> tuple[int, int]:
    """The terminal's (columns, lines), 80 x 24 where it does not say (e.g. a new pty)."""
    try:
        size = os.get_terminal_size(stream.fileno())
    except (AttributeError, ValueError, OSError):
        return 80, 24
    return size.columns or 80, size.lines or 24


def _eta(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


class Progress:
    """Progress of one job of ``total`` units (None = not known), written to ``stream``.

    Parameters
    ----------
    total : int or None
        Units expected; may be set later (``bar.total = n``) or estimated from ``fraction``.
    unit : str
        What is counted (``events``, ``lines``, ``records``), plural.
    desc : str
        A short label in front of every line (``replay``, ``importing x.jsonl``).
    enabled : bool or None
        True: show progress (a bar on a terminal, plain lines otherwise); False: nothing;
        None: only when ``stream`` is a terminal.
    stream : text stream
        Where progress goes (default ``sys.stderr`` at construction).
    every_s : float or None
        Seconds between plain lines (default :data:`PLAIN_EVERY_S`) or redraws of the bar
        (default :data:`TERMINAL_EVERY_S`).
    """

    def __init__(self, total: int | None = None, *, unit: str = "events", desc: str = "",
                 enabled: bool | None = None, stream: TextIO | None = None,
                 every_s: float | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.tty = _isatty(self.stream)
        self.enabled = self.tty if enabled is None else bool(enabled)
        self.unit, self.desc = unit, desc
        self.every_s = every_s if every_s is not None else (
            TERMINAL_EVERY_S if self.tty else PLAIN_EVERY_S)
        self.done = 0
        self.postfix = ""
        self.closed = not self.enabled
        self._total = total
        self._fraction: float | None = None
        self._started = self._last_line = time.monotonic()
        self._bar: tqdm | None = None
        if self.enabled and self.tty:
            columns, lines = _screen(self.stream)
            self._bar = tqdm(total=total, desc=desc or None, unit=f" {unit}", file=self.stream,
                             ncols=columns, nrows=lines, mininterval=self.every_s, leave=True)

    # -- the total ----------------------------------------------------------------------------

    @property
    def total(self) -> int | None:
        """Units expected: given, or estimated from the last ``fraction`` (None = unknown)."""
        if self._total is not None:
            return self._total
        if self._fraction and self._fraction > 0:
            return max(self.done, int(round(self.done / min(self._fraction, 1.0))))
        return None

    @total.setter
    def total(self, value: int | None) -> None:
        self._total = value
        if self._bar is not None:
            self._bar.total = value

    # -- updates ------------------------------------------------------------------------------

    def update(self, n: int = 1, *, fraction: float | None = None) -> None:
        """``n`` more units done; ``fraction`` (0..1) of the job done when the total is unknown."""
        self.update_to(self.done + n, fraction=fraction)

    def update_to(self, done: int, *, fraction: float | None = None) -> None:
        """``done`` units done in all (see :meth:`update`)."""
        step = done - self.done
        self.done = done
        if fraction is not None:
            self._fraction = min(max(fraction, 0.0), 1.0)
        if self.closed:
            return
        if self._bar is not None:
            if self._total is None and self._fraction:
                self._bar.total = self.total
            self._bar.update(step)
            return
        now = time.monotonic()
        if now - self._last_line >= self.every_s:
            self._last_line = now
            self._line(self._running_text(now))

    def set_postfix(self, text: str) -> None:
        """Extra text after the counts (``12,000 appended``), shown from the next update on."""
        self.postfix = text
        if self._bar is not None and not self.closed:
            self._bar.set_postfix_str(text, refresh=False)

    def close(self) -> None:
        """The final state: the bar at its end (terminal) or one final plain line."""
        self._finish(final=True)

    # -- context manager ----------------------------------------------------------------------

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        # after an error, no final line: the command's one-line error is what matters
        self._finish(final=exc_type is None)

    # -- output -------------------------------------------------------------------------------

    def _finish(self, *, final: bool) -> None:
        if self.closed:
            return
        self.closed = True
        if self._bar is not None:
            if final and self._total is None:
                self._bar.total = self.done  # an estimated total ends as the true count
            self._bar.refresh()
            self._bar.close()
            return
        if final:
            elapsed_s = max(time.monotonic() - self._started, 1e-9)
            text = (f"{self.done:,} {self.unit} in {elapsed_s:.1f} s "
                    f"({self.done / elapsed_s:,.0f} {self.unit}/s)")
            self._line(text + (f", {self.postfix}" if self.postfix else ""))

    def _running_text(self, now: float) -> str:
        elapsed_s = max(now - self._started, 1e-9)
        rate = self.done / elapsed_s
        total = self.total
        if total:
            text = f"{self.done:,}"
            if self._total is not None:
                text += f"/{total:,}"
            text += f" {self.unit} ({min(100.0, 100.0 * self.done / total):.0f} %)"
        else:
            text = f"{self.done:,} {self.unit}"
        text += f", {rate:,.0f} {self.unit}/s"
        if total and rate > 0 and total > self.done:
            text += f", ETA {_eta((total - self.done) / rate)}"
        return text + (f", {self.postfix}" if self.postfix else "")

    def _line(self, text: str) -> None:
        self.stream.write((f"{self.desc}: " if self.desc else "") + text + "\n")
        self.stream.flush()


def progress(total: int | None = None, *, unit: str = "events", desc: str = "",
             enabled: bool | None = None, stream: TextIO | None = None,
             every_s: float | None = None) -> Progress:
    """A :class:`Progress` (also a context manager that closes it)."""
    return Progress(total, unit=unit, desc=desc, enabled=enabled, stream=stream,
                    every_s=every_s)


def enabled_from_args(args: argparse.Namespace) -> bool:
    """Whether a command shows progress: on unless ``--no-progress``.

    On means a bar when stderr is a terminal and plain lines when it is not. With a
    ``--no-progress`` flag of its own (``args.no_progress``) only that flag counts;
    otherwise ``args.progress`` set to False (a ``--progress/--no-progress`` pair with
    default None or True) turns progress off; a command without either always shows it.
    """
    if hasattr(args, "no_progress"):
        return not args.no_progress
    return getattr(args, "progress", None) is not False
