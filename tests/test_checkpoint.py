"""Checkpoints of the chain head: a truncated and a rewritten ledger are caught.

Each attack is made on a copy of a real DuckDB ledger with DuckDB's own SQL, as someone
with write access to the file would; the rewrite recomputes the whole chain, so the
plain chain check passes and only the signed checkpoint, kept elsewhere, tells.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import duckdb
import pytest

from ledger import open_ledger
from ledger.chain import GENESIS, chain_hash, payload_hash
from ledger.checkpoint import check_checkpoint, make_checkpoint, read_checkpoint, write_checkpoint
from schemas.events import Event, set_timestamp_ns
from schemas.stockpile.v1 import events_pb2 as pb
from security.pki import init_ca, issue
from zenoh_helpers import PYTHON

SITE = "cp"
T0_NS = 1_790_000_000 * 1_000_000_000
N_EVENTS = 40


def _clock(seq: int) -> Event:
    msg = pb.Clock()
    set_timestamp_ns(msg.time, T0_NS + seq * 10**9)
    return Event("clock", "sim.clock", 1, seq, T0_NS + seq * 10**9, msg.SerializeToString())


@pytest.fixture(scope="module")
def signed(tmp_path_factory):
    """A ledger of 40 events, the site PKI, a foreign PKI, and a signed checkpoint."""
    base = tmp_path_factory.mktemp("checkpoint")
    pki, foreign = base / "pki", base / "foreign"
    init_ca(SITE, pki)
    issue(pki, "ledger", "ledger")
    init_ca("elsewhere", foreign)
    issue(foreign, "ledger", "ledger")
    path = base / "ledger.duckdb"
    with open_ledger(path) as store:
        store.append([_clock(i) for i in range(N_EVENTS)])
        checkpoint = make_checkpoint(store, SITE, T0_NS, key_path=pki / "ledger.key",
                                     certificate_path=pki / "ledger.pem")
    cp_file = write_checkpoint(checkpoint, base / "checkpoints")
    return {"base": base, "pki": pki, "foreign": foreign, "ledger": path, "cp": cp_file}


def _verify(ledger: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([PYTHON, "-m", "stockpile.cli", "ledger", "verify", "--ledger",
                           str(ledger), *args], capture_output=True, text=True, timeout=120)


def _copy(signed: dict, name: str) -> Path:
    target = signed["base"] / name
    shutil.copyfile(signed["ledger"], target)
    return target


def test_an_intact_ledger_holds_its_checkpoint(signed):
    cp = read_checkpoint(signed["cp"])
    assert cp.global_seq == N_EVENTS - 1 and cp.signer == "ledger"
    assert "PRIVATE" not in signed["cp"].read_text()     # the certificate, never the key
    done = _verify(signed["ledger"], "--checkpoint", str(signed["cp"].parent), "--ca",
                   str(signed["pki"] / "ca.pem"))
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines()[1] == (
        f"ok: checkpoint (signed by ledger): the ledger holds the checkpointed prefix up to "
        f"global_seq {N_EVENTS - 1}")


def test_a_truncated_ledger_passes_the_chain_and_fails_the_checkpoint(signed):
    ledger = _copy(signed, "truncated.duckdb")
    with duckdb.connect(str(ledger)) as con:
        con.execute("DELETE FROM event_log WHERE global_seq >= ?", [N_EVENTS - 10])
    plain = _verify(ledger)
    assert plain.returncode == 0 and plain.stdout.startswith("ok: 30 rows verified")
    done = _verify(ledger, "--checkpoint", str(signed["cp"]), "--ca", str(signed["pki"] / "ca.pem"))
    assert done.returncode == 1
    assert done.stdout.splitlines()[1].startswith(
        f"FAILED: checkpoint TRUNCATED (signed by ledger): the ledger ends at global_seq "
        f"{N_EVENTS - 11}")
    assert "10 rows are gone" in done.stdout


def test_a_rewritten_and_rechained_ledger_fails_the_checkpoint(signed):
    ledger = _copy(signed, "rewritten.duckdb")
    forged = pb.Clock()
    set_timestamp_ns(forged.time, T0_NS + 999 * 10**9)
    with duckdb.connect(str(ledger)) as con:
        rows = con.execute("SELECT global_seq, type, source, epoch, seq, valid_time_ns, "
                           "recorded_time_ns, payload FROM event_log ORDER BY global_seq"
                           ).fetchall()
        previous = GENESIS
        for g, t, src, ep, sq, v, r, payload in rows:
            if g == 3:
                payload = forged.SerializeToString()
            digest = payload_hash(bytes(payload))
            previous = chain_hash(previous, g, t, src, ep, sq, v, r, digest)
            con.execute("UPDATE event_log SET payload = ?, payload_sha256 = ?, chain_sha256 = ? "
                        "WHERE global_seq = ?", [bytes(payload), digest, previous, g])
    plain = _verify(ledger)
    assert plain.returncode == 0, plain.stdout     # the chain alone cannot tell
    done = _verify(ledger, "--checkpoint", str(signed["cp"]))
    assert done.returncode == 1
    assert done.stdout.splitlines()[1].startswith(
        f"FAILED: checkpoint REWRITTEN (signed by ledger): global_seq {N_EVENTS - 1} has chain")


def test_an_altered_or_foreign_checkpoint_is_refused(signed, tmp_path):
    data = json.loads(signed["cp"].read_text())
    data["global_seq"] = N_EVENTS - 20          # to pass off a truncated ledger
    altered = tmp_path / "altered.json"
    altered.write_text(json.dumps(data))
    with open_ledger(signed["ledger"], read_only=True) as store:
        report = check_checkpoint(store, read_checkpoint(altered))
        assert (report.ok, report.finding) == (False, "bad-signature")
        assert "does not match" in report.detail
        # signed by a ledger certificate of another CA
        foreign = make_checkpoint(store, SITE, T0_NS, key_path=signed["foreign"] / "ledger.key",
                                  certificate_path=signed["foreign"] / "ledger.pem")
        site_ca = (signed["pki"] / "ca.pem").read_bytes()
        report = check_checkpoint(store, foreign, ca_pem=site_ca)
        assert (report.ok, report.finding) == (False, "bad-signature")
        assert "not issued by this site CA" in report.detail
        assert check_checkpoint(store, foreign).ok    # without the CA, only the signature
        unsigned = make_checkpoint(store, SITE, T0_NS)
        assert unsigned.signature is None and check_checkpoint(store, unsigned).ok
        assert not check_checkpoint(store, unsigned, ca_pem=site_ca).ok


def _assay_ledger(path: Path) -> None:
    """A lot, an assay of it, and an assay of an undeclared lot (flagged unknown_lot)."""
    lot = pb.LotDeclared(lot_id="LOT-A")
    set_timestamp_ns(lot.time, T0_NS)
    events = [Event("lot_declared", "lims", 1, 0, T0_NS, lot.SerializeToString())]
    for seq, lot_id in ((0, "LOT-A"), (1, "LOT-Z")):
        a = pb.Assay(assay_id=f"AS-{seq}", lot_id=lot_id, status=pb.FINAL, lab_id="lab1")
        a.analytes.update({"Fe": 62.5})
        set_timestamp_ns(a.window_start, T0_NS)
        set_timestamp_ns(a.window_end, T0_NS + 10**9)
        set_timestamp_ns(a.reported_time, T0_NS + 2 * 10**9)
        events.append(Event("assay", "lab1", 1, seq, T0_NS + 10**9,
                            a.SerializeToString()))
    with open_ledger(path) as store:
        result = store.append(events)
        assert result.appended == 3, result
        assert [o.flags for o in result.outcomes] == [(), (), ("unknown_lot",)]


@pytest.mark.parametrize("edit, problem", [
    ("UPDATE event_log SET body = json_object('assay_id', 'AS-0', 'analytes', "
     "json_object('Fe', 70.0)) WHERE global_seq = 1",
     "stored body does not match the payload"),
    ("UPDATE event_log SET flags = NULL WHERE global_seq = 2",
     "flags [] where the payloads before it give ['unknown_lot']"),
    ("UPDATE event_log SET flags = 'unknown_lot' WHERE global_seq = 1",
     "flags ['unknown_lot'] where the payloads before it give []"),
], ids=["assay-body", "flag-dropped", "flag-added"])
def test_plain_verify_catches_an_edited_body_or_flag(tmp_path, edit, problem):
    """The views read the stored JSON body and flags, outside the chained fields: verify
    recomputes them from the hashed payloads."""
    ledger = tmp_path / "l.duckdb"
    _assay_ledger(ledger)
    assert _verify(ledger).returncode == 0
    with duckdb.connect(str(ledger)) as con:
        before = con.execute("SELECT avg(\"Fe\") FROM assays").fetchone()[0]
        con.execute(edit)
    done = _verify(ledger)
    assert done.returncode == 1, done.stdout
    assert problem in done.stdout, done.stdout
    if "body" in edit:   # the edit did reach what an auditor's SQL reads
        with duckdb.connect(str(ledger)) as con:
            assert con.execute("SELECT avg(\"Fe\") FROM assays").fetchone()[0] != before


@pytest.mark.parametrize("edit, problem", [
    ("DELETE FROM gaps", "0 gap rows where the rows give 1: gap 0 of sim.clock epoch 1 seq "
     "2..3 opened at"),
    ("UPDATE gaps SET last_seq = 2", "gap row 0 is gap 0 of sim.clock epoch 1 seq 2..2"),
    ("UPDATE gaps SET first_seq = 1, last_seq = 3", "gap row 0 is gap 0 of sim.clock epoch 1 "
     "seq 1..3"),
    ("UPDATE gaps SET closed_recorded_ns = 5", "closed at 5 where the rows give"),
], ids=["gap-deleted", "gap-shrunk", "gap-over-stored", "gap-closed"])
def test_plain_verify_catches_an_edited_gap_row(tmp_path, edit, problem):
    """Seqs 2 and 3 never arrived: the open gap 2..3 is what the stored rows imply."""
    ledger = tmp_path / "g.duckdb"
    with open_ledger(ledger) as store:
        store.append([_clock(i) for i in (0, 1, 4, 5)])
        assert [(g.first_seq, g.last_seq) for g in store.gaps(open_only=True)] == [(2, 3)]
    assert _verify(ledger).returncode == 0
    with duckdb.connect(str(ledger)) as con:
        con.execute(edit)
    done = _verify(ledger)
    assert done.returncode == 1 and problem in done.stdout, done.stdout


def test_checkpoints_in_an_mcap_file_are_checked_each(signed, tmp_path):
    """The recorder's convention (``EventWriter.write_checkpoint``): the JSON bytes on a
    schema-less channel; an altered copy in the file is its own finding."""
    from replay.mcap_writer import EventWriter
    from ledger.checkpoint import checkpoint_topic, read_mcap_checkpoints

    original = signed["cp"].read_bytes()
    data = json.loads(original)
    data["global_seq"] = N_EVENTS - 20
    session = tmp_path / "session.mcap"
    writer = EventWriter(session)
    writer.write_checkpoint(checkpoint_topic(SITE), original, T0_NS)
    writer.write_checkpoint(checkpoint_topic(SITE), json.dumps(data).encode(), T0_NS + 1)
    writer.close()
    found, problem = read_mcap_checkpoints(session)
    assert problem is None and [t for t, _cp in found] == [T0_NS, T0_NS + 1]
    assert found[0][1] == read_checkpoint(signed["cp"])
    done = _verify(signed["ledger"], "--checkpoint", str(session), "--ca",
                   str(signed["pki"] / "ca.pem"))
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert lines[1] == (f"ok: checkpoint 1/2 of {session} (signed by ledger): the ledger holds "
                        f"the checkpointed prefix up to global_seq {N_EVENTS - 1}")
    assert lines[2].startswith(f"FAILED: checkpoint BAD-SIGNATURE 2/2 of {session} (unsigned): "
                               "the checkpoint does not hold")
    # a message on the channel that is not a checkpoint: one line, exit 2
    broken = tmp_path / "broken.mcap"
    writer = EventWriter(broken)
    writer.write_checkpoint(checkpoint_topic(SITE), b"not json", T0_NS)
    writer.close()
    done = _verify(signed["ledger"], "--checkpoint", str(broken))
    assert done.returncode == 2 and done.stdout == ""
    assert len(done.stderr.splitlines()) == 1 and "is not a checkpoint" in done.stderr
