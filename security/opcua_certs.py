"""OPC UA application-instance certificates: self-signed RSA, the application URI in the
subjectAltName, as OPC UA's ``Basic256Sha256`` security policy requires.

An OPC UA application (the PLC adapter, a machine PLC, the simulator's PLC server)
identifies itself with an application-instance certificate: RSA (``Basic256Sha256``
takes 2048 to 4096 bits, signatures SHA-256), its application URI as a URI in the
subjectAltName (and the host names it answers on as DNS / IP entries), key usages
digital signature, non-repudiation, key and data encipherment, and both TLS usages
(server and client authentication).  Each side pins the other's certificate
(``docs/integration.md``, "Machine PLCs over OPC UA").

:func:`make_application_certificate` writes ``NAME.der`` (the certificate, DER, 0644) and
``NAME.key`` (the private key, unencrypted PKCS#8 PEM, 0600 from creation; never printed
or logged) and returns both paths.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
from pathlib import Path
from typing import Iterable

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from security.files import write_private, write_public

__all__ = ["DEFAULT_DAYS", "RSA_BITS", "make_application_certificate", "application_uri_of",
           "file_format"]

#: validity of a new application certificate, days
DEFAULT_DAYS = 825
#: RSA key size (Basic256Sha256 allows 2048 to 4096)
RSA_BITS = 2048


def _alt_names(uri: str, hosts: Iterable[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(uri)]
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return names


def make_application_certificate(directory: str | Path, name: str, application_uri: str, *,
                                 hosts: Iterable[str] = ("localhost", "127.0.0.1"),
                                 days: int = DEFAULT_DAYS, force: bool = False
                                 ) -> tuple[Path, Path]:
    """Make a self-signed application-instance certificate and its key.

    Parameters
    ----------
    directory : str or Path
        Where to write ``NAME.der`` and ``NAME.key`` (created if missing).
    name : str
        File name stem and the certificate's common name.
    application_uri : str
        The application's URI (``urn:...``), the subjectAltName URI.
    hosts : iterable of str
        Host names and addresses the application answers on (DNS / IP entries).
    days : int
        Validity from now, days.
    force : bool
        Replace an existing key (otherwise FileExistsError).

    Returns
    -------
    (Path, Path)
        The certificate (DER) and the private key (PEM, 0600).
    """
    if not application_uri or ":" not in application_uri:
        raise ValueError(f"an application URI looks like urn:site:name, got {application_uri!r}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / f"{name}.der", directory / f"{name}.key"
    key = rsa.generate_private_key(public_exponent=65537, key_size=RSA_BITS)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name),
                         x509.NameAttribute(NameOID.ORGANIZATION_NAME, "stockpile-ledger")])
    now = dt.datetime.now(dt.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(subject).issuer_name(subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=int(days)))
            .add_extension(x509.SubjectAlternativeName(_alt_names(application_uri, hosts)),
                           critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=True,
                                         key_encipherment=True, data_encipherment=True,
                                         key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(key, hashes.SHA256()))
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    write_private(key_path, pem, force=force)
    write_public(cert_path, cert.public_bytes(serialization.Encoding.DER))
    return cert_path, key_path


def application_uri_of(path: str | Path) -> str:
    """The application URI (the first subjectAltName URI) of a certificate file (DER or
    PEM); ValueError (one line) when it is not a certificate or names no URI."""
    data = Path(path).read_bytes()
    try:
        cert = (x509.load_pem_x509_certificate(data) if data.lstrip().startswith(b"-----")
                else x509.load_der_x509_certificate(data))
    except ValueError:
        raise ValueError(f"{path}: not a DER or PEM certificate") from None
    try:
        uris = cert.extensions.get_extension_for_class(
            x509.SubjectAlternativeName).value.get_values_for_type(x509.UniformResourceIdentifier)
    except x509.ExtensionNotFound:
        uris = []
    if not uris:
        raise ValueError(f"{path}: the certificate names no application URI (subjectAltName URI)")
    return uris[0]


def file_format(path: str | Path) -> str:
    """``"pem"`` or ``"der"``: how a certificate or key file is encoded, from its content
    (OPC UA libraries guess it from the file name, and ``NAME.key`` is PEM here)."""
    return "pem" if Path(path).read_bytes().lstrip().startswith(b"-----") else "der"
