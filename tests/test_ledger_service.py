"""The ledger service as a real process: batches, queryables, head, SIGKILL and recovery."""

from __future__ import annotations

import json
import threading
from collections import Counter
from pathlib import Path

import pytest
import zenoh

from schemas.events import encode_attachment, key_expr, set_timestamp_ns
from schemas.stockpile.v1 import events_pb2 as pb
from ledger import open_ledger
from services.ledger_client import LedgerClient, LedgerQueryError
from services.service import EventPublisher
from zenoh_helpers import (
    PYTHON,
    client_args,
    log_lines,
    open_router,
    site_pki,
    stockpile,
    stop,
    wait_liveliness,
    wait_until,
)

import subprocess

SITE = "load"
T0_NS = 1_790_000_000 * 1_000_000_000


def _clock(t_ns: int) -> pb.Clock:
    msg = pb.Clock()
    set_timestamp_ns(msg.time, t_ns)
    return msg


def _start_ledger(path: Path, endpoint: str, log: Path, *extra: str,
                  pki: Path | None = None) -> subprocess.Popen:
    return stockpile("service", "ledger", "--ledger", str(path), "--site", SITE,
                     "--status-period", "1", *client_args(endpoint, pki, "ledger"), *extra,
                     stderr_path=log)


def test_ledger_service_appends_serves_reads_and_quarantines(tmp_path):
    router, endpoint = open_router()
    path = tmp_path / "ledger.duckdb"
    ledger = _start_ledger(path, endpoint, tmp_path / "ledger.log")
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
        client = LedgerClient(router, SITE, timeout_s=10)
        assert client.head()["global_seq"] == -1
        publisher = EventPublisher(router, SITE, "sim.clock", epoch=5)
        for i in range(300):
            publisher.publish(_clock(T0_NS + i * 1_000_000_000))
        # a sample without the identity attachment and one with a broken payload
        router.put(key_expr(SITE, "clock", "bad.one"), b"\x01\x02")
        router.put(key_expr(SITE, "assay", "bad.two"), b"\xff\xff\xff",
                   attachment=encode_attachment(1, 0, T0_NS))
        client.wait_for(lambda h: h["global_seq"] >= 299, 30)
        wait_until(lambda: client.stats()["quarantined"] == 2, 30, "two quarantined samples")

        records = client.read(0)
        assert [r.seq for r in records] == list(range(300))
        assert [r.global_seq for r in records] == list(range(300))
        assert all(r.source == "sim.clock" and r.epoch == 5 for r in records)
        assert [r.seq for r in client.read(100, 110)] == list(range(100, 110))
        assert client.read(0, types=["assay"]) == []
        as_of = client.as_of(T0_NS + 9 * 1_000_000_000, 2**62)
        assert [r.seq for r in as_of] == list(range(10))
        stats = client.stats()
        assert stats["events"] == 300 and stats["per_source"] == {"sim.clock": 300}
        assert client.gaps() == []
        with pytest.raises(LedgerQueryError, match="valid_time_ns"):  # a query missing V
            client._records("as_of", {})  # noqa: SLF001
        head = client.head()
    finally:
        code = stop(ledger)
        router.close()
    assert code == 0
    lines = log_lines(tmp_path / "ledger.log")
    assert any(line["msg"] == "quarantined" for line in lines)
    assert lines[-1]["msg"] == "stopped" and lines[-1]["reason"] == "SIGTERM"
    # what the service answered is what the file holds
    with open_ledger(path, read_only=True) as store:
        stored = list(store.read())
        assert [r.payload for r in stored] == [r.payload for r in records]
        assert store.head().chain_sha256.hex() == head["chain_sha256"]
        assert len(store.quarantine()) == 2
        assert store.verify().ok


def _start_loadgens(tmp_path: Path, endpoint: str, *, n: int, rate: float, duration_s: float,
                    cache: int, pki: Path | None = None
                    ) -> tuple[list[subprocess.Popen], list[Path]]:
    procs, reports = [], []
    for i in range(n):
        report = tmp_path / f"load{i}.json"
        reports.append(report)
        procs.append(subprocess.Popen(
            [PYTHON, "-m", "services.loadgen", "--site", SITE, "--source", f"load{i}",
             "--rate", str(rate), "--duration", str(duration_s), "--cache", str(cache),
             "--linger", "300", "--wait-subscriber", "60", "--report", str(report),
             "--seed", str(i), *client_args(endpoint, pki, f"load{i}")],
            stderr=open(tmp_path / f"load{i}.log", "w"), stdout=subprocess.DEVNULL))
    return procs, reports


@pytest.mark.slow
@pytest.mark.parametrize("cache_samples", [60_000, 1_000], ids=["cache-covers-outage",
                                                                 "cache-too-small"])
def test_sigkill_mid_run_loses_nothing_or_records_the_exact_gaps(tmp_path, cache_samples):
    """4 publishers x 2,000 events/s x 12 s; the ledger service is SIGKILLed mid-run.

    With a publisher cache larger than the outage every event must end in the ledger
    exactly once; with a small cache the unrecoverable ones must be exactly the open
    gaps, and nothing else may be missing.  Over mutual TLS, with the access control
    generated for the roles (the publishers are PLCs, each its own source).
    """
    n_pub, rate, duration_s = 4, 2000.0, 12.0
    pki = site_pki(tmp_path / "pki", SITE,
                   {"ledger": "ledger", **{f"load{i}": "plc" for i in range(n_pub)}})
    router, endpoint = open_router(pki, SITE)
    seen: Counter[str] = Counter()
    lock = threading.Lock()

    def count(sample) -> None:
        with lock:
            seen[str(sample.key_expr).rsplit("/", 1)[1]] += 1

    watcher = router.declare_subscriber(f"stockpile/{SITE}/@v1/**", count)
    path = tmp_path / "ledger.duckdb"
    ledger = _start_ledger(path, endpoint, tmp_path / "ledger1.log", pki=pki)
    loadgens: list[subprocess.Popen] = []
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
        client = LedgerClient(router, SITE, timeout_s=20)
        loadgens, reports = _start_loadgens(tmp_path, endpoint, n=n_pub, rate=rate,
                                            duration_s=duration_s, cache=cache_samples,
                                            pki=pki)
        # kill once the first ledger has committed a good part of the run
        client.wait_for(lambda h: h["global_seq"] >= 12_000, 90)
        ledger.kill()
        assert ledger.wait(30) == -9
        with lock:
            at_kill = dict(seen)
        # an outage longer than the small cache: 3,000 more events per source
        wait_until(lambda: all(seen[f"load{i}"] >= at_kill.get(f"load{i}", 0) + 3_000
                               for i in range(n_pub)), 90, "3,000 events per source while down")
        ledger = _start_ledger(path, endpoint, tmp_path / "ledger2.log", pki=pki)
        wait_until(lambda: all(r.exists() for r in reports), 120, "the publishers' reports")
        published = {}
        for r in reports:
            rep = json.loads(r.read_text())
            published[rep["source"]] = (rep["epoch"], rep["count"])
            assert rep["count"] == int(rate * duration_s)
            assert rep["rate_hz"] >= 0.95 * rate, rep  # the publishers kept their rate

        def accounted() -> bool:
            stats = client.stats()
            gaps = client.gaps(open_only=True)
            for source, (_epoch, n) in published.items():
                missing = sum(g["last_seq"] - g["first_seq"] + 1 for g in gaps
                              if g["source"] == source)
                if stats["per_source"].get(source, 0) + missing != n:
                    return False
            return True

        wait_until(accounted, 120, "every published event stored or in a gap", interval_s=0.2)
    finally:
        for proc in loadgens:
            stop(proc)
        code = stop(ledger)
        watcher.undeclare()
        router.close()
    assert code == 0

    with open_ledger(path, read_only=True) as store:
        assert store.verify().ok
        open_gaps = store.gaps(open_only=True)
        lost_total = 0
        for source, (epoch, n) in published.items():
            rows = list(store.read(sources=[source]))
            seqs = [r.seq for r in rows]
            assert len(seqs) == len(set(seqs)), f"{source}: duplicates in the ledger"
            assert {r.epoch for r in rows} == {epoch}
            assert all(0 <= s < n for s in seqs)
            gap_seqs: set[int] = set()
            for g in open_gaps:
                if g.source == source:
                    assert g.epoch == epoch
                    span = set(range(g.first_seq, g.last_seq + 1))
                    assert not (span & gap_seqs)
                    gap_seqs |= span
            missing = set(range(n)) - set(seqs)
            assert missing == gap_seqs, f"{source}: missing events not exactly the open gaps"
            lost_total += len(missing)
    if cache_samples >= rate * duration_s:
        assert lost_total == 0, "the cache covered the outage: nothing may be lost"
    else:
        # 3,000 events per source were published while the ledger was down, the cache
        # holds 1,000: at least 2,000 per source could not be recovered
        assert lost_total >= n_pub * 2_000
    lines = log_lines(tmp_path / "ledger2.log")
    assert any(line["msg"] == "serving" and int(line["head"]) >= 12_000 for line in lines)


def test_a_client_waiting_for_the_ledger_gives_up_at_once_when_stopped():
    # a "ledger" that takes every query and never answers (it holds the queries open)
    import time

    from services.ledger_client import LedgerUnavailable
    from services.ledger_service import query_key
    from services.service import ZenohOptions

    router, endpoint = open_router()
    held: list = []
    session = None
    try:
        queryable = router.declare_queryable(query_key("stuck", "head"), held.append)
        session = zenoh.open(ZenohOptions(mode="client", connect=(endpoint,)).to_config())
        # without a stop event the wait is the query's whole timeout (Zenoh then
        # answers "Timeout" itself)
        t0 = time.monotonic()
        with pytest.raises((LedgerUnavailable, LedgerQueryError)):
            LedgerClient(session, "stuck", timeout_s=1.0).head()
        assert time.monotonic() - t0 >= 0.9
        # with one, setting it ends a 30 s wait at once (a service's SIGTERM)
        stop = threading.Event()
        timer = threading.Timer(0.3, stop.set)
        timer.start()
        t0 = time.monotonic()
        with pytest.raises(LedgerUnavailable, match="stopped"):
            LedgerClient(session, "stuck", timeout_s=30.0, stop=stop).head()
        assert 0.25 <= time.monotonic() - t0 < 3.0
        assert held, "the queries reached the stuck queryable"
        queryable.undeclare()
    finally:
        held.clear()
        if session is not None:
            session.close()
        router.close()
