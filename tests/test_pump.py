"""services.pump.SamplePump on a real router and two client sessions (loopback, TLS off,
scouting off): every sample reaches ``on_sample`` in order on the pump's own thread, a
failing ``on_sample`` is reported and the pump goes on, and close() ends the thread."""

from __future__ import annotations

import random
import threading

import pytest
import zenoh

from services.pump import SamplePump
from services.service import ZenohOptions, open_session
from zenoh_helpers import open_router, wait_until

KEY = "stockpile/t/@v1/joint_reading/p0"


@pytest.fixture
def sessions():
    router, endpoint = open_router()
    client = ZenohOptions(mode="client", connect=(endpoint,))
    pub, sub = open_session(client), open_session(client)
    yield pub, sub
    for session in (pub, sub, router):
        session.close()


def test_every_sample_reaches_on_sample_in_order_on_the_pumps_thread(sessions, seed):
    pub, sub = sessions
    n = random.Random(seed).randint(500, 3_000)
    got, threads, errors = [], set(), []

    def on_sample(sample) -> None:
        threads.add(threading.current_thread().name)
        index = int(sample.payload.to_bytes())
        if index % 97 == 13:
            raise ValueError(f"refused {index}")
        got.append(index)

    pump = SamplePump(lambda handler: sub.declare_subscriber(KEY, handler), on_sample,
                      capacity=64, name="test-pump", on_error=errors.append)
    try:
        publisher = pub.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: publisher.matching_status.matching, 20, "the subscriber to match")
        for i in range(n):
            publisher.put(str(i).encode())
        refused = [i for i in range(n) if i % 97 == 13]
        wait_until(lambda: len(got) + len(errors) >= n, 30, f"{n} samples at the pump")
    finally:
        pump.close()
    assert got == [i for i in range(n) if i % 97 != 13]
    assert [str(e) for e in errors] == [f"refused {i}" for i in refused]
    assert threads == {"test-pump"}
    assert not pump._thread.is_alive()


def test_capacity_must_be_positive(sessions):
    _pub, sub = sessions
    with pytest.raises(ValueError, match="capacity must be >= 1"):
        SamplePump(lambda handler: sub.declare_subscriber(KEY, handler), print, capacity=0)
