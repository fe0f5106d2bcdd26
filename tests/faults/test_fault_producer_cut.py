"""A producer is cut off from the router for 30 s of wall time, then reconnects.

The cut: the producer process is stopped (SIGSTOP) for 30 s and continued (SIGCONT).
Its TCP link stays open, but a stopped process answers no keep-alive, so the router
closes its session when the Zenoh lease (10 s) runs out: the producer's publisher
liveliness token disappears for the rest of the site (the test sees it go), exactly as
for a PLC whose network link failed.  When it continues, the producer finds its session
gone, reconnects, and catches up on the 30 s of events its schedule owes (loadgen paces
against the monotonic clock), which the ledger must take, recover or record as exact gaps.
"""

from __future__ import annotations

import signal
import time

import zenoh

from harness import SITE, Yard
from services.service import ZenohOptions, open_session
from zenoh_helpers import wait_until

RATE_HZ = 500.0
DURATION_S = 38.0
#: wall time the producer is cut off, s
CUT_S = 30.0


def test_producer_cut_off_for_30_s_reconnects_and_nothing_is_lost(tmp_path):
    with Yard(tmp_path, services=("ledger",)) as yard:
        yard.start()
        tap = open_session(ZenohOptions(mode="client", connect=(yard.endpoint,),
                                        tls_dir=str(yard.pki), tls_name="tap"))
        tokens: list[tuple[float, str]] = []
        watcher = tap.liveliness().declare_subscriber(
            f"stockpile/{SITE}/@v1/*/load0/@adv/**",
            lambda s: tokens.append((time.monotonic(), str(s.kind))), history=True)
        try:
            [cut, _other] = yard.start_loadgens(rate_hz=RATE_HZ, duration_s=DURATION_S)
            wait_until(lambda: yard.poller.samples and all(
                yard.poller.samples[-1][1].get(p, 0) >= RATE_HZ * 3
                for p in yard.producer_names), 60, "3 s of events from every producer")
            cut.process.send_signal(signal.SIGSTOP)
            t_stop = time.monotonic()
            try:
                wait_until(lambda: any(t > t_stop and k == str(zenoh.SampleKind.DELETE)
                                       for t, k in tokens), CUT_S,
                           "the router to drop the stopped producer's session")
                dropped_s = next(t for t, k in tokens if t > t_stop) - t_stop
                wait_until(lambda: time.monotonic() >= t_stop + CUT_S, CUT_S + 1, "30 s")
            finally:
                cut.process.send_signal(signal.SIGCONT)
            fault_end = time.monotonic()
            wait_until(lambda: any(t > fault_end and k == str(zenoh.SampleKind.PUT)
                                   for t, k in tokens), 60, "the producer's token to return")
            row = yard.finish("producer cut off 30 s (SIGSTOP/SIGCONT; lease expiry)",
                              [fault_end], extra={"cut_s": CUT_S,
                                                  "session_dropped_after_s": round(dropped_s, 1)})
        finally:
            watcher.undeclare()
            tap.close()
    assert row["published"] == len(yard.producer_names) * RATE_HZ * DURATION_S
    assert row["gap_events"] == 0 and row["ledgered"] == row["published"], row
