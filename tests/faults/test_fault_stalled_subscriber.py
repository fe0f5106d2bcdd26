"""A subscriber stops reading for 8 s; its publisher is held back, and no link is closed.

Under congestion control BLOCK a subscriber that falls behind (a service catching up on
the publishers' caches after a restart, a ledger whose disk is full) fills the router's
queue towards it, which holds back the router and then the publishers.  Zenoh closes a
link whose BLOCK message waited longer than ``wait_before_close``, losing what was on
the way; every service then asks the caches again, which is more of the same load.  The
services set that wait to ``services.zenoh_config.BLOCK_WAIT_BEFORE_CLOSE_US``.

The case: a ``stockpile service router`` process over mutual TLS, a ``services.loadgen``
producer process publishing scans (BLOCK, no history asked by anyone), and a plain subscriber in the test
whose callback stops for ``STALL_S`` at the ``STALL_AT``-th event.  Every event must
arrive exactly once with no recovery at all, the producer's liveliness token must never
go (its link stayed up), and the producer's own publish stamps must show it was held
back for most of the stall (the backpressure reached it).
"""

from __future__ import annotations

import json
import subprocess
import threading
import time

import zenoh

from harness import SITE
from schemas.events import decode_attachment
from services.service import ZenohOptions, open_session
from services.zenoh_config import BLOCK_WAIT_BEFORE_CLOSE_US
from zenoh_helpers import (PYTHON, client_args, free_port, log_lines, site_pki, stockpile, stop,
                           wait_until)

#: scans of BEAMS ranges (4 bytes each) at RATE_HZ: 16 MB/s, so that the stall outlasts what
#: the sockets' buffers hold and the backpressure reaches the producer
RATE_HZ = 1_000.0
BEAMS = 4_000
DURATION_S = 14.0
#: how long the subscriber's callback stops, s: beyond zenoh's own 5 s default
STALL_S = 8.0
#: the event at which it stops
STALL_AT = 1_000
STAMP_EVERY = 10


def test_a_stalled_subscriber_holds_its_publisher_back_and_loses_nothing(tmp_path):
    assert BLOCK_WAIT_BEFORE_CLOSE_US > STALL_S * 1e6
    pki = site_pki(tmp_path / "pki", SITE, {"load0": "scanner", "slow": "recorder",
                                            "watch": "recorder"})
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router_log = tmp_path / "router.log"
    router = stockpile("service", "router", "--site", SITE, "--listen", endpoint,
                       "--tls-dir", str(pki), "--tls-name", "router", stderr_path=router_log)
    producer = None
    sessions: list[zenoh.Session] = []
    seqs: list[int] = []
    stalled: list[float] = []
    release = threading.Event()

    def on_sample(sample) -> None:
        _epoch, seq, _valid = decode_attachment(sample.attachment.to_bytes())
        seqs.append(seq)
        if seq == STALL_AT:
            stalled.append(time.monotonic())
            release.wait(STALL_S)   # the fault: the callback stops reading for STALL_S

    try:
        wait_until(lambda: any(r.get("msg") == "routing" for r in log_lines(router_log))
                   or router.poll() is not None, 60, "the router to listen")
        assert router.poll() is None, router_log.read_text()[-2000:]
        options = {name: ZenohOptions(mode="client", connect=(endpoint,), tls_dir=str(pki),
                                      tls_name=name) for name in ("slow", "watch")}
        slow, watch = (open_session(options[n]) for n in ("slow", "watch"))
        sessions += [slow, watch]
        tokens: list[str] = []
        watch.liveliness().declare_subscriber(f"stockpile/{SITE}/@v1/*/load0/@adv/**",
                                              lambda s: tokens.append(str(s.kind)))
        slow.declare_subscriber(f"stockpile/{SITE}/@v1/scan/load0", on_sample)
        report = tmp_path / "load0.json"
        producer = subprocess.Popen(
            [PYTHON, "-m", "services.loadgen", "--site", SITE, "--source", "load0",
             "--type", "scan", "--beams", str(BEAMS), "--rate", str(RATE_HZ), "--duration", str(DURATION_S), "--cache", "100",
             "--wait-subscriber", "60", "--report", str(report), "--linger", "600",
             "--stamp-every", str(STAMP_EVERY), *client_args(endpoint, pki, "load0")],
            stderr=open(tmp_path / "load0.log", "wb"))
        wait_until(report.exists, DURATION_S + STALL_S + 60, "the producer's report")
        published = json.loads(report.read_text())
        count = int(published["count"])
        wait_until(lambda: len(seqs) >= count, 60, f"{count} events at the subscriber")
        token_kinds = list(tokens)   # before the producer is stopped (its token goes then)
    finally:
        release.set()
        for session in sessions:
            session.close()
        codes = [stop(p) for p in (producer, router) if p is not None]
    assert stalled, "the subscriber never reached the stall"
    assert seqs == list(range(count)), (
        f"{len(seqs)} events for {count} published; missing "
        f"{sorted(set(range(count)) - set(seqs))[:10]}, duplicated {len(seqs) - len(set(seqs))}")
    assert str(zenoh.SampleKind.DELETE) not in token_kinds, (
        f"the producer's link closed: {token_kinds}")
    stamps = [t for _i, t in published["stamps"]]
    held_s = max(b - a for a, b in zip(stamps, stamps[1:]))
    assert held_s > STALL_S / 2, f"the producer was never held back (longest pause {held_s:.2f} s)"
    assert codes[-1] == 0, f"the router exited {codes[-1]}"
