"""``stockpile audit cuts|history|assays|survey``: audit and reconciliation reports for people.

The computations are in audit.report; this module parses options, shows progress
on stderr during long folds and prints readable tables (or one JSON object with
``--json``).  The ledger is opened read-only.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from urllib.parse import urlsplit
from typing import Any, Sequence

from common.figures import plus_minus
from common.options import (add_bitemporal, add_duration, add_ledger, add_max_rows,
                            add_progress, describe_ledger, format_duration_s, is_ledger_url)
from schemas.analytes import canonical_name
from schemas.jsonl import json_safe
from schemas.times import NS_PER_S, format_time_ns, parse_time_ns

from common.progress import Progress, enabled_from_args, progress
from ledger import open_ledger
from ledger.mirror import is_database_url, ledger_for, mirrored_sites
from audit.report import audit_assays, audit_cuts, audit_history
from audit.surveys import audit_surveys

# -- output helpers -------------------------------------------------------------------------


def _dump(obj: dict[str, Any]) -> None:
    json.dump(json_safe(obj), sys.stdout, indent=1, allow_nan=False)
    print()


def _num(value: float | None, fmt: str = ",.1f") -> str:
    if value is None or not isinstance(value, (int, float)) or not math.isfinite(value):
        return "-"
    return format(value, fmt)


def _pm(value: float | None, sd: float | None, fmt: str = ",.1f") -> str:
    """``62.10 +/- 0.30``: a figure and its standard deviation (the figure alone when the
    sd is unknown, ``-`` when the figure is)."""
    text = _num(value, fmt)
    return text if text == "-" else text + plus_minus(sd, fmt)


def _when(ns: int | None) -> str:
    """UTC time for tables: ``2026-11-01 01:13:17`` (seconds, no zone)."""
    if ns is None:
        return "-"
    return format_time_ns(ns // NS_PER_S * NS_PER_S).replace("T", " ").rstrip("Z")


def table(headers: Sequence[str], rows: Sequence[Sequence[str]], *, right: Sequence[bool] | None = None,
          indent: int = 2) -> str:
    """A plain text table: a header, a rule and aligned columns."""
    widths = [len(h) for h in headers]
    for row in rows:
        widths = [max(w, len(c)) for w, c in zip(widths, row)]
    right = right or [False] * len(headers)
    pad = " " * indent

    def line(cells):
        return pad + "  ".join(c.rjust(w) if r else c.ljust(w)
                               for c, w, r in zip(cells, widths, right)).rstrip()

    out = [line(headers), pad + "  ".join("-" * w for w in widths)]
    out.extend(line(row) for row in rows)
    return "\n".join(out)


def _fold_progress(label: str, args: argparse.Namespace) -> Progress:
    """Progress of a long fold on stderr, in geometry events (the total estimated from the
    fraction of valid time folded)."""
    return progress(unit="geometry events", desc=label, enabled=enabled_from_args(args))


def _open(args: argparse.Namespace, site: str | None = None):
    """The ledger ``--ledger`` names (a file, which must exist, or a ``postgresql://``
    URL), or a site's mirror in a head office's (``--site``), read-only."""
    path = ledger_for(args.ledger, site or args.site)
    if not is_ledger_url(path) and not Path(path).exists():
        raise ValueError(f"no ledger at {describe_ledger(path)}")
    return open_ledger(path, read_only=True)


def _sites(args: argparse.Namespace) -> list[str | None]:
    """The sites a report covers: without ``--site``, every mirrored one of a head office
    (a directory, or a database URL naming no ``schema=`` whose database holds
    ``site_<site>`` schemas), else the one ledger ``--ledger`` and ``--site`` name
    (``[None]``)."""
    if args.site is not None:
        return [None]
    if is_database_url(args.ledger):
        if "schema=" not in urlsplit(args.ledger).query:
            return list(mirrored_sites(args.ledger)) or [None]
    elif Path(args.ledger).is_dir():
        return list(mirrored_sites(args.ledger)) or [None]
    return [None]


def _known(args) -> int | None:
    return parse_time_ns(args.known_time) if getattr(args, "known_time", None) else None


# -- truth (simulator) ----------------------------------------------------------------------


def load_truth_cuts(path: str) -> dict[str, dict[str, Any]]:
    """``cut_id -> {"grade": {...}, "tonnes": t}`` from a simulator ``truth.json``."""
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"no truth file at {path}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not JSON ({exc.msg})") from None
    cuts = data.get("cuts") if isinstance(data, dict) else None
    if not isinstance(cuts, list):
        raise ValueError(f"{path} has no 'cuts' list (a simulator truth.json is expected)")
    out = {}
    for c in cuts:
        if isinstance(c, dict) and "cut_id" in c:
            out[str(c["cut_id"])] = {
                "grade": {k: float(v) for k, v in (c.get("grade") or {}).items()},
                "tonnes": float(c.get("true_tonnes", math.nan)),
                "lots": {k: float(v) for k, v in sorted((c.get("tonnes_by_lot") or {}).items(),
                                                         key=lambda kv: -kv[1])}}
    return out


# -- commands -------------------------------------------------------------------------------


def _cut_row(c, truth: dict[str, dict[str, Any]] | None, analyte: str,
             threshold_pp: float) -> dict[str, Any]:
    """One cut of an :func:`audit.report.audit_cuts` report as a JSON-ready row (with the
    simulator's truth beside it when ``truth`` is given)."""
    row = {
        "cut_id": c.cut_id, "bench_id": c.bench_id,
        "start_time": format_time_ns(c.start_time_ns), "end_time": format_time_ns(c.end_time_ns),
        "start_time_ns": c.start_time_ns, "end_time_ns": c.end_time_ns,
        "estimated_known_time": format_time_ns(c.estimated_known_ns),
        "estimated_known_time_ns": c.estimated_known_ns,
        "tonnes_at_end_t": c.tonnes_at_end_t, "tonnes_t": c.tonnes_t,
        "tonnes_sd": c.tonnes_sd_t, "tonnes_scale_t": c.tonnes_scale_t,
        "grade_at_end_pct": c.grade_at_end_pct, "grade_pct": c.grade_pct,
        "grade_sd": c.grade_sd_pp,
        "delta_pp": c.delta_pp, "assayed_fraction_at_end": c.assayed_fraction_at_end,
        "assayed_fraction": c.assayed_fraction, "lots_t": c.lots_t,
        "residual_m3": c.residual_m3, "changed": c.changed(threshold_pp),
        "reprojected": c.reprojected,
    }
    if truth is not None:
        t = truth.get(c.cut_id)
        row["truth_grade_pct"] = t["grade"] if t else None
        row["truth_tonnes_t"] = t["tonnes"] if t else None
        row["truth_lots_t"] = t["lots"] if t else None
        if t and analyte in t["grade"]:
            err_then = abs(c.grade_at_end_pct.get(analyte, math.nan) - t["grade"][analyte])
            err_now = abs(c.grade_pct.get(analyte, math.nan) - t["grade"][analyte])
            row["closer_to_truth"] = (bool(err_now < err_then)
                                      if math.isfinite(err_now) and math.isfinite(err_then)
                                      else None)
    return row


def _cuts_table(report, rows: list[dict[str, Any]], with_truth: bool, a: str) -> str:
    """The cuts report as a text table for analyte ``a`` (truth columns when ``with_truth``)."""
    headers = ["cut", "ended (UTC)", "geom t", "belt t", f"{a} then %", f"{a} at K %", "d pp",
               "assayed then/K"]
    right = [False, False, True, True, True, True, True, False]
    if with_truth:
        headers += [f"{a} truth %", "closer"]
        right += [True, False]
    headers.append("lots (t)")
    right.append(False)
    if with_truth:
        headers.append("truth lots (t)")
        right.append(False)
    body = []
    for c, row in zip(report.cuts, rows):
        cells = [c.cut_id, _when(c.end_time_ns), _pm(c.tonnes_t, c.tonnes_sd_t),
                 _num(c.tonnes_scale_t), _num(c.grade_at_end_pct.get(a), ".2f"),
                 _pm(c.grade_pct.get(a), c.grade_sd_pp.get(a), ".2f"),
                 _num(c.delta_pp.get(a), "+.2f"),
                 f"{c.assayed_fraction_at_end:.2f} / {c.assayed_fraction:.2f}"]
        if with_truth:
            tg = (row.get("truth_grade_pct") or {}).get(a)
            closer = row.get("closer_to_truth")
            cells += [_num(tg, ".2f"), "-" if closer is None else ("yes" if closer else "no")]
        cells.append(", ".join(f"{lot} {t:,.0f}" for lot, t in c.lots_t.items()) or "-")
        if with_truth:
            cells.append(", ".join(f"{lot} {t:,.0f}" for lot, t in
                                   (row.get("truth_lots_t") or {}).items()) or "-")
        body.append(cells)
    return table(headers, body, right=right)


def _print_cuts(report, rows: list[dict[str, Any]], with_truth: bool, a: str,
                threshold_pp: float) -> None:
    """The cuts report for people: a heading, the table and what changed."""
    print(f"pile {report.pile_id}: {len(rows)} reclaim cuts; grade as estimated when each cut "
          f"ended vs as known at {format_time_ns(report.known_time_ns)} ({a}; --analyte to "
          f"change; +/-: one standard deviation)")
    if not rows:
        print("  no reclaim cuts in the ledger for this pile")
        return
    print(_cuts_table(report, rows, with_truth, a))
    changed = [r["cut_id"] for r in rows if r["changed"]]
    print(f"\n  {len(changed)} of {len(rows)} cuts changed grade after the cut ended by more than "
          f"{threshold_pp:g} pp (late or superseding assays)"
          + (f": {', '.join(changed)}" if changed else ""))
    if with_truth:
        closer = [r for r in rows if r.get("closer_to_truth")]
        print(f"  {len(closer)} of {len(rows)} cuts are closer to the simulator's truth as known "
              f"at K than as estimated at the time ({a}); the lots columns show how much of "
              f"the rest is the cuts' modelled lot mix")
    reproj = [r["cut_id"] for r in rows if r["reprojected"]]
    if reproj:
        print(f"  re-projected on their own (a geometry event arrived late): {', '.join(reproj)}")


def cmd_cuts(args: argparse.Namespace) -> int:
    truth = load_truth_cuts(args.truth) if args.truth else None
    with _open(args) as store, _fold_progress("audit cuts", args) as bar:
        head = store.head().global_seq
        report = audit_cuts(store, args.pile, _known(args),
                            progress=lambda fraction, events: bar.update_to(events,
                                                                            fraction=fraction))
    analyte = canonical_name(args.analyte, report.analytes)
    if report.analytes and analyte not in report.analytes:
        raise ValueError(f"analyte {analyte!r} is not in this ledger (it has "
                         f"{', '.join(report.analytes)})")
    rows = [_cut_row(c, truth, analyte, args.threshold_pp) for c in report.cuts]
    if args.json:
        _dump({"pile_id": report.pile_id, "known_time": format_time_ns(report.known_time_ns),
               "known_time_ns": report.known_time_ns, "head_global_seq": head,
               "analytes": list(report.analytes), "pile_tonnes_t": report.pile_tonnes_t, "threshold_pp": args.threshold_pp,
               "cuts": rows})
        return 0
    _print_cuts(report, rows, truth is not None, analyte, args.threshold_pp)
    return 0


def _survey_row(r) -> dict[str, Any]:
    return {"survey_id": r.survey_id, "time": format_time_ns(r.time_ns),
            "recorded_time": format_time_ns(r.recorded_time_ns), "provider": r.provider,
            "accuracy_m": r.accuracy_m, "points": r.points, "cells": r.cells,
            "area_m2": r.area_m2, "survey_m3": r.survey_m3, "model_then_m3": r.model_then_m3,
            "model_now_m3": r.model_now_m3, "diff_then_m3": r.diff_then_m3,
            "diff_now_m3": r.diff_now_m3, "diff_then_pct": r.diff_then_pct,
            "diff_now_pct": r.diff_now_pct, "density_t_m3": r.density_t_m3,
            "diff_then_t": r.diff_then_t, "diff_now_t": r.diff_now_t,
            "map": {"block_m": r.block_m, "origin_m": list(r.map_origin_m),
                    "diff_m3": r.map_m3.tolist()},
            "largest_blocks": [{"x_m": x, "y_m": y, "diff_m3": d}
                               for x, y, d in r.largest_blocks()],
            "rebase": None if r.rebase is None else {
                "cells_scaled": r.rebase.cells_scaled,
                "cells_bare_above": r.rebase.cells_bare_above,
                "volume_change_m3": r.rebase.volume_change_m3,
                "tonnes_change_t": r.rebase.volume_change_m3 * r.density_t_m3,
                "deposits": [{"lot_id": lot, "pass_id": pass_id, "volume_change_m3": dv}
                             for lot, pass_id, dv in r.rebase.deposits_m3]}}


def _print_rebase(rebase, density_t_m3: float) -> None:
    """The audit trail of a rebase on a survey (the pile's policy)."""
    print(f"  rebased on it (the pile's policy): {rebase.cells_scaled:,} cells scaled, "
          f"{_num(rebase.volume_change_m3, '+,.1f')} m3 "
          f"({_num(rebase.volume_change_m3 * density_t_m3, '+,.1f')} t); "
          f"{rebase.cells_bare_above:,} bare cells the survey shows above the ground left bare")
    for lot, pass_id, dv in rebase.deposits_m3:
        print(f"    {pass_id or '-'} (lot {lot or '-'}): {_num(dv, '+,.1f')} m3")


def cmd_survey(args: argparse.Namespace) -> int:
    with _open(args) as store:
        rows = audit_surveys(store, args.pile, _known(args), block_m=args.block_m)
    if args.json:
        _dump({"pile_id": args.pile, "surveys": [_survey_row(r) for r in rows]})
        return 0
    if not rows:
        print(f"no survey of pile {args.pile} in the ledger")
        return 0
    for r in rows:
        print(f"survey {r.survey_id} at {format_time_ns(r.time_ns)} ({r.provider or '-'}, "
              f"{r.points:,} points over {r.area_m2:,.0f} m2)")
        print(f"  survey {_num(r.survey_m3)} m3; model {_num(r.model_now_m3)} m3 as known "
              f"now, {_num(r.model_then_m3)} m3 as known then")
        print(f"  difference (survey - model): now {_num(r.diff_now_m3, '+,.1f')} m3 "
              f"{_num(r.diff_now_t, '+,.1f')} t {_num(r.diff_now_pct, '+.2f')} %; then "
              f"{_num(r.diff_then_m3, '+,.1f')} m3 {_num(r.diff_then_pct, '+.2f')} %")
        blocks = r.largest_blocks()
        if blocks:
            print(f"  where ({r.block_m:g} m blocks, site frame): " + "; ".join(
                f"x {x:.0f} y {y:.0f}: {d:+,.1f} m3" for x, y, d in blocks))
        if r.rebase is not None:
            _print_rebase(r.rebase, r.density_t_m3)
    return 0


def cmd_history(args: argparse.Namespace) -> int:
    every = int(round(args.every * NS_PER_S))
    start = parse_time_ns(args.start) if args.start else None
    end = parse_time_ns(args.end) if args.end else None
    with _open(args) as store, _fold_progress("audit history", args) as bar:
        head = store.head().global_seq
        report = audit_history(store, args.pile, every, _known(args), start_ns=start, end_ns=end,
                               progress=lambda fraction, events: bar.update_to(
                                   events, fraction=fraction), max_rows=args.max_rows)
    analyte = canonical_name(args.analyte, report.analytes)
    if report.analytes and analyte not in report.analytes:
        raise ValueError(f"analyte {analyte!r} is not in this ledger (it has "
                         f"{', '.join(report.analytes)})")
    if args.json:
        _dump({"pile_id": report.pile_id, "known_time": format_time_ns(report.known_time_ns),
               "known_time_ns": report.known_time_ns, "head_global_seq": head,
               "every_ns": report.every_ns,
               "analytes": list(report.analytes),
               "points": [{"valid_time": format_time_ns(p.valid_time_ns),
                           "valid_time_ns": p.valid_time_ns,
                           "volume_m3": p.volume_m3, "tonnes_t": p.tonnes_t,
                           "tonnes_sd": p.tonnes_sd_t, "grade_pct": p.grade_pct,
                           "grade_sd": p.grade_sd_pp, "assayed_fraction": p.assayed_fraction,
                           "volume_then_m3": p.volume_then_m3, "tonnes_then_t": p.tonnes_then_t,
                           "grade_then_pct": p.grade_then_pct,
                           "assayed_fraction_then": p.assayed_fraction_then,
                           "delta_pp": p.delta_pp, "reprojected": p.reprojected}
                          for p in report.points]})
        return 0
    a = analyte
    print(f"pile {report.pile_id}: tonnes and grade every {format_duration_s(args.every)} of "
          f"valid time, as known at {format_time_ns(report.known_time_ns)} (K) and as known at "
          f"the time ({a}; +/-: one standard deviation)")
    headers = ["valid time (UTC)", "t at K", "t then", f"{a} at K %", f"{a} then %", "d pp",
               "assayed K/then"]
    body = [[_when(p.valid_time_ns), _pm(p.tonnes_t, p.tonnes_sd_t), _num(p.tonnes_then_t),
             _pm(p.grade_pct.get(a), p.grade_sd_pp.get(a), ".2f"),
             _num(p.grade_then_pct.get(a), ".2f"),
             _num(p.delta_pp.get(a), "+.2f"),
             f"{p.assayed_fraction:.2f} / {p.assayed_fraction_then:.2f}"]
            for p in report.points]
    print(table(headers, body, right=[False, True, True, True, True, True, False]))
    return 0


def _with_site(site: str | None, rows: list[dict]) -> list[dict]:
    """Rows of one site's report with a leading ``site`` field (a head office's report)."""
    return rows if site is None else [{"site": site, **row} for row in rows]


def cmd_assays(args: argparse.Namespace) -> int:
    reports = []
    for site in _sites(args):
        with _open(args, site) as store:
            reports.append((site, audit_assays(store, _known(args)),
                            store.head().global_seq))
    many = reports[0][0] is not None   # a head office's sites: a site column in every table
    report = reports[0][1]
    labs = [row for site, r, _head in reports for row in _with_site(site, [lab.__dict__ for lab in r.labs])]
    lists = {key: [row for site, r, _head in reports for row in _with_site(site, getattr(r, key))]
             for key in ("superseded", "provisional", "unknown_lots", "lots_without_assays",
                         "signatures")}
    assays = sum(r.assays for _site, r, _head in reports)
    if args.json:
        _dump({"known_time": format_time_ns(report.known_time_ns),
               "known_time_ns": report.known_time_ns,
               "head_global_seq": (reports[0][2] if not many else
                                   {site: h for site, _r, h in reports}),
               "assays": assays, "labs": labs, **lists})
        return 0

    def cells(row: dict, values: list[str]) -> list[str]:
        return [row["site"], *values] if many else values

    def heads(*names: str) -> list[str]:
        return ["site", *names] if many else list(names)

    print(f"{assays} assays as known at {format_time_ns(report.known_time_ns)}")
    print("\n  lateness per lab (recorded time - end of the sampling window, hours)")
    if labs:
        bins = list(labs[0]["histogram"])
        headers = heads("lab", "assays", "min h", "median h", "mean h", "p90 h", "max h", *bins)
        body = [cells(lab, [lab["lab_id"], str(lab["assays"]), _num(lab["min_h"], ".2f"),
                            _num(lab["median_h"], ".2f"), _num(lab["mean_h"], ".2f"),
                            _num(lab["p90_h"], ".2f"), _num(lab["max_h"], ".2f"),
                            *[str(lab["histogram"][b]) for b in bins]]) for lab in labs]
        print(table(headers, body, right=[False] * (1 + many) + [True] * (len(headers) - 1 - many),
                    indent=4))
    else:
        print("    none")
    print(f"\n  superseded assays ({len(lists['superseded'])})")
    if lists["superseded"]:
        body = [cells(s, [s["assay_id"], s["lot_id"], s["status"] or "?", s["superseded_by"],
                          s["by_status"], _when(s["superseded_at_ns"]),
                          ", ".join(f"{a} {s['delta_pp'][a]:+.2f}" for a in ("Fe", "SiO2")
                                    if a in s["delta_pp"]) + " pp" if s["delta_pp"] else "-"])
                for s in lists["superseded"]]
        print(table(heads("assay", "lot", "status", "superseded by", "its status", "at (UTC)",
                          "change"), body, indent=4))
    else:
        print("    none")
    print(f"\n  provisional assays ({len(lists['provisional'])})")
    if lists["provisional"]:
        body = [cells(p, [p["assay_id"], p["lot_id"], p["lab_id"], _when(p["recorded_ns"]),
                          p["replaced_by"] or ("still provisional" if p["open"] else "-")])
                for p in lists["provisional"]]
        print(table(heads("assay", "lot", "lab", "recorded (UTC)", "replaced by"), body, indent=4))
    else:
        print("    none")
    print(f"\n  assays for lots not declared when recorded ({len(lists['unknown_lots'])})")
    if lists["unknown_lots"]:
        body = [cells(u, [u["assay_id"], u["lot_id"], u["lab_id"], _when(u["recorded_ns"]),
                          "yes" if u["declared_by_k"] else "no"]) for u in lists["unknown_lots"]]
        print(table(heads("assay", "lot", "lab", "recorded (UTC)", "declared by K"), body,
                    indent=4))
    else:
        print("    none")
    _print_signers(lists["signatures"])
    print(f"\n  lots without assays ({len(lists['lots_without_assays'])})")
    if lists["lots_without_assays"]:
        body = [cells(lot, [lot["lot_id"], _when(lot["declared_ns"]),
                            _num(lot["planned_tonnes_t"])])
                for lot in lists["lots_without_assays"]]
        print(table(heads("lot", "declared (UTC)", "planned t"), body, indent=4))
    else:
        print("    none")
    return 0


def _print_signers(signatures: list[dict]) -> None:
    """Who vouched for the results: per signing key, its assays (unsigned ones apart)."""
    by_signer: dict = {}
    for s in signatures:
        by_signer.setdefault(s["signer"], []).append(s)
    print(f"\n  who signed the results ({len(by_signer)} signers, unsigned counted apart)")
    body = []
    for signer, group in sorted(by_signer.items(), key=lambda kv: (kv[0] is None, kv[0] or "")):
        ids = [s["assay_id"] for s in group]
        shown = ", ".join(ids[:5]) + (f", ... ({len(ids) - 5} more)" if len(ids) > 5 else "")
        who = (f"{group[0]['signer_name']} ({group[0]['signer_role']})"
               if group[0]["signer_name"] else "(undeclared key)") if signer else "unsigned"
        body.append([signer or "-", who, str(len(group)), shown])
    print(table(["key id", "holder", "assays", "assay ids"], body, indent=4) if body
          else "    none")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "audit", help="audit and reconciliation reports (cuts, history, assays)",
        description="Audit and reconciliation reports from the ledger alone: what each cut "
        "graded as estimated at the time vs as known now, the pile over time, and how late "
        "the labs report.")
    sub = p.add_subparsers(dest="audit", metavar="REPORT", required=True, parser_class=type(p))

    def common(sp, *, pile: bool, fold: bool) -> None:
        add_ledger(sp, help="opened read-only; or a head office's ledgers (every site's "
                   "for assays, or --site)")
        sp.add_argument("--site", help="the site whose mirror to read in a head office's --ledger")
        if pile:
            sp.add_argument("--pile", required=True, help="pile id")
        add_bitemporal(sp, valid=False)
        sp.add_argument("--json", action="store_true", help="one JSON object instead of tables")
        if fold:
            sp.add_argument("--analyte", default="Fe",
                            help="analyte shown in the table (default %(default)s; --json has all)")
            add_progress(sp)

    c = sub.add_parser("cuts", help="each cut: grade as estimated when it ended vs as known at K",
                       description="One row per reclaim cut: tonnes (geometry and belt scale), "
                       "grade as estimated when the cut ended (as of its end, as known when the "
                       "ledger first knew the cut), grade as known at K, the difference, the "
                       "assayed fractions and the contributing lots.")
    common(c, pile=True, fold=True)
    c.add_argument("--truth", metavar="TRUTH_JSON",
                   help="a simulator truth.json: adds the true grade per cut beside the figures")
    c.add_argument("--threshold-pp", type=float, default=0.01,
                   help="a cut 'changed' when a grade moved more than this (default %(default)s pp)")
    c.set_defaults(func=cmd_cuts)

    h = sub.add_parser("history", help="pile tonnes and grade over valid time, as known at K "
                       "and as known then",
                       description="The pile's volume, tonnes and grade at regular steps of valid "
                       "time, each as known at K and as known at the time, with the difference "
                       "in percentage points.")
    common(h, pile=True, fold=True)
    add_duration(h, "--every", required=True,
                 help="valid (site) time between rows, with a unit: 1h, 30min, 90s ...")
    h.add_argument("--from", dest="start", metavar="T",
                   help="first valid time (default: the pile's declaration)")
    h.add_argument("--to", dest="end", metavar="T",
                   help="last valid time (default: the last in the ledger)")
    add_max_rows(h, what="rows (valid times)")
    h.set_defaults(func=cmd_history)

    v = sub.add_parser("survey", help="each survey against the model: volumes, the "
                       "difference and where it lies",
                       description="One row per survey of the pile (stockpile survey import): "
                       "the model's volume over the surveyed cells as of the survey's time, as "
                       "known then and as known at K, the survey's volume, the difference in "
                       "m3, t and %, and the blocks where it lies.")
    common(v, pile=True, fold=False)
    v.add_argument("--block-m", type=float, default=10.0, metavar="M",
                   help="edge of the difference map's blocks, metres (default 10)")
    v.set_defaults(func=cmd_survey)

    a = sub.add_parser("assays", help="lateness per lab, superseded and provisional assays, "
                       "unknown lots, lots without assays",
                       description="How late each laboratory reports (from sampling to the "
                       "ledger), superseded and provisional assays, assays of unknown lots and "
                       "lots without an assay, as known at K.")
    common(a, pile=False, fold=False)
    a.set_defaults(func=cmd_assays)
