"""Each service of a ``stockpile run`` yard is SIGKILLed in turn; the supervisor restarts it.

The yard runs every service a site runs under ``stockpile run``: the ledger, the localizer,
the recorder (recording in hourly parts, ``split_duration = "1h"``), the projector and the
dashboard (following pile ``P1``), and the scanner and the GNSS reader on real ptys fed by
``serial_feeder.py`` (an LMS200 at 75 Hz, GGA at 10 Hz); two producers publish 500
events/s each for 30 s.  Each service is killed (SIGKILL, no chance to flush) once the
one before is back.  `stockpile run` must restart every one; the restarted ledger must
recover what it missed from the producers' caches, and the closing check must find every
producer event exactly once or in an exact gap.  The scanner's and the GNSS reader's
events (published by the services themselves; a killed one loses what it had not sent,
as any edge process would) must be, per (source, epoch), dense: stored once or inside an
open gap record from 0 to the highest sequence, and a restarted reader publishes under a
new epoch.
"""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

from harness import MACHINE, Yard
from ledger import open_ledger
from zenoh_helpers import PYTHON, log_lines, stop, wait_until

RATE_HZ = 500.0
DURATION_S = 30.0
SERVICES = ("ledger", "localizer", "recorder", "projector", "dashboard", "scanner", "gnss")
DEVICE_SOURCES = (f"{MACHINE}.scanner", f"{MACHINE}.gnss")
FEEDER = Path(__file__).with_name("serial_feeder.py")


def start_feeder(base: Path) -> tuple[subprocess.Popen, dict[str, str]]:
    """The serial feeder process and its pty paths ``{"scanner": ..., "gnss": ...}``."""
    proc = subprocess.Popen([PYTHON, str(FEEDER)], stdout=subprocess.PIPE,
                            stderr=open(base / "feeder.log", "w"), text=True)
    line = proc.stdout.readline()
    assert line, f"the serial feeder exited {proc.poll()}: {(base / 'feeder.log').read_text()}"
    return proc, json.loads(line)


def device_streams_are_dense(path: Path) -> dict[str, list[int]]:
    """Per device source, its epochs; asserts each (source, epoch) holds 0..max exactly once
    or in an open gap, and at least 2 epochs (the restart)."""
    epochs: dict[str, list[int]] = {}
    with open_ledger(path, read_only=True) as store:
        infos = {(i.source, i.epoch): i for i in store.streams()}
        open_gaps = store.gaps(open_only=True)
        for source in DEVICE_SOURCES:
            counts: dict[int, int] = {}
            for r in store.read(sources=[source]):
                counts[r.epoch] = counts.get(r.epoch, 0) + 1
            for epoch, stored in counts.items():
                info = infos[(source, epoch)]
                in_gaps = sum(g.last_seq - g.first_seq + 1 for g in open_gaps
                              if (g.source, g.epoch) == (source, epoch))
                assert stored + in_gaps == info.max_seq + 1, \
                    (source, epoch, stored, in_gaps, info)
            epochs[source] = sorted(counts)
            assert len(counts) >= 2, f"{source}: no new epoch after its restart: {counts}"
    return epochs


def test_each_service_sigkilled_in_turn_is_restarted_and_nothing_is_lost(tmp_path):
    feeder, devices = start_feeder(tmp_path)
    try:
        with Yard(tmp_path, services=SERVICES, devices=devices) as yard:
            yard.start()
            yard.start_loadgens(rate_hz=RATE_HZ, duration_s=DURATION_S)
            wait_until(lambda: yard.poller.samples and all(
                yard.poller.samples[-1][1].get(p, 0) >= RATE_HZ * 4
                for p in (*yard.producer_names, *DEVICE_SOURCES[:1])),
                60, "4 s of events from every producer and the scanner in the ledger")
            kills, back_s = [], {}
            for name in SERVICES:
                t_kill, back_s[name] = yard.kill_service(name)
                kills.append(t_kill)
            for source in DEVICE_SOURCES:   # the restarted readers publish again
                before = yard.poller.samples[-1][1].get(source, 0)
                wait_until(lambda: yard.poller.samples[-1][1].get(source, 0) > before + 5, 60,
                           f"new events of {source} after its restart")
            row = yard.finish("SIGKILL each of 7 services in turn (stockpile run)", kills,
                              extra={"back_s": {k: round(v, 2) for k, v in back_s.items()}})
    finally:
        stop(feeder)
    exited = [r for r in log_lines(yard.run_log) if r.get("msg") == "exited"]
    assert [r["name"] for r in exited] == list(SERVICES)
    assert all(int(r["code"]) == -signal.SIGKILL for r in exited)
    assert row["published"] == len(yard.producer_names) * RATE_HZ * DURATION_S
    # the caches (50,000 samples per key) cover each outage: nothing may be lost
    assert row["gap_events"] == 0 and row["ledgered"] == row["published"], row
    print("device epochs:", device_streams_are_dense(yard.ledger_path))


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
