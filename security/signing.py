"""Signatures with a site certificate's key, checked against the certificate and the site CA.

A service signs with the private key of its site certificate (ECDSA P-256, SHA-256, as
:mod:`security.pki` issues them); anyone holding the certificate checks the signature,
and with the site CA's certificate also that the certificate is the site's.  Nothing
here prints or logs key material.

- :func:`sign` -> DER signature bytes;
- :func:`check` raises :class:`SignatureInvalid` (with the reason) or returns the
  signer's common name.
"""

from __future__ import annotations

from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID


class SignatureInvalid(ValueError):
    """A signature that does not hold, or a certificate the site CA did not sign."""


def sign(data: bytes, key_path: str | Path) -> bytes:
    """The ECDSA-SHA256 signature (DER) of ``data`` with the PEM private key at ``key_path``."""
    key = serialization.load_pem_private_key(Path(key_path).read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{key_path}: not an EC private key")
    return key.sign(data, ec.ECDSA(hashes.SHA256()))


def common_name(certificate_pem: bytes) -> str:
    """The subject common name of a PEM certificate ("" when it has none)."""
    cert = x509.load_pem_x509_certificate(certificate_pem)
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""


def check(data: bytes, signature: bytes, certificate_pem: bytes,
          ca_pem: bytes | None = None) -> str:
    """Check ``signature`` over ``data`` with the certificate's public key, and (with
    ``ca_pem``) that the site CA signed the certificate; return the signer's common name.

    Raises
    ------
    SignatureInvalid
        The signature does not match, or the CA did not sign the certificate.
    """
    try:
        cert = x509.load_pem_x509_certificate(certificate_pem)
    except ValueError as exc:
        raise SignatureInvalid(f"unreadable certificate: {exc}") from None
    public = cert.public_key()
    if not isinstance(public, ec.EllipticCurvePublicKey):
        raise SignatureInvalid("the certificate's key is not an EC key")
    try:
        public.verify(signature, data, ec.ECDSA(hashes.SHA256()))
    except InvalidSignature:
        raise SignatureInvalid("the signature does not match the signed fields") from None
    if ca_pem is not None:
        ca = x509.load_pem_x509_certificate(ca_pem)
        try:
            cert.verify_directly_issued_by(ca)
        except (InvalidSignature, ValueError, TypeError):
            raise SignatureInvalid(f"the certificate of {common_name(certificate_pem)!r} was "
                                   "not issued by this site CA") from None
    return common_name(certificate_pem)
