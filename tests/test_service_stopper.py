"""SIGINT/SIGTERM handling every service shares (:class:`services.service.Stopper`), and
the stack dump a running service writes on SIGUSR1 (:mod:`stockpile.service_cli`)."""

from __future__ import annotations

import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from services.service import Inbox
from tests.zenoh_helpers import log_lines, service_on_a_stuck_ledger, stop, wait_until

ROOT = Path(__file__).resolve().parents[1]

# The main thread holds the stop event's lock, as it does for a moment inside
# ``event.wait()``, when SIGTERM lands: Python runs the handler right there, in that
# thread.  A handler that called ``Event.set()`` waited for that lock forever (a live
# projector once ignored SIGTERM this way); the run has a timeout so such a hang fails.
SIGNAL_INSIDE_WAIT = """
import os, signal
from services.service import Stopper
stopper = Stopper()
with stopper.event._cond:
    os.kill(os.getpid(), signal.SIGTERM)
    before = stopper.is_set()
print(before, stopper.wait(10), stopper.signal_name)
"""

# The main thread waits inside C code that never returns to Python (a second lock of a
# plain pthread mutex it already holds, through ctypes, which lets the GIL go), so
# Python never runs the signal handler: the stop must come from the C-level handler
# alone.  Another thread exits the process once the stopper is set; a stop that needed
# the Python handler hangs until the run's timeout.
SIGNAL_WHILE_MAIN_THREAD_IS_IN_C = """
import ctypes, os, signal, sys, threading
from services.service import Stopper
stopper = Stopper()
libc = ctypes.CDLL(None)
mutex = ctypes.create_string_buffer(64)        # zeroed: PTHREAD_MUTEX_INITIALIZER
assert libc.pthread_mutex_lock(mutex) == 0

def exit_when_stopped():
    stopper.wait()
    print("stopped by", stopper.signal_name, flush=True)
    os._exit(0)

def send_sigterm_soon():
    print("main thread blocked", flush=True)
    os.kill(os.getpid(), signal.SIGTERM)

threading.Thread(target=exit_when_stopped, daemon=True).start()
threading.Timer(0.2, send_sigterm_soon).start()
libc.pthread_mutex_lock(mutex)                 # never returns
print("the main thread came back", flush=True)
os._exit(3)
"""


def test_a_signal_landing_while_the_main_thread_holds_the_stop_events_lock_still_stops():
    done = subprocess.run([sys.executable, "-c", SIGNAL_INSIDE_WAIT], cwd=ROOT, timeout=30,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    # the event was set once the lock was let go, not inside the block
    assert done.stdout.split() == ["False", "True", "SIGTERM"]


def test_sigterm_stops_while_the_main_thread_waits_inside_c_code():
    done = subprocess.run([sys.executable, "-c", SIGNAL_WHILE_MAIN_THREAD_IS_IN_C],
                          cwd=ROOT, timeout=30, capture_output=True, text=True)
    assert done.returncode == 0, (done.stdout, done.stderr)
    assert done.stdout.splitlines() == ["main thread blocked", "stopped by SIGTERM"]


def test_a_running_service_dumps_its_threads_stacks_on_sigusr1_and_keeps_running(tmp_path):
    log = tmp_path / "service.log"
    with service_on_a_stuck_ledger("projector", log, "--pile", "P1") as process:
        process.send_signal(signal.SIGUSR1)
        wait_until(lambda: "projector_service.py" in log.read_text(), 20, "the stack dump")
        text = log.read_text()
        # the main thread's stack: waiting for the ledger's answer to its first query
        assert "in head" in text and "ledger_client.py" in text
        assert process.poll() is None            # a dump, not a stop
        code = stop(process, timeout_s=20)
    assert code == 0
    assert log_lines(log)[-1]["msg"] == "stopped"


# A signal lands 10 ms into a 50 ms wait for a committed head, and its handler runs
# for 200 ms, past the wait's deadline.  CPython 3.11's ``SimpleQueue.get(timeout=)``
# then waited again without a timeout, until the next item: a live dashboard that
# waited so never saw SIGTERM's stop.  A head put after 5 s tells a hang from a timeout.
SIGNAL_OUTLASTS_A_WAIT_FOR_A_HEAD = """
import os, signal, threading, time
from services.projector_service import newest_head
from services.service import Inbox
heads = Inbox()
signal.signal(signal.SIGUSR2, lambda signum, frame: time.sleep(0.2))
threading.Timer(0.01, os.kill, (os.getpid(), signal.SIGUSR2)).start()
threading.Timer(5.0, heads.put, (99,)).start()
started = time.monotonic()
got = newest_head(heads, 0.05)
print(got, time.monotonic() - started < 2.0, flush=True)
os._exit(0)
"""


def test_a_signal_whose_handler_outlasts_a_wait_for_a_head_ends_the_wait():
    done = subprocess.run([sys.executable, "-c", SIGNAL_OUTLASTS_A_WAIT_FOR_A_HEAD],
                          cwd=ROOT, timeout=30, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["None", "True"]


def test_an_inbox_hands_items_over_in_order_and_wakes_a_waiting_get_at_once():
    inbox = Inbox()
    with pytest.raises(queue.Empty):
        inbox.get_nowait()
    started = time.monotonic()
    with pytest.raises(queue.Empty):
        inbox.get(0.05)
    assert time.monotonic() - started >= 0.05
    for item in (1, 2, 3):
        inbox.put(item)
    assert inbox.qsize() == 3
    assert [inbox.get(0), inbox.get_nowait(), inbox.get(10.0)] == [1, 2, 3]
    # a put from another thread ends a long wait at once, many times over
    for item in range(200):
        threading.Timer(0.001, inbox.put, (item,)).start()
        started = time.monotonic()
        assert inbox.get(10.0) == item
        assert time.monotonic() - started < 5.0
    assert inbox.qsize() == 0
