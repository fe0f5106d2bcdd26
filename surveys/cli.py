"""``stockpile survey import``: a drone or laser survey (LAS/LAZ) into the ledger."""

from __future__ import annotations

import argparse
import json
import math

from common.options import add_ledger, add_progress, epsg_code, positive_int
from common.progress import enabled_from_args, progress as progress_bar
from ledger import open_ledger
from schemas.times import format_time_ns, parse_time_ns
from surveys.importer import CHUNK_POINTS, import_survey


def cmd_import(args: argparse.Namespace) -> int:
    time_ns = parse_time_ns(args.time)
    if not (args.accuracy_m >= 0 and math.isfinite(args.accuracy_m)):
        raise ValueError(f"--accuracy-m must be a finite number >= 0, got {args.accuracy_m}")
    with open_ledger(args.ledger) as store, progress_bar(
            unit="points", desc=f"survey {args.file}", enabled=enabled_from_args(args)) as bar:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update_to(done)

        result = import_survey(args.file, store, args.pile, time_ns, epsg=args.crs,
                               provider=args.provider, accuracy_m=args.accuracy_m,
                               survey_id=args.survey_id, chunk_points=args.chunk_points,
                               progress=progress)
    if args.json:
        print(json.dumps(result.__dict__, indent=1))
    else:
        print(f"survey {result.survey_id} of {args.pile} at {format_time_ns(time_ns)}: "
              f"{result.points:,} points ({result.points_in_grid:,} in the pile's grid, "
              f"EPSG:{result.crs_epsg}) -> {result.cells:,} cells; {result.outcome}"
              + (f" ({result.reason})" if result.reason else ""))
    return 0 if result.outcome in ("appended", "duplicate") else 2


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("survey", help="surveys of the piles: import LAS/LAZ",
                              description="Surveys of the piles (drone or laser, LAS/LAZ).")
    sub = p.add_subparsers(dest="what", metavar="WHAT", required=True)
    q = sub.add_parser("import", help="a LAS/LAZ survey into the ledger as one survey event",
                       description="Read a LAS/LAZ file in bounded memory, take its points "
                       "to the site frame, decimate them to the pile's grid (mean height "
                       "per cell) and append one survey event.")
    q.add_argument("file", metavar="FILE", help="the LAS or LAZ file")
    add_ledger(q, help="appended to")
    q.add_argument("--pile", required=True, help="pile id")
    q.add_argument("--time", required=True, metavar="T",
                   help="when the survey was flown (ISO-8601 or UTC ns): its valid time")
    q.add_argument("--crs", type=epsg_code, metavar="EPSG",
                   help="the file's projected CRS (default: the one its header names)")
    q.add_argument("--provider", default="", help="who flew or scanned it")
    q.add_argument("--accuracy-m", type=float, default=0.0, metavar="M",
                   help="its stated vertical accuracy, one sd, metres (default 0: not stated)")
    q.add_argument("--survey-id", help="default: <pile>-<unix seconds of --time>")
    q.add_argument("--chunk-points", type=lambda t: positive_int(t, "a point count"),
                   default=CHUNK_POINTS, metavar="N",
                   help=f"points read at a time (default {CHUNK_POINTS:,})")
    add_progress(q)
    q.add_argument("--json", action="store_true", help="the outcome as JSON")
    q.set_defaults(func=cmd_import)

