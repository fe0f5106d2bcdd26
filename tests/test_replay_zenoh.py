"""Replay onto Zenoh and the recorder service, as real processes on a loopback router.

A small session file (scans, joint readings, clock ticks and assays from three
sources, seeded) is replayed onto Zenoh while the ledger service and the recorder
service (rotating its file by size) listen.  Checks: the ledger then holds exactly
the file's identities with byte-identical payloads; replaying the same file again
adds nothing; ``--rate`` paces by valid time and ``--topics`` selects; the recorder's
parts, SIGKILLed at the end and recovered, hold every event exactly once.
"""

from __future__ import annotations

import math
import random
import subprocess
import sys
import time
from pathlib import Path

from mcap.reader import make_reader

from ledger import open_ledger
from replay.mcap_records import RawMessage
from replay.mcap_scan import McapScan
from replay.mcap_writer import EventWriter
from replay.replay import iter_events
from schemas import pb
from schemas.events import key_expr, make_event, set_timestamp_ns
from stockpile.cli import main as stockpile_main
from services.ledger_client import LedgerClient
from zenoh_helpers import (
    client_args,
    log_lines,
    open_router,
    stockpile,
    stop,
    wait_liveliness,
    wait_until,
)

SITE = "replaysite"
T0_NS = 1_793_491_200 * 1_000_000_000
from schemas.times import NS_PER_S as S  # noqa: E402


def _stamp(msg, name: str, t_ns: int):
    set_timestamp_ns(getattr(msg, name), t_ns)
    return msg


def _session(path: Path, seed: int) -> list:
    """Write a 3-site-second session of 3 sources to ``path``; return its events."""
    from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan

    rng = random.Random(seed)
    events, seqs = [], {"sim.clock": 0, "bwr1.encoders": 0, "bwr1.scanner": 0}

    def add(msg, source: str) -> None:
        events.append(make_event(msg, source=source, epoch=7, seq=seqs[source]))
        seqs[source] += 1

    for i in range(300):  # 100 Hz for 3 s
        t = T0_NS + i * S // 100
        if i % 10 == 0:
            add(_stamp(pb.Clock(), "time", t), "sim.clock")
        add(_stamp(pb.JointReading(machine_id="bwr1", travel_m=rng.uniform(0, 60),
                                   slew_rad=rng.uniform(-1, 1), luff_rad=rng.uniform(-0.2, 0.2)),
                   "time", t), "bwr1.encoders")
        if i % 3 == 0:
            scan = LaserScan(frame_id="bwr1/scanner", start_angle=-math.radians(50),
                             end_angle=math.radians(50),
                             ranges=[rng.uniform(1, 40) for _ in range(401)])
            add(_stamp(scan, "timestamp", t), "bwr1.scanner")
    writer = EventWriter(path, chunk_size_bytes=64 * 1024)
    for e in events:  # received 5 ms after it happened
        writer.write_event(SITE, e, e.valid_time_ns + 5_000_000)
    writer.close()
    return events


def _identities(events) -> list[tuple]:
    return sorted((e.type, e.source, e.epoch, e.seq, e.valid_time_ns, bytes(e.payload))
                  for e in events)


def _last_status(log: Path) -> dict[str, str]:
    status = [r for r in log_lines(log) if r.get("msg") == "status"]
    return status[-1] if status else {}


def test_replay_publishes_exact_identities_idempotently_and_the_recorder_keeps_them(
        tmp_path, capsys, seed):
    session = tmp_path / "session.mcap"
    events = _session(session, seed)
    n = len(events)
    router, endpoint = open_router()
    ledger_log, recorder_log = tmp_path / "ledger.log", tmp_path / "recorder.log"
    ledger = stockpile("service", "ledger", "--ledger", str(tmp_path / "ledger.duckdb"),
                       "--site", SITE, "--status-period", "0.2", *client_args(endpoint),
                       stderr_path=ledger_log)
    recorder = stockpile("service", "recorder", "--out", str(tmp_path / "rec.mcap"),
                         "--site", SITE, "--split-size", "200000", "--flush-interval", "0.2",
                         "--status-period", "0.2", *client_args(endpoint),
                         stderr_path=recorder_log)
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
        wait_liveliness(router, f"stockpile/{SITE}/@live/recorder/**", 30)
        client = LedgerClient(router, SITE, timeout_s=10)

        # 1. the file onto Zenoh as fast as it goes, by the real command in its own process
        first = _replay_process(session, endpoint, "--max", "--linger", "0.5")
        assert first.returncode == 0, first.stderr[-2000:]
        assert f"published {n:,} events" in first.stdout
        wait_until(lambda: client.stats()["events"] == n, 30, "the ledger to hold the session")
        wait_until(lambda: int(_last_status(recorder_log).get("recorded", 0)) == n, 30,
                   "the recorder to hold the session")

        # a sample that is no event (no identity attachment): quarantined by the ledger,
        # kept by the recorder
        router.put(key_expr(SITE, "clock", "bad.one"), b"\x01\x02")
        wait_until(lambda: client.stats()["quarantined"] == 1, 30, "the ledger's quarantine")
        wait_until(lambda: int(_last_status(recorder_log).get("malformed", 0)) == 1, 30,
                   "the recorder to keep the malformed sample")

        # 2. the same file again (in this process this time): the ledger adds nothing
        code = stockpile_main(["replay", str(session), "--publish", "--max", "--linger", "0.2",
                               "--no-progress", *client_args(endpoint)])
        assert code == 0
        # (at least n: a new publisher's cache may also be asked when its token appears,
        # services/resubscribe.py, and what that brings is duplicates too)
        wait_until(lambda: int(_last_status(ledger_log).get("duplicate", 0)) >= n, 30,
                   "the ledger to see the second replay as duplicates")
        assert client.stats()["events"] == n
        wait_until(lambda: int(_last_status(recorder_log).get("duplicates", 0)) >= n, 30,
                   "the recorder to drop the second replay as duplicates")

        # 3. paced by valid time: 3 site seconds of clock ticks at 4x take about 0.75 s
        capsys.readouterr()
        started = time.monotonic()
        code = stockpile_main(["replay", str(session), "--publish", "--rate", "4", "--topics",
                               f"stockpile/{SITE}/@v1/clock/**", "--linger", "0",
                               "--no-progress", *client_args(endpoint)])
        whole_s = time.monotonic() - started
        out = capsys.readouterr().out
        ticks = sum(1 for e in events if e.type == "clock")
        assert code == 0 and f"published {ticks} events" in out, out
        paced_s = float(out.split(" s = ")[0].rsplit(" in ", 1)[1])  # the publishing itself
        span_s = (max(e.valid_time_ns for e in events if e.type == "clock") - T0_NS) / S
        assert span_s / 4 * 0.95 <= paced_s <= whole_s, (paced_s, span_s)
        assert paced_s < span_s / 4 + 1.0, (paced_s, span_s)  # not real time (1x: 2.9 s)

        # 4. the recorder flushed every part; kill it without warning
        wait_until(lambda: _messages_in(tmp_path) == n, 30, "the recorder's files to hold it all")
        recorder.kill()
        recorder.wait(10)
    finally:
        if recorder.poll() is None:
            stop(recorder)
        stop(ledger)
        router.close()

    with open_ledger(tmp_path / "ledger.duckdb", read_only=True) as store:
        assert _identities(r for r in store.read()) == _identities(events)
        assert store.gaps() == []
        assert [q.code for q in store.quarantine()] == ["bad_attachment"]

    parts = sorted(tmp_path.glob("rec-*.mcap"))
    assert len(parts) >= 2, parts  # rotated by size
    *closed, killed = parts
    for part in closed:  # complete files
        with open(part, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            assert reader.get_summary() is not None
            assert sum(1 for _ in reader.iter_messages()) > 0
    fixed = tmp_path / "fixed.mcap"
    capsys.readouterr()
    code = stockpile_main(["record", "--recover", str(killed), str(fixed)])
    out = capsys.readouterr().out
    assert code == 1 and "lost: 0 messages and an unknown number" in out  # it was never closed
    recorded = [e for part in closed for e in iter_events(part)] + list(iter_events(fixed))
    assert _identities(recorded) == _identities(events)  # each exactly once, nothing lost
    # replayed into a ledger, the recording gives the events and the quarantined sample
    again = tmp_path / "again.duckdb"
    for part in [*closed, fixed]:
        assert stockpile_main(["replay", str(part), "--ledger", str(again), "--no-progress"]) == 0
    with open_ledger(again, read_only=True) as store:
        assert _identities(store.read()) == _identities(events)
        assert [(q.source, q.raw) for q in store.quarantine()] == [("bad.one", b"\x01\x02")]


def _messages_in(folder: Path) -> int:
    """Messages readable now in the recorder's parts (the open one read as it stands)."""
    total = 0
    for part in sorted(folder.glob("rec-*.mcap")):
        with McapScan(part) as scan:
            total += sum(1 for r in scan.records() if type(r) is RawMessage)
    return total


def _replay_process(session: Path, endpoint: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", "replay", str(session),
                           "--publish", *args, "--no-progress", *client_args(endpoint)],
                          capture_output=True, text=True, timeout=120)
