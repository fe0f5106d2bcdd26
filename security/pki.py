"""The site PKI: a certificate authority that a yard runs itself, and a certificate per
service.

Keys are ECDSA on P-256, certificates are signed with ECDSA-SHA256: the key type Zenoh's
TLS (rustls) accepts everywhere.  Keys are written as unencrypted PKCS#8 PEM (a service
reads its key unattended), with mode 0600 from the moment the file is created; nothing
here prints or logs key material.  The functions return what they wrote; the command
line (:mod:`security.cli`) prints it.

A certificate's subject is ``CN=<name>, OU=<role>, O=<site>``: the common name identifies
the service (Zenoh's access control matches it), the organisational unit records its role
(one of :data:`ROLES`).  Every certificate is for TLS client authentication; a ``router``
certificate is also for server authentication and names the hosts it answers on
(default ``localhost`` and ``127.0.0.1``).  A head office's PKI issues two more roles:
``hq`` (the head-office service) and ``uplink`` (a site router's link into the head
office, named ``<site>.router``; ``docs/security.md``).

Layout of the CA directory (``init_ca``; ``issue`` writes there unless given ``out_dir``)::

    ca.pem        the site CA's certificate (public: every service needs it)
    ca.key        the site CA's private key (0600; keep it on the CA machine)
    crl.pem       the certificate revocation list, signed by the CA (public)
    index.json    every certificate issued: name, role, serial, validity, revocation, and
                  where it was written (relative to the CA directory, so that the
                  directory can be moved or restored elsewhere)
    .lock         held while ``issue`` or ``revoke`` rewrites the index
    NAME.pem      the certificate issued to NAME
    NAME.key      NAME's private key (0600)

``issue(..., out_dir=DIR)`` writes ``NAME.pem``, ``NAME.key`` and copies of ``ca.pem`` and
``crl.pem`` to DIR instead: a directory a service is given as its TLS directory, without
the CA's key.  :func:`renew_crl` re-signs ``crl.pem`` before its nextUpdate lapses.  The CA directory stays the record:
``index.json`` lists the certificate either way.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import ipaddress
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sequence

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from security.files import PUBLIC_MODE as _PUBLIC_MODE
from security.files import write_private as _write_private, write_public as _write_public
from security.crl import DEFAULT_CRL_VALID_DAYS, REVOCATION_REASONS, sign_crl

#: the roles the product knows; a certificate records one (its subject's OU)
ROLES: tuple[str, ...] = ("router", "scanner", "gnss", "plc", "localizer", "lab", "ledger",
                          "projector", "recorder", "dashboard", "auditor", "replay", "hq",
                          "uplink")

#: roles whose certificate is also a TLS server certificate (with host names)
SERVER_ROLES: tuple[str, ...] = ("router",)

#: a router certificate's hosts when none are given
DEFAULT_ROUTER_SANS: tuple[str, ...] = ("localhost", "127.0.0.1")

CA_CERT = "ca.pem"
CA_KEY = "ca.key"
CRL = "crl.pem"
INDEX = "index.json"
#: the lock ``issue`` and ``revoke`` hold while they read and rewrite the index
LOCK = ".lock"

#: file names of the CA directory, which an issued name may not take
RESERVED_NAMES = frozenset({"ca", "crl", "index"})

DEFAULT_CA_VALID_DAYS = 3650
DEFAULT_CERT_VALID_DAYS = 365
#: a certificate is valid from this long before it was issued (clocks of the yard differ)
NOT_BEFORE_SKEW_S = 300


_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
_SECONDS_PER_DAY = 86_400
_DIR_MODE = 0o700


# -- records ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class CaResult:
    """What :func:`init_ca` wrote."""

    site: str
    ca_dir: Path
    cert_path: Path
    key_path: Path
    crl_path: Path
    index_path: Path
    serial: str
    not_after: dt.datetime


@dataclass(frozen=True)
class IssuedCertificate:
    """What :func:`issue` wrote (``ca_copy_path``, ``crl_copy_path``: the copies of
    ``ca.pem`` and ``crl.pem`` in ``out_dir``, None when it was the CA directory)."""

    name: str
    role: str
    serial: str
    not_after: dt.datetime
    cert_path: Path
    key_path: Path
    ca_copy_path: Path | None
    dns_names: tuple[str, ...] = ()
    ip_addresses: tuple[str, ...] = ()
    crl_copy_path: Path | None = None


@dataclass(frozen=True)
class CrlRenewal:
    """What :func:`renew_crl` wrote: the CRL, its number, when it was signed and when it
    lapses, and how many serials it lists."""

    crl_path: Path
    crl_number: int
    last_update: dt.datetime
    next_update: dt.datetime
    revoked: int


@dataclass(frozen=True)
class Revocation:
    """What :func:`revoke` did: the certificates it revoked (index entries) and the files
    it rewrote."""

    revoked: tuple[dict, ...]
    reason: str
    crl_path: Path
    index_path: Path
    crl_number: int


@dataclass
class Index:
    """``index.json``: the site, the CA's certificate and every certificate issued."""

    site: str
    ca: dict
    crl_number: int = 0
    certificates: list[dict] = field(default_factory=list)

    def to_json(self) -> dict:
        return {"site": self.site, "ca": self.ca, "crl_number": self.crl_number,
                "certificates": self.certificates}


# -- helpers ---------------------------------------------------------------------------------


def _utc_now(now: dt.datetime | None) -> dt.datetime:
    if now is None:
        return dt.datetime.now(dt.timezone.utc).replace(microsecond=0)
    if now.tzinfo is None:
        raise ValueError("now must be timezone-aware (UTC)")
    return now.astimezone(dt.timezone.utc).replace(microsecond=0)


def iso_utc(moment: dt.datetime) -> str:
    """``2026-11-28T20:00:00Z``."""
    return moment.astimezone(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def serial_hex(serial: int) -> str:
    """A serial number as upper-case hex with an even number of digits (as openssl shows
    it)."""
    text = format(serial, "X")
    return text if len(text) % 2 == 0 else "0" + text


def parse_serial(text: str) -> int:
    """A serial number from hex (``0x`` and ``:`` separators allowed); ValueError if it is
    not hex."""
    cleaned = text.strip().lower().removeprefix("0x").replace(":", "")
    if not cleaned or not re.fullmatch(r"[0-9a-f]+", cleaned):
        raise ValueError(f"not a serial number (hex): {text!r}")
    return int(cleaned, 16)


def check_name(name: str) -> str:
    """A certificate name is also a file name: letters, digits, ``.``, ``_``, ``-`` (up
    to 64), not starting with a punctuation mark, and not ``ca``, ``crl`` or ``index``."""
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
        raise ValueError(f"name must be 1-64 letters, digits, '.', '_' or '-' starting with a "
                         f"letter or digit, got {name!r}")
    if name.lower() in RESERVED_NAMES:
        raise ValueError(f"name {name!r} is taken by the CA's own files "
                         f"({', '.join(sorted(RESERVED_NAMES))})")
    return name


def check_role(role: str) -> str:
    """``role`` if it is one of :data:`ROLES`, else ValueError listing them."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}: choose from {', '.join(ROLES)}")
    return role


def _check_valid_days(valid_days: int) -> int:
    if isinstance(valid_days, bool) or not isinstance(valid_days, int) or valid_days <= 0:
        raise ValueError(f"valid days must be a positive whole number of days, got {valid_days!r}")
    return valid_days


def _refuse_existing(paths: Iterable[Path], what: str) -> None:
    existing = [str(p) for p in paths if p.exists()]
    if existing:
        raise FileExistsError(f"{what} exists: {', '.join(existing)} (use --force to replace)")


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _cert_pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _read_cert(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(Path(path).read_bytes())
    except FileNotFoundError:
        raise FileNotFoundError(f"no certificate at {path}") from None
    except ValueError as exc:
        raise ValueError(f"{path} is not a PEM certificate ({exc})") from None


@contextlib.contextmanager
def _locked(ca_dir: Path) -> Iterator[None]:
    """Hold the CA directory's lock (an exclusive ``flock`` on ``.lock``): two ``issue``
    or ``revoke`` runs at once do not lose each other's index entries."""
    fd = os.open(Path(ca_dir) / LOCK, os.O_RDWR | os.O_CREAT, _PUBLIC_MODE)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _load_ca(ca_dir: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey, Index]:
    ca_dir = Path(ca_dir)
    for name in (CA_CERT, CA_KEY, INDEX):
        if not (ca_dir / name).is_file():
            raise FileNotFoundError(f"{ca_dir} is not a site CA directory: no {name} "
                                    f"(make one with stockpile pki init)")
    cert = _read_cert(ca_dir / CA_CERT)
    key = serialization.load_pem_private_key((ca_dir / CA_KEY).read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{ca_dir / CA_KEY} is not an EC key")
    if key.public_key().public_numbers() != cert.public_key().public_numbers():
        raise ValueError(f"{ca_dir / CA_KEY} is not the key of {ca_dir / CA_CERT}")
    return cert, key, read_index(ca_dir)


def read_index(ca_dir: Path) -> Index:
    """The CA directory's ``index.json``."""
    path = Path(ca_dir) / INDEX
    try:
        data = json.loads(path.read_text())
        return Index(site=data["site"], ca=data["ca"], crl_number=int(data["crl_number"]),
                     certificates=list(data["certificates"]))
    except FileNotFoundError:
        raise FileNotFoundError(f"no {INDEX} in {ca_dir}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path} is damaged ({type(exc).__name__}: {exc})") from None


def certificate_path(ca_dir: Path | str, entry: dict) -> Path:
    """Where an index entry's certificate was written: ``cert_path`` is relative to the
    CA directory (an index of an older version holds absolute paths, kept as they are)."""
    path = Path(entry["cert_path"])
    return path if path.is_absolute() else Path(ca_dir) / path


def _relative_to_ca(ca_dir: Path, path: Path) -> str:
    return os.path.relpath(path.resolve(), Path(ca_dir).resolve())


def _write_index(ca_dir: Path, index: Index) -> Path:
    """Write ``index.json``; an older entry's absolute ``cert_path`` inside the CA
    directory is rewritten relative to it."""
    path = Path(ca_dir) / INDEX
    root = Path(ca_dir).resolve()
    for entry in index.certificates:
        old = Path(entry.get("cert_path") or ".")
        if old.is_absolute() and old.is_relative_to(root):
            entry["cert_path"] = _relative_to_ca(ca_dir, old)
    _write_public(path, (json.dumps(index.to_json(), indent=2) + "\n").encode())
    return path


def _name_attrs(common_name: str, site: str, unit: str | None) -> x509.Name:
    attrs = [x509.NameAttribute(NameOID.ORGANIZATION_NAME, site)]
    if unit is not None:
        attrs.append(x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, unit))
    attrs.append(x509.NameAttribute(NameOID.COMMON_NAME, common_name))
    return x509.Name(attrs)


def _first(name: x509.Name, oid: x509.ObjectIdentifier) -> str | None:
    values = name.get_attributes_for_oid(oid)
    return str(values[0].value) if values else None


# -- the CA ----------------------------------------------------------------------------------


def init_ca(site: str, out_dir: Path | str, *, valid_days: int = DEFAULT_CA_VALID_DAYS,
            force: bool = False, now: dt.datetime | None = None) -> CaResult:
    """Make a site CA in ``out_dir`` (created with mode 0700 if missing): ``ca.pem``,
    ``ca.key`` (0600), an empty ``crl.pem`` and ``index.json``.

    Refuses (FileExistsError) when ``out_dir`` already holds a CA's certificate or key,
    unless ``force``: a new CA then replaces it and the index starts empty (certificates
    of the old CA no longer verify against the new ``ca.pem``).
    """
    if not isinstance(site, str) or not _NAME_RE.fullmatch(site):
        raise ValueError(f"site must be 1-64 letters, digits, '.', '_' or '-', got {site!r}")
    _check_valid_days(valid_days)
    now = _utc_now(now)
    out = Path(out_dir)
    paths = [out / CA_CERT, out / CA_KEY, out / CRL, out / INDEX]
    if not force:
        _refuse_existing(paths[:2], "a site CA")
    out.mkdir(mode=_DIR_MODE, parents=True, exist_ok=True)

    key = _new_key()
    name = _name_attrs(f"{site} stockpile site CA", site, None)
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (x509.CertificateBuilder()
            .subject_name(name)
            .issuer_name(name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(seconds=NOT_BEFORE_SKEW_S))
            .not_valid_after(now + dt.timedelta(days=valid_days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, key_cert_sign=True, crl_sign=True,
                                         encipher_only=False, decipher_only=False),
                           critical=True)
            .add_extension(ski, critical=False)
            .sign(key, hashes.SHA256()))
    serial = serial_hex(cert.serial_number)
    index = Index(site=site, ca={"subject": cert.subject.rfc4514_string(), "serial": serial,
                                 "not_before": iso_utc(cert.not_valid_before_utc),
                                 "not_after": iso_utc(cert.not_valid_after_utc)},
                  crl_number=0, certificates=[])

    _write_private(out / CA_KEY, _key_pem(key), force=force)
    _write_public(out / CA_CERT, _cert_pem(cert))
    _write_public(out / CRL, sign_crl(cert, key, index.crl_number, index.certificates, now))
    _write_index(out, index)
    (out / LOCK).touch(mode=_PUBLIC_MODE, exist_ok=True)
    return CaResult(site=site, ca_dir=out, cert_path=out / CA_CERT, key_path=out / CA_KEY,
                    crl_path=out / CRL, index_path=out / INDEX, serial=serial,
                    not_after=cert.not_valid_after_utc)


def _split_sans(sans: Sequence[str]) -> tuple[list[str], list[str]]:
    dns, ips = [], []
    for san in sans:
        text = str(san).strip()
        try:
            ips.append(str(ipaddress.ip_address(text)))
        except ValueError:
            if not re.fullmatch(r"[A-Za-z0-9*]([A-Za-z0-9.-]*[A-Za-z0-9])?", text):
                raise ValueError(f"not a host name or IP address: {san!r}") from None
            dns.append(text)
    return dns, ips


def issue(ca_dir: Path | str, role: str, name: str, *, out_dir: Path | str | None = None,
          valid_days: int = DEFAULT_CERT_VALID_DAYS, sans: Sequence[str] | None = None,
          force: bool = False, now: dt.datetime | None = None) -> IssuedCertificate:
    """Issue ``name`` a certificate for ``role``, signed by the CA in ``ca_dir``: a new
    key ``NAME.key`` (0600) and ``NAME.pem`` in ``out_dir`` (default: the CA directory;
    another directory also gets a copy of ``ca.pem``), recorded in ``index.json``.

    ``sans``: host names and IP addresses the certificate is valid for (a ``router``'s
    default: :data:`DEFAULT_ROUTER_SANS`; other roles: none).  The certificate may not
    outlive the CA.  Refuses (FileExistsError) to replace an existing ``NAME.key`` or
    ``NAME.pem``, or a different ``ca.pem`` in ``out_dir``, unless ``force``; a replaced
    certificate stays valid until it expires or is revoked (:func:`revoke` by serial).
    """
    check_role(role)
    check_name(name)
    _check_valid_days(valid_days)
    ca_dir = Path(ca_dir)
    _load_ca(ca_dir)                     # a clear error before the lock file is made
    with _locked(ca_dir):
        return _issue_locked(ca_dir, role, name, out_dir=out_dir, valid_days=valid_days,
                             sans=sans, force=force, now=_utc_now(now))


def _issue_locked(ca_dir: Path, role: str, name: str, *, out_dir: Path | str | None,
                  valid_days: int, sans: Sequence[str] | None, force: bool,
                  now: dt.datetime) -> IssuedCertificate:
    ca_cert, ca_key, index = _load_ca(ca_dir)
    out = ca_dir if out_dir is None else Path(out_dir)
    separate = out.resolve() != ca_dir.resolve()
    cert_path, key_path = out / f"{name}.pem", out / f"{name}.key"
    ca_copy = out / CA_CERT if separate else None
    crl_copy = out / CRL if separate else None
    ca_pem = _cert_pem(ca_cert)
    if not force:
        _refuse_existing([key_path, cert_path], f"a certificate or key for {name!r}")
        if ca_copy is not None and ca_copy.exists() and ca_copy.read_bytes() != ca_pem:
            raise FileExistsError(f"{ca_copy} is another CA's certificate (use --force to "
                                  f"replace)")

    not_before = now - dt.timedelta(seconds=NOT_BEFORE_SKEW_S)
    not_after = now + dt.timedelta(days=valid_days)
    if not_after > ca_cert.not_valid_after_utc:
        left_days = int((ca_cert.not_valid_after_utc - now).total_seconds() // _SECONDS_PER_DAY)
        raise ValueError(f"the certificate would outlive the site CA (valid until "
                         f"{iso_utc(ca_cert.not_valid_after_utc)}): give at most {left_days} "
                         f"valid days")
    if now > ca_cert.not_valid_after_utc:
        raise ValueError(f"the site CA expired at {iso_utc(ca_cert.not_valid_after_utc)}")
    if sans is None:
        sans = DEFAULT_ROUTER_SANS if role in SERVER_ROLES else ()
    dns, ips = _split_sans(sans)
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if role in SERVER_ROLES:
        usages.append(ExtendedKeyUsageOID.SERVER_AUTH)

    key = _new_key()
    builder = (x509.CertificateBuilder()
               .subject_name(_name_attrs(name, index.site, role))
               .issuer_name(ca_cert.subject)
               .public_key(key.public_key())
               .serial_number(x509.random_serial_number())
               .not_valid_before(not_before)
               .not_valid_after(not_after)
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False,
                                            key_encipherment=False, data_encipherment=False,
                                            key_agreement=False, key_cert_sign=False,
                                            crl_sign=False, encipher_only=False,
                                            decipher_only=False), critical=True)
               .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
               .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                              critical=False)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(
                   ca_key.public_key()), critical=False))
    if dns or ips:
        names: list[x509.GeneralName] = [x509.DNSName(d) for d in dns]
        names += [x509.IPAddress(ipaddress.ip_address(i)) for i in ips]
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    serial = serial_hex(cert.serial_number)

    if separate:
        out.mkdir(mode=_DIR_MODE, parents=True, exist_ok=True)
    _write_private(key_path, _key_pem(key), force=force)
    _write_public(cert_path, _cert_pem(cert))
    if ca_copy is not None and crl_copy is not None:
        _write_public(ca_copy, ca_pem)
        _write_public(crl_copy, (ca_dir / CRL).read_bytes())
    index.certificates.append({
        "name": name, "role": role, "serial": serial,
        "not_before": iso_utc(cert.not_valid_before_utc),
        "not_after": iso_utc(cert.not_valid_after_utc),
        "dns_names": dns, "ip_addresses": ips,
        "cert_path": _relative_to_ca(ca_dir, cert_path),
        "revoked": False, "revoked_at": None, "revocation_reason": None,
    })
    _write_index(ca_dir, index)
    return IssuedCertificate(name=name, role=role, serial=serial,
                             not_after=cert.not_valid_after_utc, cert_path=cert_path,
                             key_path=key_path, ca_copy_path=ca_copy, dns_names=tuple(dns),
                             ip_addresses=tuple(ips), crl_copy_path=crl_copy)


def revoke(ca_dir: Path | str, name_or_serial: str, reason: str = "unspecified", *,
           by: str | None = None, now: dt.datetime | None = None) -> Revocation:
    """Revoke certificates of the CA in ``ca_dir``: by name, every certificate of that
    name not yet revoked; by serial (hex), that one (``by``: ``"name"`` or ``"serial"``
    to take ``name_or_serial`` only as one; None: either).  Re-signs ``crl.pem`` with all
    the revoked serials and records the revocation in ``index.json``.

    ValueError for an unknown name or serial, one already revoked, an unknown reason
    (:data:`REVOCATION_REASONS`), or text that is both a name and another certificate's
    serial.
    """
    if reason not in REVOCATION_REASONS:
        raise ValueError(f"unknown reason {reason!r}: choose from "
                         f"{', '.join(REVOCATION_REASONS)}")
    if by not in (None, "name", "serial"):
        raise ValueError(f"by must be 'name', 'serial' or None, got {by!r}")
    ca_dir = Path(ca_dir)
    _load_ca(ca_dir)                     # a clear error before the lock file is made
    with _locked(ca_dir):
        return _revoke_locked(ca_dir, name_or_serial, reason, by=by, now=_utc_now(now))


def _revoke_locked(ca_dir: Path, name_or_serial: str, reason: str, *, by: str | None,
                   now: dt.datetime) -> Revocation:
    ca_cert, ca_key, index = _load_ca(ca_dir)
    by_name = [e for e in index.certificates
               if by != "serial" and e["name"] == name_or_serial]
    if by == "serial":
        wanted: int | None = parse_serial(name_or_serial)
    elif by == "name":
        wanted = None
    else:
        try:
            wanted = parse_serial(name_or_serial)
        except ValueError:
            wanted = None
    by_serial = [e for e in index.certificates
                 if wanted is not None and parse_serial(e["serial"]) == wanted]
    if by_name and by_serial and by_serial[0] not in by_name:
        raise ValueError(f"{name_or_serial!r} is a name and another certificate's serial: "
                         f"revoke by --serial or --name")
    matches = by_name or by_serial
    if not matches:
        known = sorted({e["name"] for e in index.certificates})
        raise ValueError(f"no certificate named or with serial {name_or_serial!r} in "
                         f"{ca_dir / INDEX} (issued: {', '.join(known) or 'none'})")
    targets = [e for e in matches if not e["revoked"]]
    if not targets:
        serials = ", ".join(e["serial"] for e in matches)
        raise ValueError(f"{name_or_serial} is already revoked (serial {serials})")
    for entry in targets:
        entry.update(revoked=True, revoked_at=iso_utc(now), revocation_reason=reason)
    index.crl_number += 1
    crl_path = ca_dir / CRL
    _write_public(crl_path, sign_crl(ca_cert, ca_key, index.crl_number, index.certificates,
                                       now))
    index_path = _write_index(ca_dir, index)
    return Revocation(revoked=tuple(dict(e) for e in targets), reason=reason,
                      crl_path=crl_path, index_path=index_path, crl_number=index.crl_number)


def renew_crl(ca_dir: Path | str, *, valid_days: int = DEFAULT_CRL_VALID_DAYS,
              now: dt.datetime | None = None) -> CrlRenewal:
    """Re-sign ``crl.pem`` with the same revoked serials, a higher CRL number, lastUpdate
    now and nextUpdate ``valid_days`` later (a CRL past its nextUpdate is refused by
    checkers that require a current one)."""
    _check_valid_days(valid_days)
    ca_dir = Path(ca_dir)
    _load_ca(ca_dir)                     # a clear error before the lock file is made
    now = _utc_now(now)
    with _locked(ca_dir):
        ca_cert, ca_key, index = _load_ca(ca_dir)
        index.crl_number += 1
        crl_path = ca_dir / CRL
        _write_public(crl_path, sign_crl(ca_cert, ca_key, index.crl_number, index.certificates,
                                         now, valid_days=valid_days))
        _write_index(ca_dir, index)
    return CrlRenewal(crl_path=crl_path, crl_number=index.crl_number, last_update=now,
                      next_update=now + dt.timedelta(days=valid_days),
                      revoked=sum(1 for e in index.certificates if e.get("revoked")))
