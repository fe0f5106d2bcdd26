"""``stockpile keys``: producers' signing keys and the admin's declarations of them.

- ``keys new --name N --out DIR``: an Ed25519 key pair (``N.sign.key`` 0600,
  ``N.sign.pub``); prints the key id.
- ``keys declare --admin A.sign.key --key N.sign.pub --role R --name N``: the admin's
  signed ``source_key_declared`` event (``--key`` the admin's own public key and
  ``--role admin`` make the site's trust anchor);
- ``keys revoke --admin A.sign.key --key-id ID --from T``: the signed
  ``source_key_revoked`` event.

``declare`` and ``revoke`` append the event to a ledger (``--ledger``) or to a JSON lines
file (``--out``) for ``stockpile ledger import`` at the site.  The admin's events come
from source ``site-admin``, epoch 1, numbered after those already in the ledger or file.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from common.options import PROG, add_accept_loss, add_ledger, describe_ledger
from schemas.events import Event
from schemas.jsonl import event_line
from schemas.times import parse_time_ns
from security.event_keys import ROLE_TYPES, load_public_key, load_signing_key, new_signing_key

from ledger import open_ledger
from ledger.signing import ADMIN_EPOCH, ADMIN_SOURCE, key_declaration, key_revocation

DAY_NS = 86_400 * 10**9


def cmd_new(args: argparse.Namespace) -> int:
    key_id = new_signing_key(args.out, args.name)
    print(f"{args.name}: key id {key_id}; private key {Path(args.out) / (args.name + '.sign.key')} "
          "(mode 0600: keep it on the producer's machine), public key "
          f"{Path(args.out) / (args.name + '.sign.pub')}")
    return 0


def _next_seq(args: argparse.Namespace) -> int:
    if args.ledger:
        with open_ledger(args.ledger, accept_loss=args.accept_loss) as store:
            streams = [s for s in store.streams() if (s.source, s.epoch) == (ADMIN_SOURCE, ADMIN_EPOCH)]
            return streams[0].max_seq + 1 if streams else 0
    path = Path(args.out)
    return sum(1 for _ in path.open()) if path.exists() else 0


def _emit(args: argparse.Namespace, event: Event) -> int:
    if args.ledger:
        with open_ledger(args.ledger, accept_loss=args.accept_loss) as store:
            outcome = store.append([event]).outcomes[0]
        if outcome.status != "appended":
            print(f"{PROG}: error: the ledger refused it: {outcome.reason}")
            return 1
        where = f"{describe_ledger(args.ledger)} as global_seq {outcome.global_seq}"
    else:
        with open(args.out, "a", encoding="utf-8") as out:
            out.write(event_line(event) + "\n")
        where = f"{args.out} (import it with {PROG} ledger import)"
    print(f"{event.type} seq {event.seq} signed by {event.signer}: {where}")
    return 0


def cmd_declare(args: argparse.Namespace) -> int:
    public = load_public_key(args.key)
    now = time.time_ns()
    valid_from = parse_time_ns(args.valid_from) if args.valid_from else now
    valid_until = (parse_time_ns(args.valid_until) if args.valid_until
                   else valid_from + args.valid_days * DAY_NS)
    return _emit(args, key_declaration(load_signing_key(args.admin), public, args.role,
                                       args.name, _next_seq(args), now, valid_from, valid_until))


def cmd_revoke(args: argparse.Namespace) -> int:
    revoked_from = parse_time_ns(args.revoked_from) if args.revoked_from else time.time_ns()
    return _emit(args, key_revocation(load_signing_key(args.admin), args.key_id,
                                      _next_seq(args), revoked_from, args.reason))


def _target(p: argparse.ArgumentParser) -> None:
    p.add_argument("--admin", required=True, metavar="ADMIN.sign.key",
                   help="the site admin's private signing key")
    where = p.add_mutually_exclusive_group(required=True)
    add_ledger(where, required=False, help="the event is appended to it")
    where.add_argument("--out", metavar="PATH",
                       help="append the event to this JSON lines file instead")
    add_accept_loss(p)


def register(subparsers) -> None:
    top = subparsers.add_parser("keys", help="producers' signing keys and their declarations",
                                description="Make a producer's Ed25519 signing key, and "
                                "write the site admin's signed declaration or revocation of a "
                                "key to a ledger or a JSON lines file (docs/security.md).")
    sub = top.add_subparsers(dest="keys_command", required=True, metavar="COMMAND")
    p = sub.add_parser("new", help="make a signing key pair (private key 0600)",
                       description="Make an Ed25519 signing key pair: NAME.sign.key (mode "
                       "0600) and NAME.sign.pub in DIR; print its key id.")
    p.add_argument("--name", required=True, help="file name stem, e.g. the service's name")
    p.add_argument("--out", required=True, metavar="DIR", help="where the key files go")
    p.set_defaults(func=cmd_new)

    p = sub.add_parser("declare", help="the admin's signed declaration of a public key",
                       description="Write the site admin's signed source_key_declared event "
                       "for a public key, its role and validity, to a ledger or a JSON lines "
                       "file. The admin's own key with --role admin is the site's trust anchor.")
    _target(p)
    p.add_argument("--key", required=True, metavar="NAME.sign.pub", help="the public key declared")
    p.add_argument("--role", required=True, choices=sorted(ROLE_TYPES),
                   help="what the key may sign (docs/security.md)")
    p.add_argument("--name", required=True, help="who holds the key (service or person)")
    p.add_argument("--valid-from", metavar="T", help="start of validity (default now)")
    p.add_argument("--valid-until", metavar="T", help="end of validity (default: --valid-days)")
    p.add_argument("--valid-days", type=int, default=366, help="validity in days (default 366)")
    p.set_defaults(func=cmd_declare)

    p = sub.add_parser("revoke", help="the admin's signed revocation of a key",
                       description="Write the site admin's signed source_key_revoked event: "
                       "events the key signed with a valid time from --from on are refused.")
    _target(p)
    p.add_argument("--key-id", required=True, help="the key id to revoke")
    p.add_argument("--from", dest="revoked_from", metavar="T",
                   help="events with a valid time from T on are refused (default now)")
    p.add_argument("--reason", default="", help="why, for the record")
    p.set_defaults(func=cmd_revoke)
