"""The site CA's certificate revocation list: the revocation reasons ``stockpile pki``
takes and :func:`sign_crl`, which signs a CRL listing every revoked certificate of an
index (``security.pki`` holds the CA's files and calls it)."""

from __future__ import annotations

import datetime as dt
from typing import Iterable

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec

#: how long a CRL is valid after it is signed (its nextUpdate), unless told otherwise
DEFAULT_CRL_VALID_DAYS = 365

#: the revocation reasons ``revoke`` takes (RFC 5280 names, with dashes)
REVOCATION_REASONS: dict[str, x509.ReasonFlags] = {
    "unspecified": x509.ReasonFlags.unspecified,
    "key-compromise": x509.ReasonFlags.key_compromise,
    "ca-compromise": x509.ReasonFlags.ca_compromise,
    "affiliation-changed": x509.ReasonFlags.affiliation_changed,
    "superseded": x509.ReasonFlags.superseded,
    "cessation-of-operation": x509.ReasonFlags.cessation_of_operation,
    "privilege-withdrawn": x509.ReasonFlags.privilege_withdrawn,
}


def sign_crl(ca_cert: x509.Certificate, ca_key: ec.EllipticCurvePrivateKey, crl_number: int,
             entries: Iterable[dict], now: dt.datetime, *,
             valid_days: int = DEFAULT_CRL_VALID_DAYS) -> bytes:
    """A PEM CRL signed by the CA: lastUpdate ``now``, nextUpdate ``valid_days`` later,
    number ``crl_number``, listing each index entry with ``revoked`` true (its serial in
    hex, ``revoked_at`` and ``revocation_reason``)."""
    builder = (x509.CertificateRevocationListBuilder()
               .issuer_name(ca_cert.subject)
               .last_update(now)
               .next_update(now + dt.timedelta(days=valid_days))
               .add_extension(x509.CRLNumber(crl_number), critical=False)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(
                   ca_key.public_key()), critical=False))
    for entry in entries:
        if not entry.get("revoked"):
            continue
        revoked = (x509.RevokedCertificateBuilder()
                   .serial_number(int(entry["serial"], 16))
                   .revocation_date(dt.datetime.fromisoformat(entry["revoked_at"]))
                   .add_extension(x509.CRLReason(REVOCATION_REASONS[entry["revocation_reason"]]),
                                  critical=False)
                   .build())
        builder = builder.add_revoked_certificate(revoked)
    crl = builder.sign(ca_key, hashes.SHA256())
    return crl.public_bytes(serialization.Encoding.PEM)
