"""``project(store, pile_id, V, K)``: the pile as of valid time V as known at K.

The edge of the projector: it reads the ledger (``as_of``), runs the fold
(:mod:`projector.fold`, no I/O inside) on a state of its own, fresh or loaded from a
snapshot (:class:`SnapshotStore`), and joins grades as known at K.

Snapshots hold the geometric state after folding every geometry event up to a
position ``(valid ns, global seq)`` as known when the ledger's head was ``head_seq``.
One is usable for a query (V, K) when its position is at or before V, every event
folded into it was recorded by K (so a snapshot taken with everything known also
serves an earlier K), and no geometry event at or before its position was recorded
after it by K (a late scan or cut makes the snapshot unusable for any K past that
event's arrival, never silently wrong): the check reads only the events appended
after the snapshot.
"""

from __future__ import annotations

import math
import os
import pickle
import struct
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import zstandard

from schemas.events import decode_payload

from projector import fold as F
from projector.grades import (AssayRecord, grade_from_map, GradeClasses, effective_assays,
                                     grade_classes)
from projector.grid import GridGeometry
from projector.material_fit import material_estimate
from projector.summary_sd import cut_sd, pile_sd
from projector.uncertainty import UncertaintyConfig
from projector.voxels import ClassWeights, integrate

__all__ = ["DepositSummary", "GradeJoin", "CutSummary", "PileState", "project", "grade_inputs",
           "summarise", "SnapshotStore", "CANONICAL_ANALYTES"]

CANONICAL_ANALYTES = ("Fe", "SiO2", "Al2O3", "P", "LOI")
FAR_FUTURE_NS = 2 ** 62


@dataclass(frozen=True)
class DepositSummary:
    index: int
    pass_id: str
    lot_id: str
    flagged: bool
    volume_m3: float
    tonnes: float
    grade: dict[str, float]
    assayed_fraction: float


@dataclass(frozen=True)
class CutSummary:
    cut_id: str
    bench_id: str
    start_time_ns: int
    end_time_ns: int
    volume_m3: float
    tonnes: float
    tonnes_scale: float
    grade: dict[str, float]
    assayed_fraction: float
    predicted_m3: float
    residual_m3: float
    slumped_in_m3: float
    deposits: list[dict[str, Any]]
    tonnes_sd: float = math.nan                     # t (projector.summary_sd)
    grade_sd: dict[str, float] = field(default_factory=dict)   # analyte -> pp


@dataclass
class PileState:
    """The pile as of (V, K).  Voxels are computed on demand (:meth:`voxel_grades`)."""

    pile_id: str
    valid_time_ns: int
    known_time_ns: int
    geometry: GridGeometry | None
    volume_m3: float
    tonnes: float
    grade: dict[str, float]
    assayed_fraction: float
    deposits: list[DepositSummary]
    cuts: list[CutSummary]
    counters: dict[str, int]
    state: F.ProjectorState = field(repr=False)
    analytes: tuple[str, ...] = ()
    _join: "GradeJoin | None" = field(default=None, repr=False)
    tonnes_sd: float = math.nan                     # t (projector.summary_sd)
    grade_sd: dict[str, float] = field(default_factory=dict)   # analyte -> pp

    @property
    def join(self) -> "GradeJoin | None":
        """The grades as known at K (None: the pile is not declared)."""
        return self._join

    @property
    def surface_m(self) -> np.ndarray:
        """The top surface (nx, ny), metres."""
        return self.state.stack.surface()

    @property
    def elevation_m(self) -> np.ndarray:
        """The fused height map (nx, ny), NaN where never seen."""
        return self.state.height.elevation

    @property
    def material(self) -> dict[str, Any]:
        """The pile's material as its scans show it (:func:`~projector.material_fit.material_estimate`)."""
        return material_estimate(self.state)

    def voxel_grades(self):
        """``(tonnes (nvx, nvy, nvz), grade (nvx, nvy, nvz, A) %, voxel grid)``."""
        if self.state.stack.n_deposits == 0:   # nothing deposited yet: empty voxels
            grid = integrate(self.state.stack, self.state.pile.voxel_m, None)
            tonnes = np.zeros(grid.volume_m3.shape)
            return tonnes, np.full(tonnes.shape + (len(self.analytes),), np.nan), grid
        weights = None if self._join is None else _deposit_weights(self.state, self._join)
        grid = integrate(self.state.stack, self.state.pile.voxel_m, weights)
        tonnes = grid.weighted[..., 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            grade = grid.weighted[..., 1:1 + len(self.analytes)] / tonnes[..., None]
        return tonnes, grade, grid

    def to_json(self) -> dict[str, Any]:
        return {
            "pile_id": self.pile_id, "valid_time_ns": self.valid_time_ns,
            "known_time_ns": self.known_time_ns, "volume_m3": self.volume_m3,
            "tonnes": self.tonnes, "tonnes_sd": self.tonnes_sd, "grade": self.grade,
            "grade_sd": self.grade_sd, "assayed_fraction": self.assayed_fraction,
            "deposits": [d.__dict__ for d in self.deposits],
            "cuts": [c.__dict__ for c in self.cuts], "counters": self.counters,
            "material": self.material,
        }


# -- the edge: read, fold, join --------------------------------------------------------------


def project(store, pile_id: str, valid_time_ns: int | None = None,
            known_time_ns: int | None = None, *, config: F.FoldConfig | None = None,
            snapshots: "SnapshotStore | None" = None,
            uncertainty: UncertaintyConfig | None = None) -> PileState:
    """The pile ``pile_id`` as of valid time V, as known at K (default: everything); the
    standard deviations from ``uncertainty`` (default :class:`UncertaintyConfig`'s)."""
    v = FAR_FUTURE_NS if valid_time_ns is None else int(valid_time_ns)
    k = FAR_FUTURE_NS if known_time_ns is None else int(known_time_ns)
    config = config or F.FoldConfig(pile_id=pile_id)
    state, after = None, None
    if snapshots is not None:
        found = snapshots.find(store, config, v, k)
        if found is not None:
            state, after = found
    if state is None:
        state = F.initial_state(config)
    for event in store.as_of(v, k, types=list(F.GEOMETRY_TYPES), after=after):
        F.apply(state, event)
    view = F.flush(state)   # the state is ours alone (fresh, or loaded from a file)
    lots, assays = grade_inputs(store, v, k)
    return summarise(view, lots, assays, valid_time_ns=v, known_time_ns=k,
                     uncertainty=uncertainty)


def grade_inputs(store, valid_time_ns: int, known_time_ns: int
                 ) -> tuple[dict[str, dict[str, float]], list[AssayRecord]]:
    """The ledger's grade facts as of (V, K): ``lots`` (lot id -> planned grade, analyte ->
    mass %) and every assay (:class:`projector.grades.AssayRecord`), the inputs of
    :func:`summarise`."""
    lots, assays = {}, []
    for event in store.as_of(int(valid_time_ns), int(known_time_ns),
                             types=["lot_declared", "assay"]):
        msg = decode_payload(event.type, event.payload)
        if event.type == "lot_declared":
            lots[msg.lot_id] = grade_from_map(msg.planned_grade)
        else:
            assays.append(AssayRecord.from_message(msg, event.recorded_time_ns))
    return lots, assays


def analytes_of(lots: dict[str, dict[str, float]], assays: list[AssayRecord]) -> tuple[str, ...]:
    names = set()
    for grade in lots.values():
        names.update(grade)
    for a in assays:
        names.update(a.analytes)
    return tuple([a for a in CANONICAL_ANALYTES if a in names]
                 + sorted(names - set(CANONICAL_ANALYTES)))


class GradeJoin:
    """Grades of material (lot, deposition times, volumes) as known at K.

    ``lots`` maps a lot id to its planned grade (analyte -> %), ``assays`` are every
    :class:`projector.grades.AssayRecord` seen (those recorded after ``known_ns``
    are ignored), ``density_default`` (t/m3) stands in where no assay reported one, and
    ``analytes`` (default: every analyte the lots and assays name) orders the grades.
    """

    def __init__(self, lots, assays, known_ns: int, density_default: float,
                 analytes: tuple[str, ...] | None = None) -> None:
        self.lots = lots
        self.analytes = analytes_of(lots, assays) if analytes is None else tuple(analytes)
        effective = effective_assays(assays, known_ns)
        self.by_lot: dict[str, list[AssayRecord]] = {}
        for a in effective:
            self.by_lot.setdefault(a.lot_id, []).append(a)
        self.density_default = density_default

    def classes(self, lot_id: str, times_ns: np.ndarray) -> GradeClasses:
        """The grade classes of material of a lot deposited at these times
        (:func:`projector.grades.grade_classes`), densities defaulted."""
        planned = self.lots.get(lot_id)
        if planned is None:   # an undeclared lot: no grade
            n_a = len(self.analytes)
            return GradeClasses(np.zeros(np.asarray(times_ns).shape[0], np.int64),
                                np.full((1, n_a), np.nan), np.zeros(1, bool),
                                np.array([self.density_default]), np.full((1, n_a), np.nan))
        c = grade_classes(lot_id, planned, self.by_lot.get(lot_id, []), times_ns,
                          self.analytes)
        # grade_classes leaves NaN where no density was reported
        density = np.where(np.isfinite(c.density_t_m3), c.density_t_m3, self.density_default)
        return GradeClasses(c.index, c.grade, c.assayed, density, c.lab_sd_pp, c.window_ns)

    def material(self, lot_id: str, times_ns, volumes_m3):
        """``(tonnes, grade-tonnes (A,), assayed tonnes, graded tonnes)`` of some material
        (volumes summed per grade class, so per class, not per cell, work)."""
        volumes = np.asarray(volumes_m3, np.float64)
        if volumes.size == 0:
            return 0.0, np.zeros(len(self.analytes)), 0.0, 0.0
        c = self.classes(lot_id, times_ns)
        tonnes = np.bincount(c.index, weights=volumes, minlength=len(c.assayed)) * c.density_t_m3
        graded = np.isfinite(c.grade).all(axis=1)
        sums = tonnes[graded] @ c.grade[graded]
        return (float(tonnes.sum()), sums, float(tonnes[c.assayed].sum()),
                float(tonnes[graded].sum()))


def _grade(sums: np.ndarray, graded_t: float, analytes) -> dict[str, float]:
    if graded_t <= 0:
        return {a: math.nan for a in analytes}
    return {a: float(s / graded_t) for a, s in zip(analytes, sums)}


def summarise(state: F.ProjectorState, lots, assays, *, valid_time_ns: int,
              known_time_ns: int, uncertainty: UncertaintyConfig | None = None) -> PileState:
    """Totals, deposits and cuts of a folded state, grades joined as known at K, each
    pile's and cut's figures with their standard deviations (:mod:`projector.summary_sd`,
    from ``uncertainty``, default :class:`UncertaintyConfig`'s)."""
    pile = state.pile
    if pile is None:
        return PileState(state.config.pile_id, valid_time_ns, known_time_ns, None, 0.0, 0.0, {},
                         0.0, [], [], dict(state.counters), state)
    join = GradeJoin(lots, assays, known_time_ns, pile.default_bulk_density_t_m3)
    analytes = join.analytes
    stack = state.stack
    area = pile.geometry.cell_area_m2
    deposits = []
    tot_t, tot_sums, tot_assayed, tot_graded, tot_v = 0.0, np.zeros(len(analytes)), 0.0, 0.0, 0.0
    for k in range(1, stack.n_deposits + 1):
        info = stack.info(k)
        cells, thick, times = stack.deposit_cells(k)
        volume = float(thick.sum() * area)
        if cells.size:
            t, sums, a_t, g_t = join.material(info.lot_id, times, thick * area)
        else:
            t, sums, a_t, g_t = 0.0, np.zeros(len(analytes)), 0.0, 0.0
        deposits.append(DepositSummary(k, info.pass_id, info.lot_id, info.flagged, volume, t,
                                       _grade(sums, g_t, analytes), a_t / t if t > 0 else 0.0))
        tot_t += t
        tot_sums += sums
        tot_assayed += a_t
        tot_graded += g_t
        tot_v += volume
    sd_config = uncertainty or UncertaintyConfig()
    cuts = [_cut_summary(c, stack, join, analytes, cut_sd(c, state, join, sd_config))
            for c in state.cuts]
    return PileState(pile.pile_id, valid_time_ns, known_time_ns, pile.geometry, tot_v, tot_t,
                     _grade(tot_sums, tot_graded, analytes),
                     tot_assayed / tot_t if tot_t > 0 else 0.0, deposits, cuts,
                     dict(state.counters), state, analytes, join,
                     **pile_sd(state, join, sd_config))


def _deposit_weights(state: F.ProjectorState, join: GradeJoin) -> list["ClassWeights"]:
    """Per deposit, :class:`projector.voxels.ClassWeights` for
    :func:`projector.voxels.integrate`: each cell's grade class and per class the bulk
    density (t/m3), then density x grade (t/m3 x %) per analyte."""
    stack = state.stack
    shape = state.pile.geometry.shape
    weights = []
    for k in range(1, stack.n_deposits + 1):
        cells, _thick, times = stack.deposit_cells(k)
        if not cells.size:
            weights.append(ClassWeights(np.zeros(shape, np.uint8),
                                        np.zeros((1, 1 + len(join.analytes)))))
            continue
        c = join.classes(stack.info(k).lot_id, times)
        table = np.column_stack([c.density_t_m3,
                                 c.density_t_m3[:, None] * np.nan_to_num(c.grade)])
        index = np.zeros(shape, np.min_scalar_type(table.shape[0] - 1))
        index.ravel()[cells] = c.index
        weights.append(ClassWeights(index, table))
    return weights


def _cut_summary(cut: F.CutRecord, stack, join: GradeJoin, analytes, sd: dict) -> CutSummary:
    per_deposit: dict[int, list] = {}
    tonnes, sums, assayed_t, graded_t, volume = 0.0, np.zeros(len(analytes)), 0.0, 0.0, 0.0
    for removal in cut.removals:
        for d in removal.deposits:
            t, s, a_t, g_t = join.material(d.info.lot_id, d.deposition_time_ns, d.cell_volume_m3)
            entry = per_deposit.setdefault(d.index, [d.info, 0.0, 0.0])
            entry[1] += d.volume_m3
            entry[2] += t
            tonnes += t
            sums += s
            assayed_t += a_t
            graded_t += g_t
            volume += d.volume_m3
    deposits = [{"deposit": k, "pass_id": info.pass_id, "lot_id": info.lot_id,
                 "flagged": info.flagged, "volume_m3": v, "tonnes": t}
                for k, (info, v, t) in sorted(per_deposit.items())]
    return CutSummary(cut.cut_id, cut.bench_id, cut.start_ns, cut.end_ns, volume, tonnes,
                      cut.belt_tonnes, _grade(sums, graded_t, analytes),
                      assayed_t / tonnes if tonnes > 0 else 0.0, cut.predicted_m3,
                      cut.residual_m3, cut.slumped_m3, deposits, **sd)


# -- snapshots --------------------------------------------------------------------------------


class SnapshotStore:
    """Geometric fold states kept in their own DuckDB file, keyed by what they include.

    A snapshot row: pile id, the fold's version and config (:func:`_config_key`: a
    snapshot of another version or config never serves a query), the position
    ``(valid ns, global seq)`` folded to, the ledger head (global seq) and its recorded
    time when it was taken, the latest recorded time of the events folded in, and the
    name of the file holding the pickled state (:func:`_pack`: zstd level 1 of the
    pickle and of each array's buffer in frames of their own, unpacked on every core
    with the arrays left in place) in the folder ``<path>.d`` beside it: DuckDB reads a
    large BLOB far slower than a file, so the table holds only the keys.  It is a cache:
    deleting both loses nothing (a file of an older layout is ignored).  How the layout
    was chosen: see docs/design-notes.md.
    """

    TABLE = "snapshots_v7"

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self.folder = Path(self.path + ".d")
        self.folder.mkdir(parents=True, exist_ok=True)
        self._con = duckdb.connect(self.path)
        self._con.execute(
            f"CREATE TABLE IF NOT EXISTS {self.TABLE} (pile_id VARCHAR, config VARCHAR, "
            "valid_ns BIGINT, global_seq BIGINT, head_seq BIGINT, known_ns BIGINT, "
            "folded_recorded_ns BIGINT, payload VARCHAR)")

    def close(self) -> None:
        self._con.close()

    def __enter__(self) -> "SnapshotStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def save(self, state: F.ProjectorState, head_seq: int, known_ns: int,
             folded_recorded_ns: int | None = None) -> None:
        """Keep ``state`` (folded from ``as_of(..., K=known_ns)`` with the head at ``head_seq``).

        ``folded_recorded_ns``: the latest recorded time of the events folded into it
        (default ``known_ns``: then it serves no query known before ``known_ns``).  The
        state's file is written (and renamed into place) before its row.
        """
        valid_ns, gseq = state.high_water
        folded = known_ns if folded_recorded_ns is None else min(folded_recorded_ns, known_ns)
        name = f"{uuid.uuid4().hex}.snap.zst"
        work = self.folder / (name + ".tmp")
        work.write_bytes(_pack(state))
        work.replace(self.folder / name)
        self._con.execute(f"INSERT INTO {self.TABLE} VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                          [state.config.pile_id, _config_key(state.config), valid_ns, gseq,
                           head_seq, known_ns, folded, name])

    def count(self, config: F.FoldConfig | None = None) -> int:
        """Snapshots kept; with ``config``, only those folded with it by this version of
        the fold (the others are never used for its queries)."""
        if config is None:
            return self._con.execute(f"SELECT count(*) FROM {self.TABLE}").fetchone()[0]
        return self._con.execute(
            f"SELECT count(*) FROM {self.TABLE} WHERE pile_id = ? AND config = ?",
            [config.pile_id, _config_key(config)]).fetchone()[0]

    def latest_valid_ns(self, config: F.FoldConfig) -> int | None:
        """The valid time of the latest snapshot folded with ``config`` by this version of
        the fold, or None."""
        return self._con.execute(
            f"SELECT max(valid_ns) FROM {self.TABLE} WHERE pile_id = ? AND config = ?",
            [config.pile_id, _config_key(config)]).fetchone()[0]

    def drop(self, config: F.FoldConfig) -> int:
        """Delete the snapshots folded with ``config`` (rows and files); returns how many."""
        return self._delete("pile_id = ? AND config = ?",
                            [config.pile_id, _config_key(config)])[0]

    def drop_other_versions(self) -> tuple[int, int]:
        """Delete the snapshots another version of the fold took (rows and files): this
        version never reads them (:func:`_config_key`).  Returns ``(snapshots, bytes)``
        deleted."""
        return self._delete("config NOT LIKE ?", [f"fold v{F.FOLD_VERSION} %"])

    def _delete(self, where: str, params: list) -> tuple[int, int]:
        """Delete the rows ``where`` selects and their files: ``(rows, file bytes)``."""
        names = self._con.execute(f"SELECT payload FROM {self.TABLE} WHERE {where}",
                                  params).fetchall()
        self._con.execute(f"DELETE FROM {self.TABLE} WHERE {where}", params)
        freed = 0
        for (name,) in names:
            path = self.folder / name
            if path.exists():
                freed += path.stat().st_size
                path.unlink()
        return len(names), freed

    def find(self, store, config: F.FoldConfig, valid_ns: int, known_ns: int):
        """``(state, position)`` of the latest usable snapshot for (V, K), or None."""
        rows = self._con.execute(
            _FIND_SNAPSHOTS, [config.pile_id, _config_key(config), valid_ns, known_ns]).fetchall()
        for v_s, g_s, head_s, name in rows:
            if not (self.folder / name).exists():   # a cache: a lost file is a miss
                continue
            if _unchanged_since(store, v_s, g_s, head_s, known_ns):
                blob = (self.folder / name).read_bytes()
                return _unpack(blob), (v_s, g_s)
        return None


# SnapshotStore.find's query, a module constant: mutmut does not mutate module-level
# constants, so its SQL in another case (which DuckDB reads the same) is no mutant
_FIND_SNAPSHOTS = (
    f"SELECT valid_ns, global_seq, head_seq, payload FROM {SnapshotStore.TABLE} "
    "WHERE pile_id = ? AND config = ? AND valid_ns <= ? AND folded_recorded_ns <= ? "
    "ORDER BY valid_ns DESC, global_seq DESC")


def _config_key(config: F.FoldConfig) -> str:
    """What a snapshot is keyed by besides its position: the fold's version (read from
    :mod:`projector.fold` when called) and config (its ``repr``)."""
    return f"fold v{F.FOLD_VERSION} {config!r}"


SNAPSHOT_MAGIC = b"SPSNAP7\0"
SNAPSHOT_THREADS = 0      # threads that pack and unpack a snapshot (0: one per usable CPU)


def _pack(state: F.ProjectorState) -> bytes:
    """A state as zstd frames, one for the pickle (protocol 5) and one per array buffer,
    so that :func:`_unpack` decompresses them on every core at once.  Layout:
    :data:`SNAPSHOT_MAGIC`, ``<Q>`` frame count, ``<Q>`` per frame its compressed length,
    then the frames (an empty buffer has no frame: length 0)."""
    buffers = []
    head = pickle.dumps(state, protocol=5, buffer_callback=buffers.append)
    frames = _per_thread(lambda: zstandard.ZstdCompressor(level=1).compress,
                         [head] + [b.raw() for b in buffers])
    lengths = [len(f) for f in frames]
    return b"".join([SNAPSHOT_MAGIC, struct.pack(f"<Q{len(lengths)}Q", len(lengths), *lengths)]
                    + frames)


def _unpack(blob: bytes) -> F.ProjectorState:
    """The state :func:`_pack` packed.  Its arrays are views of the decompressed frames (no
    copy, read-only: the stack's are immutable anyway), but for those the fold updates in
    place, which are copied: the height map's and the open face's first sightings."""
    if not blob.startswith(SNAPSHOT_MAGIC):
        raise ValueError("not a snapshot of this layout")
    offset = len(SNAPSHOT_MAGIC)
    (n_frames,) = struct.unpack_from("<Q", blob, offset)
    lengths = struct.unpack_from(f"<{n_frames}Q", blob, offset + 8)
    offset += 8 + 8 * n_frames
    view, frames = memoryview(blob), []
    for n in lengths:
        frames.append(view[offset:offset + n])
        offset += n
    parts = _per_thread(lambda: zstandard.ZstdDecompressor().decompress, frames)
    state = pickle.loads(parts[0], buffers=parts[1:])
    if state.height is not None:
        state.height = state.height.copy()
    if state.face_sightings is not None:
        state.face_sightings = tuple(a.copy() for a in state.face_sightings)
    return state


def _per_thread(make, items: list) -> list[bytes]:
    """``[f(item) for item in items]`` with an empty item giving ``b""``, the items split
    by size into one contiguous run per thread, each thread with its own ``f = make()``
    (a zstd context serves one thread; its calls release the GIL, so the runs go on in
    parallel).  zstd's own multi-frame calls are not used: they mishandle empty inputs
    (a trailing one gets no frame; frames of empty content make the parallel
    decompression fail or crash)."""
    out = [b""] * len(items)

    def run(indices) -> None:
        f = make()
        for i in indices:
            if len(items[i]):
                out[i] = f(items[i])

    n = min(_threads(), len(items))
    if n <= 1:
        run(range(len(items)))
        return out
    ends = np.cumsum([len(item) for item in items])
    runs = np.split(np.arange(len(items)), np.searchsorted(ends, ends[-1] * np.arange(1, n) / n))
    with ThreadPoolExecutor(n) as pool:
        list(pool.map(run, runs))
    return out


def _threads() -> int:
    if SNAPSHOT_THREADS:
        return SNAPSHOT_THREADS
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _unchanged_since(store, valid_ns: int, gseq: int, head_seq: int, known_ns: int) -> bool:
    """No geometry event at or before (valid_ns, gseq) arrived after ``head_seq`` by K."""
    for event in store.read(head_seq + 1, types=list(F.GEOMETRY_TYPES)):
        if event.recorded_time_ns > known_ns:
            return True
        if (event.valid_time_ns, event.global_seq) <= (valid_ns, gseq):
            return False
    return True


def build_snapshots(store, snapshots: SnapshotStore, pile_id: str, *, every_ns: int,
                    known_ns: int | None = None, config: F.FoldConfig | None = None,
                    progress=None) -> int:
    """Fold what the ledger knew at ``known_ns`` (default: now), saving a snapshot every
    ``every_ns`` of valid time and one after every reclaim cut (its face slump is the
    costliest step of the fold; a query after the cut starts past it); returns how many
    were saved.  ``progress(saved, valid_ns)`` is called after each snapshot."""
    config = config or F.FoldConfig(pile_id=pile_id)
    head = store.head()
    if known_ns is None or known_ns >= head.recorded_time_ns:
        head_seq, known = head.global_seq, head.recorded_time_ns
    else:  # the last event recorded by then (recorded time never decreases along seq)
        head_seq, known = -1, int(known_ns)
        for event in store.read():
            if event.recorded_time_ns > known:
                break
            head_seq = event.global_seq
    state = F.initial_state(config)
    next_mark = None
    saved = 0
    folded_recorded = -(2 ** 62)

    def save(valid_ns: int) -> None:
        nonlocal saved, next_mark
        snapshots.save(state, head_seq, known, folded_recorded)
        saved += 1
        if progress is not None:
            progress(saved, valid_ns)
        next_mark = valid_ns + every_ns

    for event in store.as_of(FAR_FUTURE_NS, known, types=list(F.GEOMETRY_TYPES)):
        if next_mark is None:
            next_mark = event.valid_time_ns + every_ns
        if event.valid_time_ns >= next_mark:
            save(event.valid_time_ns)
        F.apply(state, event)
        folded_recorded = max(folded_recorded, event.recorded_time_ns)
        if event.type == "reclaim_cut":
            save(event.valid_time_ns)
    return saved
