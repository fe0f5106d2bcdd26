"""Projector benchmarks: throughput of the projector's kernels, one section per stage group.

Run it from the project root with the project's virtualenv::

    .venv/bin/python bench/projector.py             # every section
    .venv/bin/python bench/projector.py --quick     # smaller inputs (smoke run)

Structure: ``SECTIONS`` is a list of section functions.  Each takes the parsed arguments
and returns a :class:`Section` (a title, a table and notes); :func:`main` runs them in
order and prints each table.  To add a benchmark, write ``section_xxx(args) -> Section``
and append it to ``SECTIONS``.

The process is pinned to one CPU and the BLAS/OpenMP pools to one thread before numpy
is imported, so the figures are single-core (section 3 also times each query on every
core, see there).

Sections
--------
1. :func:`section_georef_fuse` -- scans -> height map: ``interpolate_poses`` +
   ``clean_profile`` + ``georeference`` + ``rasterize`` + ``fuse`` on 401-beam LMS200
   scans of the full-scale hyperbolic pile of ``bench/accuracy.py`` (220 m x 30 m,
   0.25 m cells), in batches of 75 scans (one second of a 75 Hz LMS200), two passes over
   the pile (the first initialises the cells, the second updates them by Kalman steps).
   Target: >= 1,000,000 scan points per second through all stages.  Also prints the
   peak memory of the pipeline (tracemalloc, a separate untimed run) and the process's
   peak RSS.
2. :func:`section_voxels` -- voxel tonnes and grades of a full-scale pile (60 deposits,
   1-3 grade classes each, given as the query gives them: a class per cell and a table).
   Target: <= 1 s for the process's first query (its system time, page faults on new
   memory, shown beside it), with the best of two more (warm memory), and beside it the
   same weights as per-cell arrays (warm).
3. :func:`section_as_of` -- ``project(V, K)`` on a 24-hour full-scale ledger (the
   simulator's ``full-scale`` scenario with scan events, imported), from the latest usable
   snapshot, beside the same query folded from the first event.  Target: <= 2 s from a
   snapshot, on every core of the machine (a snapshot's frames unpack in parallel; the
   rest of the query runs on one) and pinned to one core; both must meet it.  The ledger is built once into ``--ledger-dir`` (about an hour of simulation
   on one core; ``--quick`` uses 2 hours of the ``demo`` scenario instead), the snapshots
   once beside it (one per ``--snapshot-every-min`` site minutes and one after every
   reclaim cut; about 5 minutes and 5.8 GB for the 24 hours).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
             "NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from dataclasses import dataclass, field, replace  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT, ROOT / "bench"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import numpy as np  # noqa: E402

from accuracy import Case, Rig, grid_for, simulate, thesis_piles  # noqa: E402
from ledger import open_ledger  # noqa: E402
from projector.fold import FoldConfig  # noqa: E402
from projector.georef import georeference, interpolate_poses  # noqa: E402
from projector.grid import GridGeometry, cell_centres  # noqa: E402
from projector.ground import height_corrections  # noqa: E402
from projector.heightmap import HeightMap, fuse, rasterize  # noqa: E402
from projector.layers import DepositInfo, LayerStack  # noqa: E402
from projector.profile import clean_profile  # noqa: E402
from projector.query import SnapshotStore, build_snapshots, project  # noqa: E402
from projector.voxels import ClassWeights, integrate  # noqa: E402
from schemas.times import NS_PER_H, NS_PER_S  # noqa: E402


@dataclass
class Section:
    """One benchmark section's output: a table (header + rows of cells) and notes."""

    title: str
    header: list[str]
    rows: list[list[str]]
    notes: list[str] = field(default_factory=list)
    ok: bool = True


ALL_CPUS: set[int] | None = None     # the CPUs this process had before pin_one_core


def pin_one_core() -> str:
    """Pin this process to one CPU (Linux); returns a description."""
    global ALL_CPUS
    try:
        ALL_CPUS = set(os.sched_getaffinity(0))
        cpu = min(ALL_CPUS)
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    except (AttributeError, OSError):
        return "not pinned (no sched_setaffinity)"


@contextlib.contextmanager
def every_core():
    """Within the block, the process may run on every CPU it had before it was pinned (the
    zstd threads that unpack a snapshot use them); pinned to one again after."""
    if ALL_CPUS is None:
        yield len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
        return
    pinned = os.sched_getaffinity(0)
    os.sched_setaffinity(0, ALL_CPUS)
    try:
        yield len(ALL_CPUS)
    finally:
        os.sched_setaffinity(0, pinned)


def print_section(number: int, s: Section) -> None:
    print(f"\n{number}. {s.title}")
    widths = [max(len(h), *(len(r[i]) for r in s.rows)) for i, h in enumerate(s.header)]
    def fmt(cells):
        return "  ".join(c.rjust(w) if i else c.ljust(w)
                         for i, (c, w) in enumerate(zip(cells, widths)))

    line = fmt(s.header)
    print(line)
    print("-" * len(line))
    for r in s.rows:
        print(fmt(r))
    for n in s.notes:
        print(n)


# --------------------------------------------------------------------------------------
# 1. scans -> height map
# --------------------------------------------------------------------------------------

STAGES = ("interpolate_poses", "clean_profile", "georeference", "ground_reference",
          "rasterize", "fuse")
TARGET_POINTS_S = 1_000_000


def _ground_offsets(geometry, t_scan, pts, sd):
    """The fold's ground reference with its defaults (every cell bare: no stack here)."""
    return height_corrections(t_scan, pts, geometry, np.ones(geometry.shape, bool), 0.0,
                              **FoldConfig("bench").ground_kwargs(sd))[0]


def _pipeline(hm, t_scan, ranges, angle_min, inc, t_pose, pose_tr, pose_q, batch, sd,
              timer=None):
    """Run all batches through the stages; ``timer`` accumulates seconds per stage."""
    clock = time.perf_counter
    for k in range(0, len(t_scan), batch):
        sl = slice(k, k + batch)
        t0 = clock()
        tr, q = interpolate_poses(t_scan[sl], t_pose, pose_tr, pose_q, max_gap_ns=NS_PER_S // 2)
        t1 = clock()
        clean = clean_profile(ranges[sl], fit_beams=FoldConfig.profile_fit_beams)
        t2 = clock()
        pts = georeference(clean, angle_min, inc, tr, q)
        t3 = clock()
        pts[..., 2] -= _ground_offsets(hm.geometry, t_scan[sl], pts, sd)[:, None]
        t4 = clock()
        obs = rasterize(hm.geometry, pts)
        t5 = clock()
        hm, _ = fuse(hm, obs, int(t_scan[sl][-1]), sd, inplace=True)   # as the fold does
        t6 = clock()
        if timer is not None:
            for name, dt in zip(STAGES, np.diff([t0, t1, t2, t3, t4, t5, t6])):
                timer[name] += dt
    return hm


def section_georef_fuse(args) -> Section:
    """Throughput of georeference + clean + rasterize + fuse, 401-beam scans, one core."""
    pile = next(p for p in thesis_piles() if p.name == "hyperbolic")
    sd = 0.05
    rig = Rig()                                   # 45 m up, 0.25 deg (401 beams), 0.1 m apart
    if args.quick:
        pile = pile.scaled(0.25)
        rig = replace(rig.scaled(0.25), max_range_m=80.0)
    case = Case(pile, "full", "noisy", sd, 0.25, rig)
    geom = grid_for(case)
    rng = np.random.default_rng(args.seed)
    passes = []
    for _ in range(2):                            # two passes, independent noise
        t_scan, _pos, ranges, angle_min, inc, t_pose, pose_tr, pose_q = simulate(case, geom, rng)
        passes.append((t_scan, ranges, t_pose, pose_tr, pose_q))
    # the second pass happens an hour later (the same ride)
    hour = NS_PER_H
    t_scan2, ranges2, t_pose2, pose_tr2, pose_q2 = passes[1]
    passes[1] = (t_scan2 + hour, ranges2, t_pose2 + hour, pose_tr2, pose_q2)
    n_beams = passes[0][1].shape[1]
    points = sum(int(p[1].size) for p in passes)
    returns = sum(int(np.isfinite(p[1]).sum()) for p in passes)
    batch = 75

    # warm-up (first calls, first-touch allocations) on one batch, then the timed run
    t_scan, ranges, t_pose, pose_tr, pose_q = passes[0]
    _pipeline(HeightMap.empty(geom), t_scan[:batch], ranges[:batch], angle_min, inc, t_pose,
              pose_tr, pose_q, batch, sd)
    timer = {s: 0.0 for s in STAGES}
    hm = HeightMap.empty(geom)
    wall0 = time.perf_counter()
    for t_scan, ranges, t_pose, pose_tr, pose_q in passes:
        hm = _pipeline(hm, t_scan, ranges, angle_min, inc, t_pose, pose_tr, pose_q, batch, sd,
                       timer)
    wall = time.perf_counter() - wall0
    seen = int(hm.seen.sum())

    # peak memory of the pipeline alone (inputs already allocated), untimed
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    hm2 = HeightMap.empty(geom)
    t_scan, ranges, t_pose, pose_tr, pose_q = passes[0]
    hm2 = _pipeline(hm2, t_scan, ranges, angle_min, inc, t_pose, pose_tr, pose_q, batch, sd)
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    maxrss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

    total = sum(timer.values())
    rows = []
    for s in STAGES:
        rows.append([s, f"{timer[s]:.3f}", f"{points / timer[s]:,.0f}",
                     f"{100 * timer[s] / total:.1f}"])
    rate = points / total
    ok = rate >= TARGET_POINTS_S
    rows.append(["all stages", f"{total:.3f}", f"{rate:,.0f}", "100.0"])
    mb = 1024 * 1024
    notes = [
        f"input: {points:,} scan points ({returns:,} returns) = 2 passes x {len(passes[0][0]):,} "
        f"scans x {n_beams} beams, batches of {batch} scans; grid {geom.nx} x {geom.ny} cells of "
        f"{geom.cell_m} m ({seen:,} seen); wall {wall:.3f} s",
        f"target >= {TARGET_POINTS_S:,} points/s through all stages: "
        f"{rate:,.0f} points/s -> {'PASS' if ok else 'MISS'}",
        f"peak memory: pipeline {peak / mb:.1f} MiB (tracemalloc, one pass; height map "
        f"{sum(a.nbytes for a in hm.grid.layers.values()) / mb:.1f} MiB, fused in place as in the fold), "
        f"process peak RSS {maxrss_mb:.0f} MiB (includes the simulated input)",
    ]
    return Section("scans -> height map (georeference + clean + rasterize + fuse), one core",
                   ["stage", "seconds", "points/s", "% time"], rows, notes, ok)


def _chevron_stack(n_deposits: int, nx: int, ny: int, cell_m: float, height_m: float,
                   seed: int):
    """A full-scale chevron pile: ``n_deposits`` triangular layers, each a pass in time."""
    g = GridGeometry(0.0, 0.0, cell_m, nx, ny)
    x, y = cell_centres(g)
    half = g.length_x_m / 2
    ridge = np.clip(height_m * (1 - np.abs(x - half) / half), 0, None)   # triangle across x
    ends = np.clip(np.minimum(y, g.length_y_m - y) * math.tan(math.radians(35)), 0, None)
    final = np.minimum(ridge, ends)
    stack = LayerStack.empty(g, 0.0)
    rng = np.random.default_rng(seed)
    for k in range(1, n_deposits + 1):
        stack = stack.open_deposit(DepositInfo(k, f"P{k}", f"LOT-{k % 7}", k * 600 * NS_PER_S))
        # chevron: each pass lays a layer following the final shape, scaled by its share
        surface = final * (k / n_deposits) ** 0.5
        stack, _ = stack.raise_to(surface, k * 600 * NS_PER_S + int(rng.integers(0, 600)) * NS_PER_S)
    return g, stack


def _voxel_weights(g, n_dep: int, analytes: int, seed: int):
    """Per deposit, the projector's grade classes and the same weights as per-cell arrays.

    A pass stacks along the pile (y), so its deposition time grows with y, and the assays'
    sampling windows cut it into one to three stretches of distinct grade and density (the
    classes :func:`projector.grades.grade_classes` gives the query).
    """
    _x, y = cell_centres(g)
    rng = np.random.default_rng(seed)
    classed, per_cell = [], []
    for _k in range(n_dep):
        n_c = int(rng.integers(1, 4))
        edges = np.sort(rng.uniform(0, g.length_y_m, n_c - 1))
        index = np.searchsorted(edges, y).astype(np.uint8)
        grade = rng.uniform([55, 3, 1, 0.05, 4], [64, 8, 3, 0.12, 8], size=(n_c, analytes))
        density = rng.uniform(2.2, 2.6, n_c)
        table = np.column_stack([density, density[:, None] * grade])
        classed.append(ClassWeights(index, table))
        per_cell.append(table[index])
    return classed, per_cell


def section_voxels(args) -> Section:
    """Voxel tonnes and grades of a full-scale pile from its layer stack (one core)."""
    nx, ny, cell = (240, 880, 0.25) if not args.quick else (120, 440, 0.5)
    n_dep, analytes = 60, 5
    g, stack = _chevron_stack(n_dep, nx, ny, cell, 30.0, args.seed)
    classed, per_cell = _voxel_weights(g, n_dep, analytes, args.seed)

    def voxel_grades(weights):
        grid = integrate(stack, 1.0, weights)
        tonnes = grid.weighted[..., 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            grades = grid.weighted[..., 1:] / tonnes[..., None]
        return grid, tonnes, grades

    def timed(weights):
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        out = voxel_grades(weights)
        r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        return out, t1 - t0, r1.ru_stime - r0.ru_stime

    (grid, tonnes, grades), seconds, sys_s = timed(classed)  # first query: new memory
    warm = min(timed(classed)[1] for _ in range(2))
    (grid_pc, _t, _g), _s, _ = timed(per_cell)
    warm_pc = min(_s, timed(per_cell)[1])
    same = bool(np.allclose(grid_pc.weighted, grid.weighted, rtol=1e-9, atol=1e-9))
    del grid_pc, _t, _g
    # memory on a further run: tracemalloc slows every allocation it traces
    peaks = []
    for weights in (classed, per_cell):
        tracemalloc.start()
        voxel_grades(weights)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    total = stack.total_volume_m3()
    err = abs(grid.total_volume_m3() / total - 1)
    occupied = int((tonnes > 0).sum())
    ok = (seconds <= 1.0 and err < 1e-9 and same
          and bool(np.isfinite(grades[tonnes > 0]).all()))
    pile = f"{g.length_y_m:g} x {g.length_x_m:g} x 30 m"
    rows = [[pile, "grade classes (query)", f"{occupied:,}", f"{len(grid.qvo):,}",
             f"{seconds:.3f}", f"{sys_s:.2f}", f"{warm:.3f}", f"{peaks[0] / 2**20:.0f} MiB",
             f"{err:.1e}"],
            [pile, "per-cell arrays", "", "", "", "", f"{warm_pc:.3f}",
             f"{peaks[1] / 2**20:.0f} MiB", ""]]
    return Section(
        f"voxel tonnes and grades (exact QVO integration), full-scale pile ({cell:g} m cells, "
        f"1 m voxels, {n_dep} deposits), one core",
        ["pile", "weights", "voxels with ore", "QVOs", "seconds", "of which system",
         "warm seconds", "peak memory", "volume error"], rows,
        [f"target <= 1 s for the first query: {seconds:.3f} s -> "
         f"{'PASS' if seconds <= 1.0 else 'MISS'}; volume error = |voxel total / stack total - 1|",
         "seconds: the process's first query (new memory: page faults, counted as system "
         "time); warm seconds: the best of two more",
         "weights: 1-3 grade classes per deposit (a pass's stretches between assay windows), "
         "given as the query gives them (a class per cell and a table) or as per-cell "
         f"(nx, ny, 6) arrays; same voxel sums both ways: {'yes' if same else 'NO'}; "
         f"warm ratio per-cell / classes = {warm_pc / warm:.2f}",
         f"stack volume {total:,.0f} m3; 5 analytes + density per cell and deposit"], ok)


def _ledger_for_as_of(args) -> tuple[Path, str]:
    """The imported simulator ledger for section 3 (built into ``--ledger-dir`` once)."""
    scenario, hours = ("demo", 2.0) if args.quick else ("full-scale", 24.0)
    out = Path(args.ledger_dir) / f"{scenario}-{hours:g}h-seed1"
    ledger = out.with_suffix(".duckdb")
    if not ledger.exists():
        if not (out / "events.jsonl").exists() or not (out / "truth.json").exists():
            print(f"  simulating {hours:g} h of {scenario!r} with scan events into {out} "
                  "(once; progress on stderr)", flush=True)
            subprocess.run([sys.executable, "-m", "stockpile.cli", "sim", "--scenario", scenario,
                            "--seed", "1", "--speed", "0", "--scan-events", "truth",
                            "--duration", f"{hours}h", "--out", str(out)],
                           check=True, stdout=subprocess.DEVNULL)
        print(f"  importing into {ledger}", flush=True)
        subprocess.run([sys.executable, "-m", "stockpile.cli", "ledger", "import",
                        str(out / "events.jsonl"), "--ledger", str(ledger), "--clock", "events"],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return ledger, scenario


def _ensure_snapshots(store, snaps, snap_path: Path, pile: str, config, args, first: int,
                      last: int, notes: list[str]) -> None:
    """Build this fold config's snapshots into ``snaps`` unless a complete set is there.

    Snapshots of another fold version (its code changed since they were built) are never
    read again: deleted; another config's never serve this one's queries: this one's are
    built.  Appends what it did to ``notes``.
    """
    every_s = 60.0 * args.snapshot_every_min
    old, freed = snaps.drop_other_versions()
    if old:
        notes.append(f"deleted {old} snapshots of another fold version "
                     f"({freed / 2**30:,.1f} GiB) from {snap_path.name}")
    mine = snaps.count(config)
    stale = snaps.count() - mine
    if stale:
        notes.append(f"{stale} snapshots of another fold config in {snap_path.name} "
                     "are ignored (delete the file and its .d folder to free the space)")
    reach = snaps.latest_valid_ns(config) if mine else None
    if mine and (reach is None or reach < last - every_s * NS_PER_S):
        # a build that was stopped part way: its snapshots stop short of the end
        notes.append(f"{snaps.drop(config)} snapshots that stopped short of the "
                     "ledger's end (a build stopped part way) were rebuilt")
        mine = 0
    if not mine:
        t_build = time.perf_counter()
        with every_core():    # the frames of each snapshot compress in parallel
            saved = build_snapshots(
                store, snaps, pile, every_ns=int(every_s * NS_PER_S), config=config,
                progress=lambda n, v: print(
                    f"  snapshot {n} at site hour {(v - first) / NS_PER_H:.2f} "
                    f"({time.perf_counter() - t_build:.0f} s)", file=sys.stderr,
                    flush=True))
        size = snap_path.stat().st_size + sum(
            f.stat().st_size for f in Path(str(snap_path) + ".d").glob("*.snap*"))
        notes.append(f"snapshots: {saved} (one per {args.snapshot_every_min:g} site "
                     f"min, {size / 2**20:,.0f} MiB) built in "
                     f"{time.perf_counter() - t_build:.1f} s into {snap_path.name}")


def _as_of_row(store, snaps, pile: str, label: str, v: int | None, k: int | None,
               scratch: bool) -> tuple[list[str], bool, int]:
    """Time one query from the snapshots (one core, every core), its peak memory and, when
    ``scratch``, the same query folded from the first event; the table row, whether it
    meets the target, and the number of cores."""
    t0 = time.perf_counter()
    fast = project(store, pile, v, k, snapshots=snaps)
    one_core = time.perf_counter() - t0
    with every_core() as n_cores:
        t0 = time.perf_counter()
        project(store, pile, v, k, snapshots=snaps)
        seconds = time.perf_counter() - t0
    # memory on a third run: tracing allocations slows numpy down
    tracemalloc.start()
    project(store, pile, v, k, snapshots=snaps)
    _cur, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    if scratch:
        t0 = time.perf_counter()
        slow = project(store, pile, v, k)
        scratch_s = time.perf_counter() - t0
        same = (math.isclose(fast.tonnes, slow.tonnes, rel_tol=1e-9)
                and len(fast.cuts) == len(slow.cuts))
        cells = [f"{scratch_s:.1f}", f"{scratch_s / seconds:.0f}x", "yes" if same else "NO"]
    else:   # not folded from the first event (--scratch)
        same, cells = True, ["-", "-", "-"]
    good = max(seconds, one_core) <= 2.0 and same
    row = [label, f"{fast.tonnes:,.0f}", str(len(fast.cuts)), f"{one_core:.2f}",
           f"{seconds:.2f}", cells[0], cells[1], f"{peak / 2**20:.0f} MiB", cells[2],
           "PASS" if good else "MISS"]
    return row, good, n_cores


def section_as_of(args) -> Section:
    """``project(V, K)`` on a 24-hour full-scale ledger, from a snapshot vs from scratch."""
    ledger, scenario = _ledger_for_as_of(args)
    snap_path = ledger.with_name(f"{ledger.stem}-snapshots-{args.snapshot_every_min:g}min.duckdb")
    pile = "P1"
    rows, ok, notes = [], True, []
    with open_ledger(ledger, read_only=True) as store:
        head = store.head()
        events = head.global_seq + 1
        first = next(iter(store.read(0, 1))).valid_time_ns
        last = max(e.valid_time_ns for e in store.read(max(0, head.global_seq - 2000)))
        hours = (last - first) / NS_PER_H
        config = FoldConfig(pile_id=pile)
        with SnapshotStore(snap_path) as snaps:
            _ensure_snapshots(store, snaps, snap_path, pile, config, args, first, last, notes)
            queries = [("the end, everything known", None, None),
                       ("1 h before the end, known then", last - NS_PER_H,
                        head.recorded_time_ns - NS_PER_H),
                       ("half way, known now", first + (last - first) // 2, None)]
            # the first query of a process also pays for imports and DuckDB's first plans
            t0 = time.perf_counter()
            project(store, pile, first + (last - first) // 3, None, snapshots=snaps)
            notes.append(f"a first (cold) query, not in the table: {time.perf_counter() - t0:.2f} s")
            for label, v, k in queries:
                scratch = args.scratch == "all" or (args.scratch == "first" and not rows)
                row, good, n_cores = _as_of_row(store, snaps, pile, label, v, k, scratch)
                ok &= good
                rows.append(row)
            notes.append(f"'snapshot s' on {n_cores} cores (the snapshot's frames unpack in "
                         "parallel; the fold and the grade join run on one), beside the same "
                         "query pinned to one core ('1 core s'); the verdict asks both to meet "
                         "the target")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    notes.insert(0, f"{scenario}: {events:,} events over {hours:.1f} site hours; "
                    f"target <= 2 s from a snapshot; process peak RSS {rss:,.0f} MiB")
    return Section("as-of query (V, K) from a snapshot vs folded from the first event",
                   ["query", "tonnes", "cuts", "1 core s", "snapshot s", "scratch s", "speed-up",
                    "peak memory", "same", "verdict"], rows, notes, ok)


SECTIONS = [section_georef_fuse, section_voxels, section_as_of]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated range noise")
    ap.add_argument("--quick", action="store_true", help="smaller inputs (smoke run)")
    ap.add_argument("--ledger-dir", default="bench/out",
                    help="where section 3 keeps its simulated ledger (default %(default)s)")
    ap.add_argument("--scratch", choices=("all", "first", "none"), default="all",
                    help="section 3: fold which queries from the first event too, to check "
                    "the snapshot's answer (a 24-hour full-scale fold takes tens of minutes)")
    ap.add_argument("--snapshot-every-min", type=float, default=10.0,
                    help="section 3: site minutes between snapshots (default %(default)s)")
    ap.add_argument("--section", type=int, action="append",
                    help="run only these sections (1-based; repeatable)")
    args = ap.parse_args(argv)
    pinned = pin_one_core()
    print(f"projector benchmarks: seed={args.seed}, numpy {np.__version__}, {pinned}"
          + (", quick" if args.quick else ""))
    ok = True
    for number, section in enumerate(SECTIONS, start=1):
        if args.section and number not in args.section:
            continue
        result = section(args)
        print_section(number, result)
        ok &= result.ok
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
