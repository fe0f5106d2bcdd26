"""The simulator publishes its events on Zenoh: a real subscriber session gets every one."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
from pathlib import Path

import zenoh

from schemas.events import event_from_sample, site_key_expr
from schemas.jsonl import decode_line
from services.zenoh_config import zenoh_config

STOCKPILE = str(Path(sys.executable).with_name("stockpile"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_every_event_arrives_on_zenoh_with_its_identity(tmp_path):
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    received = []
    lock = threading.Lock()

    def on_sample(sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        with lock:
            received.append(event_from_sample(str(sample.key_expr), sample.payload.to_bytes(),
                                              attachment))

    session = zenoh.open(zenoh_config(listen=[endpoint]))  # loopback, scouting off
    try:
        subscriber = session.declare_subscriber(site_key_expr("capelambert"), on_sample)
        sim = subprocess.run(
            [STOCKPILE, "sim", "--scenario", "demo", "--seed", "7", "--duration", "0.03",
             "--out", str(tmp_path), "--zenoh", "--listen", f"tcp/127.0.0.1:{_free_port()}",
             "--connect", endpoint, "--wait-subscriber", "30"],
            capture_output=True, text=True, timeout=300)
        assert sim.returncode == 0, sim.stderr
        expected = [decode_line(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
        # the publisher blocks rather than drops, and the session closes after the last
        # put: everything is in flight or delivered; drain by closing our subscriber
        subscriber.undeclare()
    finally:
        session.close()
    assert len(expected) > 100
    with lock:
        got = list(received)
    assert len(got) == len(expected)
    assert sorted((e.source, e.seq) for e in got) == sorted((e.source, e.seq) for e in expected)
    by_key = {(e.source, e.epoch, e.seq): e for e in got}
    for e in expected:
        assert by_key[(e.source, e.epoch, e.seq)] == e  # same payload, valid time, identity
