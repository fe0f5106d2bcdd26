"""``stockpile export surfaces|mesh|blocks|cuts``: files for mine planning and GIS.

Each subcommand projects the pile as of ``--valid-time`` as known at ``--known-time``
(:func:`projector.query.project`) and writes one file in the site's mine grid (the CRS the
site declares, or ``--crs EPSG``); it prints one line saying what it wrote, or the summary
as JSON with ``--json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from common.options import add_bitemporal, add_ledger, add_out, epsg_code
from ledger import open_ledger
from ledger.mirror import ledger_for
from projector.cli import project_from_args
from schemas.jsonl import json_safe

from exports.placement import site_crs_from_ledger



def _projected(args: argparse.Namespace):
    """(pile state, site CRS) as of the command's times."""
    with open_ledger(ledger_for(args.ledger, args.site), read_only=True) as store:
        pile = project_from_args(store, args)
        site = site_crs_from_ledger(store, pile.valid_time_ns, pile.known_time_ns, args.crs)
    return pile, site


def _report(args: argparse.Namespace, summary: dict, line: str) -> int:
    print(json.dumps(json_safe(summary), indent=1, default=str) if args.json else line)
    return 0


def cmd_surfaces(args: argparse.Namespace) -> int:
    from exports.geotiff import write_surfaces

    pile, site = _projected(args)
    s = write_surfaces(args.out, pile, site)
    return _report(args, s, f"wrote {s['path']}: {len(s['bands'])} surfaces (the ground, "
                   f"then each deposit's top) on {s['width']} x {s['height']} cells, "
                   f"EPSG:{s['epsg']} (placement within "
                   f"{s['placement_residual_m'] * 1000:.1f} mm)")


def cmd_mesh(args: argparse.Namespace) -> int:
    from exports.dxf import write_mesh

    pile, site = _projected(args)
    s = write_mesh(args.out, pile, site, contour_m=args.contour_m,
                   max_vertices=args.max_vertices)
    return _report(args, s, f"wrote {s['path']}: a polyface of {s['vertices']:,} vertices "
                   f"and {s['faces']:,} faces (every {s['step']} cells), {s['contours']:,} "
                   f"contour lines every {s['contour_m']:g} m")


def cmd_blocks(args: argparse.Namespace) -> int:
    from exports.blocks import write_blocks
    from projector.blocks import block_model

    fmt = args.format or ("parquet" if Path(args.out).suffix.lower() == ".parquet" else "csv")
    pile, site = _projected(args)
    blocks = block_model(pile)
    s = write_blocks(args.out, blocks, site, fmt, {
        "valid_time_ns": str(pile.valid_time_ns), "known_time_ns": str(pile.known_time_ns)})
    return _report(args, s, f"wrote {s['path']}: {s['rows']:,} blocks ({fmt}), "
                   f"{s['tonnes']:,.1f} t, EPSG:{site.epsg}")


def cmd_cuts(args: argparse.Namespace) -> int:
    from exports.cuts import write_cuts

    pile, site = _projected(args)
    s = write_cuts(args.out, pile, site)
    cuts = f"{s['cuts']} cut" + ("" if s["cuts"] == 1 else "s")
    return _report(args, s, f"wrote {s['path']}: {cuts}, EPSG:{s['epsg']}")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "export", help="surfaces, meshes, block models and cuts for mine planning and GIS",
        description="Write a pile as of valid time V as known at K in the site's mine grid: "
        "its surfaces as GeoTIFF, its top surface as a DXF mesh with contours, its voxel "
        "block model as CSV or Parquet, its cuts as GeoJSON.")
    sub = p.add_subparsers(dest="what", metavar="WHAT", required=True)
    jobs = (("surfaces", cmd_surfaces, "the ground, each deposit's top and the top surface "
             "as the bands of one GeoTIFF", "GeoTIFF file to write"),
            ("mesh", cmd_mesh, "the top surface as a DXF polyface mesh, with contours",
             "DXF file to write"),
            ("blocks", cmd_blocks, "the voxel block model as CSV or Parquet",
             "CSV or Parquet file to write (.parquet: Parquet)"),
            ("cuts", cmd_cuts, "each cut's footprint and grade as GeoJSON",
             "GeoJSON file to write"))
    for name, func, summary, out_help in jobs:
        q = sub.add_parser(name, help=summary, description=summary[0].upper() + summary[1:]
                           + ", in the site's mine grid.")
        add_ledger(q, help="opened read-only; or a head office's ledgers with --site")
        q.add_argument("--site", help="the site whose mirror to read in a head office's "
                       "--ledger")
        q.add_argument("--pile", required=True, help="pile id")
        add_bitemporal(q)
        q.add_argument("--snapshots", metavar="PATH",
                       help="a snapshot file to start from (DuckDB)")
        q.add_argument("--crs", type=epsg_code, metavar="EPSG",
                       help="the mine grid's projected CRS (default: the one the site "
                       "declares)")
        add_out(q, help=out_help, required=True)
        q.add_argument("--json", action="store_true", help="the summary as JSON")
        if name == "mesh":
            q.add_argument("--contour-m", type=float, default=1.0, metavar="M",
                           help="contour interval, metres (default 1)")
            q.add_argument("--max-vertices", type=int, default=32_767, metavar="N",
                           help="the most vertices of the mesh (default 32767, a "
                           "polyface's limit); the mesh skips cells to stay within it")
        if name == "blocks":
            q.add_argument("--format", choices=("csv", "parquet"),
                           help="default: from --out's suffix (.parquet, else CSV)")
        q.set_defaults(func=func)

