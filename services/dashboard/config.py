"""The dashboard's options: the :class:`Config` shared by the live service and the offline
renderer, its defaults, and the command-line arguments of ``stockpile service dashboard``
(:func:`add_arguments`, :func:`config_from_args`) plus those both commands share
(:func:`add_common_arguments`; durations through common.options.add_duration).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

from common.options import add_duration, add_out
from services.service import DEFAULT_SITE, LIVE_REORDER_S, ZenohOptions

SERVICE = "dashboard"
APP_ID = "stockpile-dashboard"
DEFAULT_EVERY_S = 300.0
DEFAULT_UPDATE_PERIOD_S = 1.0
DEFAULT_REORDER_S = LIVE_REORDER_S   # the localizer's smoothed poses come late
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
DEFAULT_DELTA_PP = 0.1
#: records per read from the ledger service (offline reads four times as many at once)
READ_CHUNK = 5_000


@dataclass
class Config:
    """Dashboard options (live service and offline renderer).

    Attributes
    ----------
    pile_id : str or None
        The first (or only) pile of :attr:`piles` (offline: None = the only pile the
        ledger declares).  Given alone it is the one pile; given with ``piles`` it must be
        their first.
    piles : tuple of str
        The piles shown, one :class:`~services.dashboard.core.Dashboard` each (own fold,
        tracker and update cadence) on one recording, fed the records read once
        (``--pile`` repeated).  Entity paths: with one pile they are the paths of the
        package docstring (``/site/...``, ``/series/...``, ``/log``, ``/cuts/table``,
        ...); with several, every entity of a pile, without exception, is under
        ``/piles/<id>`` (:func:`services.dashboard.recorder.entity_prefix`: ``<id>``
        escaped as one entity-path part), e.g. ``/piles/A/site/pile/surface/Fe``,
        ``/piles/A/series/pile/tonnes_t/known_then``, ``/piles/A/log``,
        ``/piles/A/cuts/table``, ``/piles/A/status``; lines about the whole ledger
        (gaps, quarantined input) go to every pile's log, and the blueprint has one tab
        per pile.
    serve : bool
        Host a gRPC server and the web viewer on loopback.
    rrd : str or None
        Archive the stream to this .rrd file.
    grpc_port, web_port : int
        Ports of the gRPC server and of the web viewer (``--serve``).
    every_s : float
        Valid-time seconds between history points during catch-up / offline (and between
        kept history points live).
    update_period_s : float
        Live: shortest wall time between two updates.
    analyte : str
        Analyte of the voxels' colours and the surface shown by default.
    layers : bool
        Also log the deposit boundaries (cross-sections).
    layer_step_m : float
        Distance between layer cross-sections along the pile (m).
    delta_threshold_pp : float
        Reconciliation deltas (grade as known now vs before) logged above this (pp).
    reorder_s : float
        The live fold's reorder window (site seconds).
    max_mesh_vertices : int
        Cap on the surface mesh's vertices (the mesh coarsens beyond it).
    max_voxels : int
        Cap on the voxel points of an update (voxels merge 2 x 2 x 2 ... beyond it).
    geometry_period_s : float
        Live: shortest wall time between two redraws of the surface and voxels (a cut or
        an assay redraws at once).
    plan_machine : str or None
        Offline: also plan the next bench of this bucket-wheel reclaimer at the end
        (``stockpile plan reclaim``) and show its cuts as footprints coloured by predicted
        grade (``/site/plan``, ``/plan/table``).
    plan_cuts : int
        Cuts in that bench.
    """

    pile_id: str | None = None
    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    serve: bool = False
    rrd: str | None = None
    grpc_port: int = DEFAULT_GRPC_PORT
    web_port: int = DEFAULT_WEB_PORT
    every_s: float = DEFAULT_EVERY_S
    update_period_s: float = DEFAULT_UPDATE_PERIOD_S
    analyte: str = "Fe"
    layers: bool = False
    layer_step_m: float = 5.0
    delta_threshold_pp: float = DEFAULT_DELTA_PP
    reorder_s: float = DEFAULT_REORDER_S
    max_mesh_vertices: int = 16_000
    max_voxels: int = 60_000
    geometry_period_s: float = 5.0
    status_period_s: float = 5.0
    plan_machine: str | None = None
    plan_cuts: int = 10
    piles: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        piles = tuple(self.piles) or ((self.pile_id,) if self.pile_id is not None else ())
        if self.piles and self.pile_id is not None and self.pile_id != piles[0]:
            raise ValueError(f"pile_id {self.pile_id!r} is not the first of piles {piles}")
        for i, pile in enumerate(piles):
            if not isinstance(pile, str) or not pile.strip():
                raise ValueError("--pile must name a pile")
            if pile in piles[:i]:
                raise ValueError(f"--pile {pile} is given twice")
        self.piles = piles
        self.pile_id = piles[0] if piles else None
        if self.every_s <= 0:
            raise ValueError("--every must be positive")
        if self.update_period_s < 0 or self.reorder_s < 0 or self.geometry_period_s < 0:
            raise ValueError("--update-period-s, --geometry-period-s and --reorder-s must be "
                             ">= 0")
        if self.layer_step_m <= 0:
            raise ValueError("--layer-step-m must be positive")
        if self.delta_threshold_pp < 0:
            raise ValueError("--delta-threshold-pp must be >= 0")
        if self.plan_cuts < 1:
            raise ValueError("--plan-cuts must be >= 1")
        for name in ("grpc_port", "web_port"):
            if not 0 < int(getattr(self, name)) < 65536:
                raise ValueError(f"--{name.replace('_', '-')} must be a TCP port")


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    """The options ``stockpile service dashboard`` and ``stockpile dashboard`` share."""
    parser.add_argument("--serve", action="store_true",
                        help="serve the Rerun web viewer and a gRPC server on loopback")
    add_out(parser, metavar="PATH", deprecated=("--rrd",),
            help="archive the stream to this Rerun recording (.rrd) file")
    parser.add_argument("--grpc-port", type=int, default=DEFAULT_GRPC_PORT,
                        help="gRPC port with --serve (default %(default)s)")
    parser.add_argument("--web-port", type=int, default=DEFAULT_WEB_PORT,
                        help="web viewer port with --serve (default %(default)s)")
    parser.add_argument("--analyte", default="Fe",
                        help="analyte of the voxel colours and the default surface "
                             "(default %(default)s)")
    parser.add_argument("--layers", action="store_true",
                        help="also log the deposit boundaries (cross-sections)")
    parser.add_argument("--layer-step-m", type=float, default=5.0,
                        help="distance between layer cross-sections, m (default %(default)s)")
    parser.add_argument("--delta-threshold-pp", type=float, default=DEFAULT_DELTA_PP,
                        help="log reconciliation deltas above this, percentage points "
                             "(default %(default)s)")
    parser.add_argument("--reorder-s", type=float, default=DEFAULT_REORDER_S,
                        help="site seconds of reordering before a late geometry event forces "
                             "a rebuild (default %(default)s)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``stockpile service dashboard`` options (the shared ones are added by service_cli)."""
    parser.add_argument("--pile", dest="piles", action="append", required=True,
                        metavar="PILE_ID",
                        help="pile id to show; repeat it to show several piles in one "
                        "recording, each under /piles/<id> (one pile: the usual paths)")
    add_common_arguments(parser)
    add_duration(parser, "--every", default=DEFAULT_EVERY_S,
                 help="valid (site) time between history points while catching up, with a "
                 "unit (default 5min)")
    parser.add_argument("--update-period-s", type=float, default=DEFAULT_UPDATE_PERIOD_S,
                        help="shortest wall time between live updates (default %(default)s)")
    parser.add_argument("--geometry-period-s", type=float, default=5.0,
                        help="shortest wall time between live redraws of the surface and "
                        "voxels; a cut or an assay redraws at once (default %(default)s)")


def config_from_args(args: argparse.Namespace) -> Config:
    """The live service's :class:`Config` from its parsed arguments."""
    return Config(piles=tuple(args.piles), site=args.site, zenoh=ZenohOptions.from_args(args),
                  serve=args.serve, rrd=args.out, grpc_port=args.grpc_port,
                  web_port=args.web_port, every_s=args.every,
                  update_period_s=args.update_period_s,
                  geometry_period_s=args.geometry_period_s, analyte=args.analyte,
                  layers=args.layers, layer_step_m=args.layer_step_m,
                  delta_threshold_pp=args.delta_threshold_pp, reorder_s=args.reorder_s,
                  status_period_s=args.status_period)
