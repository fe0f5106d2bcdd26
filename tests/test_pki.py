"""The site PKI (security.pki, ``stockpile pki``) on real files: the CA, a certificate per
role, key permissions, revocation, expiry warnings, and independent checks of what was
written (``cryptography`` reading it back, ``openssl verify`` / ``openssl crl`` when the
binary exists, and Zenoh's own TLS accepting the certificates for mutual TLS)."""

from __future__ import annotations

import datetime as dt
import json
import shutil
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from security import certificates, pki

OPENSSL = shutil.which("openssl")
needs_openssl = pytest.mark.skipif(OPENSSL is None, reason="no openssl binary on PATH: the "
                                   "independent check with openssl is skipped")
UTC = dt.timezone.utc
DAY_S = 86_400


def stockpile(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=120, cwd=cwd)


def openssl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([OPENSSL, *args], capture_output=True, text=True, timeout=60)


def _openssl_sees_the_crl_signed_and_the_cert_revoked(ca_dir, cert_path) -> None:
    """OpenSSL, an independent reader: the CRL verifies under the CA, and the certificate
    fails a CRL-checked verification as revoked."""
    signed = openssl("crl", "-in", str(ca_dir / "crl.pem"), "-noout",
                     "-CAfile", str(ca_dir / "ca.pem"))
    assert signed.returncode == 0 and "verify OK" in signed.stdout + signed.stderr
    chain = openssl("verify", "-crl_check", "-CAfile", str(ca_dir / "ca.pem"),
                    "-CRLfile", str(ca_dir / "crl.pem"), str(cert_path))
    assert chain.returncode != 0 and "revoked" in chain.stdout + chain.stderr


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def key_lines(path: Path) -> list[str]:
    """The base64 body lines of a PEM key (what must never be printed)."""
    return [l for l in path.read_text().splitlines() if l and not l.startswith("-----")]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A site CA made by the command, and a certificate for every role (a few by the
    command, the others by the function it calls: each command is a process start)."""
    root = tmp_path_factory.mktemp("pki")
    ca_dir = root / "ca"
    outputs = [stockpile("pki", "init", "--site", "capelambert", "--out", str(ca_dir))]
    assert outputs[0].returncode == 0, outputs[0].stderr
    by_command = ("router", "lab", "auditor")
    for role in pki.ROLES:
        if role not in by_command:
            pki.issue(ca_dir, role, f"{role}-1")
            continue
        out = stockpile("pki", "issue", "--ca", str(ca_dir), "--role", role,
                        "--name", f"{role}-1")
        assert out.returncode == 0, out.stderr
        assert len(out.stdout.splitlines()) == 1 and f"{role}-1.key" in out.stdout
        outputs.append(out)
    return ca_dir, outputs


def test_init_writes_the_layout_with_private_keys_0600(site):
    ca_dir, outputs = site
    for name in ("ca.pem", "ca.key", "crl.pem", "index.json"):
        assert (ca_dir / name).is_file(), name
    assert mode(ca_dir / "ca.key") == 0o600
    assert mode(ca_dir) == 0o700
    ca = x509.load_pem_x509_certificate((ca_dir / "ca.pem").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert isinstance(ca.public_key(), ec.EllipticCurvePublicKey)
    assert ca.public_key().curve.name == "secp256r1"
    key = serialization.load_pem_private_key((ca_dir / "ca.key").read_bytes(), password=None)
    assert key.public_key().public_numbers() == ca.public_key().public_numbers()
    assert (ca_dir / "ca.key").read_text().startswith("-----BEGIN PRIVATE KEY-----")  # PKCS#8
    line = outputs[0].stdout.strip()
    assert len(outputs[0].stdout.splitlines()) == 1 and "ca.key" in line and "ca.pem" in line
    index = json.loads((ca_dir / "index.json").read_text())
    assert index["site"] == "capelambert" and len(index["certificates"]) == len(pki.ROLES)


def test_every_role_gets_a_certificate_naming_it(site):
    ca_dir, outputs = site
    ca = x509.load_pem_x509_certificate((ca_dir / "ca.pem").read_bytes())
    index = {e["name"]: e for e in json.loads((ca_dir / "index.json").read_text())["certificates"]}
    for role in pki.ROLES:
        name = f"{role}-1"
        cert_path, key_path = ca_dir / f"{name}.pem", ca_dir / f"{name}.key"
        assert mode(key_path) == 0o600, name
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        cert.verify_directly_issued_by(ca)
        info = certificates.certificate_info(cert_path)
        assert (info.common_name, info.role, info.site) == (name, role, "capelambert")
        assert info.issuer == ca.subject.rfc4514_string() and not info.is_ca
        assert info.serial == pki.serial_hex(cert.serial_number) == index[name]["serial"]
        assert index[name]["role"] == role and index[name]["revoked"] is False
        assert index[name]["not_after"] == pki.iso_utc(info.not_after)
        assert info.not_after - info.not_before >= dt.timedelta(days=pki.DEFAULT_CERT_VALID_DAYS)
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        assert key.public_key().public_numbers() == cert.public_key().public_numbers()
        assert "clientAuth" in info.extended_key_usages
        if role == "router":
            assert "serverAuth" in info.extended_key_usages
            assert info.dns_names == ("localhost",) and info.ip_addresses == ("127.0.0.1",)
        else:
            assert "serverAuth" not in info.extended_key_usages
            assert info.dns_names == () and info.ip_addresses == ()
        assert certificates.verify_certificate(cert_path, ca_dir / "ca.pem",
                                      crl_path=ca_dir / "crl.pem").common_name == name


def test_no_key_material_is_printed(site):
    ca_dir, outputs = site
    printed = "".join(o.stdout + o.stderr for o in outputs)
    assert "PRIVATE KEY" not in printed
    for key_path in ca_dir.glob("*.key"):
        for line in key_lines(key_path):
            assert line not in printed, key_path
    listed = stockpile("pki", "list", "--ca", str(ca_dir))
    listed_json = stockpile("pki", "list", "--ca", str(ca_dir), "--json")
    assert listed.returncode == listed_json.returncode == 0
    assert "PRIVATE" not in listed.stdout + listed_json.stdout
    rows = json.loads(listed_json.stdout)["certificates"]
    assert {r["name"] for r in rows} >= {f"{r}-1" for r in pki.ROLES}
    assert all(r["status"] == "valid" for r in rows if r["name"].endswith("-1"))


@needs_openssl
def test_openssl_verifies_the_chain_independently(site):
    ca_dir, _ = site
    certs = [str(ca_dir / f"{role}-1.pem") for role in pki.ROLES]
    out = openssl("verify", "-CAfile", str(ca_dir / "ca.pem"), *certs)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.count(": OK") == len(pki.ROLES)
    client = openssl("verify", "-CAfile", str(ca_dir / "ca.pem"), "-purpose", "sslclient",
                     str(ca_dir / "lab-1.pem"))
    server = openssl("verify", "-CAfile", str(ca_dir / "ca.pem"), "-purpose", "sslserver",
                     str(ca_dir / "router-1.pem"))
    assert client.returncode == 0 and server.returncode == 0, client.stderr + server.stderr
    text = openssl("x509", "-in", str(ca_dir / "lab-1.pem"), "-noout", "-subject").stdout
    assert "OU = lab" in text and "CN = lab-1" in text


def test_issue_to_a_tls_directory_and_rotate(tmp_path):
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir, valid_days=30)
    tls = tmp_path / "tls" / "lab-2"
    first = stockpile("pki", "issue", "--ca", str(ca_dir), "--role", "lab", "--name", "lab-2",
                      "--out", str(tls), "--valid-days", "10")
    assert first.returncode == 0, first.stderr
    assert sorted(p.name for p in tls.iterdir()) == ["ca.pem", "crl.pem", "lab-2.key",
                                                     "lab-2.pem"]
    assert mode(tls / "lab-2.key") == 0o600 and mode(tls) == 0o700
    assert mode(tls / "crl.pem") == 0o644
    assert (tls / "ca.pem").read_bytes() == (ca_dir / "ca.pem").read_bytes()
    assert (tls / "crl.pem").read_bytes() == (ca_dir / "crl.pem").read_bytes()
    assert str(tls / "crl.pem") in first.stdout
    # the service directory checks a peer on its own: chain and revocation list
    certificates.verify_certificate(tls / "lab-2.pem", tls / "ca.pem", crl_path=tls / "crl.pem")
    assert not (ca_dir / "lab-2.key").exists()
    old_key, old_cert = (tls / "lab-2.key").read_bytes(), certificates.certificate_info(tls / "lab-2.pem")

    # overwrite refused: one line, exit 2, files untouched
    again = stockpile("pki", "issue", "--ca", str(ca_dir), "--role", "lab", "--name", "lab-2",
                      "--out", str(tls))
    assert again.returncode == 2 and len(again.stderr.splitlines()) == 1
    assert again.stderr.startswith("stockpile: error: ") and "--force" in again.stderr
    assert (tls / "lab-2.key").read_bytes() == old_key

    # rotation: a new key and serial; the old serial is revoked by serial, the new stays
    (tls / "lab-2.key").chmod(0o644)        # a loosened old key is not kept: 0600 again
    rotated = stockpile("pki", "issue", "--ca", str(ca_dir), "--role", "lab", "--name", "lab-2",
                        "--out", str(tls), "--force", "--valid-days", "10")
    assert rotated.returncode == 0, rotated.stderr
    assert (tls / "lab-2.key").read_bytes() != old_key and mode(tls / "lab-2.key") == 0o600
    new_cert = certificates.certificate_info(tls / "lab-2.pem")
    assert new_cert.serial != old_cert.serial
    revoked = stockpile("pki", "revoke", "--ca", str(ca_dir), "--serial", old_cert.serial,
                        "--reason", "superseded")
    assert revoked.returncode == 0, revoked.stderr
    crl = certificates.load_crl(ca_dir / "crl.pem", ca_cert_path=ca_dir / "ca.pem")
    assert certificates.is_revoked(crl, old_cert.serial) and not certificates.is_revoked(crl, tls / "lab-2.pem")
    assert not list(tls.glob(".*tmp")) and not list(ca_dir.glob(".*tmp"))

    # a certificate may not outlive the CA
    too_long = stockpile("pki", "issue", "--ca", str(ca_dir), "--role", "lab", "--name", "x",
                         "--valid-days", "400")
    assert too_long.returncode == 2 and "outlive" in too_long.stderr
    assert not (ca_dir / "x.key").exists()


def test_overwriting_a_ca_is_refused_unless_forced(tmp_path):
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    key = (ca_dir / "ca.key").read_bytes()
    out = stockpile("pki", "init", "--site", "yard", "--out", str(ca_dir))
    assert out.returncode == 2 and out.stderr.count("\n") == 1
    assert "a site CA exists" in out.stderr and (ca_dir / "ca.key").read_bytes() == key
    with pytest.raises(FileExistsError):
        pki.init_ca("yard", ca_dir)
    pki.issue(ca_dir, "scanner", "scanner-1")
    with pytest.raises(FileExistsError):
        pki.issue(ca_dir, "scanner", "scanner-1")
    forced = stockpile("pki", "init", "--site", "yard", "--out", str(ca_dir), "--force")
    assert forced.returncode == 0, forced.stderr
    assert (ca_dir / "ca.key").read_bytes() != key and mode(ca_dir / "ca.key") == 0o600
    assert pki.read_index(ca_dir).certificates == []


def test_revoke_puts_the_serial_in_a_signed_crl(tmp_path):
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    empty = certificates.load_crl(ca_dir / "crl.pem", ca_cert_path=ca_dir / "ca.pem")
    assert len(list(empty)) == 0
    lab = pki.issue(ca_dir, "lab", "lab-1")
    keep = pki.issue(ca_dir, "ledger", "ledger-1")
    assert not certificates.is_revoked(empty, lab.cert_path)
    out = stockpile("pki", "revoke", "--ca", str(ca_dir), "--name", "lab-1",
                    "--reason", "key-compromise")
    assert out.returncode == 0, out.stderr
    assert len(out.stdout.splitlines()) == 1 and lab.serial in out.stdout
    assert "crl.pem" in out.stdout and "index.json" in out.stdout
    crl = certificates.load_crl(ca_dir / "crl.pem", ca_cert_path=ca_dir / "ca.pem")
    assert certificates.is_revoked(crl, lab.serial) and certificates.is_revoked(crl, lab.cert_path)
    assert certificates.is_revoked(crl, int(lab.serial, 16))
    assert not certificates.is_revoked(crl, keep.cert_path)
    entry = crl.get_revoked_certificate_by_serial_number(int(lab.serial, 16))
    reason = entry.extensions.get_extension_for_class(x509.CRLReason).value.reason
    assert reason == x509.ReasonFlags.key_compromise
    index = {e["name"]: e for e in pki.read_index(ca_dir).certificates}
    assert index["lab-1"]["revoked"] and index["lab-1"]["revocation_reason"] == "key-compromise"
    assert not index["ledger-1"]["revoked"]
    with pytest.raises(ValueError, match="is revoked"):
        certificates.verify_certificate(lab.cert_path, ca_dir / "ca.pem", crl_path=ca_dir / "crl.pem")
    listed = json.loads(stockpile("pki", "list", "--ca", str(ca_dir), "--json").stdout)
    assert {r["name"]: r["status"] for r in listed["certificates"]} == {
        "lab-1": "revoked", "ledger-1": "valid"}

    again = stockpile("pki", "revoke", "--ca", str(ca_dir), "--name", "lab-1")
    assert again.returncode == 2 and "already revoked" in again.stderr
    unknown = stockpile("pki", "revoke", "--ca", str(ca_dir), "--name", "nobody")
    assert unknown.returncode == 2 and "issued: lab-1, ledger-1" in unknown.stderr
    if OPENSSL:
        text = openssl("crl", "-in", str(ca_dir / "crl.pem"), "-noout", "-text")
        assert text.returncode == 0, text.stderr
        assert lab.serial in text.stdout.replace(":", "").upper()
        assert keep.serial not in text.stdout.replace(":", "").upper()
        _openssl_sees_the_crl_signed_and_the_cert_revoked(ca_dir, lab.cert_path)
        fine = openssl("verify", "-crl_check", "-CAfile", str(ca_dir / "ca.pem"),
                       "-CRLfile", str(ca_dir / "crl.pem"), str(keep.cert_path))
        assert fine.returncode == 0, fine.stdout + fine.stderr


def test_expiry_warning(tmp_path):
    ca_dir = tmp_path / "ca"
    now = dt.datetime(2026, 11, 28, 12, 0, tzinfo=UTC)
    pki.init_ca("yard", ca_dir, now=now - dt.timedelta(days=30))
    soon = pki.issue(ca_dir, "gnss", "gnss-1", valid_days=3, now=now)
    expired = pki.issue(ca_dir, "plc", "plc-1", valid_days=1, now=now - dt.timedelta(days=10))
    fresh = pki.issue(ca_dir, "lab", "lab-1", valid_days=365, now=now)

    line = certificates.expiry_warning(soon.cert_path, 7 * DAY_S, now)
    assert line == (f"certificate gnss-1 ({soon.cert_path}) expires in 3 days "
                    f"(at {pki.iso_utc(soon.not_after)})")
    assert certificates.expiry_warning(soon.cert_path, 1 * DAY_S, now) is None
    assert "expires in 5 hours" in certificates.expiry_warning(
        soon.cert_path, DAY_S, soon.not_after - dt.timedelta(hours=5, minutes=10))
    gone = certificates.expiry_warning(expired.cert_path, 0, now)
    assert gone is not None and "plc-1" in gone and "expired 9 days ago" in gone
    assert certificates.expiry_warning(fresh.cert_path, 30 * DAY_S, now) is None
    with pytest.raises(ValueError, match="expired at"):
        certificates.verify_certificate(expired.cert_path, ca_dir / "ca.pem", now=now)
    assert certificates.certificate_status(pki.read_index(ca_dir).certificates[1], now) == "expired"
    if OPENSSL:
        out = openssl("verify", "-CAfile", str(ca_dir / "ca.pem"), str(expired.cert_path))
        assert out.returncode != 0 and "expired" in out.stdout + out.stderr


def test_a_certificate_from_another_ca_fails_verification(tmp_path):
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    pki.init_ca("yard", ours)
    pki.init_ca("yard", theirs)          # same site name, another key
    foreign = pki.issue(theirs, "lab", "lab-1")
    with pytest.raises(ValueError, match="was not issued by the CA"):
        certificates.verify_certificate(foreign.cert_path, ours / "ca.pem")
    with pytest.raises(ValueError, match="not signed by the CA"):
        certificates.load_crl(theirs / "crl.pem", ca_cert_path=ours / "ca.pem")
    if OPENSSL:
        out = openssl("verify", "-CAfile", str(ours / "ca.pem"), str(foreign.cert_path))
        assert out.returncode != 0, out.stdout
    # a TLS directory of the other CA is not silently mixed with ours
    with pytest.raises(FileExistsError, match="another CA"):
        pki.issue(ours, "lab", "lab-9", out_dir=theirs)


def test_a_bad_role_is_a_one_line_error_exit_2(tmp_path):
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    before = sorted(p.name for p in ca_dir.iterdir())
    out = stockpile("pki", "issue", "--ca", str(ca_dir), "--role", "chef", "--name", "x",
                    cwd=tmp_path)
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr.splitlines() == [
        "stockpile: error: unknown role 'chef': choose from router, scanner, gnss, plc, "
        "localizer, lab, ledger, projector, recorder, dashboard, auditor, replay, hq, uplink"]
    assert sorted(p.name for p in ca_dir.iterdir()) == before


@pytest.mark.parametrize("argv,needle", [
    (["issue", "--role", "lab", "--name", "../evil"], "name must be"),
    (["issue", "--role", "lab", "--name", "ca"], "taken by the CA's own files"),
    (["issue", "--role", "router", "--name", "r", "--san", "bad host!"], "not a host name"),
    (["revoke", "--name", "x", "--reason", "bored"], "invalid choice"),
    (["revoke", "--serial", "xyz"], "not a serial number"),
    (["issue", "--role", "lab", "--name", "x", "--valid-days", "0"], "must be positive"),
    (["crl", "--valid-days", "0"], "must be positive"),
    (["crl", "--valid-days", "2d"], "whole number of days"),
])
def test_bad_input_is_a_one_line_error_exit_2(argv, needle, tmp_path, capsys):
    """The same path in-process (stockpile.cli.main; a process start each is slow)."""
    from stockpile.cli import main
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    before = sorted(p.name for p in ca_dir.iterdir())
    try:
        code = main(["pki", argv[0], "--ca", str(ca_dir), *argv[1:]])
    except SystemExit as exc:            # argparse's usage errors
        code = exc.code
    out = capsys.readouterr()
    assert code == 2, out
    lines = out.err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and lines[0].startswith("stockpile"), out.err
    assert out.out == ""
    assert sorted(p.name for p in ca_dir.iterdir()) == before


def test_no_ca_directory_is_one_line(tmp_path):
    out = stockpile("pki", "issue", "--ca", str(tmp_path / "none"), "--role", "lab",
                    "--name", "lab-1")
    assert out.returncode == 2
    assert out.stderr.splitlines() == [
        f"stockpile: error: {tmp_path / 'none'} is not a site CA directory: no ca.pem "
        f"(make one with stockpile pki init)"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_zenoh_mutual_tls_accepts_the_site_certificates_only(tmp_path):
    """Zenoh's TLS (rustls) takes the keys and certificates as written: a client with a
    certificate of the site CA reaches a router that requires client certificates; one
    with a certificate of another CA does not."""
    zenoh = pytest.importorskip("zenoh")
    ca_dir, other = tmp_path / "ca", tmp_path / "other"
    pki.init_ca("yard", ca_dir)
    pki.init_ca("yard", other)
    pki.issue(ca_dir, "router", "router-1")
    pki.issue(ca_dir, "lab", "lab-1", out_dir=tmp_path / "tls-lab")
    pki.issue(other, "lab", "lab-1", out_dir=tmp_path / "tls-foreign")
    endpoint = f"tls/localhost:{_free_port()}"

    def config(mode: str, tls_dir: Path, name: str, **endpoints: list[str]):
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        for kind, value in endpoints.items():
            conf.insert_json5(f"{kind}/endpoints", json.dumps(value))
        conf.insert_json5("transport/link/tls", json.dumps({
            "root_ca_certificate": str(tls_dir / "ca.pem"), "enable_mtls": True,
            "listen_private_key": str(tls_dir / f"{name}.key"),
            "listen_certificate": str(tls_dir / f"{name}.pem"),
            "connect_private_key": str(tls_dir / f"{name}.key"),
            "connect_certificate": str(tls_dir / f"{name}.pem")}))
        return conf

    router = zenoh.open(config("router", ca_dir, "router-1", listen=[endpoint]))
    try:
        got: list[bytes] = []
        router.declare_subscriber("pki/test/**", lambda s: got.append(s.payload.to_bytes()))
        client = zenoh.open(config("client", tmp_path / "tls-lab", "lab-1",
                                   connect=[endpoint]))
        try:
            deadline = time.monotonic() + 10
            while not got and time.monotonic() < deadline:
                client.put("pki/test/x", b"hello")
                time.sleep(0.2)
        finally:
            client.close()
        assert got and got[0] == b"hello"
        with pytest.raises(zenoh.ZError):
            foreign = zenoh.open(config("client", tmp_path / "tls-foreign", "lab-1",
                                        connect=[endpoint]))
            foreign.close()
    finally:
        router.close()


def test_revoke_by_name_or_by_serial_only(tmp_path):
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    first = pki.issue(ca_dir, "lab", "lab-1")
    second = pki.issue(ca_dir, "lab", "lab-1", force=True)          # a rotation
    with pytest.raises(ValueError, match="not a serial"):
        pki.revoke(ca_dir, "lab-1", by="serial")
    with pytest.raises(ValueError, match="no certificate"):
        pki.revoke(ca_dir, first.serial, by="name")
    both = pki.revoke(ca_dir, "lab-1", "cessation-of-operation", by="name")
    assert {e["serial"] for e in both.revoked} == {first.serial, second.serial}
    crl = certificates.load_crl(ca_dir / "crl.pem")
    assert certificates.is_revoked(crl, first.serial) and certificates.is_revoked(crl, second.cert_path)
    assert both.crl_number == 1 and pki.read_index(ca_dir).crl_number == 1


def test_concurrent_issues_lose_no_index_entry(tmp_path):
    import threading
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    errors: list[BaseException] = []

    def one(i: int) -> None:
        try:
            pki.issue(ca_dir, "scanner", f"scanner-{i}")
        except BaseException as exc:     # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert sorted(e["name"] for e in pki.read_index(ca_dir).certificates) == sorted(
        f"scanner-{i}" for i in range(8))


def test_crl_renewal_keeps_the_revoked_serials_and_moves_next_update(tmp_path):
    """A CRL lapses at its nextUpdate: ``pki crl`` re-signs it with the same serials."""
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    lab = pki.issue(ca_dir, "lab", "lab-1")
    keep = pki.issue(ca_dir, "ledger", "ledger-1")
    pki.revoke(ca_dir, "lab-1", "key-compromise")
    before = certificates.load_crl(ca_dir / "crl.pem", ca_cert_path=ca_dir / "ca.pem")
    key_before = (ca_dir / "ca.key").read_bytes()
    started = dt.datetime.now(UTC).replace(microsecond=0)
    out = stockpile("pki", "crl", "--ca", str(ca_dir), "--valid-days", "7")
    assert out.returncode == 0, out.stderr
    assert len(out.stdout.splitlines()) == 1 and out.stderr == ""
    assert out.stdout.startswith("signed CRL number 2 (1 revoked), next update ")
    assert str(ca_dir / "crl.pem") in out.stdout and "PRIVATE" not in out.stdout
    crl = certificates.load_crl(ca_dir / "crl.pem", ca_cert_path=ca_dir / "ca.pem")
    number = crl.extensions.get_extension_for_class(x509.CRLNumber).value.crl_number
    assert number == 2 and pki.read_index(ca_dir).crl_number == 2
    assert certificates.is_revoked(crl, lab.serial) and not certificates.is_revoked(crl, keep.serial)
    assert crl.last_update_utc >= before.last_update_utc
    lapse = crl.next_update_utc - started
    assert dt.timedelta(days=7) <= lapse <= dt.timedelta(days=7, seconds=120)
    assert certificates.crl_next_update(ca_dir / "crl.pem") == pki.iso_utc(crl.next_update_utc)
    assert mode(ca_dir / "crl.pem") == 0o644 and mode(ca_dir / "ca.key") == 0o600
    assert (ca_dir / "ca.key").read_bytes() == key_before
    listed = stockpile("pki", "list", "--ca", str(ca_dir))
    assert f"CRL number 2, next update {pki.iso_utc(crl.next_update_utc)}" in listed.stdout
    # in-process: the default is a year; a missing CA is one line
    renewed = pki.renew_crl(ca_dir, now=started + dt.timedelta(days=1))
    assert renewed.crl_number == 3 and renewed.revoked == 1
    assert renewed.next_update == started + dt.timedelta(days=1 + pki.DEFAULT_CRL_VALID_DAYS)
    missing = stockpile("pki", "crl", "--ca", str(tmp_path / "none"))
    assert missing.returncode == 2 and len(missing.stderr.splitlines()) == 1
    assert "is not a site CA directory" in missing.stderr
    if OPENSSL:
        _openssl_sees_the_crl_signed_and_the_cert_revoked(ca_dir, lab.cert_path)


def test_a_pki_directory_can_be_backed_up_and_restored_elsewhere(tmp_path):
    """index.json holds paths relative to the PKI directory: a copy restored at another
    place is a working CA, with its keys still 0600."""
    original = tmp_path / "srv" / "pki"
    pki.init_ca("yard", original)
    pki.issue(original, "lab", "lab-1")
    pki.issue(original, "ledger", "ledger-1", out_dir=original / "tls" / "ledger-1")
    index = pki.read_index(original)
    assert [e["cert_path"] for e in index.certificates] == ["lab-1.pem",
                                                             "tls/ledger-1/ledger-1.pem"]
    assert str(tmp_path) not in (original / "index.json").read_text()

    backup = tmp_path / "backup.tar"
    shutil.make_archive(str(backup.with_suffix("")), "tar", root_dir=original)
    shutil.rmtree(original)
    restored = tmp_path / "elsewhere" / "pki-restored"
    restored.mkdir(parents=True)
    shutil.unpack_archive(str(backup), str(restored))
    assert mode(restored / "ca.key") == 0o600 and mode(restored / "lab-1.key") == 0o600
    for entry in pki.read_index(restored).certificates:
        path = pki.certificate_path(restored, entry)
        assert path.is_file() and path.is_relative_to(restored)
        certificates.verify_certificate(path, restored / "ca.pem", crl_path=restored / "crl.pem")
    # the restored CA issues, revokes and renews its CRL
    for argv in (["issue", "--ca", str(restored), "--role", "scanner", "--name", "scan-1"],
                 ["revoke", "--ca", str(restored), "--name", "lab-1"],
                 ["crl", "--ca", str(restored)],
                 ["list", "--ca", str(restored)]):
        out = stockpile("pki", *argv)
        assert out.returncode == 0, (argv, out.stderr)
    entries = {e["name"]: e for e in pki.read_index(restored).certificates}
    assert entries["scan-1"]["cert_path"] == "scan-1.pem" and entries["lab-1"]["revoked"]
    crl = certificates.load_crl(restored / "crl.pem", ca_cert_path=restored / "ca.pem")
    assert certificates.is_revoked(crl, restored / "lab-1.pem")


def test_an_older_index_with_absolute_paths_keeps_working(tmp_path):
    ca_dir = tmp_path / "ca"
    pki.init_ca("yard", ca_dir)
    lab = pki.issue(ca_dir, "lab", "lab-1")
    away = pki.issue(ca_dir, "gnss", "gnss-1", out_dir=tmp_path / "tls")
    # what an earlier version wrote: absolute paths
    data = json.loads((ca_dir / "index.json").read_text())
    data["certificates"][0]["cert_path"] = str(lab.cert_path.resolve())
    data["certificates"][1]["cert_path"] = str(away.cert_path.resolve())
    (ca_dir / "index.json").write_text(json.dumps(data, indent=2))
    entries = pki.read_index(ca_dir).certificates
    assert [pki.certificate_path(ca_dir, e) for e in entries] == [
        lab.cert_path.resolve(), away.cert_path.resolve()]
    listed = stockpile("pki", "list", "--ca", str(ca_dir), "--json")
    assert listed.returncode == 0, listed.stderr
    assert [r["status"] for r in json.loads(listed.stdout)["certificates"]] == ["valid", "valid"]
    # the next write keeps every entry and makes a path inside the CA directory relative
    pki.issue(ca_dir, "lab", "lab-2")
    paths = [e["cert_path"] for e in pki.read_index(ca_dir).certificates]
    assert paths == ["lab-1.pem", str(away.cert_path.resolve()), "lab-2.pem"]
