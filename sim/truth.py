"""Truth records of the simulated pile: what a cut removed, in JSON-safe form.

:class:`CutTruth` is exactly what one reclaimer cut took out of the world (tonnes, volume,
grade, tonnes per deposit and lot, the footprint); :func:`deposits_from_releases` sums
the stacker's releases per deposit; :func:`json_float` and :func:`jsonable` turn the
world's values into strict-JSON ones for ``truth.json``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class CutTruth:
    """Exactly what one reclaimer cut removed from the pile.

    ``tonnes`` = sum over removed parcel pieces of volume x bulk density; ``grade`` is the
    mass-weighted mean of the removed pieces per analyte (NaN when nothing was removed).
    ``footprint`` (bool, grid shape) marks the columns whose centre is inside the swept
    footprint. ``slump_m3`` is the volume that moved in the relaxation after the cut (not
    part of this cut's tonnes).
    """

    time_ns: int
    travel_m: float
    luff_rad: float
    slew_start_rad: float
    slew_end_rad: float
    tonnes: float
    volume_m3: float
    grade: dict
    tonnes_by_deposit: dict
    tonnes_by_lot: dict
    mean_deposition_time_ns: float | None
    footprint: np.ndarray = field(repr=False)
    slump_m3: float = 0.0
    slump_lost_tonnes: float = 0.0

    @property
    def footprint_cells(self) -> int:
        return int(np.count_nonzero(self.footprint))

    def to_dict(self) -> dict:
        """JSON-serialisable record (the footprint as a cell count and index bounds)."""
        fp = np.nonzero(self.footprint)
        bounds = None
        if fp[0].size:
            bounds = [int(fp[0].min()), int(fp[0].max()), int(fp[1].min()), int(fp[1].max())]
        return {"time_ns": int(self.time_ns), "travel_m": float(self.travel_m),
                "luff_rad": float(self.luff_rad), "slew_start_rad": float(self.slew_start_rad),
                "slew_end_rad": float(self.slew_end_rad), "tonnes": float(self.tonnes),
                "volume_m3": float(self.volume_m3),
                "grade": {k: json_float(v) for k, v in self.grade.items()},
                "tonnes_by_deposit": {str(k): float(v) for k, v in self.tonnes_by_deposit.items()},
                "tonnes_by_lot": {str(k): float(v) for k, v in self.tonnes_by_lot.items()},
                "mean_deposition_time_ns": json_float(self.mean_deposition_time_ns),
                "footprint_cells": self.footprint_cells, "footprint_index_bounds": bounds,
                "slump_m3": float(self.slump_m3),
                "slump_lost_tonnes": float(self.slump_lost_tonnes)}


def json_float(v):
    """A float for strict JSON: None for None, NaN and infinities."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def jsonable(v):
    """A deposit id or lot label as JSON: numpy integers as int; int, str, float and None
    as they are; anything else as its str."""
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (int, str, float)) or v is None:
        return v
    return str(v)


def deposits_from_releases(releases: list[dict], analytes: tuple[str, ...]) -> list[dict]:
    """What was stacked per deposit id, from the release records of
    :meth:`sim.world.World.deposit`: tonnes, first and last release time, lots and the
    tonnage-weighted belt grade per analyte, in order of first release."""
    out: dict = {}
    for r in releases:
        d = out.setdefault(r["deposit_id"], {"deposit_id": r["deposit_id"], "tonnes": 0.0,
                                             "lost_tonnes": 0.0, "t_first_ns": r["time_ns"],
                                             "t_last_ns": r["time_ns"], "lots": [],
                                             "_tg": np.zeros(len(analytes))})
        d["tonnes"] += r["tonnes"]
        d["lost_tonnes"] += r["lost_tonnes"]
        d["t_last_ns"] = r["time_ns"]
        if r["lot"] not in d["lots"]:
            d["lots"].append(r["lot"])
        d["_tg"] += r["tonnes"] * np.array([r["grade"][a] for a in analytes])
    res = []
    for d in out.values():
        tg = d.pop("_tg")
        d["grade"] = {a: (float(v / d["tonnes"]) if d["tonnes"] > 0 else None)
                      for a, v in zip(analytes, tg)}
        res.append(d)
    return res
