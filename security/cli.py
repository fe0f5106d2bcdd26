"""``stockpile pki``: the site PKI on the command line (:mod:`security.pki` does the work).

Each action prints one line naming the files it wrote, never key material; an error is a
ValueError or OSError, which ``stockpile`` prints as one line (exit 2).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from common.options import add_out, positive_int
from security import certificates, pki


def _cmd_init(args: argparse.Namespace) -> int:
    ca = pki.init_ca(args.site, args.out, valid_days=args.valid_days, force=args.force)
    print(f"site CA {ca.site}: wrote {ca.cert_path}, {ca.key_path} (mode 0600), {ca.crl_path}, "
          f"{ca.index_path}; serial {ca.serial}, valid until {pki.iso_utc(ca.not_after)}")
    return 0


def _cmd_issue(args: argparse.Namespace) -> int:
    cert = pki.issue(args.ca, args.role, args.name, out_dir=args.out,
                     valid_days=args.valid_days, sans=args.san, force=args.force)
    files = [str(cert.cert_path), f"{cert.key_path} (mode 0600)"]
    files += [str(p) for p in (cert.ca_copy_path, cert.crl_copy_path) if p is not None]
    hosts = list(cert.dns_names) + list(cert.ip_addresses)
    print(f"issued {cert.name} (role {cert.role}, serial {cert.serial}, valid until "
          f"{pki.iso_utc(cert.not_after)}{', hosts ' + ' '.join(hosts) if hosts else ''}): "
          f"wrote {', '.join(files)}")
    return 0


def _cmd_revoke(args: argparse.Namespace) -> int:
    by = "name" if args.name is not None else "serial"
    result = pki.revoke(args.ca, args.name if by == "name" else args.serial, args.reason, by=by)
    which = ", ".join(f"{e['name']} (serial {e['serial']})" for e in result.revoked)
    print(f"revoked {which}, reason {result.reason}: wrote {result.crl_path} "
          f"(CRL number {result.crl_number}), {result.index_path}")
    return 0


def _cmd_crl(args: argparse.Namespace) -> int:
    result = pki.renew_crl(args.ca, valid_days=args.valid_days)
    print(f"signed CRL number {result.crl_number} ({result.revoked} revoked), next update "
          f"{pki.iso_utc(result.next_update)}: wrote {result.crl_path}")
    return 0


def _cmd_list(args: argparse.Namespace) -> int:
    index = pki.read_index(args.ca)
    rows = [dict(entry, status=certificates.certificate_status(entry)) for entry in index.certificates]
    next_update = certificates.crl_next_update(Path(args.ca) / pki.CRL)
    if args.json:
        print(json.dumps({"site": index.site, "ca": index.ca, "crl_number": index.crl_number,
                          "crl_next_update": next_update, "certificates": rows}, indent=2))
        return 0
    print(f"site {index.site}: CA serial {index.ca['serial']}, valid until "
          f"{index.ca['not_after']}; CRL number {index.crl_number}, next update "
          f"{next_update or '-'}; {len(rows)} certificates")
    if rows:
        width = max(len("NAME"), *(len(r["name"]) for r in rows))
        print(f"{'NAME':<{width}}  {'ROLE':<9}  {'STATUS':<7}  {'NOT AFTER':<20}  SERIAL")
        for r in rows:
            print(f"{r['name']:<{width}}  {r['role']:<9}  {r['status']:<7}  "
                  f"{r['not_after']:<20}  {r['serial']}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``pki`` (``init``, ``issue``, ``revoke``, ``crl``, ``list``) to the ``stockpile`` parser."""
    p = subparsers.add_parser(
        "pki", help="the site PKI: a site CA, a certificate per service, revocation",
        description="The site's own certificate authority: make it (init), issue a "
        "certificate and key to each service for its role (issue), revoke one (revoke), "
        "re-sign the revocation list before it lapses (crl) and list what was issued (list). Keys are ECDSA P-256, written with mode 0600 and never "
        "printed.")
    sub = p.add_subparsers(dest="pki_command", metavar="ACTION", required=True)

    init = sub.add_parser(
        "init", help="make a site CA",
        description="Make a site CA in DIR: ca.pem, ca.key (mode 0600), an empty crl.pem and "
        "index.json. Refuses to replace an existing CA unless --force.")
    init.add_argument("--site", required=True, metavar="S", help="the site's name")
    add_out(init, metavar="DIR", required=True,
            help="the CA directory (created with mode 0700 if missing)")
    init.add_argument("--valid-days", type=_positive_days, default=pki.DEFAULT_CA_VALID_DAYS,
                      metavar="N", help="days the CA certificate is valid "
                      f"(default {pki.DEFAULT_CA_VALID_DAYS} days)")
    init.add_argument("--force", action="store_true",
                      help="replace an existing CA (its certificates then no longer verify)")
    init.set_defaults(func=_cmd_init)

    issue = sub.add_parser(
        "issue", help="issue a service its certificate and key",
        description="Issue NAME a certificate for ROLE signed by the site CA: NAME.pem and "
        "NAME.key (mode 0600) in the CA directory, or in --out DIR with copies of ca.pem and "
        "crl.pem (a service's TLS directory). The common name is NAME, the role is the subject's OU. "
        "Refuses to replace an existing key unless --force.")
    issue.add_argument("--ca", required=True, metavar="DIR", help="the site CA's directory")
    issue.add_argument("--role", required=True, metavar="ROLE",
                       help=f"one of: {', '.join(pki.ROLES)}")
    issue.add_argument("--name", required=True, metavar="NAME",
                       help="the service's name: the certificate's common name and file names")
    add_out(issue, metavar="DIR",
            help="write NAME.pem, NAME.key, ca.pem and crl.pem here (default: the CA "
            "directory)")
    issue.add_argument("--valid-days", type=_positive_days, default=pki.DEFAULT_CERT_VALID_DAYS,
                       metavar="N", help="days the certificate is valid "
                       f"(default {pki.DEFAULT_CERT_VALID_DAYS} days; at most until the CA "
                       "expires)")
    issue.add_argument("--san", nargs="+", metavar="HOST",
                       help="host names and IP addresses the certificate is valid for "
                       f"(default for a router: {' '.join(pki.DEFAULT_ROUTER_SANS)}; "
                       "other roles: none)")
    issue.add_argument("--force", action="store_true",
                       help="replace NAME's existing certificate and key (rotation); the old "
                       "certificate stays valid until revoked by --serial")
    issue.set_defaults(func=_cmd_issue)

    revoke = sub.add_parser(
        "revoke", help="revoke a certificate",
        description="Revoke a certificate: by --name, every certificate of that name not yet "
        "revoked; by --serial, that one. Re-signs crl.pem and records it in index.json.")
    revoke.add_argument("--ca", required=True, metavar="DIR", help="the site CA's directory")
    which = revoke.add_mutually_exclusive_group(required=True)
    which.add_argument("--name", metavar="NAME", help="revoke NAME's certificates")
    which.add_argument("--serial", metavar="HEX", help="revoke the certificate with this serial")
    revoke.add_argument("--reason", default="unspecified", choices=list(pki.REVOCATION_REASONS),
                        metavar="R", help="why: " + ", ".join(pki.REVOCATION_REASONS)
                        + " (default unspecified)")
    revoke.set_defaults(func=_cmd_revoke)

    crl = sub.add_parser(
        "crl", help="re-sign the revocation list",
        description="Re-sign crl.pem with the same revoked certificates, a higher CRL number "
        "and a new next update. A CRL is valid until its next update: renew it before then "
        "and copy it to wherever certificates are checked.")
    crl.add_argument("--ca", required=True, metavar="DIR", help="the site CA's directory")
    crl.add_argument("--valid-days", type=_positive_days, default=pki.DEFAULT_CRL_VALID_DAYS,
                     metavar="N", help="days until the CRL's next update "
                     f"(default {pki.DEFAULT_CRL_VALID_DAYS} days)")
    crl.set_defaults(func=_cmd_crl)

    listing = sub.add_parser(
        "list", help="list the certificates issued",
        description="List the certificates the site CA issued: name, role, status (valid, "
        "expired, revoked), expiry and serial.")
    listing.add_argument("--ca", required=True, metavar="DIR", help="the site CA's directory")
    listing.add_argument("--json", action="store_true", help="print one JSON object")
    listing.set_defaults(func=_cmd_list)


def _positive_days(text: str) -> int:
    return positive_int(text, "a whole number of days")
