"""services.resubscribe.CacheRecall on a real router that goes away and comes back.

A publisher's events are in its cache only (published while nothing subscribed to their
data); the router is closed and a new one opened on the same endpoint; when the
publisher's token comes back, the recall asks its cache and hands every event over.
Zenoh's own ``detect_late_publishers`` drops these tokens (``@v1`` in the key), so
without the recall nothing would ask.
"""

from __future__ import annotations

import random
import threading

import zenoh

from services.publishing import declare_ledger_publisher
from services.resubscribe import CacheRecall
from services.service import ZenohOptions, open_session
from zenoh_helpers import free_port, wait_until

SITE = "t"
KEY = f"stockpile/{SITE}/@v1/joint_reading/p0"


def _router(endpoint: str) -> zenoh.Session:
    return zenoh.open(ZenohOptions(mode="router", listen=(endpoint,)).to_config())


def test_recall_asks_a_returning_publishers_cache(seed):
    n_events = random.Random(seed).randint(3, 40)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = _router(endpoint)
    client = ZenohOptions(mode="client", connect=(endpoint,))
    pub_session, sub_session = open_session(client), open_session(client)
    got: list[bytes] = []
    lock = threading.Lock()

    def on_sample(sample) -> None:
        with lock:
            got.append(sample.payload.to_bytes())

    recall = None
    try:
        publisher = declare_ledger_publisher(pub_session, KEY, cache_samples=100)
        tokens = f"stockpile/{SITE}/@v1/**/@adv/pub/**"
        wait_until(lambda: any(r.ok is not None for r in
                               sub_session.liveliness().get(tokens, timeout=2)),
                   20, "the publisher's token at the subscriber")
        recall = CacheRecall(sub_session, f"stockpile/{SITE}/@v1/**", on_sample)
        for i in range(n_events):
            publisher.put(f"event {i}".encode())
        assert recall.recalls == 0 and got == []   # a present publisher is not asked

        router.close()
        router = _router(endpoint)
        wait_until(lambda: len(got) >= n_events, 60,
                   "the recall to bring the publisher's cached events")
        with lock:
            assert sorted(got) == sorted(f"event {i}".encode() for i in range(n_events))
        assert recall.recalls >= 1
        publisher.undeclare()
    finally:
        if recall is not None:
            recall.close()
        pub_session.close()
        sub_session.close()
        router.close()
