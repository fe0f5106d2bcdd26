"""The ledger writer's batch window runs from the first sample's arrival.

A sample that queued while the writer was committing the batch before has already
waited: the writer takes what is queued and commits it at once, instead of waiting a
whole window more (that wait was most of the commit latency's tail).
"""

from __future__ import annotations

import queue
import threading
import time

from ledger import open_ledger
from services.ledger_service import _STOP, Config, Writer
from services.service import ZenohOptions

#: a window no test waits out: a writer that waits it fails the test's 10 s bound
LONG_WINDOW_S = 600.0


def _writer(tmp_path, samples: queue.Queue, batch_size: int):
    store = open_ledger(str(tmp_path / "l.duckdb"))
    config = Config(site="t", zenoh=ZenohOptions(), ledger_path=str(tmp_path / "l.duckdb"),
                    batch_size=batch_size, batch_interval_s=LONG_WINDOW_S)
    return store, Writer(store, samples, None, config, on_committed=lambda: None)


def _take_in_thread(writer: Writer) -> list:
    """The writer's next batch, taken on another thread; fails after 10 s."""
    out: list = []
    done = threading.Event()

    def take() -> None:
        out.append(writer._take_batch())
        done.set()

    threading.Thread(target=take, daemon=True).start()
    assert done.wait(10.0), "the writer waited for its window although its samples were late"
    return out[0]


def test_samples_that_waited_are_taken_without_a_new_window(tmp_path):
    samples: queue.Queue = queue.Queue()
    store, writer = _writer(tmp_path, samples, batch_size=100)
    arrived = time.monotonic() - 2 * LONG_WINDOW_S   # queued while a commit ran
    for i in range(3):
        samples.put((f"k{i}", b"", None, arrived))
    try:
        batch, stop = _take_in_thread(writer)
    finally:
        store.close()
    assert [item[0] for item in batch] == ["k0", "k1", "k2"]
    assert not stop


def test_size_bound_and_stop_still_close_a_batch(tmp_path):
    samples: queue.Queue = queue.Queue()
    store, writer = _writer(tmp_path, samples, batch_size=4)
    now = time.monotonic()     # fresh samples: only the size bound can close the batch
    for i in range(6):
        samples.put((f"k{i}", b"", None, now))
    samples.put(_STOP)
    try:
        first, stop_1 = _take_in_thread(writer)
        second, stop_2 = _take_in_thread(writer)
    finally:
        store.close()
    assert [item[0] for item in first] == ["k0", "k1", "k2", "k3"] and not stop_1
    assert [item[0] for item in second] == ["k4", "k5"] and stop_2
