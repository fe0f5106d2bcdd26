"""Clean shutdown on SIGINT/SIGTERM: :class:`Stopper` and the process's signal relay.

A :class:`Stopper` is a :class:`threading.Event` that SIGINT and SIGTERM set.  The
signal reaches it through a pipe, the process's signal wakeup fd, read by one relay
thread per process, so the stop never depends on Python running the signal handler in
the main thread (see :class:`Stopper`).
"""

from __future__ import annotations

import os
import signal
import threading

__all__ = ["Stopper"]


class Stopper:
    """Turns SIGINT/SIGTERM into a :class:`threading.Event` (main thread only).

    ``stop.wait(t)`` doubles as an interruptible sleep for service loops.

    The stop does not depend on Python running the signal handler.  Python runs a
    handler in the main thread between two bytecodes, which may be inside
    ``event.wait()`` while that holds the event's lock (``Event.set()`` there would
    wait for that lock forever), or not at all while the main thread waits inside C
    code that does not return.  So the process's signal wakeup fd
    (:func:`signal.set_wakeup_fd`) is a pipe: the C-level handler writes the signal's
    number to it at once, and one relay thread per process reads it and sets the
    event of the stopper installed last.  The Python handler, when it runs, writes to
    the same pipe (in case something replaced the wakeup fd); a stop relayed twice is
    harmless.  A loop that waits for items between two looks at the event waits on an
    :class:`services.inbox.Inbox`, whose timeout a signal cannot undo.
    """

    def __init__(self, install: bool = True) -> None:
        self.event = threading.Event()
        self.signal_name: str | None = None
        if install and threading.current_thread() is threading.main_thread():
            _signal_relay(self)
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, _handled_by_the_relay)

    def set(self) -> None:
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self.event.wait(timeout_s)


def _handled_by_the_relay(signum: int, _frame: object) -> None:
    """Python-level handler of SIGINT/SIGTERM: the relay's pipe (:class:`Stopper`);
    no lock is taken here."""
    if _relay_write_fd is not None:
        try:
            os.write(_relay_write_fd, bytes((signum,)))
        except BlockingIOError:       # the pipe is full of stops already on their way
            pass


_relay_lock = threading.Lock()
_relay_write_fd: int | None = None
_relay_target: Stopper | None = None


def _signal_relay(stopper: Stopper) -> None:
    """Make ``stopper`` the one the relay thread stops (the pipe, the wakeup fd and
    the thread are set up once per process, from the main thread)."""
    global _relay_write_fd, _relay_target
    with _relay_lock:
        _relay_target = stopper
        if _relay_write_fd is None:
            read_fd, write_fd = os.pipe()
            os.set_blocking(write_fd, False)
            signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
            threading.Thread(target=_relay, args=(read_fd,), name="signal-relay",
                             daemon=True).start()
            _relay_write_fd = write_fd


def _relay(read_fd: int) -> None:
    while chunk := os.read(read_fd, 64):
        target = _relay_target
        if target is None:
            continue
        for signum in chunk:
            if signum in (signal.SIGINT, signal.SIGTERM):
                target.signal_name = signal.Signals(signum).name
                target.event.set()
