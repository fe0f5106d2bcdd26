"""Predicted tonnes and grade of planned cuts, and grade bounds for a bench.

The grade join is the projector's: each planned cut's removal (per deposit: cell volumes
and deposition times, from :meth:`projector.layers.LayerStack.clamp`) is handed to
:func:`projector.query.summarise` as a cut record, so tonnes (bulk density from
the assay, else the pile's default), grade per analyte (assays known at K, FINAL over
PROVISIONAL, superseding; the lot's planned grade where none) and the assayed fraction
come out of exactly the code that reports the pile's real cuts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from projector import fold as F
from projector.grid import GridGeometry
from projector.layers import LayerStack, Removal
from projector.query import summarise

__all__ = ["CutPrediction", "predict_cuts", "BoundsReport", "check_bounds"]


@dataclass(frozen=True)
class CutPrediction:
    """One planned cut's predicted material.

    Attributes
    ----------
    volume_m3 : float
    tonnes : float
    grade : dict
        Analyte -> mass % (NaN when nothing is removed).
    assayed_fraction : float
        Share of the tonnes whose grade comes from an assay known at K (0..1).
    deposits : list of dict
        Per deposit: ``deposit``, ``pass_id``, ``lot_id``, ``volume_m3``, ``tonnes``.
    tonnes_sd, grade_sd : float, dict
        The tonnes' standard deviation (t) and the grade's per analyte (pp)
        (:mod:`projector.summary_sd`).
    """

    volume_m3: float
    tonnes: float
    grade: dict[str, float]
    assayed_fraction: float
    deposits: list[dict]
    tonnes_sd: float = math.nan
    grade_sd: dict[str, float] = field(default_factory=dict)


def predict_cuts(geometry: GridGeometry, removals: Sequence[Removal | Sequence[Removal]],
                 lots: Mapping[str, Mapping[str, float]], assays: Sequence,
                 known_time_ns: int, default_bulk_density_t_m3: float, *,
                 pile_id: str = "", height=None) -> list[CutPrediction]:
    """Tonnes, grade and assayed fraction of each planned cut, as known at K.

    Parameters
    ----------
    geometry : GridGeometry
        The pile's grid.
    removals : sequence
        Per cut, a :class:`Removal` or a sequence of them (material taken by the cut).
    lots : mapping
        Lot id -> planned grade (analyte -> mass %).
    assays : sequence of AssayRecord
        Every assay the ledger holds (those recorded after K are ignored by the join).
    known_time_ns : int
        K (UTC ns).
    default_bulk_density_t_m3 : float
        The pile's density where no assay gives one (t/m3, > 0).
    height : projector.heightmap.HeightMap, optional
        The pile's fused height map: its variances over a cut's footprint are the
        volume's; without it every cell counts as never seen.

    Returns
    -------
    list of CutPrediction
    """
    if not (math.isfinite(default_bulk_density_t_m3) and default_bulk_density_t_m3 > 0):
        raise ValueError(f"default_bulk_density_t_m3 must be > 0, got "
                         f"{default_bulk_density_t_m3!r}")
    if isinstance(known_time_ns, bool) or not isinstance(known_time_ns, (int, np.integer)):
        raise TypeError(f"known_time_ns must be an integer (UTC ns), got {known_time_ns!r}")
    records = []
    for k, r in enumerate(removals):
        parts = [r] if isinstance(r, Removal) else list(r)
        if not all(isinstance(p, Removal) for p in parts):
            raise TypeError("removals must be Removal objects (or sequences of them)")
        records.append(F.CutRecord(f"plan-{k + 1:02d}", "plan", "", 0, 0, math.nan,
                                   removals=parts))
    # a state holding only the planned cuts: summarise joins their removals' grades
    state = F.initial_state(pile_id)
    state.pile = F.PileInfo(pile_id, geometry, 0.0, geometry.cell_m,
                            float(default_bulk_density_t_m3))
    state.stack = LayerStack.empty(geometry, 0.0)
    state.cuts = records
    state.height = height
    summary = summarise(state, dict(lots), list(assays), valid_time_ns=int(known_time_ns),
                        known_time_ns=int(known_time_ns))
    return [CutPrediction(c.volume_m3, c.tonnes, dict(c.grade), c.assayed_fraction,
                          list(c.deposits), c.tonnes_sd, dict(c.grade_sd))
            for c in summary.cuts]


@dataclass(frozen=True)
class BoundsReport:
    """Which predicted cuts fall outside grade bounds, and the bench's grade.

    Attributes
    ----------
    outside : list of dict
        Per offending cut: ``cut`` (1-based), ``analyte``, ``grade`` (%), ``bound`` ("min"
        or "max") and ``limit`` (%).
    bench_tonnes : float
    bench_grade : dict
        Tonnage-weighted grade of all the cuts (analyte -> %).
    bench_outside : list of str
        Analytes whose bench grade is outside its bounds.
    """

    outside: list[dict]
    bench_tonnes: float
    bench_grade: dict[str, float]
    bench_outside: list[str]


def check_bounds(predictions: Sequence[CutPrediction],
                 bounds: Mapping[str, tuple[float | None, float | None]]) -> BoundsReport:
    """Grade bounds (e.g. ``{"Fe": (61.0, None), "SiO2": (None, 5.0)}``) against the cuts.

    Parameters
    ----------
    predictions : sequence of CutPrediction
    bounds : mapping
        Analyte -> ``(min %, max %)``; None = no bound on that side.

    Returns
    -------
    BoundsReport

    Raises
    ------
    ValueError
        On a non-finite bound or min > max.
    """
    for analyte, (lo, hi) in bounds.items():
        for v in (lo, hi):
            if v is not None and not math.isfinite(float(v)):
                raise ValueError(f"bound for {analyte} must be finite, got {v!r}")
        if lo is not None and hi is not None and lo > hi:
            raise ValueError(f"bounds for {analyte}: min {lo} > max {hi}")
    outside = []
    tonnes = 0.0
    sums: dict[str, float] = {}
    for k, p in enumerate(predictions, 1):
        for analyte, (lo, hi) in bounds.items():
            g = p.grade.get(analyte, math.nan)
            if lo is not None and g < lo:
                outside.append({"cut": k, "analyte": analyte, "grade": g, "bound": "min",
                                "limit": float(lo)})
            if hi is not None and g > hi:
                outside.append({"cut": k, "analyte": analyte, "grade": g, "bound": "max",
                                "limit": float(hi)})
        if p.tonnes > 0:
            tonnes += p.tonnes
            for analyte, g in p.grade.items():
                if math.isfinite(g):
                    sums[analyte] = sums.get(analyte, 0.0) + p.tonnes * g
    grade = {a: (s / tonnes if tonnes > 0 else math.nan) for a, s in sums.items()}
    bench_out = [a for a, (lo, hi) in bounds.items()
                 if (lo is not None and grade.get(a, math.nan) < lo)
                 or (hi is not None and grade.get(a, math.nan) > hi)]
    return BoundsReport(outside, tonnes, grade, bench_out)
