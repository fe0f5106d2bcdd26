"""``stockpile demo``: the main job on the embedded default.

The demo runs the whole yard as separate processes wired through emulated serial
ports and Zenoh (:mod:`stockpile.orchestrate`): a loopback Zenoh router, the ledger
service, the localizer, the simulator (``demo`` scenario) writing LMS200 telegrams
and NMEA GGA to pseudo-terminals and publishing its machine, PLC, lab and clock
events, and the scanner and GNSS services reading those ports.  When the scenario
ends it stops everything in order (producers first, the ledger last) and prints a
summary: events per type, exactly-once per source (published vs ledgered), gaps,
quarantine, the pile by belt scales and assays as known at the end, the localizer's
wheel-centre RMSE against the simulator's truth, and the scans' timing error.

``--in-process`` runs the simulator alone and imports its events file into the
ledger (no services: fast, for a first look).  ``--sample`` runs the ledger on the
generated sample session (:mod:`stockpile.sample`) instead, which plants bad input
(malformed lines, an infinite range, a conflicting retransmission, a dropped
sequence number) to show the quarantine and gaps.
"""

from __future__ import annotations

import argparse
import io
import json
import textwrap
import time
from pathlib import Path

from common.options import add_duration, add_out, plain_text, positive_float, refuse_inapplicable
from schemas.events import decode_payload
from schemas.times import NS_PER_H, format_time_ns

from ledger import EventClock, open_ledger
from ledger.cli import export_lines, format_stats, import_lines
from sim.runner import Simulation
from sim.scenario import demo
from stockpile.orchestrate import fresh_ledger_path
from stockpile.sample import generate_sample
from stockpile.yard_demo import run_yard_demo


def quarantine_line(entry, width: int = 100) -> str:
    """One readable line for a quarantine entry: what it was (as far as it could be read) and
    why, the reason shortened at a word boundary to about ``width`` characters."""
    what = f"a {entry.type} event" if entry.type else "an unreadable line"
    if entry.source:
        what += f" from {entry.source}"
    if entry.seq is not None:
        what += f" (seq {entry.seq})"
    return f"{what}: {textwrap.shorten(entry.reason, width, placeholder=' ...')}"


def show_late_assay(store) -> None:
    """Print the latest-arriving assay and what was known of assays then and now."""
    print("\n== a late assay, as known then and as known now")
    assays = list(store.read(types=["assay"]))
    late = max(assays, key=lambda r: r.recorded_time_ns - r.valid_time_ns)
    body = decode_payload("assay", late.payload)
    hours = (late.recorded_time_ns - late.valid_time_ns) / NS_PER_H
    print(f"   {body.assay_id} (lot {body.lot_id}, Fe {body.analytes['Fe']:.2f} %): window ends "
          f"{format_time_ns(late.valid_time_ns)}, recorded {format_time_ns(late.recorded_time_ns)} "
          f"({hours:.1f} h late)")
    v = late.valid_time_ns
    then = sum(1 for _ in store.as_of(v, v, types=["assay"]))
    now = sum(1 for _ in store.as_of(v, store.head().recorded_time_ns, types=["assay"]))
    print(f"   assays for belt flow up to that moment: known then {then}, known now {now}")
    for r in assays:
        if r.flags:
            print(f"   flagged {','.join(r.flags)}: {decode_payload('assay', r.payload).assay_id}")


def show_round_trip(store, out_dir: Path) -> bool:
    """Export, import into an empty ledger, export again; print and return whether identical."""
    print("\n== export -> import into an empty ledger -> export")
    first = io.StringIO()
    export_lines(store, first)
    with open_ledger(fresh_ledger_path(out_dir / "copy.duckdb")) as copy:
        import_lines(copy, first.getvalue().splitlines(), name="export")
        second = io.StringIO()
        export_lines(copy, second)
    same = first.getvalue() == second.getvalue()
    print(f"   {first.getvalue().count(chr(10)):,} lines, identical: {same}")
    return same


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

    ledger_path = fresh_ledger_path(out_dir / "ledger.duckdb")
    print(f"\n== importing into {ledger_path} (recorded time = the session's clock events)")
    with open_ledger(ledger_path, EventClock()) as store:
        with sample.open("rb") as handle:
            counts = import_lines(store, handle, name=str(sample))
        print("   " + ", ".join(f"{counts[s]:,} {s}"
                                 for s in ("appended", "duplicate", "conflict", "rejected")))
        for entry in store.quarantine():
            print(f"   quarantined: {quarantine_line(entry)}")
        for gap in store.gaps(open_only=True):
            print(f"   gap: {gap.source} epoch {gap.epoch} seq {gap.first_seq}..{gap.last_seq} missing")

        print("\n== importing the same file again (idempotent)")
        with sample.open("rb") as handle:
            again = import_lines(store, handle, name=str(sample))
        print(f"   {again['appended']} appended, {again['duplicate']:,} duplicate "
              f"(conflicts and bad lines are quarantined again: {again['conflict']} + {again['rejected']})")

        show_late_assay(store)
        same = show_round_trip(store, out_dir)

        report = store.verify()
        print(f"\n== verify: {'ok' if report.ok else 'FAILED'} ({report.rows_checked:,} rows)")
        print()
        print(format_stats(store.stats(), str(ledger_path)))
    print(f"\ndone in {time.monotonic() - started:.1f} s. Try:\n"
          f"  stockpile ledger stats --ledger {ledger_path}\n"
          f"  stockpile ledger export --ledger {ledger_path} --types assay")
    return 0 if report.ok and same else 1


def run_sim_demo(out_dir: Path, seed: int = 1) -> int:
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    print(f"== simulating the demo yard (seed {seed}): 3 lots, 9 chevron passes, one reclaim "
          "bench, assays 2-6 h late", flush=True)
    sim_dir = out_dir / "sim"
    stats = Simulation(demo(), seed, sim_dir,
                       progress=lambda line: print(f"   {line}", flush=True)).run()
    print(f"   {stats.site_s / 3600:.1f} site h in {stats.wall_s:.0f} s: {stats.events:,} events, "
          f"{stats.scans:,} LMS200 telegrams ({stats.lms200_bytes / 1e6:.1f} MB), "
          f"{stats.gga:,} GGA sentences -> {sim_dir}")
    events = sim_dir / "events.jsonl"
    ledger_path = fresh_ledger_path(out_dir / "ledger.duckdb")
    print(f"\n== ledgering the published events into {ledger_path} (recorded time = site clock)")
    with open_ledger(ledger_path, EventClock()) as store:
        with events.open("rb") as handle:
            counts = import_lines(store, handle, name=str(events))
        print("   " + ", ".join(f"{counts[s]:,} {s}" for s in ("appended", "duplicate", "conflict", "rejected")))
        with events.open("rb") as handle:
            again = import_lines(store, handle, name=str(events))
        print(f"   importing again: {again['appended']} appended, {again['duplicate']:,} duplicate")

        show_late_assay(store)
        same = show_round_trip(store, out_dir)
        report = store.verify()
        print(f"\n== verify: {'ok' if report.ok else 'FAILED'} ({report.rows_checked:,} rows)")

    truth = json.loads((sim_dir / "truth.json").read_text())
    print("\n== ledger (belt scales) against the simulator's truth")
    belt = sum(p["belt_tonnes"] for p in truth["passes"])
    true = sum(p["true_tonnes"] for p in truth["passes"])
    print(f"   stacked: belt {belt:,.0f} t, true {true:,.0f} t ({(belt / true - 1) * 100:+.2f} %)")
    for c in truth["cuts"]:
        print(f"   cut {c['cut_id']}: belt {c['belt_tonnes']:7.1f} t, true {c['true_tonnes']:7.1f} t, "
              f"true Fe {c['grade']['Fe']:.2f} %, SiO2 {c['grade']['SiO2']:.2f} %")
    world = truth["world"]
    print(f"   pile at the end: {world['tonnes']:,.0f} t, {world['volume_m3']:,.0f} m3, "
          f"{world['max_height_m']:.1f} m high, Fe {world['grade']['Fe']:.2f} %; "
          f"mass balance residual {world['mass_balance']['residual_tonnes']:.1e} t")
    print(f"\ndone in {time.monotonic() - started:.0f} s. Try:\n"
          f"  stockpile ledger stats --ledger {ledger_path}\n"
          f"  stockpile ledger export --ledger {ledger_path} --types reclaim_cut assay")
    return 0 if report.ok and same else 1


#: the process demo's pacing when --speed / --idle-speed are not given (site s per wall s)
DEFAULT_SPEED = 40.0
DEFAULT_IDLE_SPEED = 2000.0

#: options that only the process demo reads (dest -> spelling)
_PROCESS_ONLY = {"speed": "--speed", "idle_speed": "--idle-speed", "record": "--record",
                 "insecure": "--insecure", "adapters": "--adapters"}


def cmd_demo(args: argparse.Namespace) -> int:
    if args.sample and args.in_process:
        raise ValueError("--sample and --in-process are two different demos: choose one")
    if args.sample:
        refuse_inapplicable(args, "demo --sample",
                            {**_PROCESS_ONLY, "duration": "--duration"})
        return run_demo(Path(args.out), args.seed)
    if args.in_process:
        refuse_inapplicable(args, "demo --in-process",
                            {**_PROCESS_ONLY, "duration": "--duration"})
        return run_sim_demo(Path(args.out), args.seed)

    return run_yard_demo(Path(args.out), seed=args.seed,
                         speed=DEFAULT_SPEED if args.speed is None else args.speed,
                         idle_speed=DEFAULT_IDLE_SPEED if args.idle_speed is None else args.idle_speed,
                         duration_h=None if args.duration is None else args.duration / 3600.0,
                         record=Path(args.record) if args.record else None,
                         insecure=bool(args.insecure), adapters=args.adapters or "sim")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="simulate the demo yard and ledger it (the main job)",
                              description=plain_text(" ".join(__doc__.split("\n\n")[1:3]))
                              if __doc__ else None)
    add_out(p, metavar="DIR", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument("--speed", type=positive_float, metavar="X",
                   help="process demo only: site seconds per wall second while machines work "
                   f"(default {DEFAULT_SPEED:g})")
    p.add_argument("--idle-speed", type=positive_float, metavar="X",
                   help="process demo only: site seconds per wall second while the yard waits "
                   f"for assays (default {DEFAULT_IDLE_SPEED:g})")
    add_duration(p, "--duration",
                 help="process demo only: stop the scenario after this much site time, with a "
                 "unit: 90min, 2h ... (default: to the end)")
    p.add_argument("--record", metavar="OUT.mcap",
                   help="process demo only: also record the live session to MCAP (stockpile "
                   "service recorder)")
    p.add_argument("--insecure", action="store_true", default=None,
                   help="process demo only: plain TCP on loopback instead of mutual TLS with "
                   "access control by role (a throw-away PKI in OUT/pki)")
    p.add_argument("--adapters", choices=("sim", "real"), default=None,
                   help="process demo only: sim (default) takes the machines', lab's and "
                   "scanner's events from the simulator; real runs them through the PLC "
                   "adapter over OPC UA, the lab adapter on LIMS files and the scanner on an "
                   "emulated LMS511 over TCP")
    p.add_argument("--in-process", action="store_true",
                   help="simulate and import the events file, without the services")
    p.add_argument("--sample", action="store_true",
                   help="run the ledger on the generated sample with planted bad input instead")
    p.set_defaults(func=cmd_demo)
