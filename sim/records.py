"""The records of a simulated run: the laboratory's results, each cut's truth, truth.json/.npz.

- :func:`lab_schedule` draws every lot's belt grade and the assays the laboratory will
  report on it; :func:`lab_windows` and :func:`window_value` give the laboratory's Fe of
  the sampling window a moment of belt flow falls in (the world's extra grade channel
  :data:`LAB_WINDOW_FE`);
- :func:`flow_grade` is the grade the belt flow carries into the world, that channel
  included;
- :func:`cut_totals` sums a cut's sub-sweeps (:class:`~sim.truth.CutTruth`) into its
  true tonnes, grade, lab-window Fe and tonnes per lot and deposit, :func:`cut_record`
  the cut's entry in truth.json;
- :func:`write_truth` writes a finished run's ground truth: ``truth.json`` (scenario,
  machine, seeds, stats, passes, cuts, assays, the world's summary, and ``material``: the
  material's parameters, every slide after a cut and every delayed failure's drawn delay,
  :meth:`sim.material.CutFaces.truth`) and ``truth.npz``
  (the surface, layer tops and parcels, the true joints, scanner poses and antenna
  positions over time, and with ``cut_surfaces`` the surface at each cut's start).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from sim.grades import BeltGrade, LabModel, LabResult
from sim.scenario import Scenario
from sim.truth import CutTruth

#: The world's extra grade channel: the laboratory's Fe (mass %) of the assay window each
#: piece of belt flow falls in (see Simulation.__init__); cut records give its mean as
#: ``lab_window_fe_pct``.
LAB_WINDOW_FE = "Fe@lab-window"


def lab_schedule(sc: Scenario, plan: list[dict],
                 rng: np.random.Generator) -> tuple[dict[str, BeltGrade], list[LabResult]]:
    """Per lot, the belt grade over its passes of ``plan``
    (:func:`sim.timetable.stacking_plan`), and every assay the laboratory reports on them,
    in the order they are reported."""
    belts = {}
    counter = [0]
    lab = LabModel(window_s=sc.assay_window_s, delay_h=sc.assay_delay_h)
    results: list[LabResult] = []
    for lot_index, lot in enumerate(sc.lots):
        spans = [p for p in plan if p["lot_index"] == lot_index]
        belt = BeltGrade(lot, spans[0]["t0"], spans[-1]["t1"], rng)
        belts[lot.lot_id] = belt
        for p in spans:
            results += lab.assays(belt, p["t0"], p["t1"], rng, counter)
    results.sort(key=lambda r: (r.reported_ns, r.assay_id))
    return belts, results


def lab_windows(results: list[LabResult], analyte: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per lot, the laboratory's final value of ``analyte`` (mass %) per sampling window:
    (window starts in UTC ns, values), in time order (a FINAL replaces the PROVISIONAL
    result of its window)."""
    final = {(r.lot_id, r.window_start_ns): r.analytes_pct[analyte]
             for r in results if r.status == "FINAL"}
    by_lot: dict[str, list[tuple[int, float]]] = {}
    for (lot, start_ns), value in sorted(final.items()):
        by_lot.setdefault(lot, []).append((start_ns, value))
    return {lot: (np.array([t for t, _ in rows], np.int64), np.array([v for _, v in rows]))
            for lot, rows in by_lot.items()}


def window_value(windows: tuple[np.ndarray, np.ndarray], time_ns: int) -> float:
    """The value of the window that holds ``time_ns`` (the first or last beyond the ends)."""
    starts, values = windows
    i = int(np.searchsorted(starts, time_ns, side="right")) - 1
    return float(values[min(max(i, 0), len(values) - 1)])


def flow_grade(belt: BeltGrade, windows: tuple[np.ndarray, np.ndarray] | None,
               planned_fe: float):
    """The grade a moment of the lot's belt flow carries into the world: a function of
    site time (UTC ns) -> the belt's analytes (mass %) followed by the :data:`LAB_WINDOW_FE`
    channel (``planned_fe`` for a lot the laboratory never sampled, ``windows`` None)."""
    def grade(tt: int) -> np.ndarray:
        return np.append(belt.at(tt), window_value(windows, tt) if windows else planned_fe)
    return grade


def cut_totals(parts: list[CutTruth], analytes) -> dict:
    """One cut's truth from its sub-sweeps: ``true_tonnes``, ``true_volume_m3``,
    ``slump_m3``, tonnage-weighted ``grade`` (mass %, NaN when nothing was taken) of
    ``analytes`` but :data:`LAB_WINDOW_FE`, whose mean is ``lab_window_fe_pct``, and
    ``tonnes_by_lot`` / ``tonnes_by_deposit`` (string keys)."""
    tonnes = sum(p.tonnes for p in parts)
    grade = {}
    for a in analytes:   # the analytes and the lab's channel
        mass = sum(p.tonnes * p.grade[a] for p in parts if p.tonnes > 0)
        grade[a] = mass / tonnes if tonnes > 0 else float("nan")
    lab_fe = grade.pop(LAB_WINDOW_FE)
    by_lot: dict[str, float] = {}
    for p in parts:
        for lot, tn in p.tonnes_by_lot.items():
            by_lot[str(lot)] = by_lot.get(str(lot), 0.0) + tn
    by_deposit: dict[str, float] = {}
    for p in parts:
        for dep, tn in p.tonnes_by_deposit.items():
            by_deposit[str(dep)] = by_deposit.get(str(dep), 0.0) + tn
    return {"true_tonnes": tonnes, "true_volume_m3": sum(p.volume_m3 for p in parts),
            "slump_m3": sum(p.slump_m3 for p in parts), "grade": grade,
            "lab_window_fe_pct": lab_fe, "tonnes_by_lot": by_lot, "tonnes_by_deposit": by_deposit}


def cut_record(c: dict, cut_id: str, totals: dict, belt_tonnes: float) -> dict:
    """A finished cut as truth.json lists it: the cut as planned (``c``: t0, t1, travel,
    luff, slews), its :func:`cut_totals` and the tonnes the belt scale weighed."""
    return {"cut_id": cut_id, "t0_ns": c["t0"], "t1_ns": c["t1"], "travel_m": c["travel"],
            "luff_rad": c["luff"], "slew_start_rad": c["slew_start"],
            "slew_end_rad": c["slew_end"], "true_tonnes": totals["true_tonnes"],
            "true_volume_m3": totals["true_volume_m3"], "belt_tonnes": belt_tonnes,
            "slump_m3": totals["slump_m3"], "grade": totals["grade"],
            "lab_window_fe_pct": totals["lab_window_fe_pct"],
            "tonnes_by_lot": totals["tonnes_by_lot"],
            "tonnes_by_deposit": totals["tonnes_by_deposit"]}


def write_truth(sim) -> None:
    """Write ``truth.json`` and ``truth.npz`` of a finished :class:`sim.runner.Simulation`
    into its ``out_dir``."""
    world = sim.world
    truth = {
        "scenario": {k: (v if isinstance(v, (int, float, str, bool, type(None))) else str(v))
                     for k, v in asdict(sim.scenario).items()
                     if k not in ("lots", "machine", "material")},
        "machine": asdict(sim.machine),
        "material": sim.faces.truth(),
        "seed": sim.seed,
        "noise_seed": sim.noise_seed,
        "stats": asdict(sim.stats),
        "passes": sim.passes,
        "cuts": sim.cuts,
        "assays": [asdict(r) for r in sim.lab_results],
        "world": world.summary(),
    }
    truth["world"].pop("cuts", None)  # per sub-sweep; the per-cut totals are in "cuts"
    (sim.out_dir / "truth.json").write_text(json.dumps(clean(truth), indent=1, sort_keys=True))
    arrays = {"surface_z": world.surface_z(), "layer_tops": world.layer_surfaces(),
              "x_centres": world.grid.x_centres, "y_centres": world.grid.y_centres,
              "joints": np.asarray(sim.truth_joints, dtype=np.float64).reshape(-1, 4),
              "scanner_poses": np.asarray(sim.truth_scans, dtype=np.float64).reshape(-1, 13),
              "antenna_enu": np.asarray(sim.truth_antenna, dtype=np.float64).reshape(-1, 4)}
    if sim.cut_surfaces:
        # a run stopped mid-cut has a surface for a cut it did not finish: not kept
        arrays["cut_surface_z"] = np.asarray(sim.truth_cut_surfaces[:len(sim.cuts)],
                                             np.float32).reshape(-1, *arrays["surface_z"].shape)
        arrays.update(sim.truth_first_cut_parcels)
    parcels = world.parcels()
    arrays.update(thickness=parcels["thickness"], time_ns=parcels["time_ns"],
                  grade=parcels["grade"], density_t_m3=parcels["density_t_m3"])
    np.savez_compressed(Path(sim.out_dir) / "truth.npz", **arrays)


def clean(value):
    """NaN/inf -> None, numpy scalars -> Python, recursively (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return clean(value.tolist())
    return value
