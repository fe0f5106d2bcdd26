"""``stockpile plan reclaim``: the next bench of a pile, planned before the wheel touches it.

The edge of the reclaim planner (:mod:`planner`): it reads the ledger (the pile
and machine declarations, the projection as of (V, K), lots and assays), runs the pure
planner and prints the landing and each cut's predicted slew range, tonnes and grade.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys

from common.figures import format_grades, plus_minus
from common.options import add_bitemporal, add_ledger
from schemas.analytes import canonical_name
from schemas.events import decode_payload
from schemas.jsonl import json_safe
from schemas.times import format_time_ns, parse_time_ns

from ledger import open_ledger
from projector.query import FAR_FUTURE_NS, grade_inputs, project
from planner.bench import PlanParams
from planner.grades import check_bounds, predict_cuts
from projector.kinematics import PlannerMachine
from planner.plan import plan_reclaim

EXIT_OK, EXIT_NO_PLAN = 0, 1
_BOUND = re.compile(r"^\s*([A-Za-z][A-Za-z0-9_]*)\s*(>=|<=)\s*([-+0-9.eE]+)\s*$")


def parse_bounds(texts: list[str]) -> dict[str, tuple[float | None, float | None]]:
    """``["Fe>=61", "SiO2<=5"]`` -> ``{"Fe": (61.0, None), "SiO2": (None, 5.0)}``; analyte
    names canonical (``FE>=61`` bounds Fe)."""
    out: dict[str, list[float | None]] = {}
    for text in texts:
        m = _BOUND.match(text)
        if m is None:
            raise ValueError(f"bad --bound {text!r}: write ANALYTE>=VALUE or ANALYTE<=VALUE "
                             "(e.g. Fe>=61.0)")
        name, op, value = canonical_name(m.group(1)), m.group(2), float(m.group(3))
        if not math.isfinite(value):
            raise ValueError(f"bad --bound {text!r}: the value must be finite")
        lo_hi = out.setdefault(name, [None, None])
        lo_hi[0 if op == ">=" else 1] = value
    return {k: (v[0], v[1]) for k, v in out.items()}


def _declarations(store, v: int, k: int, pile_id: str, machine_id: str):
    """The pile's and the machine's declarations as of (V, K); a clear error otherwise."""
    piles, machines = {}, {}
    for event in store.as_of(v, k, types=["pile_declared", "machine_declared"]):
        msg = decode_payload(event.type, event.payload)
        if event.type == "pile_declared":
            piles.setdefault(msg.pile_id, msg)
        else:
            machines[msg.machine_id] = msg
    if pile_id not in piles:
        known = ", ".join(sorted(piles)) or "none"
        raise ValueError(f"unknown pile {pile_id!r} as of that time (declared: {known})")
    reclaimers = {mid: m for mid, m in machines.items() if m.kind == 1}  # BUCKET_WHEEL_RECLAIMER
    if machine_id not in reclaimers:
        known = ", ".join(sorted(reclaimers)) or "none"
        what = "is not a bucket-wheel reclaimer" if machine_id in machines else "is unknown"
        raise ValueError(f"machine {machine_id!r} {what} as of that time "
                         f"(reclaimers declared: {known})")
    return piles[pile_id], reclaimers[machine_id]


def plan_args(ledger: str, pile: str, machine: str, *, cuts: int = 10) -> argparse.Namespace:
    """The arguments of ``stockpile plan reclaim`` with its defaults (for callers in code)."""
    return argparse.Namespace(ledger=ledger, pile=pile, machine=machine, cuts=cuts,
                              bench_height=None, spacing=None, clearance=None, bound=None,
                              valid_time=None, known_time=None, all=False)


def _check_plan_args(args: argparse.Namespace) -> None:
    """A clear error for a number of cuts, a spacing or a clearance that cannot be planned."""
    if args.cuts < 1:
        raise ValueError(f"--cuts must be >= 1, got {args.cuts}")
    for name in ("bench_height", "spacing", "clearance"):
        value = getattr(args, name)
        if value is not None and not math.isfinite(value):
            raise ValueError(f"--{name.replace('_', '-')} must be a finite number")
    if args.spacing is not None and args.spacing <= 0:
        raise ValueError(f"--spacing must be > 0, got {args.spacing}")
    if args.clearance is not None and args.clearance < 0:
        raise ValueError(f"--clearance must be >= 0, got {args.clearance}")


def _noise_warnings(state, plan, machine) -> list[str]:
    """A warning when the clearance is within the scans' surface noise (3 sd)."""
    warnings = []
    noise_m = float(getattr(state.state, "point_sd_m", math.nan))
    if math.isfinite(noise_m) and plan.params.clearance_m < 3 * noise_m:
        warnings.append(
            f"the clearance ({plan.params.clearance_m:.3g} m) is less than 3 x the surface "
            f"noise of the scans ({noise_m:.3g} m): a landing may collide where the model's "
            f"surface is low; the wheel bites at most Rv - Rk - clearance = "
            f"{machine.cutting_radius_m - machine.wheel_radius_m - plan.params.clearance_m:.3g} m")
    return warnings


def _landing_json(plan) -> dict | None:
    """The plan's landing (point, normal, wheel centre, joints, depth), or None."""
    if plan.landing is None:
        return None
    lz, search = plan.landing, plan.search
    return {
        "point_m": list(lz.point_m), "normal": list(lz.normal),
        "wheel_centre_m": list(lz.centre_m),
        "joints": {"travel_m": lz.travel_m, "slew_rad": lz.slew_rad, "luff_rad": lz.luff_rad},
        "direction": lz.direction, "cutting_depth_m": lz.cutting_depth_m,
        "bench_floor_m": lz.bench_floor_m,
        "candidates_tried": search.tried, "candidates_valid": search.valid,
    }


def _plan_json(args: argparse.Namespace, state, plan, machine, warnings: list[str]) -> dict:
    """The plan's search, landing and parameters as one JSON-ready dict (no cuts yet)."""
    search = plan.search
    return {
        "pile_id": args.pile, "machine_id": args.machine,
        "valid_time_ns": state.valid_time_ns, "known_time_ns": state.known_time_ns,
        "landing": None,
        "search": {"spacing_m": search.spacing_m, "in_region": search.in_region,
                   "tried": search.tried, "landing_valid": search.landing_valid,
                   "bench_checked": search.bench_checked, "valid": search.valid,
                   "exhaustive": search.exhaustive, "rejected": search.rejected},
        "cuts": [],
        "warnings": warnings,
        "params": {"clearance_m": plan.params.clearance_m, "min_bite_m": plan.params.min_bite_m,
                   "cut_depth_m": plan.params.cut_depth_m, "spacing_m": plan.params.spacing_m,
                   "slump": plan.params.slump, "repose_deg": plan.params.repose_deg,
                   "max_cutting_height_m": machine.max_cutting_height_m,
                   "bench_floor_m": args.bench_height},
    }


def _add_predictions(out: dict, plan, predictions, bounds) -> None:
    """Each planned cut with its predicted tonnes and grade, the bench's, and the bounds."""
    for cut, p in zip(plan.cuts, predictions):
        g = cut.geometry
        out["cuts"].append({
            "cut": cut.index + 1, "travel_m": cut.travel_m, "luff_rad": cut.luff_rad,
            "slew_start_rad": cut.slew_start_rad, "slew_end_rad": cut.slew_end_rad,
            "volume_m3": p.volume_m3, "tonnes": p.tonnes, "tonnes_sd": p.tonnes_sd,
            "grade": p.grade, "grade_sd": p.grade_sd,
            "assayed_fraction": p.assayed_fraction, "bank_m": g.bank_m,
            "slumped_m3": g.slumped_m3, "deposits": p.deposits})
    tonnes = sum(p.tonnes for p in predictions)
    assayed = sum(p.tonnes * p.assayed_fraction for p in predictions)
    report = check_bounds(predictions, bounds)
    out["bench"] = {"tonnes": tonnes, "grade": report.bench_grade,
                    "assayed_fraction": assayed / tonnes if tonnes > 0 else 0.0}
    if bounds:
        out["bounds"] = {"limits": {a: {"min": lo, "max": hi} for a, (lo, hi) in bounds.items()},
                         "cuts_outside": report.outside, "bench_outside": report.bench_outside}


def make_plan(args: argparse.Namespace, store=None) -> dict:
    """Read the ledger (or the open ``store``), plan, predict; one JSON-ready dict."""
    _check_plan_args(args)
    bounds = parse_bounds(args.bound or [])
    valid = parse_time_ns(args.valid_time) if args.valid_time else None
    known = parse_time_ns(args.known_time) if args.known_time else None
    v = FAR_FUTURE_NS if valid is None else valid
    k = FAR_FUTURE_NS if known is None else known
    if store is None:
        with open_ledger(args.ledger, read_only=True) as opened:
            return make_plan(args, opened)
    pile_msg, machine_msg = _declarations(store, v, k, args.pile, args.machine)
    state = project(store, args.pile, valid, known)
    lots, assays = grade_inputs(store, v, k)
    if state.geometry is None or state.state.stack is None:
        raise ValueError(f"pile {args.pile!r} has no projection as of that time")
    machine = PlannerMachine.from_message(machine_msg)
    tan_repose = getattr(state.state, "tan_repose", math.nan)
    repose = math.degrees(math.atan(tan_repose)) if math.isfinite(tan_repose) else None
    params = PlanParams(spacing_m=args.spacing, clearance_m=args.clearance, repose_deg=repose)
    plan = plan_reclaim(state.state.stack, machine, n_cuts=args.cuts,
                        bench_floor_m=args.bench_height, params=params, exhaustive=args.all)
    density = float(pile_msg.default_bulk_density_t_m3) or 2.4
    warnings = _noise_warnings(state, plan, machine)
    predictions = predict_cuts(state.geometry, [c.removal for c in plan.cuts], lots, assays,
                               state.known_time_ns, density, pile_id=args.pile,
                               height=state.state.height)
    out = _plan_json(args, state, plan, machine, warnings)
    out["landing"] = _landing_json(plan)
    _add_predictions(out, plan, predictions, bounds)
    return out


def print_plan(out: dict) -> None:
    v, k = out["valid_time_ns"], out["known_time_ns"]
    when_v = "everything" if v >= 2 ** 62 else format_time_ns(v)
    when_k = "now" if k >= 2 ** 62 else format_time_ns(k)
    s = out["search"]
    print(f"reclaim plan: pile {out['pile_id']}, machine {out['machine_id']}, as of {when_v}, "
          f"as known {when_k}")
    print(f"  candidates: {s['tried']} tried on a {s['spacing_m']:g} m grid "
          f"({s['in_region']} in the cutting region facing the rail), {s['landing_valid']} "
          f"pass their first cut, {s['valid']} valid of {s['bench_checked']} benches checked"
          + ("" if s["exhaustive"] else " (first valid in order of cutting depth)"))
    if s["rejected"]:
        print("  rejected: " + ", ".join(f"{k} {v}" for k, v in s["rejected"].items()))
    for w in out["warnings"]:
        print(f"  warning: {w}")
    lz = out["landing"]
    if lz is None:
        print("  no valid landing")
        return
    j = lz["joints"]
    print(f"  landing point ({', '.join(f'{v:.2f}' for v in lz['point_m'])}) m, wheel centre "
          f"({', '.join(f'{v:.2f}' for v in lz['wheel_centre_m'])}) m")
    print(f"  joints: travel {j['travel_m']:.3f} m, slew {math.degrees(j['slew_rad']):.2f} deg, "
          f"luff {math.degrees(j['luff_rad']):.2f} deg; bench floor {lz['bench_floor_m']:.2f} m, "
          f"cutting depth {lz['cutting_depth_m']:.2f} m, "
          f"advancing {'+' if lz['direction'] > 0 else '-'}y")
    print(f"\n  {'cut':>3} {'travel m':>10} {'slew deg':>17} {'tonnes +/- sd':>22} {'assayed':>7}"
          "  grade (+/-: one standard deviation)")
    for c in out["cuts"]:
        slew = f"{math.degrees(c['slew_start_rad']):7.2f}->{math.degrees(c['slew_end_rad']):7.2f}"
        fmt = ",.1f" if c["tonnes"] >= 100 else ".4g"
        tonnes = f"{c['tonnes']:{fmt}}{plus_minus(c.get('tonnes_sd'), fmt)}"
        print(f"  {c['cut']:>3} {c['travel_m']:>10.3f} {slew:>17} {tonnes:>22} "
              f"{c['assayed_fraction']:>7.2f}  {format_grades(c['grade'], c.get('grade_sd'))}")
    b = out["bench"]
    print(f"\n  bench: {b['tonnes']:,.4g} t, {format_grades(b['grade'])} "
          f"(assayed fraction {b['assayed_fraction']:.2f})")
    if "bounds" in out:
        bad = out["bounds"]["cuts_outside"]
        if bad:
            for o in bad:
                side = "below" if o["bound"] == "min" else "above"
                print(f"  cut {o['cut']}: {o['analyte']} {o['grade']:.2f} % is {side} "
                      f"{o['limit']:g} %")
        else:
            print("  every cut is within the grade bounds")
        if out["bounds"]["bench_outside"]:
            print("  the bench as a whole is outside for: "
                  + ", ".join(out["bounds"]["bench_outside"]))


def cmd_plan_reclaim(args: argparse.Namespace) -> int:
    out = make_plan(args)
    if args.json:
        json.dump(json_safe(out), sys.stdout, indent=1)
        print()
    else:
        print_plan(out)
    if out["landing"] is None:
        print(f"stockpile: no valid landing for pile {args.pile!r} with machine "
              f"{args.machine!r} ({out['search']['tried']} candidates tried)", file=sys.stderr)
        return EXIT_NO_PLAN
    return EXIT_OK


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "plan", help="plan reclaim work before the wheel touches the pile",
        description="Plans from the ledger's projection of a pile.")
    sub = p.add_subparsers(dest="plan_command", metavar="WHAT", required=True,
                           parser_class=type(p))
    r = sub.add_parser(
        "reclaim", help="the next bench: landing point, slew ranges, tonnes and grade per cut",
        description="Choose a collision-free landing for the machine's bucket wheel on the "
        "pile as of valid time V as known at K (the largest cutting depth among the valid "
        "landings), then cut the bench cut by cut on a copy of the pile and predict each "
        "cut's slew range, tonnes and grade.  Exit code 1 when no landing is valid.")
    add_ledger(r, help="opened read-only")
    r.add_argument("--pile", required=True, help="pile id")
    r.add_argument("--machine", required=True, help="bucket-wheel reclaimer id")
    r.add_argument("--bench-height", type=float, metavar="Z",
                   help="bench floor (m, site frame): the lowest point of the cutting "
                   "envelope, wheel centre at Z + Rv (default: anywhere in the top H of the pile)")
    r.add_argument("--cuts", type=int, default=10, metavar="N", help="cuts in the bench (10)")
    add_bitemporal(r)
    r.add_argument("--bound", action="append", metavar="ANALYTE>=X|ANALYTE<=X",
                   help="grade bound to check the predicted cuts against (repeatable), "
                   "e.g. --bound 'Fe>=61' --bound 'SiO2<=5'")
    r.add_argument("--spacing", type=float, metavar="M",
                   help="candidate grid spacing (m; default Rv / 5)")
    r.add_argument("--clearance", type=float, metavar="M",
                   help="safety margin on the wheel body and under the boom (m; default 0.1 Rv)")
    r.add_argument("--all", action="store_true",
                   help="check every candidate's whole bench (default: stop at the first valid "
                   "one in order of cutting depth)")
    r.add_argument("--json", action="store_true", help="one JSON object instead of text")
    r.set_defaults(func=cmd_plan_reclaim)
