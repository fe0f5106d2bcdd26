"""The fold's state: :class:`ProjectorState` and the records it holds.

One pile's geometry (the fused height map and the layer stack with its deposits), its
stacking passes (:class:`PassRecord`) and reclaim cuts (:class:`CutRecord`), the scanner
poses and the scans waiting for one (:class:`PendingScan`), the lots and assays the
grade join reads, and the fold's counters.  The fold updates a state in place
(:func:`projector.fold.apply`); :meth:`ProjectorState.copy` keeps a snapshot.  Also the
few questions every part of the fold asks of a state: whether rises still belong to the
last pass (:func:`settling_last_pass`), the latest pass or cut boundary
(:func:`last_event_ns`), and a padded block of cells (:func:`around`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from projector.config import FoldConfig
from projector.kinematics import Reclaimer
from projector.grades import AssayRecord
from projector.grid import GridGeometry
from projector.layers import LayerStack, Removal

__all__ = ["PileInfo", "PassRecord", "CutRecord", "PendingScan", "ProjectorState", "RebaseRecord",
           "initial_state", "settling_last_pass", "last_event_ns", "around"]


@dataclass(frozen=True)
class PileInfo:
    """What ``pile_declared`` said."""

    pile_id: str
    geometry: GridGeometry
    ground_z_m: float
    voxel_m: float
    default_bulk_density_t_m3: float
    #: the site's policy: the model follows each survey of the pile (:mod:`projector.rebase`)
    survey_rebase: bool = False


@dataclass(frozen=True)
class RebaseRecord:
    """What one rebase on a survey changed (:mod:`projector.rebase`).

    ``deposits_m3``: per deposit touched, ``(lot id, pass id, volume change m3)``;
    cells: surveyed cells whose columns were scaled, and surveyed cells the model held as
    bare but the survey shows above the ground by more than the survey's accuracy (left
    bare: they have no composition to scale).
    """

    survey_id: str
    time_ns: int
    cells_scaled: int
    cells_bare_above: int
    volume_change_m3: float
    deposits_m3: tuple[tuple[str, str, float], ...]


@dataclass
class PassRecord:
    """One stacking pass: its deposit, its times (UTC ns) and its run along the rail (m)."""

    pass_id: str
    lot_id: str
    machine_id: str
    started_ns: int
    deposit_index: int
    ended_ns: int | None = None
    belt_tonnes: float | None = None
    start_y_m: float = math.nan
    end_y_m: float = math.nan


@dataclass
class CutRecord:
    """One reclaim cut: what the envelope removed and what scans attributed to it later."""

    cut_id: str
    bench_id: str
    machine_id: str
    start_ns: int
    end_ns: int
    belt_tonnes: float
    removals: list[Removal] = field(default_factory=list)
    predicted_m3: float = 0.0
    residual_m3: float = 0.0
    returned_m3: float = 0.0
    slumped_m3: float = 0.0
    #: the angle (deg) its face was slid to: fitted to the scans after it
    #: (:func:`projector.material_fit.close_face`), else the prior; NaN until closed
    slide_angle_deg: float = math.nan
    #: cells of its face (where a slide to repose would move the surface) the scans saw
    #: between the cut and the face's closing, and those left to the prediction
    face_cells_seen: int = 0
    face_cells_predicted: int = 0
    #: the height map's variance (m^2, NaN = never seen) before the cut at the cells of its
    #: envelope removal (``removals[0]``), in ascending flat-index order
    #: (:meth:`projector.deposits.Removal.flat_cells`); None: not kept
    footprint_var_m2: np.ndarray | None = None


@dataclass
class PendingScan:
    """A scan waiting for the scanner pose after it: its time (UTC ns), ranges (m,
    (beams,)) and first and last beam angles (rad)."""

    t_ns: int
    ranges_m: np.ndarray
    start_angle_rad: float
    end_angle_rad: float
    #: the scanner's frame (``LaserScan.frame_id``): the pose track that places it
    frame_id: str = ""


@dataclass
class PoseTrack:
    """One scanner's recent poses in the site frame (``FrameTransform`` site ->
    ``<machine>/scanner``): times (UTC ns, increasing), translations (m) and rotations
    (quaternions x, y, z, w)."""

    t_ns: list[int] = field(default_factory=list)
    xyz: list[tuple[float, float, float]] = field(default_factory=list)
    q: list[tuple[float, float, float, float]] = field(default_factory=list)

    def copy(self) -> "PoseTrack":
        return PoseTrack(list(self.t_ns), list(self.xyz), list(self.q))


@dataclass
class ProjectorState:
    """Everything the fold knows about one pile.  Build with :func:`initial_state`."""

    config: FoldConfig
    pile: PileInfo | None = None
    machines: dict[str, Reclaimer] = field(default_factory=dict)
    lots: dict[str, dict[str, float]] = field(default_factory=dict)
    passes: dict[str, PassRecord] = field(default_factory=dict)
    active_pass: str | None = None
    height: Any = None              # heightmap.HeightMap
    stack: LayerStack | None = None
    cuts: list[CutRecord] = field(default_factory=list)
    assays: list[AssayRecord] = field(default_factory=list)
    #: each scanner's pose track, by its frame (``<machine>/scanner``): a yard's scanners
    #: place their own scans
    poses: dict[str, PoseTrack] = field(default_factory=dict)
    pending: list[PendingScan] = field(default_factory=list)
    #: no waiting scan has its pose yet: True after each pass over ``pending``
    #: (:func:`projector.scans.process_scans`), False when a scan or a pose arrives that
    #: makes one ready; while it holds, a pass over every waiting scan would fuse nothing
    pending_settled: bool = False
    #: the earliest time (UTC ns) of the waiting scans of each frame id
    pending_floor_ns: dict[str, int] = field(default_factory=dict)
    flagged_loss_m3: float = 0.0
    #: recent rises of the stack's top, ``(t_ns, flat cell indices, top before (m))``
    #: (:func:`projector.cuts.journal_rises`), so a cut can undo those its own digging caused
    rises_journal: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    #: when each cell was last completed to the repose cone (UTC ns, NaN = never; shape
    #: (nx, ny); None until the first completion; replaced, never written in place): its
    #: material up to there is accounted for (:func:`projector.completion.accounted_ns`)
    completed_ns: np.ndarray | None = None
    point_sd_m: float = 0.05       # resolved from the config and the pile
    margin_m: float = 0.02
    process_sd_m: float = 0.01     # the height map's creep per observation (resolved)
    tan_repose: float = math.nan   # last estimate of tan(angle of repose)
    #: the tops of deposits 1 .. this one are fitted (:func:`projector.cuts.fit_buried_boundaries`)
    boundaries_fitted: int = 0
    #: the last scan height offset applied, ``(scan t_ns, offset m)``
    #: (:func:`projector.scans.reference_ground`)
    ground_offset: tuple[int, float] = (-(2 ** 62), 0.0)
    #: the latest cut's face while its slide waits for the scans after it
    #: (a :class:`projector.material_fit.OpenFace`, immutable; None: no face open)
    open_face: Any = None
    #: the open face's first sightings since its cut, ``(heights m, times UTC ns)`` over
    #: its region (NaN: not yet seen; :func:`projector.material_fit.note_sightings`)
    face_sightings: Any = None
    #: every face slide fitted to the scans: ``(cut id, angle deg, cells seen)``
    slide_fits: list[tuple[str, float, int]] = field(default_factory=list)
    #: every later failure of a face the scans saw: ``(seen at UTC ns, volume moved m3)``
    delayed_failures: list[tuple[int, float]] = field(default_factory=list)
    #: every rebase on a survey (records are immutable)
    rebases: list[RebaseRecord] = field(default_factory=list)
    counters: dict[str, int] = field(default_factory=dict)
    high_water: tuple[int, int] = (-(2 ** 62), -1)   # (valid ns, global seq) folded so far

    def count(self, key: str, n: int = 1) -> None:
        """Add ``n`` to the counter ``key``."""
        self.counters[key] = self.counters.get(key, 0) + n

    def copy(self) -> "ProjectorState":
        """A deep enough copy for a snapshot (arrays are copied; records are immutable)."""
        return replace(
            self, machines=dict(self.machines), lots={k: dict(v) for k, v in self.lots.items()},
            passes={k: replace(v) for k, v in self.passes.items()},
            height=None if self.height is None else self.height.copy(),
            stack=None if self.stack is None else self.stack.copy(),
            cuts=[replace(c, removals=list(c.removals)) for c in self.cuts],
            assays=list(self.assays),
            poses={frame: track.copy() for frame, track in self.poses.items()},
            pending=list(self.pending), pending_floor_ns=dict(self.pending_floor_ns),
            counters=dict(self.counters),
            rises_journal=list(self.rises_journal), slide_fits=list(self.slide_fits),
            face_sightings=(None if self.face_sightings is None
                            else tuple(a.copy() for a in self.face_sightings)),
            delayed_failures=list(self.delayed_failures), rebases=list(self.rebases))


def initial_state(config: FoldConfig | str) -> ProjectorState:
    """The state before any event (``config`` may be just the pile id)."""
    if isinstance(config, str):
        config = FoldConfig(pile_id=config)
    return ProjectorState(config=config)


def settling_last_pass(state: ProjectorState) -> bool:
    """Whether rises now still belong to the pass that ended last.

    The scanner sees a stacked layer only when it passes over it, often after the
    pass has ended: until the next cut, a rise is that pass's material (it is the top
    deposit then).
    """
    if not state.passes or state.stack.n_deposits == 0:
        return False
    last = max(state.passes.values(), key=lambda p: p.started_ns)
    if last.deposit_index != state.stack.n_deposits:
        return False
    last_cut = max((c.end_ns for c in state.cuts), default=None)
    return last_cut is None or (last.ended_ns or last.started_ns) > last_cut


def last_event_ns(state: ProjectorState) -> int:
    """The latest pass or cut boundary: a flagged deposit opened before it is not reused."""
    times = [p.ended_ns or p.started_ns for p in state.passes.values()]
    times += [c.end_ns for c in state.cuts]
    return max(times) if times else -(2 ** 62)


def around(ix: np.ndarray, iy: np.ndarray, pad: int, geometry: GridGeometry):
    """The block of cells holding (ix, iy), padded by ``pad`` cells: (slice, slice)."""
    return (slice(max(0, int(ix.min()) - pad), min(geometry.nx, int(ix.max()) + pad + 1)),
            slice(max(0, int(iy.min()) - pad), min(geometry.ny, int(iy.max()) + pad + 1)))
