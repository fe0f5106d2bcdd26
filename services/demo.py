"""``stockpile demo``: the main job on the embedded default.

Until the yard simulator and the services exist, the demo generates the sample
session (:mod:`ledger.sample`), imports it into a fresh DuckDB ledger with the
site clock following the session's ``clock`` events, and shows what the ledger
knows: counts, quarantine, gaps, the chain, idempotent re-import, an exact
export/import round trip, and a late assay seen "as known then" and "as known now".
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

from schemas.events import decode_payload

from ledger import EventClock, open_ledger
from ledger.cli import export_lines, format_stats, import_lines
from ledger.sample import generate_sample
from ledger.times import format_time_ns


def _fresh(path: Path) -> Path:
    for suffix in ("", ".wal"):
        candidate = Path(str(path) + suffix)
        if candidate.exists():
            candidate.unlink()
    return path


def run_demo(out_dir: Path, seed: int = 7) -> int:
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    print(f"== generating the sample yard session (seed {seed})")
    session = generate_sample(seed)
    sample = out_dir / "sample.jsonl"
    sample.write_text("\n".join(session.lines) + "\n")
    print(f"   {len(session.lines):,} lines, {format_time_ns(session.start_ns)} .. "
          f"{format_time_ns(session.end_ns)} -> {sample}")
    print("   planted: " + ", ".join(f"{k} {v}" for k, v in session.planted.items()))

    ledger_path = _fresh(out_dir / "ledger.duckdb")
    print(f"\n== importing into {ledger_path} (recorded time = the session's clock events)")
    with open_ledger(ledger_path, EventClock()) as store:
        with sample.open("rb") as handle:
            counts = import_lines(store, handle, name=str(sample))
        print("   " + ", ".join(f"{counts[s]:,} {s}"
                                 for s in ("appended", "duplicate", "conflict", "rejected")))
        for entry in store.quarantine():
            print(f"   quarantined: {entry.type or '?'} from {entry.source or '?'} "
                  f"seq {entry.seq}: {entry.reason[:100]}")
        for gap in store.gaps(open_only=True):
            print(f"   gap: {gap.source} epoch {gap.epoch} seq {gap.first_seq}..{gap.last_seq} missing")

        print("\n== importing the same file again (idempotent)")
        with sample.open("rb") as handle:
            again = import_lines(store, handle, name=str(sample))
        print(f"   {again['appended']} appended, {again['duplicate']:,} duplicate "
              f"(conflicts and bad lines are quarantined again: {again['conflict']} + {again['rejected']})")

        print("\n== a late assay, as known then and as known now")
        assays = list(store.read(types=["assay"]))
        late = max(assays, key=lambda r: r.recorded_time_ns - r.valid_time_ns)
        body = decode_payload("assay", late.payload)
        hours = (late.recorded_time_ns - late.valid_time_ns) / 3.6e12
        print(f"   {body.assay_id} (lot {body.lot_id}, Fe {body.analytes['Fe']:.2f} %): sampled "
              f"{format_time_ns(late.valid_time_ns)}, recorded {format_time_ns(late.recorded_time_ns)} "
              f"({hours:.1f} h late)")
        v = late.valid_time_ns
        then = sum(1 for _ in store.as_of(v, v, types=["assay"]))
        now = sum(1 for _ in store.as_of(v, store.head().recorded_time_ns, types=["assay"]))
        print(f"   assays with valid time <= its window end: known then {then}, known now {now}")
        flagged = [r for r in assays if r.flags]
        for r in flagged:
            print(f"   flagged {','.join(r.flags)}: {decode_payload('assay', r.payload).assay_id}")

        print("\n== export -> import into an empty ledger -> export")
        first = io.StringIO()
        export_lines(store, first)
        copy_path = _fresh(out_dir / "copy.duckdb")
        with open_ledger(copy_path) as copy:
            import_lines(copy, first.getvalue().splitlines(), name="export")
            second = io.StringIO()
            export_lines(copy, second)
        same = first.getvalue() == second.getvalue()
        print(f"   {first.getvalue().count(chr(10)):,} lines, identical: {same}")

        report = store.verify()
        print(f"\n== verify: {'ok' if report.ok else 'FAILED'} ({report.rows_checked:,} rows)")
        print()
        print(format_stats(store.stats(), str(ledger_path)))
    print(f"\ndone in {time.monotonic() - started:.1f} s. Try:\n"
          f"  .venv/bin/stockpile ledger stats --ledger {ledger_path}\n"
          f"  .venv/bin/stockpile ledger export --ledger {ledger_path} --types assay")
    return 0 if report.ok and same else 1


def cmd_demo(args: argparse.Namespace) -> int:
    return run_demo(Path(args.out), args.seed)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="run the demo on the embedded sample yard session",
                              description=__doc__.split("\n\n")[1] if __doc__ else None)
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--seed", type=int, default=7, help="sample generator seed (default 7)")
    p.set_defaults(func=cmd_demo)
