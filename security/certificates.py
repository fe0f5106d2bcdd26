"""Reading certificates and CRLs of the site PKI back: what a certificate says, whether the
site CA issued it and still vouches for it, and how soon it expires.  Pure functions;
:mod:`security.pki` makes and revokes."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from security.pki import (_first, _read_cert, _utc_now, iso_utc, parse_serial,
                          serial_hex)

@dataclass(frozen=True)
class CertificateInfo:
    """What a certificate says (read back by :func:`certificate_info`)."""

    path: Path
    common_name: str | None
    role: str | None
    site: str | None
    serial: str
    not_before: dt.datetime
    not_after: dt.datetime
    subject: str
    issuer: str
    is_ca: bool
    dns_names: tuple[str, ...] = ()
    ip_addresses: tuple[str, ...] = ()
    extended_key_usages: tuple[str, ...] = ()


_EKU_NAMES = {ExtendedKeyUsageOID.CLIENT_AUTH: "clientAuth",
              ExtendedKeyUsageOID.SERVER_AUTH: "serverAuth"}


def load_crl(path: Path | str, *, ca_cert_path: Path | str | None = None
             ) -> x509.CertificateRevocationList:
    """Parse a PEM CRL; with ``ca_cert_path``, also check that the CA signed it
    (ValueError if not)."""
    path = Path(path)
    try:
        crl = x509.load_pem_x509_crl(path.read_bytes())
    except FileNotFoundError:
        raise FileNotFoundError(f"no CRL at {path}") from None
    if ca_cert_path is not None:
        ca = _read_cert(Path(ca_cert_path))
        if crl.issuer != ca.subject or not crl.is_signature_valid(ca.public_key()):
            raise ValueError(f"{path} is not signed by the CA of {ca_cert_path}")
    return crl


def crl_next_update(path: Path | str) -> str | None:
    """The nextUpdate of the CRL at ``path`` (``2027-11-28T20:00:00Z``), None when the
    file is missing or has none."""
    try:
        crl = load_crl(path)
    except (OSError, ValueError):
        return None
    moment = crl.next_update_utc
    return None if moment is None else iso_utc(moment)


def is_revoked(crl: x509.CertificateRevocationList,
               certificate: x509.Certificate | int | str | Path) -> bool:
    """Whether ``crl`` lists ``certificate`` (a certificate, its serial as an int or hex,
    or the path of a PEM certificate)."""
    if isinstance(certificate, x509.Certificate):
        serial = certificate.serial_number
    elif isinstance(certificate, Path):
        serial = _read_cert(certificate).serial_number
    elif isinstance(certificate, int):
        serial = certificate
    else:
        serial = parse_serial(certificate)
    return crl.get_revoked_certificate_by_serial_number(serial) is not None


def certificate_info(path: Path | str) -> CertificateInfo:
    """What the PEM certificate at ``path`` says: common name, role (OU), site (O), serial,
    validity, issuer, host names."""
    path = Path(path)
    cert = _read_cert(path)
    try:
        basic = cert.extensions.get_extension_for_class(x509.BasicConstraints).value
        is_ca = basic.ca
    except x509.ExtensionNotFound:
        is_ca = False
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        dns = tuple(san.get_values_for_type(x509.DNSName))
        ips = tuple(str(i) for i in san.get_values_for_type(x509.IPAddress))
    except x509.ExtensionNotFound:
        dns, ips = (), ()
    try:
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        usages = tuple(_EKU_NAMES.get(u, u.dotted_string) for u in eku)
    except x509.ExtensionNotFound:
        usages = ()
    return CertificateInfo(
        path=path, common_name=_first(cert.subject, NameOID.COMMON_NAME),
        role=_first(cert.subject, NameOID.ORGANIZATIONAL_UNIT_NAME),
        site=_first(cert.subject, NameOID.ORGANIZATION_NAME),
        serial=serial_hex(cert.serial_number), not_before=cert.not_valid_before_utc,
        not_after=cert.not_valid_after_utc, subject=cert.subject.rfc4514_string(),
        issuer=cert.issuer.rfc4514_string(), is_ca=is_ca, dns_names=dns, ip_addresses=ips,
        extended_key_usages=usages)


def verify_certificate(cert_path: Path | str, ca_cert_path: Path | str, *,
                       crl_path: Path | str | None = None,
                       now: dt.datetime | None = None) -> CertificateInfo:
    """Check that the CA at ``ca_cert_path`` signed the certificate at ``cert_path``, that
    both are valid at ``now`` and (with ``crl_path``) that the CA's CRL does not list it.
    Returns its :func:`certificate_info`; ValueError naming what failed."""
    now = _utc_now(now)
    cert, ca = _read_cert(Path(cert_path)), _read_cert(Path(ca_cert_path))
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        raise ValueError(f"{cert_path} was not issued by the CA of {ca_cert_path}") from None
    for what, c in (("certificate", cert), ("site CA", ca)):
        if now < c.not_valid_before_utc:
            raise ValueError(f"the {what} is not valid before {iso_utc(c.not_valid_before_utc)}")
        if now > c.not_valid_after_utc:
            raise ValueError(f"the {what} expired at {iso_utc(c.not_valid_after_utc)}")
    if crl_path is not None:
        crl = load_crl(crl_path, ca_cert_path=ca_cert_path)
        if is_revoked(crl, cert):
            raise ValueError(f"{cert_path} is revoked (serial {serial_hex(cert.serial_number)})")
    return certificate_info(cert_path)


def _human_span(seconds: float) -> str:
    seconds = abs(seconds)
    for unit, size in (("day", 86_400), ("hour", 3600), ("minute", 60)):
        if seconds >= size:
            count = int(seconds // size)
            return f"{count} {unit}{'s' if count != 1 else ''}"
    return f"{int(seconds)} seconds"


def expiry_warning(cert_path: Path | str, warn_before_s: float,
                   now: dt.datetime | None = None) -> str | None:
    """A warning line when the certificate at ``cert_path`` expires within
    ``warn_before_s`` seconds of ``now`` (or has expired), else None:
    ``certificate NAME (PATH) expires in 12 days (at 2026-12-10T20:00:00Z)``."""
    now = _utc_now(now)
    info = certificate_info(cert_path)
    left_s = (info.not_after - now).total_seconds()
    if left_s > warn_before_s:
        return None
    who = f"certificate {info.common_name} ({cert_path})"
    if left_s <= 0:
        return f"{who} expired {_human_span(left_s)} ago (at {iso_utc(info.not_after)})"
    return f"{who} expires in {_human_span(left_s)} (at {iso_utc(info.not_after)})"


def certificate_status(entry: dict, now: dt.datetime | None = None) -> str:
    """``revoked``, ``expired`` or ``valid`` for an ``index.json`` entry."""
    if entry.get("revoked"):
        return "revoked"
    if dt.datetime.fromisoformat(entry["not_after"]) < _utc_now(now):
        return "expired"
    return "valid"
