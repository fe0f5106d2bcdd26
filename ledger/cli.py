"""``stockpile ledger ...``: import, export, verify, stats, backup and restore.

``--ledger`` is a ledger file or a ``postgresql://`` URL (a PostgreSQL ledger); import and
export move a ledger between the two with identical export lines and the same chain.
Backup and restore are the DuckDB file's: a PostgreSQL ledger is backed up with the
server's own tools (``pg_basebackup``, ``pg_dump``; docs/deployment.md).

Exit codes: 0 ok, 1 verification failed, 2 bad usage or an error (one line on stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import IO

from common.progress import Progress, enabled_from_args, progress as progress_bar

from common.options import (DEFAULT_BATCH_SIZE, add_accept_loss, add_analytes, add_batch_size,
                            add_bitemporal, add_clock, add_ledger, add_out, add_progress,
                            add_types, describe_ledger, is_ledger_url)
from schemas.analytes import policy_from_args as analyte_options
from schemas.events import EVENT_TYPES
from schemas.jsonl import event_line

from ledger import backup, head_file, open_ledger
from ledger.errors import LedgerLocked, NotSupportedError
from ledger.clock import clock_by_name
from ledger.importing import (TO_REJECT_FILE, RejectFile, default_rejects_path,
                              import_lines)
from ledger.records import STATUSES, LedgerStats
from ledger.signing import add_signing_options, policy_from_args
from ledger.store import LedgerStore
from ledger.checkpoint import (Checkpoint, check_checkpoint, is_mcap, latest_checkpoint,
                               read_checkpoint, read_mcap_checkpoints)
from ledger.views import check_declared
from ledger.wire import stats_to_json
from schemas.times import format_time_ns, parse_time_ns

DEFAULT_BATCH = DEFAULT_BATCH_SIZE
EXIT_OK, EXIT_VERIFY_FAILED, EXIT_USAGE = 0, 1, 2


def export_lines(store: LedgerStore, out: IO[str], *, types: list[str] | None = None,
                 as_of_valid_ns: int | None = None, as_of_known_ns: int | None = None,
                 progress: Progress | None = None) -> int:
    """Write canonical JSON lines (with recorded time) to ``out``; return the count.

    Without as-of bounds, events come in global order (an exact copy: importing the
    output into an empty ledger and exporting again gives identical lines).  With
    bounds, events come in (valid time, global seq) order, as the projector reads
    them; such an export is for reading, not for re-importing.
    """
    if as_of_valid_ns is None and as_of_known_ns is None:
        rows = store.read(types=types)
    else:
        far = 2**63 - 1
        rows = store.as_of(far if as_of_valid_ns is None else as_of_valid_ns,
                           far if as_of_known_ns is None else as_of_known_ns, types=types)
    n = 0
    for row in rows:
        out.write(event_line(row))
        out.write("\n")
        n += 1
        if progress is not None and n % 1_000 == 0:
            progress.update_to(n)
    return n


def format_stats(stats: LedgerStats, path: str) -> str:
    """Human-readable ``ledger stats``."""
    lines = [f"ledger {path}",
             f"  events      {stats.events:,} (head global_seq {stats.head.global_seq}, "
             f"chain {stats.head.chain_sha256.hex()[:16]}...)"]
    if stats.valid_time_range_ns:
        lo, hi = stats.valid_time_range_ns
        lines.append(f"  valid time  {format_time_ns(lo)} .. {format_time_ns(hi)}")
    if stats.recorded_time_range_ns:
        lo, hi = stats.recorded_time_range_ns
        lines.append(f"  recorded    {format_time_ns(lo)} .. {format_time_ns(hi)}")
    lines.append("  per type")
    lines += [f"    {name:<18} {n:>10,}" for name, n in stats.per_type.items()]
    lines.append("  per source")
    lines += [f"    {name:<18} {n:>10,}" for name, n in stats.per_source.items()]
    lines.append(f"  gaps        {stats.open_gaps} open ({stats.missing_events:,} events missing), "
                 f"{stats.closed_gaps} closed")
    codes = ", ".join(f"{c} {n}" for c, n in stats.quarantine_by_code.items()) or "-"
    lines.append(f"  quarantine  {stats.quarantined} ({codes})")
    flags = ", ".join(f"{f} {n}" for f, n in stats.flagged.items()) or "-"
    lines.append(f"  flagged     {flags}")
    return "\n".join(lines)


# -- commands -------------------------------------------------------------------------------


def cmd_import(args: argparse.Namespace) -> int:
    clock = clock_by_name(args.clock)
    source = getattr(sys.stdin, "buffer", sys.stdin) if args.file == "-" else None
    if source is None and not Path(args.file).is_file():
        raise FileNotFoundError(f"no such file: {args.file}")
    analytes = analyte_options(args)
    if analytes is not None and analytes.declared:
        check_declared(analytes.declared)   # before the file is created
    rejects = RejectFile(args.rejects or default_rejects_path(args.ledger))
    with open_ledger(args.ledger, clock, signing=policy_from_args(args),
                     accept_loss=args.accept_loss, analytes=analytes) as store, rejects:
        handle = source or open(args.file, "rb")
        size_bytes = 0 if source is not None else Path(args.file).stat().st_size
        try:
            with progress_bar(unit="lines", desc=f"importing {Path(args.file).name}",
                              enabled=enabled_from_args(args)) as bar:
                counts = import_lines(store, handle, name=args.file, batch_size=args.batch_size,
                                      progress=bar, fraction=(lambda: handle.tell() / size_bytes)
                                      if size_bytes else None, rejects=rejects)
        finally:
            if source is None:
                handle.close()
        head = store.head().global_seq
    rejects_file = str(rejects.path) if counts[TO_REJECT_FILE] else None
    if args.json:
        print(json.dumps({**counts, "head_global_seq": head, "rejects_file": rejects_file}))
    else:
        print(f"imported {args.file}: {counts['lines']:,} lines -> "
              + ", ".join(f"{counts[s]:,} {s}" for s in STATUSES)
              + (f", {counts[TO_REJECT_FILE]:,} to the reject file {rejects_file}"
                 if rejects_file else "")
              + f" (ledger {describe_ledger(args.ledger)}, head global_seq {head})")
    if rejects_file:
        n = counts[TO_REJECT_FILE]
        print(f"stockpile: error: {n:,} line{'s' if n != 1 else ''} could not be stored even in "
              f"the quarantine; see {rejects_file}", file=sys.stderr)
        return EXIT_USAGE
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    for name in args.types or ():
        if name not in EVENT_TYPES:
            raise ValueError(f"unknown event type {name!r}; known: {', '.join(EVENT_TYPES)}")
    valid = parse_time_ns(args.valid_time) if args.valid_time is not None else None
    known = parse_time_ns(args.known_time) if args.known_time is not None else None
    with open_ledger(args.ledger, read_only=True) as store:
        out = sys.stdout if args.out in (None, "-") else open(args.out, "w")
        everything = args.types is None and valid is None and known is None
        try:
            with progress_bar(store.head().global_seq + 1 if everything else None,
                              desc="exporting", enabled=enabled_from_args(args)) as bar:
                n = export_lines(store, out, types=args.types, as_of_valid_ns=valid,
                                 as_of_known_ns=known, progress=bar)
        finally:
            if out is not sys.stdout:
                out.close()
    if out is not sys.stdout:
        print(f"exported {n:,} events to {args.out}", file=sys.stderr)
    return EXIT_OK


def cmd_verify(args: argparse.Namespace) -> int:
    checkpoints = _checkpoint_arg(args.checkpoint) if args.checkpoint else []
    ca_pem = Path(args.ca).read_bytes() if args.ca else None
    signing = policy_from_args(args)
    with open_ledger(args.ledger, read_only=True, signing=signing) as store:
        report = store.verify()
        head = store.head()
        found = [(label, check_checkpoint(store, cp, ca_pem=ca_pem)) for label, cp in checkpoints]
        # a PostgreSQL ledger has no head sidecar: its server keeps the committed head
        sidecar_ok, sidecar = ((True, "") if is_ledger_url(args.ledger)
                               else head_file.compare(store, args.ledger))
    ok = report.ok and sidecar_ok
    if report.ok:
        print(f"ok: {report.rows_checked:,} rows verified, head global_seq {head.global_seq}, "
              f"chain {head.chain_sha256.hex()}")
        anchor = ("the admin key given" if signing and signing.admin_key_id
                  else "the ledger's own admin declaration (pin it with --admin-key)")
        if report.signatures:
            print(f"ok: {report.signatures:,} signatures hold, keys anchored by {anchor}")
    else:
        where = ("" if report.first_bad_seq is None
                 else f"first bad row global_seq {report.first_bad_seq}: ")
        print(f"FAILED: {where}{report.problem} ({report.rows_checked:,} rows before it are "
              "intact)")
    if not sidecar_ok:
        print(f"FAILED: head sidecar: {sidecar}")
    for label, result in found:
        signer = f" (signed by {result.signer})" if result.signer else " (unsigned)"
        if result.ok:
            print(f"ok: checkpoint{label}{signer}: {result.detail}")
        else:
            print(f"FAILED: checkpoint {result.finding.upper()}{label}{signer}: {result.detail}")
            ok = False
    return EXIT_OK if ok else EXIT_VERIFY_FAILED


def _checkpoint_arg(path: str) -> list[tuple[str, Checkpoint]]:
    """(label, checkpoint) to check: a checkpoint file, the latest one of a directory, or
    every checkpoint a recorded MCAP file holds (labelled ``i/n of FILE``)."""
    target = Path(path)
    if is_mcap(target):
        checkpoints, problem = read_mcap_checkpoints(target)
        if problem is not None:
            print(f"stockpile: warning: {target} is damaged ({problem}); the "
                  f"{len(checkpoints)} checkpoints before the damage are checked",
                  file=sys.stderr)
        if not checkpoints:
            raise ValueError(f"no checkpoints in {target}" + (f" ({problem})" if problem else
                             " (was a ledger service publishing them while it recorded?)"))
        return [(f" {i}/{len(checkpoints)} of {target}", cp)
                for i, (_log_time, cp) in enumerate(checkpoints, 1)]
    if target.is_dir():
        latest = latest_checkpoint(target)
        if latest is None:
            raise ValueError(f"no checkpoint files in {target}")
        target = latest
    elif not target.exists():
        raise FileNotFoundError(f"no such checkpoint: {target}")
    return [("", read_checkpoint(target))]


def cmd_stats(args: argparse.Namespace) -> int:
    with open_ledger(args.ledger, read_only=True) as store:
        stats = store.stats()
    if args.json:
        print(json.dumps(stats_to_json(stats), indent=2))
    else:
        print(format_stats(stats, describe_ledger(args.ledger)))
    return EXIT_OK


def refuse_postgres_backup(ledger: str, what: str) -> None:
    """Raise NotSupportedError (one line naming the server's tools) when ``ledger`` is a
    PostgreSQL URL: ``stockpile ledger backup|restore`` copy a DuckDB file."""
    if is_ledger_url(ledger):
        raise NotSupportedError(
            f"stockpile ledger {what} copies a DuckDB file; {describe_ledger(ledger)} is a "
            "PostgreSQL ledger: back it up with pg_basebackup (the whole server, for a "
            "standby or point-in-time recovery) or pg_dump --schema (one ledger), and "
            "restore with the server's tools (docs/deployment.md)")


def cmd_backup(args: argparse.Namespace) -> int:
    refuse_postgres_backup(args.ledger, "backup")
    if not Path(args.ledger).is_file():
        raise FileNotFoundError(f"no ledger at {args.ledger}")
    target = Path(args.to).resolve()
    from ledger.duckdb_store import DuckDBStore   # deferred: duckdb is heavy

    try:
        store = open_ledger(args.ledger, accept_loss=args.accept_loss)
    except LedgerLocked:
        store = open_ledger(args.ledger, read_only=True)   # through the service holding it
    with store:
        if isinstance(store, DuckDBStore):
            with progress_bar(unit="bytes", desc="backing up",
                              enabled=enabled_from_args(args)) as bar:
                manifest = backup.backup(store, target, progress=bar)
        else:
            request = getattr(store, "request_backup", None)
            if request is None:
                raise NotSupportedError(f"the service holding {args.ledger} takes no backups")
            print(f"stockpile: asking the ledger service to back up {args.ledger} between "
                  "two batches", file=sys.stderr)
            request(str(target))
            manifest = backup.read_manifest(target)
    print(f"backed up {args.ledger} to {target}: {manifest.describe()}, "
          f"{manifest.rows_verified:,} rows verified")
    return EXIT_OK


def cmd_restore(args: argparse.Namespace) -> int:
    refuse_postgres_backup(args.ledger, "restore")
    with progress_bar(unit="bytes", desc="checking the backup",
                      enabled=enabled_from_args(args)) as bar:
        manifest = backup.restore(args.backup, args.ledger, force=args.force, progress=bar)
    print(f"restored {args.ledger} from {args.backup}: {manifest.describe()}, "
          f"{manifest.rows_verified:,} rows verified (taken from {manifest.source})")
    return EXIT_OK


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``ledger`` and its subcommands to the ``stockpile`` parser."""
    ledger = subparsers.add_parser(
        "ledger", help="import, export, verify and summarise an event ledger",
        description="Work with an append-only event ledger (a DuckDB file, or a "
        "PostgreSQL ledger given as a postgresql:// URL).")
    sub = ledger.add_subparsers(dest="ledger_command", metavar="COMMAND", required=True)

    p = sub.add_parser("import", help="append canonical JSON lines (creates the ledger if missing)",
                       description="Append canonical JSON lines to a ledger. Bad lines are "
                       "quarantined with their reason and raw bytes; the rest is kept. A line "
                       "the ledger cannot hold even in its quarantine goes to the reject file "
                       "(exit 2).")
    p.add_argument("file", help="JSON lines file, or - for standard input")
    add_ledger(p, help="created if missing")
    add_batch_size(p)
    add_clock(p, help="recorded time from the wall clock or from the file's clock events "
              "(lines with recorded_time_ns keep theirs)")
    p.add_argument("--json", action="store_true", help="print the counts as JSON")
    p.add_argument("--rejects", metavar="PATH",
                   help="where lines the ledger cannot hold even in its quarantine are written "
                   "(default: LEDGER.rejects.jsonl; created only when needed)")
    add_signing_options(p)
    add_accept_loss(p)
    add_analytes(p)
    p.set_defaults(func=cmd_import)

    p = sub.add_parser("export", help="print events as canonical JSON lines",
                       description="Print events as canonical JSON lines on standard output.")
    add_ledger(p)
    add_types(p)
    add_bitemporal(p, deprecated=True)
    add_out(p, help="write to PATH instead of standard output", deprecated=("-o", "--output"))
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("verify", help="recompute the hash chain and name the first bad row",
                       description="Recompute payload hashes and the hash chain, and with "
                       "--checkpoint prove the ledger still holds a checkpointed prefix (not "
                       "truncated, not rewritten); compare the file with its head sidecar "
                       "(a lost tail). Exit 1 if a check fails.")
    add_ledger(p)
    p.add_argument("--checkpoint", metavar="FILE|DIR|MCAP",
                   help="a checkpoint file the ledger service wrote, a directory of them "
                   "(the latest is used), or a session the recorder wrote (each is checked)")
    p.add_argument("--ca", metavar="CA.pem",
                   help="the site CA's certificate: the checkpoint must be signed by one of "
                   "its certificates")
    p.add_argument("--admin-key", metavar="FILE",
                   help="the site admin's public signing key: the key declarations in the "
                   "ledger must chain to it (default: the ledger's own admin declaration)")
    p.set_defaults(func=cmd_verify)

    p = sub.add_parser("stats", help="counts per type and source, gaps, quarantine, time ranges",
                       description="Summarise a ledger: events per type and per source, "
                       "sequence gaps, quarantined lines and the valid and recorded time ranges.")
    add_ledger(p)
    p.add_argument("--json", action="store_true", help="print as JSON")
    p.set_defaults(func=cmd_stats)

    p = sub.add_parser("backup", help="a consistent, verified copy (through the service "
                       "holding the ledger, if one does)",
                       description="Copy the ledger as of one committed head into DIR (the "
                       "database, its head sidecar and a manifest), verify the copy's chain "
                       "and head, and print the head and the file's sha256. While a ledger "
                       "service holds the ledger, the service takes the copy between batches.")
    p.add_argument("--ledger", required=True, help="ledger file (a PostgreSQL ledger: "
                   "pg_basebackup or pg_dump)")
    p.add_argument("--to", required=True, metavar="DIR", help="backup directory (new or empty)")
    add_accept_loss(p)
    add_progress(p)
    p.set_defaults(func=cmd_backup)

    p = sub.add_parser("restore", help="check a backup and make it the ledger",
                       description="Check a backup (manifest, sha256, the chain from genesis, "
                       "the head) and install it as the ledger file with a matching head "
                       "sidecar. Refuses to replace an existing ledger without --force, and "
                       "while a process holds it.")
    p.add_argument("backup", metavar="DIR", help="a directory stockpile ledger backup wrote")
    p.add_argument("--ledger", required=True, help="ledger file to create (or replace; a "
                   "PostgreSQL ledger: the server's tools)")
    p.add_argument("--force", action="store_true", help="replace an existing ledger")
    add_progress(p)
    p.set_defaults(func=cmd_restore)
