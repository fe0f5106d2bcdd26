"""Fault: the ledger's disk fills mid-run, then space is freed (issue: reliability, item 3).

Real parts: a ledger service process with its file on a small tmpfs, a load generator
process publishing a known run of scans (``services.loadgen``: AdvancedPublisher with a
cache, congestion control BLOCK), a loopback router in the test.  Mid-run a filler file
takes every free byte.  The service must pause (alarm ``disk_full`` on its status key
with the OS error, process alive, its queue full so the publisher is held back), and
once the filler is deleted resume by itself: every published event in the ledger
exactly once, no open gap, ``stockpile ledger verify`` ok.  One line per run reports
fault, events published, events ledgered, gaps and seconds to recover.
"""

from __future__ import annotations

import json
import subprocess
import threading
import time
from pathlib import Path

import pytest

from disk_helpers import fill, small_disk
from ledger import open_ledger
from services.ledger_disk import status_key
from services.ledger_service import head_key
from zenoh_helpers import (PYTHON, client_args, log_lines, open_router, stockpile, stop,
                           wait_liveliness, wait_until)

SITE = "diskfull"
SOURCE = "load.disk"
#: the watermark, MiB: above what the filler leaves, below the tmpfs's size
MIN_FREE_MB = 4
#: the ledger service's queue, samples: small, so a pause backs up to the publisher fast
QUEUE_SIZE = 500


class Watch:
    """The ledger's published heads and status messages, as the test's router sees them."""

    def __init__(self, session) -> None:
        self.lock = threading.Lock()
        self.head = -1
        self.statuses: list[tuple[float, dict]] = []
        self._subs = [
            session.declare_subscriber(head_key(SITE), self._on_head),
            session.declare_subscriber(status_key(SITE), self._on_status),
        ]

    def _on_head(self, sample) -> None:
        with self.lock:
            self.head = max(self.head, json.loads(sample.payload.to_bytes())["global_seq"])

    def _on_status(self, sample) -> None:
        with self.lock:
            self.statuses.append((time.monotonic(), json.loads(sample.payload.to_bytes())))

    def first(self, predicate, since: float = 0.0) -> tuple[float, dict] | None:
        with self.lock:
            return next(((t, s) for t, s in self.statuses if t >= since and predicate(s)), None)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def _alarms(status: dict) -> set[str]:
    return set(filter(None, str(status.get("alarm", "")).split(",")))


def _retries(log: Path) -> int:
    """The ledger's count of retries of its held batch, from its last status line."""
    counts = [int(line.get("disk_full_retries", 0)) for line in log_lines(log)
              if line.get("msg") == "status"]
    return counts[-1] if counts else 0


def _run_disk_full(tmp_path: Path, *, rate_hz: float, duration_s: float, retries: int,
                   disk_mb: int) -> dict:
    """One run on a tmpfs of ``disk_mb`` MiB: ``retries`` is how long the disk stays
    full, in retries of the held batch (one a second)."""
    router, endpoint = open_router()
    watch = Watch(router)
    ledger = loadgen = None
    report = tmp_path / "load.json"
    try:
        with small_disk(tmp_path / "disk", disk_mb) as disk:
            path = disk / "ledger.duckdb"
            ledger = stockpile("service", "ledger", "--ledger", str(path), "--site", SITE,
                               "--status-period", "0.5", "--queue-size", str(QUEUE_SIZE),
                               "--batch-size", "200", "--min-free-mb", str(MIN_FREE_MB),
                               *client_args(endpoint), stderr_path=tmp_path / "ledger.log")
            wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
            assert watch.first(lambda s: "low_disk" in _alarms(s)) is None
            loadgen = subprocess.Popen(
                [PYTHON, "-m", "services.loadgen", "--site", SITE, "--source", SOURCE,
                 "--type", "scan", "--beams", "101", "--rate", str(rate_hz),
                 "--duration", str(duration_s), "--cache", "100000", "--linger", "300",
                 "--wait-subscriber", "30", "--report", str(report), *client_args(endpoint)],
                stderr=open(tmp_path / "load.log", "w"), stdout=subprocess.DEVNULL)
            wait_until(lambda: watch.head >= 500, 30, "500 events committed before the fault")

            filler = disk / "filler"
            fill(filler)
            filled_at = time.monotonic()
            wait_until(lambda: watch.first(lambda s: "disk_full" in _alarms(s), filled_at),
                       20, "the disk_full alarm on the status key")
            _t, alarm = watch.first(lambda s: "disk_full" in _alarms(s), filled_at)
            assert alarm["error"] == "No space left on device", alarm
            assert alarm["free_bytes"] < MIN_FREE_MB << 20, alarm
            assert _alarms(alarm) == {"disk_full", "low_disk"}, alarm
            # paused, not crashed: alive, and its queue full, so the publisher is held back
            wait_until(lambda: watch.first(lambda s: s.get("backlog", 0) >= QUEUE_SIZE - 1,
                                           filled_at), 20, "the ledger's queue full")
            assert ledger.poll() is None and loadgen.poll() is None
            head_paused = watch.head
            # the fault lasts until the ledger has retried the held batch this many times
            # (from the log: a pause longer than Zenoh's block budget drops the link, and
            # with it the status key, until the ledger reconnects)
            wait_until(lambda: _retries(tmp_path / "ledger.log") >= retries, retries * 3 + 10,
                       f"{retries} retries of the held batch", interval_s=0.5)
            assert ledger.poll() is None, "the ledger service died on a full disk"
            assert watch.head == head_paused, "a batch committed on a full disk"

            filler.unlink()
            freed_at = time.monotonic()
            wait_until(lambda: watch.first(lambda s: "disk_full" not in _alarms(s), freed_at),
                       30, "the disk_full alarm cleared")
            recovered_at = watch.first(lambda s: "disk_full" not in _alarms(s), freed_at)[0]
            wait_until(report.exists, 120, "the publisher's report")
            published = json.loads(report.read_text())
            wait_until(lambda: watch.head >= published["count"] - 1, 180,
                       "every published event committed")
            caught_up_at = time.monotonic()
            assert stop(ledger) == 0
            ledger = None
            verify = subprocess.run([PYTHON, "-m", "stockpile.cli", "ledger", "verify",
                                     "--ledger", str(path)], capture_output=True, text=True)
            assert verify.returncode == 0, verify.stderr
            with open_ledger(path, read_only=True) as store:
                rows = list(store.read(sources=[SOURCE]))
                gaps = store.gaps()
                open_gaps = store.gaps(open_only=True)
                assert store.verify().ok
    finally:
        for process in (loadgen, ledger):
            if process is not None:
                stop(process)
        watch.close()
        router.close()

    seqs = [r.seq for r in rows]
    assert {r.epoch for r in rows} == {published["epoch"]}
    assert sorted(seqs) == list(range(published["count"])), "not every event exactly once"
    assert open_gaps == []
    lines = log_lines(tmp_path / "ledger.log")
    paused = [line for line in lines if line["msg"].startswith("ledger paused")]
    assert paused and "No space left on device" in paused[0]["detail"], paused
    assert any(line["msg"].startswith("ledger resumed") for line in lines)
    assert not any(line["msg"] == "writer failed" for line in lines)
    result = {"fault": "disk_full", "published": published["count"], "ledgered": len(rows),
              "gaps_open": len(open_gaps), "gaps_closed": len(gaps) - len(open_gaps),
              "recover_s": round(recovered_at - freed_at, 2),
              "caught_up_s": round(caught_up_at - freed_at, 2)}
    print(" ".join(f"{k}={v}" for k, v in result.items()))
    return result


def test_a_full_disk_pauses_the_ledger_and_it_resumes_losing_nothing(tmp_path):
    result = _run_disk_full(tmp_path, rate_hz=500.0, duration_s=12.0, retries=3, disk_mb=24)
    assert result["published"] == result["ledgered"] == 6_000


@pytest.mark.long_fault
def test_a_full_disk_for_a_minute_pauses_the_ledger_losing_nothing(tmp_path):
    """Longer than Zenoh holds a BLOCK publisher back: the router drops the ledger's link,
    the publisher goes on into its cache, and the ledger, resumed, takes the rest from
    the cache through its gap repair (closed gaps, none open).  The publisher goes on
    after the pause: the ledger learns of the jump from the next live event."""
    result = _run_disk_full(tmp_path, rate_hz=500.0, duration_s=90.0, retries=60,
                            disk_mb=128)
    assert result["published"] == result["ledgered"] == 45_000
