"""When the stacking passes' stackers crossed each row of cells.

A pass's stacker runs along the rail (y) from ``start_y_m`` to ``end_y_m`` at a steady
speed between the pass's start and end; a pass still running ends, by assumption, after
the typical duration of the passes before it.  From that: where each row lies along the
rail (:func:`row_y_m`), when a pass crossed it (:func:`crossing_ns`), which pass crossed
each row last (:func:`last_crossings`) and which cells a pass crossed since they were last
seen (:func:`stale`), the stacker's speed (:func:`stacker_speed_m_s`) and the crest its
boom pours on (:func:`row_crests_m`).  Times are UTC ns (float64 where computed).
"""

from __future__ import annotations

import math
from typing import Iterable

import numpy as np

from schemas.times import NS_PER_S

from projector.grid import GridGeometry, cell_centre
from projector.state import PassRecord, ProjectorState

__all__ = ["row_y_m", "typical_pass_s", "assumed_end_ns", "crossing_ns", "stacker_speed_m_s",
           "row_crests_m", "last_crossings", "stale"]


def row_y_m(geometry: GridGeometry) -> np.ndarray:
    """Where each row of cells lies along the rail: the y (m) of its centres, shape (ny,)."""
    return cell_centre(geometry, 0, np.arange(geometry.ny))[1]


def typical_pass_s(passes: Iterable[PassRecord]) -> float | None:
    """The median duration of the passes that ended (s), None when none has."""
    ended = [(p.ended_ns - p.started_ns) / NS_PER_S for p in passes if p.ended_ns is not None]
    return float(np.median(ended)) if ended else None


def assumed_end_ns(record: PassRecord, typical_s: float | None) -> float | None:
    """When a pass ended (UTC ns, float), or for one still running when it will, after the
    typical duration of the passes before it (None when none has ended)."""
    if record.ended_ns is not None:
        return float(record.ended_ns)
    return None if typical_s is None else float(record.started_ns) + typical_s * NS_PER_S


def crossing_ns(record: PassRecord, y_m: np.ndarray, now_ns: int,
                typical_s: float | None) -> np.ndarray:
    """When the stacker of a pass passed each position ``y_m`` along the rail (UTC ns,
    float64, shape of ``y_m``).

    The stacker moves from ``start_y_m`` to ``end_y_m`` at a steady speed between the
    pass's start and end; a pass still running ends, by assumption, after the typical
    duration ``typical_s`` of the passes before it (or ``now_ns`` when none ended yet).
    """
    t0 = float(record.started_ns)
    t1 = assumed_end_ns(record, typical_s)
    if t1 is None:
        t1 = float(max(now_ns, record.started_ns + 1))
    span = record.end_y_m - record.start_y_m
    if not math.isfinite(span) or span == 0:
        return np.full(y_m.shape, t0)
    frac = np.clip((y_m - record.start_y_m) / span, 0.0, 1.0)
    return t0 + frac * (t1 - t0)


def stacker_speed_m_s(record: PassRecord, typical_s: float | None) -> float:
    """The pass's stacker speed along the rail (m/s; NaN when its run or duration is
    unknown): its run over its duration (:func:`assumed_end_ns` for a running pass)."""
    t1 = assumed_end_ns(record, typical_s)
    run_m = abs(record.end_y_m - record.start_y_m)
    if t1 is None or t1 <= record.started_ns or not run_m > 0:
        return math.nan
    return run_m / ((t1 - record.started_ns) / NS_PER_S)


def row_crests_m(geometry: GridGeometry, top_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, crest)``: the cells' x centres (nx,) and, per row, the x of the highest cell of
    ``top_m`` (ny,), where a stacker's boom pours (m)."""
    x = cell_centre(geometry, np.arange(geometry.nx), 0)[0]
    return x, x[np.argmax(top_m, axis=0)]


def last_crossings(state: ProjectorState,
                   t_ns: int) -> tuple[list[PassRecord], np.ndarray, np.ndarray]:
    """The passes, and for each row along the rail (shape (ny,)) the index into them of the
    pass whose stacker crossed it last by ``t_ns`` and when (UTC ns, float64; -inf where
    none has, index 0 there)."""
    passes = list(state.passes.values())
    ny = state.pile.geometry.ny
    if not passes:
        return passes, np.zeros(ny, dtype=np.intp), np.full(ny, -np.inf)
    typical = typical_pass_s(passes)
    y = row_y_m(state.pile.geometry)
    crossings = np.stack([crossing_ns(record, y, t_ns, typical) for record in passes])
    crossings[crossings > t_ns] = -np.inf
    latest = np.argmax(crossings, axis=0)
    return passes, latest, crossings[latest, np.arange(ny)]


def stale(state: ProjectorState, t_ns: int, seen_ns: np.ndarray | None = None) -> np.ndarray:
    """Cells (nx, ny) never seen, or crossed by a pass's stacker since last seen by ``t_ns``
    (``seen_ns``: when each cell was last seen, UTC ns, NaN never; default the height
    map's ``last_update_ns``)."""
    seen = state.height.grid["last_update_ns"] if seen_ns is None else seen_ns
    _passes, _latest, last_crossing = last_crossings(state, t_ns)
    with np.errstate(invalid="ignore"):
        return ~np.isfinite(seen) | (seen < last_crossing[None, :])
