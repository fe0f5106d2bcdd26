"""Signed events keep their signer and signature through MCAP (issue 37).

Real parts throughout: Ed25519 keys made and declared as a site does
(:mod:`ledger.testing_signing`), DuckDB ledgers opened with the admin key pinned, the
``stockpile`` command line run in this process, the MCAP files read back with the
``mcap`` library.  The recorder's path runs a Zenoh router over mutual TLS on loopback,
the recorder service as a process with its site certificate and the lab publishing
signed assays through an ``EventPublisher`` (the helpers of ``tests/zenoh_helpers.py``).

1. export-mcap -> replay --ledger --admin-key: the replayed ledger is the same ledger,
   row for row (signer and signature included), verifies with the same head chain and
   quarantines nothing; the file holds one signature message before each signed event.
2. record -> replay --ledger --admin-key: the lab's signed assays are appended with the
   signatures the lab made (its unsigned ones quarantined as ``unsigned``); record ->
   replay --publish: a subscriber receives each event exactly as the lab published it,
   signed ones with their version-2 attachment.
3. A signature message tampered with in the file: that event is quarantined as
   ``bad_signature``, every other one kept.
"""

from __future__ import annotations

import base64
import json
import subprocess
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from ledger import open_ledger
from ledger.clock import ManualClock
from ledger.signing import SigningPolicy, sign_event
from ledger.testing_signing import assay, key_declared, make_keys
from replay.recover import recover
from replay.mcap_format import SIGNATURE_SUFFIX, decode_signature, encode_signature
from replay.replay import iter_events
from schemas.events import Event, set_timestamp_ns
from schemas.stockpile.v1 import events_pb2 as pb
from services.publishing import EventPublisher
from services.service import ZenohOptions, open_session
from cli_in_process import run
from stockpile.cli import main as stockpile
from zenoh_helpers import (EventSink, PYTHON, client_args, log_lines, open_router, site_pki,
                           stockpile as stockpile_process, stop_all, wait_liveliness, wait_until)

SITE = "sigyard"
S = 10**9
T0_NS = 1_790_000_000 * S
N_ASSAYS = 6


@pytest.fixture(scope="module")
def signed_ledger(tmp_path_factory):
    """A ledger that requires signed assays: the admin's and the lab's keys declared,
    signed assays, and an unsigned clock event between them."""
    base = tmp_path_factory.mktemp("signed")
    keys = make_keys(base / "keys", "admin", "lab")
    admin, lab = keys["admin"], keys["lab"]
    path = base / "yard.duckdb"
    clock = ManualClock(T0_NS)
    with open_ledger(path, clock, signing=SigningPolicy(frozenset({"assay"}),
                                                        admin.key_id)) as store:
        result = store.append([key_declared(admin, admin, "admin", "site admin", 0, T0_NS),
                               key_declared(admin, lab, "lab", "lab1", 1, T0_NS)])
        assert result.appended == 2, result
        for n in range(N_ASSAYS):
            clock.set_ns(T0_NS + (n + 1) * 60 * S)
            assert store.append([sign_event(assay(n, T0_NS + n * S, fe=60.0 + n), lab)]).appended == 1
        assert store.quarantine() == [] and store.verify().ok
    return {"ledger": path, "admin_pub": base / "keys" / "admin.sign.pub", "keys": keys,
            "base": base}


@pytest.fixture(scope="module")
def exported(signed_ledger):
    out = signed_ledger["base"] / "export.mcap"
    assert stockpile(["export-mcap", "--ledger", str(signed_ledger["ledger"]), "--out", str(out),
                      "--site", SITE, "--no-progress"]) == 0
    return out


def _rows(path: Path) -> list:
    with open_ledger(path, read_only=True) as store:
        return list(store.read())


def test_export_then_replay_into_a_ledger_requiring_signatures_is_the_same_ledger(
        signed_ledger, exported, tmp_path, capsys):
    fresh = tmp_path / "replayed.duckdb"
    admin_key = str(signed_ledger["admin_pub"])
    code, out, err = run(capsys, "replay", str(exported), "--ledger", str(fresh),
                         "--admin-key", admin_key, "--no-progress")
    assert code == 0, out + err
    n = 2 + N_ASSAYS
    assert f"{n} events -> {n} appended, 0 duplicate, 0 conflict, 0 rejected" in out
    assert f"{n} signed events kept their signatures (checked against" in out
    original, replayed = _rows(signed_ledger["ledger"]), _rows(fresh)
    assert replayed == original                          # every field, signer and signature
    assert all(r.signer is not None and len(r.signature) == 64 for r in replayed)
    with open_ledger(fresh, read_only=True) as store, \
            open_ledger(signed_ledger["ledger"], read_only=True) as source:
        assert store.quarantine() == []
        assert store.head() == source.head()            # the same head chain
    code, out, err = run(capsys, "ledger", "verify", "--ledger", str(fresh),
                         "--admin-key", admin_key)
    assert code == 0 and out.startswith(f"ok: {n} rows verified"), out + err
    assert "keys anchored by the admin key given" in out, out
    # a second replay adds nothing
    code, out, _ = run(capsys, "replay", str(exported), "--ledger", str(fresh),
                       "--admin-key", admin_key, "--no-progress")
    assert code == 0 and f"0 appended, {n} duplicate" in out
    # --topics selects a signature channel by its events' topic
    only = tmp_path / "assays.duckdb"
    with open_ledger(only, ManualClock(T0_NS)) as store:
        store.append([r.to_event() for r in original[:2]])   # the key declarations
    code, out, err = run(capsys, "replay", str(exported), "--ledger", str(only), "--admin-key",
                         admin_key, "--topics", f"stockpile/{SITE}/@v1/assay/**",
                         "--no-progress")
    assert code == 0 and f"{N_ASSAYS} appended, 0 duplicate, 0 conflict, 0 rejected" in out, \
        out + err
    assert _rows(only) == original


def test_the_file_holds_one_signature_message_before_each_signed_event(signed_ledger, exported):
    rows = {(r.source, r.epoch, r.seq): r for r in _rows(signed_ledger["ledger"])}
    with open(exported, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        messages = list(reader.iter_messages(log_time_order=False))
    signatures = [(c, m) for _s, c, m in messages if c.topic.endswith(SIGNATURE_SUFFIX)]
    events = [(c, m) for _s, c, m in messages if not c.topic.endswith(SIGNATURE_SUFFIX)]
    assert len(signatures) == len(events) == len(rows)
    for i, (channel, message) in enumerate(signatures):
        event_channel, event = events[i]
        # written just before its event: same sequence and times, on <topic>/@signature
        assert messages.index((_schema_of(messages, channel), channel, message)) == \
            messages.index((_schema_of(messages, event_channel), event_channel, event)) - 1
        assert channel.topic == event_channel.topic + SIGNATURE_SUFFIX
        assert channel.schema_id == 0 and channel.message_encoding == "json"
        assert channel.metadata == {"kind": "stockpile.signature", **event_channel.metadata}
        assert (message.sequence, message.log_time, message.publish_time) == (
            event.sequence, event.log_time, event.publish_time)
        row = rows[(event_channel.metadata["source"], int(event_channel.metadata["epoch"]),
                    event.sequence)]
        body = json.loads(message.data)
        assert body == {"signer": row.signer,
                        "signature": base64.b64encode(row.signature).decode()}
        assert decode_signature(message.data) == (row.signer, row.signature)
    assert [(e.signer, e.signature) for e in iter_events(exported)] == [
        (r.signer, r.signature) for r in rows.values()]



def test_recover_keeps_the_signature_channels(exported, tmp_path):
    fixed = tmp_path / "fixed.mcap"
    assert not recover(exported, fixed).report.damaged
    assert list(iter_events(fixed)) == list(iter_events(exported))
    assert all(e.signature is not None for e in iter_events(fixed))


def _schema_of(messages, channel):
    return next(s for s, c, _m in messages if c is channel)


def _rewrite(source: Path, target: Path, change) -> None:
    """Copy ``source`` into ``target`` with the ``mcap`` library, message by message in
    file order, ``change(channel, message)`` giving each message's new data."""
    with open(source, "rb") as f, open(target, "wb") as out:
        reader = make_reader(f)
        writer = Writer(out)
        writer.start()
        schemas, channels = {}, {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding,
                                                            schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding,
                    schemas[schema.id] if schema is not None else 0, channel.metadata)
            writer.add_message(channels[channel.id], message.log_time,
                               change(channel, message), message.publish_time,
                               message.sequence)
        writer.finish()


def test_a_tampered_signature_message_is_quarantined_as_bad_signature(
        signed_ledger, exported, tmp_path, capsys):
    victim = 3  # the lab's assay of seq 3

    def tamper(channel, message) -> bytes:
        if channel.topic.endswith(SIGNATURE_SUFFIX) and channel.metadata["source"] == "lab1" \
                and message.sequence == victim:
            signer, signature = decode_signature(message.data)
            return encode_signature(signer, bytes([signature[0] ^ 1]) + signature[1:])
        return message.data

    tampered = tmp_path / "tampered.mcap"
    _rewrite(exported, tampered, tamper)
    fresh = tmp_path / "replayed.duckdb"
    code, out, err = run(capsys, "replay", str(tampered), "--ledger", str(fresh),
                         "--admin-key", str(signed_ledger["admin_pub"]), "--no-progress")
    n = 2 + N_ASSAYS
    assert code == 0, out + err
    assert f"{n} events -> {n - 1} appended, 0 duplicate, 0 conflict, 1 rejected" in out
    original = [r for r in _rows(signed_ledger["ledger"])
                if not (r.source == "lab1" and r.seq == victim)]
    with open_ledger(fresh, read_only=True) as store:
        kept = list(store.read())
        [entry] = store.quarantine()
        assert entry.code == "bad_signature", entry
        assert (entry.source, entry.seq) == ("lab1", victim)
        assert store.verify().ok
    # the others as they were (their global seqs and chain after the gap differ)
    assert [r._replace(global_seq=0, chain_sha256=b"") for r in kept] == [
        r._replace(global_seq=0, chain_sha256=b"") for r in original]


def test_a_file_without_signatures_replays_unsigned_and_a_signing_ledger_says_so(
        signed_ledger, tmp_path, capsys):
    lab = signed_ledger["keys"]["lab"]
    admin = signed_ledger["keys"]["admin"]
    source = tmp_path / "source.duckdb"
    with open_ledger(source, ManualClock(T0_NS)) as store:   # no policy: keeps unsigned
        store.append([key_declared(admin, admin, "admin", "site admin", 0, T0_NS),
                      key_declared(admin, lab, "lab", "lab1", 1, T0_NS), assay(0, T0_NS)])
    plain = tmp_path / "plain.mcap"
    assert stockpile(["export-mcap", "--ledger", str(source), "--out", str(plain),
                      "--no-progress"]) == 0
    assert [e.signer for e in iter_events(plain)] == [admin.key_id, admin.key_id, None]
    fresh = tmp_path / "fresh.duckdb"
    code, out, err = run(capsys, "replay", str(plain), "--ledger", str(fresh),
                         "--admin-key", str(signed_ledger["admin_pub"]), "--no-progress")
    assert code == 0 and "2 appended, 0 duplicate, 0 conflict, 1 rejected" in out, out + err
    with open_ledger(fresh, read_only=True) as store:
        assert [q.code for q in store.quarantine()] == ["unsigned"]
    code, _out, err = run(capsys, "replay", str(plain), "--publish", "--admin-key",
                          str(signed_ledger["admin_pub"]))
    assert code == 2 and "--admin-key and --signed-types are for --ledger" in err


# -- the recorder -----------------------------------------------------------------------------

LAB_EPOCH, UNSIGNED_EPOCH = 7, 8


def _lab_assay(n: int) -> pb.Assay:
    msg = pb.Assay(assay_id=f"AS-{n:04d}", lot_id="LOT-1", status=pb.FINAL, lab_id="lab1")
    msg.analytes.update({"Fe": 60.0 + n / 10})
    set_timestamp_ns(msg.window_start, T0_NS + n * 60 * S)
    set_timestamp_ns(msg.window_end, T0_NS + (n + 1) * 60 * S)
    return msg


def _recorded(log: Path) -> int:
    status = [r for r in log_lines(log) if r.get("msg") == "status"]
    return int(status[-1].get("recorded", 0)) if status else 0


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The lab publishes signed assays (and, from an older unsigned setup, a few unsigned
    ones) through an mTLS router while the recorder service records them."""
    base = tmp_path_factory.mktemp("recording")
    keys = make_keys(base / "keys", "admin", "lab1")
    pki = site_pki(base / "pki", SITE, {"rec1": "recorder", "lab1": "lab",
                                        "replay1": "replay"})
    router, endpoint = open_router(pki, SITE)
    mcap_path, recorder_log = base / "session.mcap", base / "recorder.log"
    recorder = lab = None
    signed_events, unsigned_events = [], []
    try:
        recorder = stockpile_process("service", "recorder", "--site", SITE, "--out",
                                     str(mcap_path), "--flush-interval", "0.2",
                                     "--status-period", "0.2",
                                     *client_args(endpoint, pki, "rec1"),
                                     stderr_path=recorder_log)
        wait_liveliness(router, f"stockpile/{SITE}/@live/recorder/**", 60)
        lab = open_session(ZenohOptions(mode="client", connect=(endpoint,), tls_dir=str(pki),
                                        tls_name="lab1"))
        signing = EventPublisher(lab, SITE, "lab1", epoch=LAB_EPOCH, signing_key=keys["lab1"])
        plain = EventPublisher(lab, SITE, "lab1", epoch=UNSIGNED_EPOCH)
        for n in range(N_ASSAYS):
            signed_events.append(signing.publish(_lab_assay(n)))
            if n % 3 == 0:
                unsigned_events.append(plain.publish(_lab_assay(100 + n)))
        total = len(signed_events) + len(unsigned_events)
        wait_until(lambda: _recorded(recorder_log) >= total or recorder.poll() is not None, 60,
                   f"the recorder to record {total} assays")
        assert _recorded(recorder_log) == total, recorder_log.read_text()[-2000:]
        signing.close()
        plain.close()
    finally:
        if lab is not None:
            lab.close()
        codes = stop_all(recorder)
    assert codes == [0], recorder_log.read_text()[-2000:]
    yield {"base": base, "keys": keys, "pki": pki, "router": router, "endpoint": endpoint,
           "mcap": mcap_path, "signed": signed_events, "unsigned": unsigned_events}
    router.close()


def test_recorded_signed_assays_replay_into_a_ledger_requiring_signatures(recording, tmp_path,
                                                                          capsys):
    keys = recording["keys"]
    admin, lab = keys["admin"], keys["lab1"]
    assert all(e.signer == lab.key_id for e in recording["signed"])
    fresh = tmp_path / "replayed.duckdb"
    with open_ledger(fresh, ManualClock(T0_NS),
                     signing=SigningPolicy(frozenset({"assay"}), admin.key_id)) as store:
        assert store.append([key_declared(admin, admin, "admin", "site admin", 0, 0),
                             key_declared(admin, lab, "lab", "lab1", 1, 0)]).appended == 2
    code, out, err = run(capsys, "replay", str(recording["mcap"]), "--ledger", str(fresh),
                         "--admin-key", str(recording["base"] / "keys" / "admin.sign.pub"),
                         "--no-progress")
    n, m = len(recording["signed"]), len(recording["unsigned"])
    assert code == 0, out + err
    assert f"{n + m} events -> {n} appended, 0 duplicate, 0 conflict, {m} rejected" in out
    with open_ledger(fresh, read_only=True) as store:
        rows = list(store.read(types=["assay"]))
        assert [q.code for q in store.quarantine()] == ["unsigned"] * m
        assert {(q.epoch, q.seq) for q in store.quarantine()} == {
            (e.epoch, e.seq) for e in recording["unsigned"]}
        assert store.verify().ok
    # each assay as the lab signed it: identity, payload, signer and signature
    assert [r.to_event(keep_recorded_time=False) for r in rows] == recording["signed"]
    with open(recording["mcap"], "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        closing = [r for r in reader.iter_metadata() if r.name == "stockpile.recording"]
        topics = sorted({c.topic for _s, c, _m in reader.iter_messages()})
    assert json.loads(closing[0].metadata["signatures"]) == n
    assert topics == [f"stockpile/{SITE}/@v1/assay/lab1",
                      f"stockpile/{SITE}/@v1/assay/lab1{SIGNATURE_SUFFIX}"]


def test_replay_onto_zenoh_publishes_signed_events_with_their_signatures(recording):
    sink = EventSink(recording["router"], SITE, "assay", "lab1")
    try:
        done = subprocess.run([PYTHON, "-m", "stockpile.cli", "replay", str(recording["mcap"]),
                               "--publish", "--max", "--linger", "1", "--no-progress",
                               *client_args(recording["endpoint"], recording["pki"],
                                            "replay1")],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stdout + done.stderr
        total = len(recording["signed"]) + len(recording["unsigned"])
        wait_until(lambda: len(sink.events) >= total, 30, "the replayed assays to arrive")
    finally:
        sink.close()
    received = {(e.epoch, e.seq): e for e in sink.events}
    assert len(received) == total
    # the version-2 attachment: signer and signature as the lab made them
    for event in recording["signed"] + recording["unsigned"]:
        assert isinstance(received[(event.epoch, event.seq)], Event)
        assert received[(event.epoch, event.seq)] == event
