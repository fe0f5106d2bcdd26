"""The yard network: the router over mutual TLS on loopback, access control by role.

Real processes: ``stockpile service router`` with the ACL generated from the site PKI
(``stockpile pki``), the ledger service connected to it as a client with its
certificate, and client sessions holding the lab's, a scanner's, an auditor's and a
foreign CA's certificates.  Each case is checked on the router's log and on the ledger
file afterwards.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
from pathlib import Path

import pytest
import zenoh

from ledger import open_ledger
from ledger.signing import sign_event
from schemas.events import encode_attachment, key_expr, make_event, set_timestamp_ns
from security.event_keys import load_signing_key
from schemas.stockpile.v1 import events_pb2 as pb
from services.ledger_client import LedgerClient, LedgerUnavailable
from services.publishing import EventPublisher
from services.service import ZenohOptions, open_session
from zenoh_helpers import PYTHON, free_port, log_lines, stockpile, stop, wait_until

SITE = "yard"
T0_NS = 1_790_000_000 * 1_000_000_000
LAB_EPOCH = 7
NAMES = {"router": "router", "ledger": "ledger", "lab1": "lab", "scan1": "scanner",
         "audit1": "auditor"}


def _pki(*args: str) -> None:
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", "pki", *args], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def _keys(*args: str) -> str:
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", "keys", *args], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout


def _signing_keys(keys: Path, ledger: Path) -> list[str]:
    """The site admin's key (the anchor), the lab's, and an old lab key revoked from T0:
    declared in the ledger before the service starts; the ledger service's arguments."""
    for name in ("admin", "lab1", "lab1-old", "stranger"):
        _keys("new", "--name", name, "--out", str(keys))
    admin = ("--admin", str(keys / "admin.sign.key"), "--ledger", str(ledger))
    _keys("declare", *admin, "--key", str(keys / "admin.sign.pub"), "--role", "admin",
          "--name", "site admin", "--valid-from", "0", "--valid-days", "36500")
    for name in ("lab1", "lab1-old"):
        _keys("declare", *admin, "--key", str(keys / f"{name}.sign.pub"), "--role", "lab",
              "--name", name, "--valid-from", "0", "--valid-days", "36500")
    old_id = load_signing_key(keys / "lab1-old.sign.key").key_id
    _keys("revoke", *admin, "--key-id", old_id, "--from", str(T0_NS), "--reason", "left the lab")
    return ["--admin-key", str(keys / "admin.sign.pub")]


@contextlib.contextmanager
def running_yard(base: Path, *, signed: bool = False):
    """A site PKI, a foreign CA, the router and the ledger service over mTLS (with
    ``signed``, a ledger that requires signed assays from declared keys); on exit both
    processes are stopped (and must exit 0)."""
    pki, foreign, mixed = base / "pki", base / "foreign", base / "mixed"
    _pki("init", "--site", SITE, "--out", str(pki))
    for name, role in NAMES.items():
        _pki("issue", "--ca", str(pki), "--role", role, "--name", name)
    _pki("init", "--site", "elsewhere", "--out", str(foreign))
    _pki("issue", "--ca", str(foreign), "--role", "lab", "--name", "lab1")
    # trusts the site CA, but holds a lab1 certificate the site CA never signed
    mixed.mkdir()
    shutil.copy(pki / "ca.pem", mixed / "ca.pem")
    for suffix in (".pem", ".key"):
        shutil.copy(foreign / f"lab1{suffix}", mixed / f"lab1{suffix}")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router_log, ledger_log = base / "router.log", base / "ledger.log"
    router = stockpile("service", "router", "--site", SITE, "--listen", endpoint,
                       "--tls-dir", str(pki), "--tls-name", "router", stderr_path=router_log)
    ledger = None
    try:
        wait_until(lambda: any(l.get("msg") == "routing" for l in log_lines(router_log)), 30,
                   "the router to listen")
        signing = _signing_keys(base / "keys", base / "yard.duckdb") if signed else []
        ledger = stockpile("service", "ledger", "--site", SITE, "--ledger",
                           str(base / "yard.duckdb"), "--mode", "client", "--connect", endpoint,
                           "--tls-dir", str(pki), "--tls-name", "ledger", *signing,
                           stderr_path=ledger_log)
        auditor = _client(endpoint, pki, "audit1")
        wait_until(lambda: _answers(auditor), 60, "the ledger to answer the auditor")
        yield {"endpoint": endpoint, "pki": pki, "mixed": mixed, "router_log": router_log,
               "ledger_path": base / "yard.duckdb", "auditor": auditor}
        auditor.close()
    finally:
        codes = [stop(p) for p in (ledger, router) if p is not None]
    assert codes == [0] * len(codes)


def _client(endpoint: str, tls_dir: Path, name: str) -> zenoh.Session:
    return open_session(ZenohOptions(mode="client", connect=(endpoint,), tls_dir=str(tls_dir),
                                     tls_name=name))


def _answers(session: zenoh.Session) -> bool:
    try:
        LedgerClient(session, SITE, timeout_s=2).head()
        return True
    except LedgerUnavailable:
        return False


def _assay(assay_id: str, fe: float) -> pb.Assay:
    msg = pb.Assay(assay_id=assay_id, lot_id="LOT-1", status=pb.FINAL, lab_id="lab1")
    msg.analytes.update({"Fe": fe})
    set_timestamp_ns(msg.window_start, T0_NS)
    set_timestamp_ns(msg.window_end, T0_NS + 60 * 10**9)
    set_timestamp_ns(msg.reported_time, T0_NS + 3600 * 10**9)
    return msg


def _refused(router_log: Path, subject: str, message: str, key: str) -> bool:
    return any(l.get("msg") == "refused" and l.get("subject") == subject
               and l.get("message") == message and l.get("key") == key
               for l in log_lines(router_log))


def test_the_lab_appends_and_nobody_else_can(tmp_path):
    with running_yard(tmp_path) as yard:
        _attempts(yard)
    # the file, read directly once the service has stopped: the lab's result only
    with open_ledger(tmp_path / "yard.duckdb", read_only=True) as store:
        records = list(store.read())
        # the genuine result holds the lab's (epoch, seq 0); nothing was quarantined as a
        # conflict with a forgery
        assert [(r.type, r.source, r.epoch, r.seq) for r in records] == [
            ("assay", "lab1", LAB_EPOCH, 0)]
        msg = pb.Assay.FromString(records[0].payload)
        assert msg.assay_id == "AS-0001" and msg.analytes["Fe"] == 62.5
        assert store.quarantine() == [] and store.verify().ok
    # the service's checkpoint at its clean stop, signed with its certificate: the file
    # holds the checkpointed prefix
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", "ledger", "verify", "--ledger",
                           str(tmp_path / "yard.duckdb"), "--checkpoint",
                           str(tmp_path / "yard.duckdb.checkpoints"), "--ca",
                           str(tmp_path / "pki" / "ca.pem")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines()[1] == ("ok: checkpoint (signed by ledger): the ledger "
                                           "holds the checkpointed prefix up to global_seq 0")


def _attempts(yard: dict) -> None:
    endpoint, pki = yard["endpoint"], yard["pki"]
    auditor = LedgerClient(yard["auditor"], SITE, timeout_s=10)
    forged = _assay("AS-FORGED", 70.0).SerializeToString()
    assay_key = key_expr(SITE, "assay", "lab1")

    # the sequence hijack: a scanner's certificate puts forged results on the lab's key
    # with the lab's epoch and its next sequence numbers, ahead of the lab.  The router
    # refuses them (and the scanner cannot read the ledger either)
    scanner = _client(endpoint, pki, "scan1")
    for seq in range(3):
        scanner.put(assay_key, forged, attachment=encode_attachment(LAB_EPOCH, seq, T0_NS))
    wait_until(lambda: _refused(yard["router_log"], "scan1", "put", assay_key), 30,
               "the router to log the scanner's refused put")
    with pytest.raises(LedgerUnavailable):
        LedgerClient(scanner, SITE, timeout_s=2).head()
    wait_until(lambda: _refused(yard["router_log"], "scan1", "query",
                                f"stockpile/{SITE}/@ledger/q/head"), 30,
               "the router to log the scanner's refused query")

    # an auditor reads the ledger, and cannot publish
    yard["auditor"].put(assay_key, forged, attachment=encode_attachment(LAB_EPOCH, 0, T0_NS))
    wait_until(lambda: _refused(yard["router_log"], "audit1", "put", assay_key), 30,
               "the router to log the auditor's refused put")

    # a certificate from another CA, and plain TCP: no link at all
    with pytest.raises(OSError, match="cannot open the Zenoh session"):
        _client(endpoint, yard["mixed"], "lab1")
    plain = "tcp/" + endpoint.split("/", 1)[1]
    with pytest.raises(OSError, match="cannot open the Zenoh session"):
        open_session(ZenohOptions(mode="client", connect=(plain,)))

    # the lab's genuine result goes in
    lab = _client(endpoint, pki, "lab1")
    publisher = EventPublisher(lab, SITE, "lab1", epoch=LAB_EPOCH)
    publisher.publish(_assay("AS-0001", 62.5))
    auditor.wait_for(lambda h: h["global_seq"] >= 0, 30)
    scanner.close()
    lab.close()
    stats = auditor.stats()
    assert stats["events"] == 1 and stats["per_source"] == {"lab1": 1}
    assert stats["quarantined"] == 0


def test_the_ledger_keeps_the_labs_signed_assay_and_quarantines_the_rest(tmp_path):
    """A client with a valid lab certificate: its assay signed with the lab's declared key
    is appended; unsigned, wrongly signed, signed with an undeclared key and with a revoked
    key, each is quarantined with its reason."""
    with running_yard(tmp_path, signed=True) as yard:
        keys = tmp_path / "keys"
        lab_key = load_signing_key(keys / "lab1.sign.key")
        lab = _client(yard["endpoint"], yard["pki"], "lab1")
        good = EventPublisher(lab, SITE, "lab1", epoch=LAB_EPOCH, signing_key=lab_key)
        good.publish(_assay("AS-0001", 62.5))
        EventPublisher(lab, SITE, "lab1", epoch=LAB_EPOCH + 1).publish(_assay("AS-0002", 70.0))
        # the lab's key id with a signature over another payload
        other = sign_event(make_event(_assay("AS-0001", 62.5), source="lab1", epoch=1, seq=0),
                           lab_key)
        forged = make_event(_assay("AS-0003", 70.0), source="lab1", epoch=LAB_EPOCH + 2, seq=0)
        lab.put(key_expr(SITE, "assay", "lab1"), forged.payload,
                attachment=encode_attachment(forged.epoch, 0, forged.valid_time_ns,
                                             lab_key.key_id, other.signature))
        for epoch, name in ((LAB_EPOCH + 3, "stranger"), (LAB_EPOCH + 4, "lab1-old")):
            EventPublisher(lab, SITE, "lab1", epoch=epoch,
                           signing_key=load_signing_key(keys / f"{name}.sign.key")
                           ).publish(_assay(f"AS-{name}", 70.0))
        auditor = LedgerClient(yard["auditor"], SITE, timeout_s=10)
        auditor.wait_for(lambda h: auditor.stats()["quarantined"] >= 4
                         and auditor.stats()["per_type"].get("assay") == 1, 60)
        lab.close()
    with open_ledger(tmp_path / "yard.duckdb", read_only=True) as store:
        [row] = list(store.read(types=["assay"]))
        assert (row.source, row.epoch, row.signer) == ("lab1", LAB_EPOCH, lab_key.key_id)
        assert pb.Assay.FromString(row.payload).analytes["Fe"] == 62.5
        assert sorted((q.epoch, q.code) for q in store.quarantine()) == [
            (LAB_EPOCH + 1, "unsigned"), (LAB_EPOCH + 2, "bad_signature"),
            (LAB_EPOCH + 3, "unknown_key"), (LAB_EPOCH + 4, "revoked_key")]
        assert store.verify().ok
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", "ledger", "verify", "--ledger",
                           str(tmp_path / "yard.duckdb"), "--admin-key",
                           str(tmp_path / "keys" / "admin.sign.pub")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "ok: 5 signatures hold, keys anchored by the admin key given" in done.stdout
    # the audit says who vouched for the result
    audit = subprocess.run([PYTHON, "-m", "stockpile.cli", "audit", "assays", "--ledger",
                            str(tmp_path / "yard.duckdb"), "--json"],
                           capture_output=True, text=True, timeout=120)
    assert audit.returncode == 0, audit.stderr
    [vouched] = json.loads(audit.stdout)["signatures"]
    assert (vouched["assay_id"], vouched["signer"], vouched["signer_name"],
            vouched["signer_role"]) == ("AS-0001", lab_key.key_id, "lab1", "lab")


def test_the_generated_acl_denies_by_default_and_drops_revoked_names():
    from services.acl import access_control, members_from_index

    members = members_from_index([
        {"name": "lab1", "role": "lab", "revoked": False},
        {"name": "scan1", "role": "scanner", "revoked": False},
        {"name": "scan1", "role": "scanner", "revoked": True,        # compromised: no rights
         "revocation_reason": "key-compromise"},
        {"name": "audit1", "role": "auditor"},
        {"name": "audit1", "role": "auditor", "revoked": True,       # rotated: name kept
         "revocation_reason": "superseded"},
    ])
    assert members == {"lab1": "lab", "audit1": "auditor"}
    acl = access_control(SITE, members)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {
        "cert:audit1": ["audit1"], "cert:lab1": ["lab1"]}
    lab_puts = [r for r in acl["rules"] if r["id"].startswith("lab1:")
                and "put" in r["messages"] and r["flows"] == ["ingress"]]
    assert [sorted(r["key_exprs"]) for r in lab_puts] == [
        [f"stockpile/{SITE}/@v1/assay/lab1", f"stockpile/{SITE}/@v1/lot_declared/lab1"]]
    auditor_ingress = {m for r in acl["rules"] if r["id"].startswith("audit1:")
                       and r["flows"] == ["ingress"] for m in r["messages"]}
    # reads only: the ledger's queries and head, and which services are live
    assert auditor_ingress == {"query", "declare_subscriber", "declare_liveliness_subscriber",
                               "liveliness_query"}
    assert all(r["permission"] == "allow" for r in acl["rules"])
    with pytest.raises(ValueError, match="unknown role 'boss'"):
        access_control(SITE, {"x": "boss"})


def test_a_service_warns_before_its_certificate_expires(tmp_path):
    pki = tmp_path / "pki"
    _pki("init", "--site", SITE, "--out", str(pki))
    _pki("issue", "--ca", str(pki), "--role", "router", "--name", "router", "--valid-days", "1")
    log = tmp_path / "router.log"
    router = stockpile("service", "router", "--site", SITE, "--listen",
                       f"tls/127.0.0.1:{free_port()}", "--tls-dir", str(pki), "--tls-name",
                       "router", "--cert-warn", "2d", stderr_path=log)
    try:
        wait_until(lambda: any(l.get("msg") == "certificate" for l in log_lines(log)), 30,
                   "the certificate warning")
    finally:
        assert stop(router) == 0
    (line,) = [l for l in log_lines(log) if l.get("msg") == "certificate"]
    assert line["level"] == "warning"
    assert line["problem"].startswith(f"certificate router ({pki / 'router.pem'}) expires in")
    assert "BEGIN" not in log.read_text()   # no key or certificate material in the log


def test_the_refusal_log_skips_permission_tables_and_counts_repeats():
    """Zenoh's access-control trace, as the router reads it: the decisions listed when a
    key's permissions are cached are not traffic; a refused message is logged once, then
    counted."""
    from services.router import RefusalLog

    refusals = RefusalLog(-1)
    who = "abc on Interface(lo)+CertCommonName(scan1)+Transport(Tls)+abc"
    key = "stockpile/yard/@v1/assay/lab1"
    refusals.take(f"TRACE access_control: ACL (ingress): caching permissions for `{key}` ...")
    for kind in ("Query", "Reply", "Put", "Delete", "Declare/Undeclare Subscriber",
                 "Declare/Undeclare Queryable", "Declare/Undeclare Liveliness Token",
                 "Liveliness Query", "Declare Liveliness Subscriber"):
        refusals.take(f"TRACE access_control: {who} is unauthorized to {kind} (ingress) on {key}")
    refusals.take(f"TRACE access_control: {who} is authorized to Put (ingress) on other/key")
    assert refusals.counts == {}
    refusals.take(f"TRACE access_control: {who} is authorized to Put (ingress) on {key}")
    assert refusals.counts == {}     # the table's tenth line
    for _ in range(3):
        refusals.take(f"TRACE access_control: {who} is unauthorized to Put (ingress) on {key}")
    assert refusals.counts == {("scan1", "put", "ingress", key): 3}
