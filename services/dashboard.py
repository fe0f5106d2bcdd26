"""The operators' Rerun dashboard: live (``stockpile service dashboard``) and offline.

``stockpile service dashboard --pile ID [--serve] [--rrd PATH]`` follows the ledger
service over Zenoh exactly like the projector service (a catch-up read of everything
committed, then every committed head; :class:`services.projector_service.LiveProjection`
folds it) and logs the pile to Rerun: ``--serve`` hosts a gRPC server on loopback and
the Rerun web viewer for operators' browsers, ``--rrd`` archives the same stream to a
file.  ``stockpile dashboard --ledger PATH --rrd OUT`` renders a finished ledger
offline through the same code (records in global order, as the live service would
have seen them).

Timelines come from the data, never the wall clock: ``valid_time`` (timestamp, the
pile's valid time V of the update) and ``ledger_seq`` (sequence, the ledger's global
seq the update includes, so K).  Each update is the pile as of V as known at K, with
``V = max(K, newest valid time read)`` and the update taken at a recorded-time boundary
during catch-up and offline, so it equals ``project(store, pile, V, K)``.

Entities (numbers carry their units in the path):

``/site``                          right-handed, z up (site ENU, metres)
``/site/pile/surface/<analyte>``   Mesh3D of the top surface (one vertex per voxel column),
                                   coloured by the grade of the top voxel (blue low, red
                                   high); one entity per analyte, Fe shown by default
``/site/pile/voxels``              Points3D, one per non-empty voxel, coloured by
                                   ``--analyte``, radius grows with its tonnes (hidden
                                   by default in the blueprint)
``/site/pile/layers``              LineStrips3D, deposit boundaries in cross-sections
                                   (``--layers``), coloured by lot
``/site/machines/<id>``            LineStrips3D: rail, slew tower, boom, wheel, from the
                                   latest ``<id>/wheel`` (or ``<id>/scanner`` through the
                                   declared mount) ``frame_transform`` and the kinematics
``/site/scan``                     Points3D, the latest scan georeferenced
``/site/cuts``                     LineStrips3D, each reclaim cut's footprint at its floor
``/site/plan``                     LineStrips3D, offline with ``--plan-machine``: the next
                                   bench's planned cuts, footprints at their floor coloured by
                                   predicted grade (``/plan/table``: the same as a table)
``/series/pile/tonnes_t/{known_then,known_now}``, ``/series/pile/grade_pct/<A>/...``,
``/series/pile/assayed_fraction/...``, ``/series/pile/volume_m3``: Scalars
``/series/cuts/tonnes_t/{geometry,belt_scale}``, ``/series/cuts/grade_pct/<A>/{at_end,
known_now}``, ``/series/cuts/assayed_fraction/{at_end,known_now}``: one point per cut at
its end time
``/log``                           TextLog: lots, passes, cuts, assay arrivals (lateness),
                                   superseded assays, reconciliation deltas above
                                   ``--delta-threshold-pp``, gaps, quarantined input
``/cuts/table``, ``/status``, ``/legend``: TextDocuments (markdown), latest only

"As known then" is logged once per update.  "As known now" is re-evaluated from a
compact inventory of each history point (volume per lot and deposition second) with the
assays known at the newest K: offline it is logged once, at the end, as known at the
ledger's head; live it is logged with each update and re-logged for past points when a
late assay revises them (the newest row at a valid time is the current figure).
Only the latest state of each 3D entity is sent, and only when it changed.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from services.service import DEFAULT_SITE, Inbox, Stopper, ZenohOptions

SERVICE = "dashboard"
APP_ID = "stockpile-dashboard"
S = 1_000_000_000
DEFAULT_EVERY_S = 300.0
DEFAULT_UPDATE_PERIOD_S = 1.0
DEFAULT_REORDER_S = 5.0
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
DEFAULT_DELTA_PP = 0.1
READ_CHUNK = 5_000
#: bins of deposition time in a history point's inventory (grades join per bin), ns
INVENTORY_BIN_NS = 1_000_000_000
MAX_HISTORY_POINTS = 20_000
GREY = (150, 150, 150)

__all__ = ["Config", "add_arguments", "config_from_args", "main", "render_ledger", "register",
           "Dashboard", "RenderResult", "blueprint"]


# -- configuration --------------------------------------------------------------------------


@dataclass
class Config:
    """Dashboard options (live service and offline renderer).

    Attributes
    ----------
    pile_id : str or None
        The pile (offline: None = the only pile the ledger declares).
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

    def __post_init__(self) -> None:
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


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--serve", action="store_true",
                        help="serve the Rerun web viewer and a gRPC server on loopback")
    parser.add_argument("--rrd", metavar="PATH", help="archive the stream to this .rrd file")
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
    parser.add_argument("--pile", dest="pile_id", required=True, help="pile id to show")
    _add_common(parser)
    parser.add_argument("--every", default="5min", metavar="DURATION",
                        help="valid time between history points while catching up "
                        "(default %(default)s)")
    parser.add_argument("--update-period-s", type=float, default=DEFAULT_UPDATE_PERIOD_S,
                        help="shortest wall time between live updates (default %(default)s)")
    parser.add_argument("--geometry-period-s", type=float, default=5.0,
                        help="shortest wall time between live redraws of the surface and "
                        "voxels; a cut or an assay redraws at once (default %(default)s)")


def config_from_args(args: argparse.Namespace) -> Config:
    return Config(pile_id=args.pile_id, site=args.site, zenoh=ZenohOptions.from_args(args),
                  serve=args.serve, rrd=args.rrd, grpc_port=args.grpc_port,
                  web_port=args.web_port, every_s=_duration_s(args.every),
                  update_period_s=args.update_period_s,
                  geometry_period_s=args.geometry_period_s, analyte=args.analyte,
                  layers=args.layers, layer_step_m=args.layer_step_m,
                  delta_threshold_pp=args.delta_threshold_pp, reorder_s=args.reorder_s,
                  status_period_s=args.status_period)


# -- small pure helpers ---------------------------------------------------------------------

_ANCHORS = np.array([[49, 54, 149], [69, 117, 180], [116, 173, 209], [171, 217, 233],
                     [254, 224, 144], [253, 174, 97], [244, 109, 67], [215, 48, 39]], float)


def colour_map(values, lo: float, hi: float) -> np.ndarray:
    """Values -> RGB uint8 (n, 3): blue at ``lo``, red at ``hi``; NaN grey."""
    v = np.asarray(values, np.float64)
    out = np.empty(v.shape + (3,), np.uint8)
    ok = np.isfinite(v)
    span = hi - lo if hi > lo else 1.0
    t = np.clip((v[ok] - lo) / span, 0.0, 1.0) * (len(_ANCHORS) - 1)
    i = np.minimum(t.astype(int), len(_ANCHORS) - 2)
    f = (t - i)[:, None]
    out[ok] = np.round(_ANCHORS[i] * (1 - f) + _ANCHORS[i + 1] * f).astype(np.uint8)
    out[~ok] = GREY
    return out


def lot_colour(lot_id: str) -> tuple[int, int, int]:
    """A stable colour per lot id."""
    import zlib

    h = zlib.crc32(lot_id.encode()) & 0xFFFFFF
    return (64 + (h & 0x7F), 64 + ((h >> 8) & 0x7F), 64 + ((h >> 16) & 0x7F))


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def wheel_from_scanner(position, quaternion_xyzw, mount) -> tuple[np.ndarray, np.ndarray]:
    """The wheel frame's pose (centre, rotation) from the scanner's site pose and the
    declared mount ``(R_wheel_scanner, t_wheel_scanner)``: the inverse of
    ``p_scanner = c + R_wheel t_mount``, ``R_scanner = R_wheel R_mount``."""
    r_site_scanner = _quat_matrix(quaternion_xyzw)
    r_wheel_scanner, t_wheel_scanner = mount
    r_site_wheel = r_site_scanner @ np.asarray(r_wheel_scanner).T
    return np.asarray(position, float) - r_site_wheel @ np.asarray(t_wheel_scanner), r_site_wheel


def joints_from_wheel_pose(machine, centre, rotation: np.ndarray) -> tuple[float, float, float]:
    """(travel m, slew rad, luff rad) from the wheel frame's pose (DOMAIN.md §3).

    The wheel frame's x axis is the boom's horizontal direction ``(sin slew, cos slew, 0)``.
    """
    c = np.asarray(centre, float)
    s = (c[2] - machine.rail_z_m - machine.pivot_height_m) / machine.l5_m
    luff = math.asin(min(1.0, max(-1.0, s)))
    rho = machine.l4_m + machine.l5_m * math.cos(luff)
    slew = math.atan2(rotation[0, 0], rotation[1, 0])
    travel = c[1] - rho * math.cos(slew)
    return travel, slew, luff


def machine_strips(machine, travel_m: float, slew_rad: float, luff_rad: float,
                   wheel_radius_m: float) -> list[np.ndarray]:
    """Line strips of a reclaimer: slew tower, pivot arm, boom, wheel (site frame, m)."""
    base = np.array([machine.rail_x_m, travel_m, machine.rail_z_m])
    top = base + [0.0, 0.0, machine.pivot_height_m]
    d = np.array([math.sin(slew_rad), math.cos(slew_rad), 0.0])
    pivot = top + machine.l4_m * d
    centre = pivot + machine.l5_m * (math.cos(luff_rad) * d + [0.0, 0.0, math.sin(luff_rad)])
    a = np.linspace(0.0, 2 * math.pi, 33)
    up = np.array([0.0, 0.0, 1.0])
    wheel = centre + wheel_radius_m * (np.cos(a)[:, None] * d + np.sin(a)[:, None] * up)
    spokes = np.array([centre + wheel_radius_m * d, centre - wheel_radius_m * d, centre,
                       centre + wheel_radius_m * up, centre - wheel_radius_m * up])
    return [np.array([base, top, pivot]), np.array([pivot, centre]), wheel, spokes]


def cut_outline(machine, travel_m: float, luff_rad: float, slew_start_rad: float,
                slew_end_rad: float, n: int = 24) -> np.ndarray:
    """Closed outline of a cut's swept footprint at the envelope's bottom (site frame, m)."""
    rho = machine.l4_m + machine.l5_m * math.cos(luff_rad)
    c_z = machine.rail_z_m + machine.pivot_height_m + machine.l5_m * math.sin(luff_rad)
    hw = machine.half_width_m
    lo, hi = sorted((slew_start_rad, slew_end_rad))
    if hi - lo >= 2 * math.pi:
        lo, hi = 0.0, 2 * math.pi
    a = np.linspace(lo, hi, n)
    z = c_z - machine.cutting_radius_m
    out = [(machine.rail_x_m + r * np.sin(a), travel_m + r * np.cos(a))
           for r in (rho + hw, max(rho - hw, 0.0))]
    xs = np.concatenate([out[0][0], out[1][0][::-1], out[0][0][:1]])
    ys = np.concatenate([out[0][1], out[1][1][::-1], out[0][1][:1]])
    return np.column_stack([xs, ys, np.full(xs.size, z)])


def inventory(pile_state) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """A history point's material: per deposit ``(lot, mean times ns, volumes m3)`` per
    :data:`INVENTORY_BIN_NS` of deposition time (the grade join needs nothing else)."""
    state = pile_state.state
    if state.pile is None or state.stack is None:
        return []
    stack = state.stack
    area = state.pile.geometry.cell_area_m2
    out = []
    for k in range(1, stack.n_deposits + 1):
        thick = stack.thickness(k)
        mask = thick > 0
        if not mask.any():
            continue
        times = stack.deposition_time_ns(k)[mask]
        vol = thick[mask] * area
        ok = np.isfinite(times)
        key = np.where(ok, np.floor(np.where(ok, times, 0.0) / INVENTORY_BIN_NS), -1.0)
        uniq, inv = np.unique(key, return_inverse=True)
        vsum = np.bincount(inv, weights=vol, minlength=uniq.size)
        tsum = np.bincount(inv, weights=np.where(ok, times, 0.0) * vol, minlength=uniq.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_t = np.where(uniq >= 0, tsum / vsum, np.nan)
        out.append((stack.info(k).lot_id, mean_t, vsum))
    return out


def join_inventory(inv, lots: dict, assays: list, known_ns: int, analytes: tuple,
                   density_default: float) -> tuple[float, dict[str, float], float]:
    """``(tonnes, grade %, assayed fraction)`` of an inventory as known at K (the join of
    :func:`projector.query.summarise`, per deposition-time bin)."""
    from projector.query import GradeJoin

    join = GradeJoin(lots, assays, int(known_ns), density_default, tuple(analytes))
    tonnes, assayed_t, graded_t = 0.0, 0.0, 0.0
    sums = np.zeros(len(analytes))
    for lot, times, vols in inv:
        t, s, a_t, g_t = join.material(lot, times, vols)
        tonnes += t
        sums += s
        assayed_t += a_t
        graded_t += g_t
    grade = ({a: float(s / graded_t) for a, s in zip(analytes, sums)} if graded_t > 0
             else {a: math.nan for a in analytes})
    return tonnes, grade, (assayed_t / tonnes if tonnes > 0 else 0.0)


def blueprint(analytes: Iterable[str], analyte: str = "Fe", *, layers: bool = False,
              pile: tuple[float, float, float, float, float] | None = None):
    """The default layout: 3D pile | time series and logs.

    ``pile = (origin_x_m, origin_y_m, width_m, length_m, ground_z_m)`` aims the 3D camera at
    the declared footprint (from the far side of the rail, looking down on the pile).
    """
    import rerun.blueprint as rrb

    eye = None
    if pile is not None:
        x0, y0, width, length, z0 = pile
        xc, yc, size = x0 + width / 2, y0 + length / 2, max(width, length)
        eye = rrb.EyeControls3D(position=[xc + 0.95 * size, yc - 1.15 * size, z0 + 0.8 * size],
                                look_target=[xc, yc, z0 + 2.0], eye_up=[0.0, 0.0, 1.0])
    everything = rrb.TimeAxis(view_range=rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                                       end=rrb.TimeRangeBoundary.infinite()))

    def series(name: str, origin: str):
        return rrb.TimeSeriesView(name=name, origin=origin, axis_x=everything)

    analytes = list(analytes) or [analyte]
    shown = analyte if analyte in analytes else analytes[0]
    hidden = {f"/site/pile/surface/{a}": rrb.EntityBehavior(visible=False)
              for a in analytes if a != shown}
    hidden["/site/pile/voxels"] = rrb.EntityBehavior(visible=False)
    if not layers:
        hidden["/site/pile/layers"] = rrb.EntityBehavior(visible=False)
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(name=f"Pile: surface coloured by {shown} (blue low, red high)",
                                  origin="/site", overrides=hidden, eye_controls=eye),
                rrb.Tabs(rrb.TextLogView(name="Log", origin="/log"),
                         rrb.TextDocumentView(name="Cuts", origin="/cuts"),
                         rrb.TextDocumentView(name="Status", origin="/status"),
                         rrb.TextDocumentView(name="Legend", origin="/legend")),
                row_shares=[3, 1]),
            rrb.Vertical(
                series("Pile tonnes (t)", "/series/pile/tonnes_t"),
                series(f"Pile {shown} (%)", f"/series/pile/grade_pct/{shown}"),
                series("Cuts: tonnes (t), geometry vs belt scale", "/series/cuts/tonnes_t"),
                series(f"Cuts: {shown} (%) at the end vs known now",
                       f"/series/cuts/grade_pct/{shown}"),
                series("Assayed fraction", "/series/pile/assayed_fraction"),
            ),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="valid_time"),
        collapse_panels=True)


# -- the dashboard: records in, Rerun out ---------------------------------------------------


@dataclass
class _Point:
    valid_ns: int
    seq: int
    inventory: list
    density_default: float
    now: tuple[float, dict[str, float], float]
    now_logged: bool = False


@dataclass
class _Machine:
    machine_id: str
    reclaimer: Any
    wheel_radius_m: float
    mount: tuple[np.ndarray, np.ndarray] | None   # scanner in wheel: (R, t)
    pose: tuple[int, np.ndarray, np.ndarray] | None = None   # (t, centre, R) of the wheel
    logged_pose_ns: int | None = None
    rail_logged: bool = False


class Dashboard:
    """Takes ledger records in global order and logs the pile to a Rerun recording.

    Parameters
    ----------
    rec : rerun.RecordingStream
    pile_id : str
    config : Config
    """

    def __init__(self, rec, pile_id: str, config: Config, *, offline: bool = False) -> None:
        from services.projector_service import LiveProjection

        self.rec, self.pile_id, self.config = rec, pile_id, config
        self.projection = LiveProjection(pile_id, int(config.reorder_s * S))
        self.max_valid_ns = -(2 ** 62)
        self.known_ns = -(2 ** 62)
        self.seq = -1
        self.updates = 0
        self.rebuilds = 0
        self.last_update_valid_ns: int | None = None
        self.last_update_seq = -1
        #: live: "as known now" logged with each update and re-logged when revised; before
        #: (catch-up, offline) it waits for :meth:`flush_known_now`
        self.live = False
        self._update_v: int | None = None
        self._mesh_shape: tuple[int, int] | None = None
        #: offline the blueprint (with the camera on the pile) goes with the sinks, once;
        #: live it is re-sent when the pile is first known or analytes are added
        self.offline = offline
        self._camera_set = offline
        self._mesh_analytes: set[str] = set()
        self._last_3d_wall = -math.inf
        self.last_point_valid_ns: int | None = None
        self.points: list[_Point] = []
        self.machines: dict[str, _Machine] = {}
        self.scanner_poses: dict[str, deque] = {}
        self.latest_scan = None
        self.cut_msgs: dict[str, Any] = {}
        self.cuts_logged: dict[str, dict[str, float]] = {}   # cut -> grade as last logged now
        self.cut_at_end: dict[str, Any] = {}
        self.assays_by_id: dict[str, Any] = {}
        self.grade_range: dict[str, list[float]] = {}
        self.reasons: set[str] = set()
        self.assay_version = 0
        self._joined_version = 0
        self._cuts_sig = None
        self._last_state = None
        self._blueprint_analytes: tuple[str, ...] = ()
        self._geometry_dirty = True
        rec.log("/site", _rr().ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    # -- time ---------------------------------------------------------------------------

    @property
    def valid_ns(self) -> int:
        """The newest valid time read, or K if later (an update's V is at least this)."""
        return max(self.max_valid_ns, self.known_ns)

    def _at(self, valid_ns: int | None = None, seq: int | None = None) -> None:
        if valid_ns is None:
            valid_ns = self._update_v if self._update_v is not None else self.valid_ns
        self.rec.set_time("valid_time", timestamp=np.datetime64(int(valid_ns), "ns"))
        self.rec.set_time("ledger_seq", sequence=int(self.seq if seq is None else seq))

    def log_text(self, text: str, level: str = "INFO", *, valid_ns: int | None = None,
                 seq: int | None = None) -> None:
        rr = _rr()
        self._at(valid_ns, seq)
        self.rec.log("/log", rr.TextLog(text, level=getattr(rr.TextLogLevel, level)))

    # -- records ------------------------------------------------------------------------

    def add(self, record) -> None:
        """Take one committed record (global order)."""
        from schemas.events import decode_payload

        self.projection.add(record)
        self.seq = max(self.seq, record.global_seq)
        self.known_ns = max(self.known_ns, record.recorded_time_ns)
        self.max_valid_ns = max(self.max_valid_ns, record.valid_time_ns)
        kind = record.type
        if kind in ("scan", "frame_transform", "stack_started", "stack_ended",
                    "reclaim_cut", "pile_declared", "machine_declared"):
            self._geometry_dirty = True
        if kind == "frame_transform":
            self._on_pose(record, decode_payload(kind, record.payload))
        elif kind == "scan":
            self.latest_scan = record   # decoded only if it is still the latest at an update
        elif kind == "machine_declared":
            self._on_machine(decode_payload(kind, record.payload))
        elif kind == "reclaim_cut":
            msg = decode_payload(kind, record.payload)
            if msg.pile_id == self.pile_id:
                self.cut_msgs[msg.cut_id] = msg
                self.reasons.add("cut")
                self.log_text(f"cut {msg.cut_id} (bench {msg.bench_id}) ended: belt scale "
                              f"{msg.tonnes:,.1f} t", seq=record.global_seq)
        elif kind == "assay":
            self._on_assay(record, decode_payload(kind, record.payload))
        elif kind == "lot_declared":
            msg = decode_payload(kind, record.payload)
            self._widen_range(dict(msg.planned_grade))
            self.assay_version += 1
            self.reasons.add("lot")
            self.log_text(f"lot {msg.lot_id} declared: {msg.planned_tonnes:,.0f} t planned, "
                          + ", ".join(f"{k} {v:.2f} %" for k, v in msg.planned_grade.items()),
                          seq=record.global_seq)
        elif kind in ("stack_started", "stack_ended"):
            msg = decode_payload(kind, record.payload)
            if msg.pile_id == self.pile_id:
                self.reasons.add("pass")
                text = (f"stacking pass {msg.pass_id} started (lot {msg.lot_id})"
                        if kind == "stack_started"
                        else f"stacking pass {msg.pass_id} ended: belt scale {msg.tonnes:,.1f} t")
                self.log_text(text, seq=record.global_seq)

    def _widen_range(self, grade: dict[str, float]) -> None:
        for a, v in grade.items():
            if math.isfinite(v):
                r = self.grade_range.setdefault(a, [v, v])
                r[0], r[1] = min(r[0], v), max(r[1], v)

    def _on_assay(self, record, msg) -> None:
        from projector.grades import coerce_time_ns

        self.assay_version += 1
        self.reasons.add("assay")
        self._widen_range(dict(msg.analytes))
        late_h = (record.recorded_time_ns - coerce_time_ns(msg.window_end)) / (3600 * S)
        status = {1: "PROVISIONAL", 2: "FINAL"}.get(int(msg.status), str(msg.status))
        unknown = "unknown_lot" in (getattr(record, "flags", ()) or ())
        self.log_text(
            f"assay {msg.assay_id} ({status}) for lot {msg.lot_id} from {msg.lab_id or record.source}"
            f" arrived {late_h:.2f} h after its window: "
            + ", ".join(f"{k} {v:.2f} %" for k, v in msg.analytes.items())
            + (" (lot not declared)" if unknown else ""),
            "WARN" if unknown else "INFO", seq=record.global_seq)
        if msg.supersedes:
            old = self.assays_by_id.get(msg.supersedes)
            change = ""
            if old is not None:
                change = ": " + ", ".join(
                    f"{k} {old.analytes[k]:.2f} -> {v:.2f} %" for k, v in msg.analytes.items()
                    if k in old.analytes and abs(v - old.analytes[k]) > 1e-12)
            self.log_text(f"assay {msg.supersedes} superseded by {msg.assay_id} ({status})"
                          + change, "WARN", seq=record.global_seq)
        self.assays_by_id[msg.assay_id] = msg

    def _on_machine(self, msg) -> None:
        from projector.envelope import Reclaimer

        if int(msg.kind) != 1:   # BUCKET_WHEEL_RECLAIMER
            return
        mount = None
        if msg.HasField("scanner"):
            t = msg.scanner.translation
            r = msg.scanner.rotation
            mount = (_quat_matrix((r.x, r.y, r.z, r.w)), np.array([t.x, t.y, t.z]))
        self.machines[msg.machine_id] = _Machine(msg.machine_id, Reclaimer.from_message(msg),
                                                 float(msg.wheel_radius_m) or 0.0, mount)

    def _on_pose(self, record, msg) -> None:
        from projector.grades import coerce_time_ns

        if msg.parent_frame_id != "site" or "/" not in msg.child_frame_id:
            return
        machine_id, frame = msg.child_frame_id.split("/", 1)
        t = coerce_time_ns(msg.timestamp)
        p = np.array([msg.translation.x, msg.translation.y, msg.translation.z])
        q = (msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w)
        if frame == "scanner":
            poses = self.scanner_poses.setdefault(machine_id, deque(maxlen=64))
            poses.append((t, p, q))
        m = self.machines.get(machine_id)
        if m is None:
            return
        if frame == "wheel":
            pose = (t, p, _quat_matrix(q))
        elif frame == "scanner" and m.mount is not None:
            centre, r_site_wheel = wheel_from_scanner(p, q, m.mount)
            pose = (t, centre, r_site_wheel)
        else:
            return
        if m.pose is None or pose[0] >= m.pose[0]:
            m.pose = pose

    # -- updates ------------------------------------------------------------------------

    def due(self, *, boundary: bool) -> bool:
        """Whether an update is due (at a recorded-time boundary during catch-up/offline)."""
        if not boundary or self.seq < 0 or self.seq == self.last_update_seq:
            return False
        if self.reasons:
            return True
        return (self.last_update_valid_ns is None
                or self.valid_ns - self.last_update_valid_ns >= int(self.config.every_s * S))

    def next_valid_ns(self) -> int:
        """V of the next update: :attr:`valid_ns`, or 1 ns after the last update's V when
        the ledger grew without the valid time advancing (still the same as-of set:
        every record read has valid time <= V)."""
        v = self.valid_ns
        if self.last_update_valid_ns is not None:
            v = max(v, self.last_update_valid_ns + 1)
        return v

    def update(self) -> bool:
        """Log the pile as of V as known at K; returns False if there was nothing to log."""
        if self.seq < 0 or self.seq == self.last_update_seq:
            return False
        self.projection.advance()
        state = self.projection.summary()
        if state.geometry is None:
            self.reasons.clear()
            return False
        v = self.next_valid_ns()
        self._update_v = v
        self.updates += 1
        if not self._camera_set:
            self._ensure_styles(state.analytes)
            self._send_blueprint(make_active=True)   # the camera on the pile, once
            self._camera_set = True
        self._at(v, self.seq)
        keep_point = (not self.live or self.last_point_valid_ns is None or bool(self.reasons)
                      or v - self.last_point_valid_ns >= int(self.config.every_s * S))
        self._log_totals(state, now=self.live)
        if keep_point:
            self._keep_point(state, v)
        grades_changed = self.assay_version != self._joined_version
        self._log_cuts(state)
        redraw = self._geometry_dirty or grades_changed
        if (redraw and self.live and not grades_changed and "cut" not in self.reasons
                and time.monotonic() - self._last_3d_wall < self.config.geometry_period_s):
            redraw = False   # live: the surface and voxels at most every geometry_period_s
        if redraw:
            self._log_pile_3d(state)
            self._geometry_dirty = False
            self._last_3d_wall = time.monotonic()
        self._log_machines()
        self._log_scan()
        self._log_status(state)
        if grades_changed and self.live:
            self._revise_history(state, v)
        self._joined_version = self.assay_version
        self.reasons.clear()
        self.last_update_valid_ns = v
        self.last_update_seq = self.seq
        self._last_state = state
        self._update_v = None
        return True

    def _series(self, path: str, value: float) -> None:
        if value is not None and math.isfinite(value):
            self.rec.log(path, _rr().Scalars(float(value)))

    def _log_figures(self, suffix: str, tonnes: float, grade: dict, assayed: float) -> None:
        self._series(f"/series/pile/tonnes_t/{suffix}", tonnes)
        self._series(f"/series/pile/assayed_fraction/{suffix}", assayed)
        for a, g in grade.items():
            self._series(f"/series/pile/grade_pct/{a}/{suffix}", g)

    def _log_totals(self, state, *, now: bool) -> None:
        self._ensure_styles(state.analytes)
        self._log_figures("known_then", state.tonnes, state.grade, state.assayed_fraction)
        if now:
            self._log_figures("known_now", state.tonnes, state.grade, state.assayed_fraction)
        self._series("/series/pile/volume_m3", state.volume_m3)

    def _ensure_styles(self, analytes) -> None:
        if tuple(analytes) == self._blueprint_analytes or not analytes:
            return
        rr = _rr()
        new = [a for a in analytes if a not in self._blueprint_analytes]
        first = not self._blueprint_analytes
        self._blueprint_analytes = tuple(analytes)
        if first:
            styles = {"/series/pile/tonnes_t/known_then": ("as known then", [90, 160, 255]),
                      "/series/pile/tonnes_t/known_now": ("as known now", [240, 120, 40]),
                      "/series/pile/assayed_fraction/known_then": ("as known then", [90, 160, 255]),
                      "/series/pile/assayed_fraction/known_now": ("as known now", [240, 120, 40]),
                      "/series/cuts/assayed_fraction/at_end": ("cuts at their end", [90, 160, 255]),
                      "/series/cuts/assayed_fraction/known_now": ("cuts known now", [240, 120, 40]),
                      "/series/pile/volume_m3": ("pile volume m3", [200, 200, 200])}
            for path, (name, colour) in styles.items():
                self.rec.log(path, rr.SeriesLines(names=name, colors=[colour]), static=True)
            for path, name, colour in (("/series/cuts/tonnes_t/geometry", "geometry", [240, 120, 40]),
                                       ("/series/cuts/tonnes_t/belt_scale", "belt scale",
                                        [90, 160, 255])):
                self.rec.log(path, rr.SeriesPoints(names=name, colors=[colour],
                                                   marker_sizes=[4.0]), static=True)
        for a in new:
            self.rec.log(f"/series/pile/grade_pct/{a}/known_then",
                         rr.SeriesLines(names=f"{a} % as known then", colors=[[90, 160, 255]]),
                         static=True)
            self.rec.log(f"/series/pile/grade_pct/{a}/known_now",
                         rr.SeriesLines(names=f"{a} % as known now", colors=[[240, 120, 40]]),
                         static=True)
            self.rec.log(f"/series/cuts/grade_pct/{a}/at_end",
                         rr.SeriesPoints(names=f"{a} % at the cut's end", colors=[[90, 160, 255]],
                                         marker_sizes=[4.0]), static=True)
            self.rec.log(f"/series/cuts/grade_pct/{a}/known_now",
                         rr.SeriesPoints(names=f"{a} % known now", colors=[[240, 120, 40]],
                                         marker_sizes=[4.0]), static=True)
        if not first and not self.offline:
            self._send_blueprint(make_active=False)

    def _pile_box(self):
        pile = self.projection.state.pile
        if pile is None:
            return None
        g = pile.geometry
        return (g.origin_x_m, g.origin_y_m, g.length_x_m, g.length_y_m, pile.ground_z_m)

    def _send_blueprint(self, *, make_active: bool) -> None:
        self.rec.send_blueprint(blueprint(self._blueprint_analytes or ("Fe",),
                                          self.config.analyte, layers=self.config.layers,
                                          pile=self._pile_box()),
                                make_active=make_active, make_default=True)

    def _keep_point(self, state, v: int) -> None:
        pile = state.state.pile
        point = _Point(v, self.seq, inventory(state), pile.default_bulk_density_t_m3,
                       (state.tonnes, dict(state.grade), state.assayed_fraction),
                       now_logged=self.live)
        self.points.append(point)
        self.last_point_valid_ns = v
        if len(self.points) > MAX_HISTORY_POINTS:   # thin the older half, keep the newest
            half = len(self.points) // 2
            self.points = self.points[:half:2] + self.points[half:]

    def _revise_history(self, state, v: int) -> int:
        """Live: re-evaluate the kept history points as known now; re-log those that moved."""
        lots, assays = self.projection.lots, self.projection.assays
        changed = 0
        for point in self.points:
            if point.valid_ns >= v:
                continue
            now = join_inventory(point.inventory, lots, assays, self.known_ns, state.analytes,
                                 point.density_default)
            if _same(now, point.now):
                continue
            point.now = now
            changed += 1
            self._at(point.valid_ns, self.seq)
            self._log_figures("known_now", *now)
        if changed:
            self.log_text(f"{changed} past history point(s) revised as known now", "INFO",
                          valid_ns=v)
        return changed

    def flush_known_now(self) -> None:
        """Log "as known now" (at the latest K) for every history point and cut not yet logged
        so (the end of an offline render or of the live catch-up); then go live."""
        state = self._last_state
        if state is not None:
            lots, assays = self.projection.lots, self.projection.assays
            for point in self.points:
                if point.now_logged:
                    continue
                if point.seq == self.last_update_seq and point.valid_ns == self.last_update_valid_ns:
                    now = (state.tonnes, dict(state.grade), state.assayed_fraction)
                else:
                    now = join_inventory(point.inventory, lots, assays, self.known_ns,
                                         state.analytes, point.density_default)
                point.now, point.now_logged = now, True
                self._at(point.valid_ns, self.seq)
                self._log_figures("known_now", *now)
            for cut in state.cuts:
                self._log_cut_now(cut)
        self.live = True

    def _log_cut_now(self, cut) -> None:
        self._at(cut.end_time_ns, self.seq)
        self._series("/series/cuts/assayed_fraction/known_now", cut.assayed_fraction)
        for a, g in cut.grade.items():
            self._series(f"/series/cuts/grade_pct/{a}/known_now", g)

    def _log_cuts(self, state) -> None:
        rr = _rr()
        threshold = self.config.delta_threshold_pp
        rows = []
        for cut in state.cuts:
            grade = dict(cut.grade)
            if cut.cut_id not in self.cut_at_end:
                self.cut_at_end[cut.cut_id] = cut
                self._at(cut.end_time_ns, self.seq)
                self._series("/series/cuts/tonnes_t/geometry", cut.tonnes)
                self._series("/series/cuts/tonnes_t/belt_scale", cut.tonnes_scale)
                self._series("/series/cuts/assayed_fraction/at_end", cut.assayed_fraction)
                for a, g in grade.items():
                    self._series(f"/series/cuts/grade_pct/{a}/at_end", g)
                if self.live:
                    self._log_cut_now(cut)
                self.cuts_logged[cut.cut_id] = grade
            else:
                before = self.cuts_logged[cut.cut_id]
                moved = {a: g - before.get(a, math.nan) for a, g in grade.items()
                         if math.isfinite(g) and math.isfinite(before.get(a, math.nan))
                         and abs(g - before[a]) > 1e-9}
                if moved:
                    if self.live:
                        self._log_cut_now(cut)
                    self.cuts_logged[cut.cut_id] = grade
                    big = {a: d for a, d in moved.items() if abs(d) > threshold}
                    if big:
                        at_end = self.cut_at_end[cut.cut_id].grade
                        self.log_text(
                            f"reconciliation: cut {cut.cut_id} "
                            + ", ".join(f"{a} {before[a]:.2f} -> {grade[a]:.2f} % ({d:+.2f} pp; "
                                        f"at its end {at_end.get(a, math.nan):.2f} %)"
                                        for a, d in big.items())
                            + f", assayed fraction {cut.assayed_fraction:.2f}", "WARN",
                            valid_ns=self.next_valid_ns())
            at_end = self.cut_at_end[cut.cut_id]
            a0 = self.config.analyte if self.config.analyte in grade else next(iter(grade), "")
            rows.append(f"| {cut.cut_id} | {_iso(cut.end_time_ns)} | {cut.tonnes:,.1f} | "
                        f"{cut.tonnes_scale:,.1f} | {at_end.grade.get(a0, math.nan):.2f} | "
                        f"{grade.get(a0, math.nan):.2f} | "
                        f"{grade.get(a0, math.nan) - at_end.grade.get(a0, math.nan):+.2f} | "
                        f"{at_end.assayed_fraction:.2f} / {cut.assayed_fraction:.2f} |")
        v = self.next_valid_ns()
        if rows:
            a0 = self.config.analyte
            self._at(v)
            self.rec.log("/cuts/table", rr.TextDocument(
                f"### Reclaim cuts of pile {self.pile_id} as known at ledger seq {self.seq:,}\n\n"
                f"| cut | ended (UTC) | geometry t | belt scale t | {a0} at end % | {a0} now % "
                f"| d pp | assayed end / now |\n|---|---|---|---|---|---|---|---|\n"
                + "\n".join(rows), media_type=rr.MediaType.MARKDOWN))
        sig = tuple((c.cut_id, round(c.grade.get(self.config.analyte, math.nan), 6))
                    for c in state.cuts)
        if sig != self._cuts_sig and self.cut_msgs:
            self._cuts_sig = sig
            strips, labels, colours = [], [], []
            lo, hi = self._range(self.config.analyte)
            for cut in state.cuts:
                msg = self.cut_msgs.get(cut.cut_id)
                m = self.machines.get(msg.machine_id) if msg is not None else None
                if m is None:
                    continue
                strips.append(cut_outline(m.reclaimer, msg.travel_m, msg.luff_rad,
                                          msg.slew_start_rad, msg.slew_end_rad))
                labels.append(cut.cut_id)
                colours.append(colour_map([cut.grade.get(self.config.analyte, math.nan)],
                                          lo, hi)[0])
            if strips:
                self._at(v)
                self.rec.log("/site/cuts", rr.LineStrips3D(strips, labels=labels, colors=colours,
                                                           radii=0.15))

    def log_plan(self, plan: dict) -> int:
        """Show a reclaim plan (:func:`planner.cli.make_plan`): each planned cut's
        footprint at its floor coloured by its predicted grade, and a table; returns the
        number of cuts shown."""
        rr = _rr()
        m = self.machines.get(plan["machine_id"])
        if m is None or m.reclaimer is None or not plan["cuts"]:
            return 0
        analyte = self.config.analyte
        strips, labels, grades = [], [], []
        for c in plan["cuts"]:
            strips.append(cut_outline(m.reclaimer, c["travel_m"], c["luff_rad"],
                                      c["slew_start_rad"], c["slew_end_rad"]))
            g = c["grade"].get(analyte, math.nan)
            grades.append(g)
            labels.append(f"plan {c['cut']}: {c['tonnes']:,.4g} t, {analyte} {g:.2f} %")
        # the pile's colour scale, widened to the planned grades (none saturates)
        lo, hi = self._range(analyte)
        finite = [g for g in grades if math.isfinite(g)]
        if finite:
            lo, hi = min(lo, *finite), max(hi, *finite)
        self._at(self.next_valid_ns())
        self.rec.log("/site/plan", rr.LineStrips3D(strips, labels=labels,
                                                   colors=colour_map(grades, lo, hi), radii=0.2))
        rows = "\n".join(
            f"| {c['cut']} | {c['travel_m']:.2f} | {math.degrees(c['slew_start_rad']):.1f} -> "
            f"{math.degrees(c['slew_end_rad']):.1f} | {c['tonnes']:,.4g} | "
            f"{c['grade'].get(analyte, math.nan):.2f} | {c['assayed_fraction']:.2f} |"
            for c in plan["cuts"])
        self.rec.log("/plan/table", rr.TextDocument(
            f"### Next bench of pile {self.pile_id} by {plan['machine_id']} (planned)\n\n"
            f"Footprints coloured by predicted {analyte}: {lo:.3f} % blue to {hi:.3f} % red.\n\n"
            f"| cut | travel m | slew deg | tonnes | {analyte} % | assayed |\n"
            f"|---|---|---|---|---|---|\n{rows}", media_type=rr.MediaType.MARKDOWN))
        return len(strips)

    def _range(self, analyte: str) -> tuple[float, float]:
        lo, hi = self.grade_range.get(analyte, (math.nan, math.nan))
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return 0.0, 1.0
        pad = max(0.05 * (hi - lo), 1e-3 * max(abs(hi), 1.0))
        return lo - pad, hi + pad

    def _log_pile_3d(self, state) -> None:
        rr = _rr()
        pile = state.state.pile
        if state.state.stack.n_deposits == 0 or not state.analytes:
            return   # nothing stacked yet
        tonnes, grade, grid = state.voxel_grades()
        nvx, nvy, nvz = tonnes.shape
        m = grid.cells_per_voxel
        surface = state.surface_m
        nx, ny = surface.shape
        step = 1
        while (math.ceil(nvx / step) * math.ceil(nvy / step)) > self.config.max_mesh_vertices:
            step += 1
        k = m * step
        pad_x, pad_y = (-nx) % k, (-ny) % k
        z = np.pad(surface, ((0, pad_x), (0, pad_y)), mode="edge")
        z = z.reshape(z.shape[0] // k, k, z.shape[1] // k, k).mean(axis=(1, 3))
        mx, my = z.shape
        xs = grid.origin_x_m + (np.arange(mx) + 0.5) * k * pile.geometry.cell_m
        ys = grid.origin_y_m + (np.arange(my) + 0.5) * k * pile.geometry.cell_m
        positions = np.column_stack([np.repeat(xs, my), np.tile(ys, mx), z.ravel()])
        ii = (np.arange(mx - 1)[:, None] * my + np.arange(my - 1)[None, :]).ravel()
        tri = np.concatenate([np.column_stack([ii, ii + my, ii + 1]),
                              np.column_stack([ii + 1, ii + my, ii + my + 1])]).astype(np.uint32)
        # the top voxel with material of each voxel column, then per mesh vertex
        has = tonnes > 0
        top = np.where(has.any(axis=2), nvz - 1 - np.argmax(has[:, :, ::-1], axis=2), -1)
        # the mesh's triangles never change for a pile (its grid is fixed): static, once
        new_shape = (mx, my) != self._mesh_shape
        self._mesh_shape = (mx, my)
        self._at()
        for ai, a in enumerate(state.analytes):
            col = np.full((nvx, nvy), np.nan)
            sel = top >= 0
            col[sel] = grade[np.nonzero(sel)[0], np.nonzero(sel)[1], top[sel], ai]
            col = np.pad(col, ((0, (-nvx) % step), (0, (-nvy) % step)), constant_values=np.nan)
            col = col[::step, ::step][:mx, :my]
            lo, hi = self._range(a)
            colours = colour_map(col.ravel(), lo, hi)
            path = f"/site/pile/surface/{a}"
            if new_shape or a not in self._mesh_analytes:
                self.rec.log(path, rr.Mesh3D.from_fields(triangle_indices=tri), static=True)
                self._mesh_analytes.add(a)
            if self._geometry_dirty or new_shape:
                self.rec.log(path, rr.Mesh3D.from_fields(vertex_positions=positions,
                                                         vertex_colors=colours))
            else:   # only the grades moved (an assay): the colours alone
                self.rec.log(path, rr.Mesh3D.from_fields(vertex_colors=colours))
        # voxels: one batched entity coloured by the chosen analyte, radius ~ tonnes^(1/3);
        # a big pile's voxels are merged f x f x f (tonnes summed, grades tonnage-weighted)
        # until at most max_voxels remain, so an update stays a few MB at full scale
        a0 = self.config.analyte if self.config.analyte in state.analytes else (
            state.analytes[0] if state.analytes else None)
        if has.any() and a0 is not None:
            ai = state.analytes.index(a0)
            t_vox = tonnes
            g_vox = np.where(has, grade[..., ai], 0.0)
            f = 1
            while int(np.count_nonzero(t_vox > 0)) > self.config.max_voxels:
                f *= 2
                t_vox, g_vox = _merge_voxels(tonnes, np.where(has, grade[..., ai], 0.0), f)
            ix, iy, iz = np.nonzero(t_vox > 0)
            v = grid.voxel_m * f
            centres = np.column_stack([grid.origin_x_m + (ix + 0.5) * v,
                                       grid.origin_y_m + (iy + 0.5) * v,
                                       grid.z0_m + (iz + 0.5) * v])
            t = t_vox[ix, iy, iz]
            full = v ** 3 * pile.default_bulk_density_t_m3
            radii = 0.5 * v * np.clip(np.cbrt(t / full), 0.15, 1.0)
            lo, hi = self._range(a0)
            self.rec.log("/site/pile/voxels", rr.Points3D(
                centres, colors=colour_map(g_vox[ix, iy, iz], lo, hi), radii=radii))
        else:
            self.rec.log("/site/pile/voxels", rr.Clear(recursive=False))
        if self.config.layers:
            self._log_layers(state)
        legend = "\n".join(f"| {a} | {self._range(a)[0]:.2f} | {self._range(a)[1]:.2f} |"
                           for a in state.analytes)
        self.rec.log("/legend", rr.TextDocument(
            "### Colours\n\nSurface, voxels and cut footprints: blue = low, red = high, grey = "
            "no grade.\nVoxel radius grows with the voxel's tonnes.\n\n| analyte | blue at % | "
            "red at % |\n|---|---|---|\n" + legend, media_type=rr.MediaType.MARKDOWN))

    def _log_layers(self, state) -> None:
        rr = _rr()
        stack = state.state.stack
        geometry = state.state.pile.geometry
        xs = geometry.origin_x_m + (np.arange(geometry.nx) + 0.5) * geometry.cell_m
        step = max(1, int(round(self.config.layer_step_m / geometry.cell_m)))
        strips, colours = [], []
        for iy in range(step // 2, geometry.ny, step):
            y = geometry.origin_y_m + (iy + 0.5) * geometry.cell_m
            for k in range(1, stack.n_deposits + 1):
                thick = stack.thickness(k)[:, iy]
                cols = np.nonzero(thick > 1e-3)[0]
                if cols.size < 2:
                    continue
                lo, hi = cols.min(), cols.max() + 1
                zk = stack.surface_k(k)[lo:hi, iy]
                strips.append(np.column_stack([xs[lo:hi], np.full(hi - lo, y), zk]))
                colours.append(lot_colour(stack.info(k).lot_id))
        if strips:
            self.rec.log("/site/pile/layers", rr.LineStrips3D(strips, colors=colours, radii=0.03))

    def _log_machines(self) -> None:
        rr = _rr()
        for m in self.machines.values():
            if not m.rail_logged:
                pile = self.projection.state.pile
                if pile is not None:
                    g = pile.geometry
                    y0, y1 = g.origin_y_m - 40.0, g.origin_y_m + g.length_y_m + 40.0
                    r = m.reclaimer
                    self.rec.log(f"/site/machines/{m.machine_id}/rail_m", rr.LineStrips3D(
                        [[[r.rail_x_m, y0, r.rail_z_m], [r.rail_x_m, y1, r.rail_z_m]]],
                        colors=[[120, 120, 120]], radii=0.3), static=True)
                    m.rail_logged = True
            if m.pose is None or m.pose[0] == m.logged_pose_ns:
                continue
            t, centre, rot = m.pose
            travel, slew, luff = joints_from_wheel_pose(m.reclaimer, centre, rot)
            strips = machine_strips(m.reclaimer, travel, slew, luff,
                                    m.wheel_radius_m or m.reclaimer.cutting_radius_m * 0.7)
            self._at()
            self.rec.log(f"/site/machines/{m.machine_id}", rr.LineStrips3D(
                strips, colors=[[250, 200, 40]] * len(strips), radii=0.25,
                labels=[m.machine_id] + [""] * (len(strips) - 1)))
            m.logged_pose_ns = t

    def _log_scan(self) -> None:
        from projector import georef
        from projector.grades import coerce_time_ns

        if self.latest_scan is None:
            return
        rr = _rr()
        from schemas.events import decode_payload

        msg = decode_payload("scan", self.latest_scan.payload)
        self.latest_scan = None
        frame = msg.frame_id or ""
        machine_id = frame.split("/", 1)[0] if "/" in frame else next(iter(self.scanner_poses), "")
        poses = self.scanner_poses.get(machine_id)
        ranges = np.asarray(msg.ranges, np.float64)
        if not poses or ranges.size < 2:
            return
        t = coerce_time_ns(msg.timestamp)
        pt = np.array([p[0] for p in poses], np.int64)
        order = np.argsort(pt, kind="stable")
        pt = pt[order]
        xyz = np.array([poses[i][1] for i in order])
        q = np.array([poses[i][2] for i in order])
        if t <= pt[0]:
            tr, qq = xyz[:1], q[:1]
        elif t >= pt[-1]:
            tr, qq = xyz[-1:], q[-1:]
        else:
            tr, qq = georef.interpolate_poses(np.array([t]), pt, xyz, q, max_gap_ns=10 * S)
        if not np.isfinite(tr).all():
            return
        inc = (msg.end_angle - msg.start_angle) / (ranges.size - 1)
        pts = georef.georeference(ranges[None, :], msg.start_angle, inc, tr, qq).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        self._at()
        self.rec.log("/site/scan", rr.Points3D(pts, colors=[[255, 255, 255]], radii=0.08))

    def _log_status(self, state) -> None:
        rr = _rr()
        counters = ", ".join(f"{k} {v:,}" for k, v in sorted(state.counters.items()))
        self.rec.log("/status", rr.TextDocument(
            f"### Pile {self.pile_id}\n\n"
            f"- valid time V: {_iso(self.valid_ns)}\n- known time K: {_iso(self.known_ns)} "
            f"(ledger seq {self.seq:,})\n- volume {state.volume_m3:,.1f} m3, "
            f"{state.tonnes:,.1f} t, assayed fraction {state.assayed_fraction:.2f}\n- grade: "
            + ", ".join(f"{a} {g:.2f} %" for a, g in state.grade.items() if math.isfinite(g))
            + f"\n- deposits {len(state.deposits)}, cuts {len(state.cuts)}, "
            f"updates {self.updates}, rebuilds {self.rebuilds}\n- fold: {counters}",
            media_type=rr.MediaType.MARKDOWN))


def _merge_voxels(tonnes: np.ndarray, grade: np.ndarray, f: int):
    """Voxels merged ``f x f x f``: ``(tonnes, tonnage-weighted grade)`` (grade 0 where empty)."""
    pads = [(0, (-n) % f) for n in tonnes.shape]
    t = np.pad(tonnes, pads)
    tg = np.pad(tonnes * grade, pads)
    shape = (t.shape[0] // f, f, t.shape[1] // f, f, t.shape[2] // f, f)
    t = t.reshape(shape).sum(axis=(1, 3, 5))
    tg = tg.reshape(shape).sum(axis=(1, 3, 5))
    with np.errstate(invalid="ignore", divide="ignore"):
        return t, np.where(t > 0, tg / t, 0.0)


def _same(a, b, tol: float = 1e-9) -> bool:
    if abs(a[0] - b[0]) > tol * max(1.0, abs(b[0])) or abs(a[2] - b[2]) > tol:
        return False
    for k, v in a[1].items():
        w = b[1].get(k, math.nan)
        if math.isfinite(v) != math.isfinite(w) or (math.isfinite(v) and abs(v - w) > tol):
            return False
    return True


def _iso(ns: int) -> str:
    from schemas.times import format_time_ns

    return format_time_ns(int(ns) // S * S)


def _rr():
    import rerun as rr

    return rr


# -- sources and the recording --------------------------------------------------------------


def make_recording(config: Config, analytes: Iterable[str] = ("Fe", "SiO2", "Al2O3", "P", "LOI"),
                   *, recording_id: str | None = None, pile=None):
    """A RecordingStream with our sinks (file and/or loopback gRPC server) and blueprint.

    Returns ``(rec, grpc_uri or None)``.  The log time and log tick timelines are disabled:
    the timelines come from the data.
    """
    import rerun as rr

    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    rr.set_log_time_enabled(False, recording=rec)
    rr.set_log_tick_enabled(False, recording=rec)
    bp = blueprint(analytes, config.analyte, layers=config.layers, pile=pile)
    sinks = []
    uri = None
    if config.serve:
        for name, port in (("--grpc-port", config.grpc_port), ("--web-port", config.web_port)):
            if not _port_free(int(port)):
                raise OSError(f"{name} {port}: the port is in use on 127.0.0.1")
        server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=int(config.grpc_port))
        uri = server.uri
        sinks.append(server)
    if config.rrd:
        Path(config.rrd).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(config.rrd)))
    if sinks:
        rec.set_sinks(*sinks, default_blueprint=bp)
    else:
        rec.set_sinks(rr.FileSink("/dev/null"), default_blueprint=bp)
    if config.serve and not _wait_listening(int(config.grpc_port), 10.0, None):
        rec.disconnect()
        raise OSError(f"the gRPC server did not start on 127.0.0.1:{config.grpc_port}")
    return rec, uri


def _port_free(port: int) -> bool:
    import socket

    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _close_recording(rec) -> None:
    """Flush and disconnect; a sink that died (a server thread) becomes one OSError."""
    try:
        rec.flush(timeout_sec=60.0)
    except RuntimeError as exc:
        raise OSError(f"Rerun: {exc}") from None
    finally:
        rec.disconnect()


class WebViewer:
    """The Rerun web viewer for operators' browsers, connected to our gRPC server.

    It is the ``rerun`` viewer binary shipped with rerun-sdk, run as a child process with
    ``--web-viewer --bind 127.0.0.1`` so it listens on loopback only (the Python API's
    ``serve_web_viewer`` binds every interface); without that command it falls back to
    the Python API.  :meth:`close` stops the child.
    """

    def __init__(self, config: Config, uri: str) -> None:
        import shutil
        import subprocess
        from urllib.parse import quote

        self.process = None
        self.url = f"http://127.0.0.1:{config.web_port}/?url={quote(uri, safe='')}"
        command = _rerun_binary() or shutil.which("rerun")
        if command:
            self.process = subprocess.Popen(
                [command, "--web-viewer", "--bind", "127.0.0.1", "--web-viewer-port",
                 str(int(config.web_port)), uri],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            if not _wait_listening(int(config.web_port), 20.0, self.process):
                self.close()
                raise OSError(f"the Rerun web viewer did not start on port {config.web_port}")
        else:   # pragma: no cover - rerun-sdk ships the command
            import rerun as rr

            rr.serve_web_viewer(web_port=int(config.web_port), open_browser=False,
                                connect_to=uri)

    def close(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(10)
            except Exception:  # noqa: BLE001 - it must not outlive us
                self.process.kill()
                self.process.wait()
        self.process = None


def _rerun_binary() -> str | None:
    """The viewer binary rerun-sdk ships (``rerun_cli/rerun``): run directly, not through its
    Python wrapper, so that terminating it stops the viewer."""
    try:
        import rerun_cli
    except ImportError:   # pragma: no cover
        return None
    exe = Path(rerun_cli.__file__).with_name("rerun")
    return str(exe) if exe.exists() else None


def _wait_listening(port: int, timeout_s: float, process) -> bool:
    """Until something accepts TCP connections on 127.0.0.1:port (or ``process`` exits)."""
    import socket

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            return False
        with socket.socket() as sock:
            sock.settimeout(0.2)
            if sock.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.1)
    return False


class _StoreSource:
    """The offline source: a read-only ledger store, the client's interface."""

    def __init__(self, store, head_seq: int) -> None:
        self.store, self.head_seq = store, head_seq

    def read(self, start: int = 0, stop: int | None = None):
        return self.store.read(start, stop)

    def head(self) -> dict[str, Any]:
        return {"global_seq": self.head_seq}


def _feed(dash: Dashboard, records: Iterable, *, updates: bool = True,
          rebuild: Callable[[], None] | None = None, on_record=None) -> int:
    """Add records, updating at recorded-time boundaries when due; returns records added."""
    n = 0
    for record in records:
        if (updates and dash.seq >= 0 and record.recorded_time_ns > dash.known_ns
                and dash.due(boundary=True)):
            if dash.projection.stale and rebuild is not None:
                rebuild()
            dash.update()
        dash.add(record)
        if record.type in ("scan", "frame_transform", "reclaim_cut", "stack_started",
                           "stack_ended", "pile_declared", "machine_declared") and n % 64 == 0:
            dash.projection.advance()
        n += 1
        if on_record is not None:
            on_record(n)
    return n


def _rebuild_from(source, dash: Dashboard) -> None:
    """Refold the projection from the source up to the dashboard's position (stale state)."""
    from services.projector_service import catch_up

    upto = dash.seq
    dash.projection.reset()
    catch_up(source, dash.projection, upto)
    dash.projection.advance()
    dash.rebuilds += 1
    dash.log_text(f"rebuilt the projection from the ledger (a geometry event arrived late), "
                  f"seq {upto:,}", "WARN")


def _log_gaps_and_quarantine(dash: Dashboard, gaps, quarantine, seen: set, known_ns: int) -> None:
    """Log gaps and quarantined input the ledger knew by ``known_ns`` (each once)."""
    for g in gaps:
        key = ("gap", g.gap_id, g.closed_recorded_ns is not None and g.closed_recorded_ns <= known_ns)
        if g.opened_recorded_ns > known_ns or key in seen:
            continue
        seen.add(key)
        if key[2]:
            dash.log_text(f"gap {g.gap_id} closed: {g.source} epoch {g.epoch} seq "
                          f"{g.first_seq}..{g.last_seq}", "INFO")
        else:
            dash.log_text(f"gap {g.gap_id} open: {g.source} epoch {g.epoch} seq {g.first_seq}.."
                          f"{g.last_seq} ({g.size:,} events missing)", "WARN")
    for q in quarantine:
        key = ("q", q.quarantine_id)
        if q.recorded_time_ns > known_ns or key in seen:
            continue
        seen.add(key)
        dash.log_text(f"quarantined {q.type or '?'} from {q.source or '?'}: {q.code}: "
                      f"{q.detail}", "ERROR")


# -- offline --------------------------------------------------------------------------------


@dataclass(frozen=True)
class RenderResult:
    pile_id: str
    records: int
    updates: int
    history_points: int
    rebuilds: int
    head_seq: int
    known_time_ns: int
    tonnes_t: float
    rrd: str | None
    url: str | None = None
    planned_cuts: int = 0


def single_pile(store) -> str:
    """The only pile the ledger declares (ValueError if none or several)."""
    from schemas.events import decode_payload

    piles = []
    for event in store.read(types=["pile_declared"]):
        pid = decode_payload(event.type, event.payload).pile_id
        if pid not in piles:
            piles.append(pid)
    if not piles:
        raise ValueError("the ledger declares no pile")
    if len(piles) > 1:
        raise ValueError(f"the ledger declares several piles ({', '.join(piles)}): pass --pile")
    return piles[0]


def render_ledger(path: str, pile_id: str | None, config: Config, *,
                  progress: Callable[[int, int], None] | None = None,
                  recording_id: str | None = None, keep_serving: Stopper | None = None
                  ) -> RenderResult:
    """Render a finished ledger to Rerun (``config.rrd`` and/or ``config.serve``).

    Raises ValueError for a missing ledger or an unknown pile.
    """
    from ledger import open_ledger
    from schemas.events import decode_payload

    if not Path(path).exists():
        raise ValueError(f"no ledger at {path}")
    with open_ledger(path, read_only=True) as store:
        head = store.head()
        if head.global_seq < 0:
            raise ValueError(f"the ledger {path} is empty")
        pile_id = pile_id or single_pile(store)
        piles = {}
        for e in store.read(types=["pile_declared"]):
            msg = decode_payload(e.type, e.payload)
            piles.setdefault(msg.pile_id, (msg.origin_x_m, msg.origin_y_m, msg.width_m,
                                           msg.length_m, msg.ground_z_m))
        if pile_id not in piles:
            raise ValueError(f"pile {pile_id!r} is not declared in {path}")
        analytes = _analytes(store)
        rec, uri = make_recording(config, analytes, recording_id=recording_id,
                                  pile=piles[pile_id])
        viewer = None
        try:
            viewer = WebViewer(config, uri) if config.serve and uri else None
            url = viewer.url if viewer else None
            if url:
                print(f"dashboard: web viewer at {url} (gRPC {uri})", file=sys.stderr,
                      flush=True)
            result = _render(store, head, pile_id, rec, config, progress, url, str(path))
            if keep_serving is not None and config.serve:
                print(f"dashboard: serving {url} until interrupted", file=sys.stderr, flush=True)
                keep_serving.wait()
        finally:
            if viewer is not None:
                viewer.close()
            _close_recording(rec)
    return result


def _render(store, head, pile_id: str, rec, config: Config, progress, url,
            ledger_path: str = "") -> RenderResult:
    """Feed every record of ``store`` to a :class:`Dashboard` (the body of render_ledger)."""
    dash = Dashboard(rec, pile_id, config, offline=True)
    source = _StoreSource(store, head.global_seq)
    gaps, quarantine = store.gaps(), store.quarantine()
    seen: set = set()
    total = head.global_seq + 1

    def on_record(n: int) -> None:
        if progress is not None and n % 5000 == 0:
            progress(n, total)

    def rebuild() -> None:
        _rebuild_from(source, dash)

    records = 0
    for chunk_start in range(0, total, READ_CHUNK * 4):
        chunk = list(store.read(chunk_start, min(total, chunk_start + READ_CHUNK * 4)))
        records += _feed(dash, chunk, rebuild=rebuild,
                         on_record=lambda n, base=records: on_record(base + n))
        if gaps or quarantine:
            _log_gaps_and_quarantine(dash, gaps, quarantine, seen, dash.known_ns)
    if dash.projection.stale:
        rebuild()
    dash.projection.advance(everything=True)
    dash.reasons.add("end")
    dash.update()   # everything read (a no-op when the last update already had it all)
    _log_gaps_and_quarantine(dash, gaps, quarantine, seen, dash.known_ns)
    dash.flush_known_now()
    planned = 0
    if config.plan_machine:
        from planner.cli import make_plan, plan_args

        plan = make_plan(plan_args(ledger_path, pile_id, config.plan_machine,
                                   cuts=config.plan_cuts), store)
        planned = dash.log_plan(plan)
    if progress is not None:
        progress(total, total)
    state = dash._last_state
    return RenderResult(pile_id, records, dash.updates, len(dash.points), dash.rebuilds,
                        head.global_seq, dash.known_ns,
                        float(state.tonnes) if state is not None else math.nan,
                        config.rrd, url, planned)


def _analytes(store) -> tuple[str, ...]:
    from projector.query import CANONICAL_ANALYTES
    from schemas.events import decode_payload

    names: set[str] = set()
    for e in store.read(types=["lot_declared"]):
        names.update(decode_payload(e.type, e.payload).planned_grade)
    return tuple([a for a in CANONICAL_ANALYTES if a in names]
                 + sorted(names - set(CANONICAL_ANALYTES))) or CANONICAL_ANALYTES


def cmd_dashboard(args: argparse.Namespace) -> int:
    if not args.rrd and not args.serve:
        raise ValueError("give --rrd OUT and/or --serve")
    config = Config(pile_id=args.pile, serve=args.serve, rrd=args.rrd, grpc_port=args.grpc_port,
                    web_port=args.web_port, every_s=_duration_s(args.every),
                    analyte=args.analyte, layers=args.layers, layer_step_m=args.layer_step_m,
                    delta_threshold_pp=args.delta_threshold_pp, reorder_s=args.reorder_s,
                    plan_machine=args.plan_machine, plan_cuts=args.plan_cuts)
    t0 = time.monotonic()
    tty = sys.stderr.isatty()
    last = [0.0]

    def progress(done: int, total: int) -> None:
        if not (tty or args.progress):
            return
        now = time.monotonic()
        if now - last[0] < 1.0 and done < total:
            return
        last[0] = now
        text = f"dashboard: {done:,} of {total:,} records ({100 * done / max(total, 1):.0f} %)"
        sys.stderr.write(("\r" + text) if tty and not args.progress else text + "\n")
        sys.stderr.flush()

    stopper = Stopper() if args.serve else None
    result = render_ledger(args.ledger, args.pile, config, progress=progress,
                           keep_serving=stopper)
    if tty and not args.progress:
        sys.stderr.write("\n")
    print(f"dashboard: pile {result.pile_id}: {result.records:,} records, {result.updates} "
          f"updates, {result.history_points} history points, {result.rebuilds} rebuilds, "
          f"{result.tonnes_t:,.1f} t at the end"
          + (f", {result.planned_cuts} planned cuts" if args.plan_machine else "")
          + (f" -> {result.rrd}" if result.rrd else "")
          + f" ({time.monotonic() - t0:.1f} s)")
    return 0


def _duration_s(text: str) -> float:
    from audit.cli import parse_duration_ns

    return parse_duration_ns(text) / S


def register(subparsers: argparse._SubParsersAction) -> None:
    """``stockpile dashboard --ledger PATH --rrd OUT``: render a finished ledger."""
    p = subparsers.add_parser(
        "dashboard", help="render a ledger to a Rerun dashboard (.rrd and/or the web viewer)",
        description="Render a finished ledger offline to the operators' Rerun dashboard: the "
        "same entities, timelines and blueprint as `stockpile service dashboard`.")
    p.add_argument("--ledger", required=True, help="ledger file (opened read-only)")
    p.add_argument("--pile", help="pile id (default: the only pile the ledger declares)")
    _add_common(p)
    p.add_argument("--every", default="5min", metavar="DURATION",
                   help="valid time between history points (default %(default)s)")
    p.add_argument("--progress", action="store_true",
                   help="progress lines on stderr even when it is not a terminal")
    p.add_argument("--plan-machine", metavar="ID",
                   help="also plan the next bench of this reclaimer and show its cuts as "
                   "footprints coloured by predicted grade")
    p.add_argument("--plan-cuts", type=int, default=10, metavar="N",
                   help="cuts in the planned bench (default %(default)s)")
    p.set_defaults(func=cmd_dashboard)


# -- live -----------------------------------------------------------------------------------


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the live dashboard until SIGINT/SIGTERM (or ``stopper``); return the exit code."""
    from services.ledger_client import LedgerClient, LedgerUnavailable
    from services.service import ServiceRuntime

    if not config.pile_id:
        raise ValueError("--pile is required")
    if not config.serve and not config.rrd:
        raise ValueError("give --serve and/or --rrd PATH")
    heads = Inbox()
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=config.pile_id,
                             status_period_s=config.status_period_s, stopper=stopper)
    rec, uri = make_recording(config)
    runtime.open(backlog=lambda: heads.qsize(), error_keys=("errors",), announce=False)
    with runtime:
        status = runtime.status
        assert status is not None and runtime.stopper is not None
        for name in ("records", "updates", "rebuilds", "errors"):
            status.add(name, 0)
        viewer = subscriber = None
        try:
            if config.serve and uri:
                viewer = WebViewer(config, uri)
                runtime.log("serving", web=viewer.url, grpc=uri)
            # a wait for the ledger inside Zenoh runs no signal handler: the client polls
            # the stopper, so SIGTERM ends it at once rather than after a query's timeout
            client = LedgerClient(runtime.session, config.site, stop=runtime.stopper.event)
            subscriber = client.follow_head(lambda head: heads.put(head["global_seq"]))
            _follow(config, runtime, status, client, heads, rec)
        except LedgerUnavailable:
            if not runtime.stopper.is_set():   # given up because the service stops: fine
                raise
        finally:
            if subscriber is not None:
                try:
                    subscriber.undeclare()
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass
            if viewer is not None:
                viewer.close()
            _close_recording(rec)
    return 0


def _follow(config: Config, runtime, status, client, heads: Inbox, rec) -> None:
    """The live loop: catch up, go live, update until stopped."""
    from services.projector_service import newest_head

    dash = Dashboard(rec, config.pile_id, config)
    seen_gaps: set = set()
    quarantined = [0]

    def rebuild() -> None:
        _rebuild_from(client, dash)
        status.add("rebuilds")

    def read_to(head_seq: int, *, updates: bool) -> int:
        n = 0
        while dash.seq < head_seq and not runtime.stopper.is_set():
            stop = min(head_seq + 1, dash.seq + 1 + READ_CHUNK)
            records = client.read(dash.seq + 1, stop)
            if not records:
                break
            n += _feed(dash, records, updates=updates, rebuild=rebuild)
        status.add("records", n)
        return n

    def poll_gaps() -> None:
        try:
            for g in client.gaps():
                key = (g.get("gap_id"), g.get("closed_recorded_ns") is not None)
                if key in seen_gaps:
                    continue
                seen_gaps.add(key)
                level = "INFO" if key[1] else "WARN"
                dash.log_text(f"gap {g.get('gap_id')} {'closed' if key[1] else 'open'}: "
                              f"{g.get('source')} epoch {g.get('epoch')} seq "
                              f"{g.get('first_seq')}..{g.get('last_seq')}", level)
            stats = client.stats()
            q = int(stats.get("quarantined", 0))
            if q > quarantined[0]:
                dash.log_text(f"{q - quarantined[0]} input(s) quarantined (total {q}: "
                              + ", ".join(f"{k} {v}" for k, v in
                                          (stats.get("quarantine_by_code") or {}).items())
                              + ")", "ERROR")
                quarantined[0] = q
        except Exception as exc:  # noqa: BLE001 - retried at the next poll
            if runtime.stopper.is_set():   # given up because the service stops
                return
            status.add("errors")
            runtime.log("poll failed", level="warn", error=f"{type(exc).__name__}: {exc}")

    head = client.head()["global_seq"]
    n = read_to(head, updates=True)
    if dash.projection.stale:
        rebuild()
    dash.update()
    status.add("updates", dash.updates)
    dash.flush_known_now()   # the history as known at the head; live from here on
    poll_gaps()
    runtime.log("caught up", records=n, head=head, updates=dash.updates)
    runtime.announce()
    last_update = time.monotonic()
    last_poll = time.monotonic()
    stop = runtime.stopper
    while not stop.is_set():
        target = newest_head(heads, 0.05)
        try:
            if target is not None and target > dash.seq:
                read_to(target, updates=False)
            now = time.monotonic()
            if now - last_poll >= 5.0:
                poll_gaps()
                last_poll = now
            if now - last_update >= config.update_period_s:
                if dash.projection.stale:
                    rebuild()
                if dash.update():
                    status.add("updates")
                    last_update = now
        except Exception as exc:  # noqa: BLE001 - a failed read is retried later
            if stop.is_set():     # a read given up because the service stops
                break
            status.add("errors")
            runtime.log("update failed", level="warn",
                        error=f"{type(exc).__name__}: {exc}")
            stop.wait(0.5)
