"""The recorder keeps the ledger's signed checkpoints, and an auditor checks a ledger
against the recorded session.

Real parts: a Zenoh router over mutual TLS on loopback with the access control generated
from a site PKI, the ledger service (checkpoints every second while the ledger grows)
and the recorder service as processes with their site certificates, the lab publishing
through an ``EventPublisher``; the MCAP file is read back with the ``mcap`` library and
checked with ``stockpile ledger verify --checkpoint SESSION.mcap``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import duckdb
import pytest
from mcap.reader import make_reader

from ledger import open_ledger
from ledger.checkpoint import read_mcap_checkpoints
from replay.recover import recover
from schemas.events import set_timestamp_ns
from schemas.stockpile.v1 import events_pb2 as pb
from services.publishing import EventPublisher
from services.service import ZenohOptions, open_session
from zenoh_helpers import (PYTHON, client_args, log_lines, open_router, site_pki, stockpile,
                           stop_all, wait_liveliness, wait_until)

SITE = "cpyard"
T0_NS = 1_790_000_000 * 1_000_000_000
TOPIC = f"stockpile/{SITE}/@ledger/checkpoint"
BATCH = 5


def _assay(n: int) -> pb.Assay:
    msg = pb.Assay(assay_id=f"AS-{n:04d}", lot_id="LOT-1", status=pb.FINAL, lab_id="lab1")
    msg.analytes.update({"Fe": 60.0 + n / 10})
    set_timestamp_ns(msg.window_start, T0_NS + n * 60 * 10**9)
    set_timestamp_ns(msg.window_end, T0_NS + (n + 1) * 60 * 10**9)
    set_timestamp_ns(msg.reported_time, T0_NS + (n + 60) * 60 * 10**9)
    return msg


def _recorded(log: Path) -> set[int]:
    """The global seqs of the checkpoints the recorder logged as written."""
    return {int(line["global_seq"]) for line in log_lines(log)
            if line.get("msg") == "checkpoint recorded"}


def _verify(ledger: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "stockpile.cli", "ledger", "verify", "--ledger",
                           str(ledger), *args], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Two batches of the lab's assays, each followed by a checkpoint the recorder kept."""
    base = tmp_path_factory.mktemp("recorded")
    pki = site_pki(base / "pki", SITE, {"ledger": "ledger", "rec1": "recorder",
                                        "lab1": "lab"})
    router, endpoint = open_router(pki, SITE)
    ledger_path, mcap_path = base / "yard.duckdb", base / "session.mcap"
    ledger_log, recorder_log = base / "ledger.log", base / "recorder.log"
    ledger = recorder = None
    lab = None
    try:
        ledger = stockpile("service", "ledger", "--site", SITE, "--ledger", str(ledger_path),
                           "--checkpoint-every", "1s", *client_args(endpoint, pki, "ledger"),
                           stderr_path=ledger_log)
        recorder = stockpile("service", "recorder", "--site", SITE, "--out", str(mcap_path),
                             *client_args(endpoint, pki, "rec1"), stderr_path=recorder_log)
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 60)
        wait_liveliness(router, f"stockpile/{SITE}/@live/recorder/**", 60)
        lab = open_session(ZenohOptions(mode="client", connect=(endpoint,), tls_dir=str(pki),
                                        tls_name="lab1"))
        publisher = EventPublisher(lab, SITE, "lab1", epoch=7)
        for batch in range(2):
            for n in range(batch * BATCH, (batch + 1) * BATCH):
                publisher.publish(_assay(n))
            last = (batch + 1) * BATCH - 1
            wait_until(lambda: last in _recorded(recorder_log)
                       or recorder.poll() is not None or ledger.poll() is not None, 60,
                       f"the recorder to keep the checkpoint of global_seq {last}")
            assert recorder.poll() is None and ledger.poll() is None
        publisher.close()
    finally:
        if lab is not None:
            lab.close()
        codes = stop_all(recorder, ledger)
        router.close()
    assert codes == [0, 0], (recorder_log.read_text()[-2000:], ledger_log.read_text()[-2000:])
    return {"base": base, "pki": pki, "ledger": ledger_path, "mcap": mcap_path,
            "checkpoints": Path(str(ledger_path) + ".checkpoints"), "recorder_log": recorder_log}


def test_the_recording_holds_each_checkpoint_byte_for_byte(session):
    with open(session["mcap"], "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        channels = [c for c in summary.channels.values() if c.topic == TOPIC]
        assert len(channels) == 1
        assert channels[0].message_encoding == "json" and channels[0].schema_id == 0
        recorded = [m.data for _s, _c, m in reader.iter_messages(topics=[TOPIC])]
        events = [c for _s, c, _m in reader.iter_messages() if c.topic != TOPIC]
        closing = [m for m in reader.iter_metadata() if m.name == "stockpile.recording"]
    assert len(events) == 2 * BATCH
    files = {p.read_bytes() for p in session["checkpoints"].glob("checkpoint-*.json")}
    assert recorded and set(recorded) <= files          # unchanged: the signature still holds
    seqs = [json.loads(data)["global_seq"] for data in recorded]
    assert BATCH - 1 in seqs and 2 * BATCH - 1 in seqs and seqs == sorted(seqs)
    assert json.loads(closing[0].metadata["checkpoints"]) == len(recorded)
    found, problem = read_mcap_checkpoints(session["mcap"])
    assert problem is None and [cp.global_seq for _t, cp in found] == seqs
    assert all(cp.signer == "ledger" and cp.site == SITE for _t, cp in found)


def test_the_ledger_verifies_against_the_recorded_session(session):
    done = _verify(session["ledger"], "--checkpoint", str(session["mcap"]), "--ca",
                   str(session["pki"] / "ca.pem"))
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    n = len(lines) - 1
    assert lines[0].startswith(f"ok: {2 * BATCH} rows verified") and n >= 2
    for i, line in enumerate(lines[1:], 1):
        assert line.startswith(f"ok: checkpoint {i}/{n} of {session['mcap']} (signed by "
                               f"ledger): the ledger holds the checkpointed prefix up to "
                               f"global_seq "), line
    assert lines[-1].endswith(f"global_seq {2 * BATCH - 1}")


def test_a_truncated_ledger_is_its_own_finding_against_the_session(session, tmp_path):
    ledger = tmp_path / "truncated.duckdb"
    shutil.copyfile(session["ledger"], ledger)
    keep = BATCH + 2
    with duckdb.connect(str(ledger)) as con:
        con.execute("DELETE FROM event_log WHERE global_seq >= ?", [keep])
    assert _verify(ledger).returncode == 0              # the chain alone cannot tell
    done = _verify(ledger, "--checkpoint", str(session["mcap"]), "--ca",
                   str(session["pki"] / "ca.pem"))
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    n = len(lines) - 1
    failed = [l for l in lines if l.startswith("FAILED")]
    assert failed and failed[-1] == (
        f"FAILED: checkpoint TRUNCATED {n}/{n} of {session['mcap']} (signed by ledger): the "
        f"ledger ends at global_seq {keep - 1}; the checkpoint made at "
        f"{json.loads(_last_checkpoint(session))['made_ns']} holds {2 * BATCH - 1} "
        f"({2 * BATCH - keep} rows are gone)")
    # the checkpoint of the first batch is still held: only the lost rows are reported
    assert any(l.startswith("ok: checkpoint ") and l.endswith(f"global_seq {BATCH - 1}")
               for l in lines)
    assert done.stderr == ""


def _last_checkpoint(session) -> bytes:
    found, _ = read_mcap_checkpoints(session["mcap"])
    made = found[-1][1].made_ns
    return next(p.read_bytes() for p in session["checkpoints"].glob(f"checkpoint-*-{made}.json"))


def test_replay_passes_over_the_checkpoint_channel(session, tmp_path):
    fresh = tmp_path / "replayed.duckdb"
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", "replay", str(session["mcap"]),
                           "--ledger", str(fresh), "--no-progress"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "not stockpile events" not in done.stderr
    with open_ledger(fresh, read_only=True) as store, \
            open_ledger(session["ledger"], read_only=True) as original:
        assert [(r.type, r.source, r.seq, r.payload) for r in store.read()] == [
            (r.type, r.source, r.seq, r.payload) for r in original.read()]


def test_recover_keeps_the_checkpoints_and_a_cut_file_gives_those_before_the_cut(
        session, tmp_path):
    fixed = tmp_path / "fixed.mcap"
    result = recover(session["mcap"], fixed)
    assert not result.report.damaged
    assert [cp for _t, cp in read_mcap_checkpoints(fixed)[0]] == [
        cp for _t, cp in read_mcap_checkpoints(session["mcap"])[0]]
    # a copy cut short (a recorder killed): no summary; the reading says where it stopped
    cut = tmp_path / "cut.mcap"
    data = session["mcap"].read_bytes()
    cut.write_bytes(data[:len(data) - 200])
    found, problem = read_mcap_checkpoints(cut)
    assert problem is not None
    assert [cp for _t, cp in found] == [cp for _t, cp in read_mcap_checkpoints(fixed)[0]][
        :len(found)]
    done = _verify(session["ledger"], "--checkpoint", str(cut))
    if found:
        assert done.returncode == 0, done.stdout + done.stderr
        assert done.stderr.startswith(f"stockpile: warning: {cut} is damaged (")
        assert len(done.stderr.splitlines()) == 1
    else:
        assert done.returncode == 2 and done.stderr.startswith("stockpile: error: no checkpoints")


def test_a_file_without_checkpoints_is_one_line(tmp_path):
    from replay.mcap_writer import EventWriter
    empty = tmp_path / "empty.mcap"
    EventWriter(empty).close()
    ledger = tmp_path / "l.duckdb"
    with open_ledger(ledger):
        pass
    done = _verify(ledger, "--checkpoint", str(empty))
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.splitlines() == [
        f"stockpile: error: no checkpoints in {empty} (was a ledger service publishing them "
        f"while it recorded?)"]
