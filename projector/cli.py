"""``stockpile project``: the pile as of a valid time, as known at a known time."""

from __future__ import annotations

import argparse
import json
import math
import sys

from common.figures import format_grades, plus_minus
from common.options import add_bitemporal, add_ledger, describe_ledger
from schemas.times import format_time_ns, parse_time_ns

from ledger import open_ledger
from ledger.mirror import ledger_for
from projector.query import SnapshotStore, project


def _json_default(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return str(value)


def _clean(value):
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def project_from_args(store, args: argparse.Namespace):
    """``project()`` of ``--pile`` as of ``--valid-time`` as known at ``--known-time``,
    from ``--snapshots`` when given; ValueError when the pile is not declared by then."""
    valid = parse_time_ns(args.valid_time) if args.valid_time else None
    known = parse_time_ns(args.known_time) if args.known_time else None
    snapshots = SnapshotStore(args.snapshots) if args.snapshots else None
    try:
        state = project(store, args.pile, valid, known, snapshots=snapshots)
    finally:
        if snapshots is not None:
            snapshots.close()
    if state.geometry is None:
        raise ValueError(f"pile {args.pile!r} is not declared in {describe_ledger(args.ledger)} "
                         "as of that time")
    return state


def cmd_project(args: argparse.Namespace) -> int:
    with open_ledger(ledger_for(args.ledger, args.site), read_only=True) as store:
        head = store.head().global_seq   # the head this answer is computed at
        state = project_from_args(store, args)
    if args.json:
        out = {**state.to_json(), "head_global_seq": head}
        json.dump(_clean(out), sys.stdout, indent=1, default=_json_default)
        print()
        return 0
    when_v = format_time_ns(parse_time_ns(args.valid_time)) if args.valid_time else "everything"
    when_k = format_time_ns(parse_time_ns(args.known_time)) if args.known_time else "now"
    print(f"pile {state.pile_id} as of {when_v}, as known {when_k}")
    print(f"  volume {state.volume_m3:,.1f} m3, {state.tonnes:,.1f}{plus_minus(state.tonnes_sd)} t; "
          f"grade {format_grades(state.grade, state.grade_sd)} (assayed fraction "
          f"{state.assayed_fraction:.2f}; +/-: one standard deviation)")
    print(f"\n  deposits ({len(state.deposits)})")
    for d in state.deposits:
        label = d.pass_id or "(outside any pass)"
        print(f"    {d.index:>3} {label:<12} lot {d.lot_id or '-':<8} {d.volume_m3:>10,.1f} m3 "
              f"{d.tonnes:>11,.1f} t  Fe {d.grade.get('Fe', math.nan):6.2f} %  "
              f"assayed {d.assayed_fraction:.2f}")
    print(f"\n  cuts ({len(state.cuts)})")
    for c in state.cuts:
        print(f"    {c.cut_id:<10} {c.tonnes:>10,.1f}{plus_minus(c.tonnes_sd)} t (belt "
              f"{c.tonnes_scale:,.1f} t)  {format_grades(c.grade, c.grade_sd)}  assayed "
              f"{c.assayed_fraction:.2f}  "
              f"residual {c.residual_m3:+.1f} m3")
    unexplained_m3 = state.counters.get("unexplained_loss_mm3", 0) / 1e3
    if unexplained_m3:
        print(f"\n  unexplained loss {unexplained_m3:,.1f} m3: drops seen outside any cut's "
              "footprint, such as a face sliding into a cut's hole (the surface follows "
              "them; no cut is charged)")
    far_m3 = state.counters.get("far_drops_mm3", 0) / 1e3
    if far_m3:
        print(f"\n  measured below the model away from the cuts: {far_m3:,.1f} m3 (the "
              "surface keeps its own slid faces there; FoldConfig.follow_far_drops)")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "project", help="the pile as of a valid time, as known at a known time",
        description="Rebuild a pile from the ledger: its volume, tonnes and grade, its "
        "deposits and what every reclaim cut delivered, as of valid time V as known at K.")
    add_ledger(p, help="opened read-only; or a head office's ledgers with --site")
    p.add_argument("--site", help="the site whose mirror to read in a head office's --ledger")
    p.add_argument("--pile", required=True, help="pile id")
    add_bitemporal(p)
    p.add_argument("--snapshots", metavar="PATH", help="a snapshot file to start from (DuckDB)")
    p.add_argument("--json", action="store_true", help="one JSON object instead of text")
    p.set_defaults(func=cmd_project)
