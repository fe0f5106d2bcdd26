"""The Zenoh router is SIGKILLed and restarted on the same endpoint in the middle of a run.

A ``stockpile run`` yard (ledger, localizer, recorder) and two producers at 500 events/s
each for 16 s, all clients of one ``stockpile service router`` process over mutual TLS.
Once 6 s of events are in the ledger, the router is killed; 3 s later a new router
listens on the same endpoint.  Every client must find it again by itself, the ledger
must recover what the producers published while they had no router (their caches hold
it), and the closing check must find every event exactly once or in an exact gap.

The second case keeps the router away for 12 s, until the producers have published their
last event: no live sample ever tells the ledger what it missed, so it must ask the
producers' caches when their liveliness tokens come back (services.resubscribe; with a
3 s outage it happens when a client's reconnection attempt falls after the producers'
last event; see docs/operations.md).
"""

from __future__ import annotations

import time

import pytest

from harness import Yard
from zenoh_helpers import wait_until

RATE_HZ = 500.0
DURATION_S = 16.0
#: how long the site has no router, s: a short outage, and one that outlasts the
#: producers' remaining 10 s of publishing
OUTAGES_S = (3.0, 12.0)
#: the ledger normally holds everything 7 s after the restart; a stuck site fails in 45 s
DRAIN_TIMEOUT_S = 45.0


@pytest.mark.parametrize("outage_s", OUTAGES_S)
def test_router_killed_and_restarted_mid_run_loses_nothing(tmp_path, outage_s):
    with Yard(tmp_path, services=("ledger", "localizer", "recorder")) as yard:
        yard.start()
        yard.start_loadgens(rate_hz=RATE_HZ, duration_s=DURATION_S)
        wait_until(lambda: yard.poller.samples and all(
            yard.poller.samples[-1][1].get(p, 0) >= RATE_HZ * 6 for p in yard.producer_names),
            60, "6 s of events from every producer in the ledger")
        yard.router.kill()
        outage_end = time.monotonic() + outage_s
        wait_until(lambda: time.monotonic() >= outage_end, outage_s + 1, "the outage's end")
        yard.router.start()
        fault_end = time.monotonic()
        row = yard.finish(f"router SIGKILL, restarted after {outage_s:g} s", [fault_end],
                          extra={"outage_s": outage_s}, drain_timeout_s=DRAIN_TIMEOUT_S)
    assert row["published"] == len(yard.producer_names) * RATE_HZ * DURATION_S
    # the caches (50,000 samples per key) cover a 3 s outage: nothing may be lost
    assert row["gap_events"] == 0 and row["ledgered"] == row["published"], row
    # every service of `stockpile run` stayed up (a router outage is not a crash)
    assert all(len(yard.started_pids(s)) == 1 for s in ("ledger", "localizer", "recorder"))
