"""Each service of a ``stockpile run`` yard is SIGKILLed in turn; the supervisor restarts it.

The yard runs the ledger, the localizer and the recorder (recording in hourly parts,
``split_duration = "1h"``); two producers publish 500
events/s each for 20 s.  The ledger, then the localizer, then the recorder are killed
(SIGKILL, no chance to flush), each once the one before is back.  `stockpile run` must
restart every one, the restarted ledger must recover what it missed from the producers'
caches, and the closing check must find every event exactly once or in an exact gap.
"""

from __future__ import annotations

import signal


from harness import Yard
from zenoh_helpers import log_lines, wait_until

RATE_HZ = 500.0
DURATION_S = 20.0
SERVICES = ("ledger", "localizer", "recorder")


def test_each_service_sigkilled_in_turn_is_restarted_and_nothing_is_lost(tmp_path):
    with Yard(tmp_path, services=SERVICES) as yard:
        yard.start()
        yard.start_loadgens(rate_hz=RATE_HZ, duration_s=DURATION_S)
        wait_until(lambda: yard.poller.samples and all(
            yard.poller.samples[-1][1].get(p, 0) >= RATE_HZ * 4 for p in yard.producer_names),
            60, "4 s of events from every producer in the ledger")
        kills, back_s = [], {}
        for name in SERVICES:
            t_kill, back_s[name] = yard.kill_service(name)
            kills.append(t_kill)
        row = yard.finish("SIGKILL ledger, localizer, recorder in turn (stockpile run)", kills,
                          extra={"back_s": {k: round(v, 2) for k, v in back_s.items()}})
    exited = [r for r in log_lines(yard.run_log) if r.get("msg") == "exited"]
    assert [r["name"] for r in exited] == list(SERVICES)
    assert all(int(r["code"]) == -signal.SIGKILL for r in exited)
    assert row["published"] == len(yard.producer_names) * RATE_HZ * DURATION_S
    # the caches (50,000 samples per key) cover each outage: nothing may be lost
    assert row["gap_events"] == 0 and row["ledgered"] == row["published"], row


def test_a_killed_recorder_without_a_split_comes_back(tmp_path):
    """The recorder as ``docs/yard.example.toml`` would run it without a split: one
    ``--out`` file.  After a SIGKILL `stockpile run` restarts it; it records again, in a
    new numbered part beside the file it was writing (which it does not overwrite)."""
    with Yard(tmp_path, services=("ledger", "recorder"), recorder_split=False) as yard:
        yard.start()
        yard.start_loadgens(rate_hz=RATE_HZ, duration_s=6.0)
        wait_until(lambda: yard.poller.samples and all(
            yard.poller.samples[-1][1].get(p, 0) >= RATE_HZ * 2 for p in yard.producer_names),
            60, "2 s of events from every producer in the ledger")
        t_kill, _back_s = yard.kill_service("recorder", timeout_s=15)
        row = yard.finish("SIGKILL recorder writing one file (stockpile run)", [t_kill])
    assert row["ledgered"] == row["published"], row
    assert (tmp_path / "record" / "site.mcap").exists()
    assert (tmp_path / "record" / "site-0000.mcap").stat().st_size > 0
