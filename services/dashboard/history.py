"""The pile over time: the ``/series/pile/...`` figures "as known then" and "as known now".

Each update logs the pile's tonnes, grade and assayed fraction as known then.  A kept
history point (:class:`HistoryPoint`) also holds a compact inventory of the pile at its
valid time (volume per lot and deposition second, :func:`inventory`), so its figures
can be re-evaluated with the assays known at a later K (:func:`join_inventory`):
:class:`History` logs them "as known now" once at the end of a catch-up or an offline
render (:meth:`History.flush`) and, live, re-logs past points a late assay revises
(:meth:`History.revise`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from projector.query import GradeJoin
from schemas.times import NS_PER_S

#: bins of deposition time in a history point's inventory (grades join per bin), ns
INVENTORY_BIN_NS = NS_PER_S
MAX_HISTORY_POINTS = 20_000

#: ``(tonnes, grade % per analyte, assayed fraction)`` of the pile
Figures = tuple[float, dict[str, float], float]


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
                   density_default: float) -> Figures:
    """``(tonnes, grade %, assayed fraction)`` of an inventory as known at K (the join of
    :func:`projector.query.summarise`, per deposition-time bin)."""
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


def same_figures(a: Figures, b: Figures, tol: float = 1e-9) -> bool:
    """Whether two figures agree to ``tol`` (relative for tonnes; NaN grades agree)."""
    if abs(a[0] - b[0]) > tol * max(1.0, abs(b[0])) or abs(a[2] - b[2]) > tol:
        return False
    for k, v in a[1].items():
        w = b[1].get(k, math.nan)
        if math.isfinite(v) != math.isfinite(w) or (math.isfinite(v) and abs(v - w) > tol):
            return False
    return True


def _figures(state) -> Figures:
    return (state.tonnes, dict(state.grade), state.assayed_fraction)


@dataclass
class HistoryPoint:
    """The pile at one update: its V and K, inventory and figures as known now."""

    valid_ns: int
    seq: int
    inventory: list
    density_default: float
    now: Figures
    now_logged: bool = False


class History:
    """The kept history points and the ``/series/pile/...`` time series.

    Parameters
    ----------
    out : Recorder
    tracker : PileTracker
        The projection's lots and assays, K and the seq read.
    every_ns : int
        Live: valid time between two kept history points (an update with a reason is
        always kept).
    """

    def __init__(self, out, tracker, every_ns: int) -> None:
        self.out, self.tracker, self.every_ns = out, tracker, every_ns
        self.points: list[HistoryPoint] = []
        self.last_point_valid_ns: int | None = None

    def log_figures(self, suffix: str, tonnes: float, grade: dict, assayed: float) -> None:
        """The pile's figures ``known_then`` or ``known_now`` at the time last set."""
        self.out.series(f"/series/pile/tonnes_t/{suffix}", tonnes)
        self.out.series(f"/series/pile/assayed_fraction/{suffix}", assayed)
        for a, g in grade.items():
            self.out.series(f"/series/pile/grade_pct/{a}/{suffix}", g)

    def log_totals(self, state, *, now: bool) -> None:
        """An update's figures as known then (and, ``now``, as known now) and its volume."""
        self.log_figures("known_then", state.tonnes, state.grade, state.assayed_fraction)
        self.out.band("/series/pile/tonnes_t/known_then", state.tonnes, state.tonnes_sd)
        for a, g in state.grade.items():
            self.out.band(f"/series/pile/grade_pct/{a}/known_then", g, state.grade_sd.get(a))
        if now:
            self.log_figures("known_now", state.tonnes, state.grade, state.assayed_fraction)
        self.out.series("/series/pile/volume_m3", state.volume_m3)

    def keep_due(self, v: int, *, live: bool) -> bool:
        """Whether the update at ``v`` is kept as a history point (always but live)."""
        return (not live or self.last_point_valid_ns is None or bool(self.tracker.reasons)
                or v - self.last_point_valid_ns >= self.every_ns)

    def keep(self, state, v: int, *, live: bool) -> None:
        """Keep the update at ``v`` (its figures already logged as known now if ``live``);
        beyond :data:`MAX_HISTORY_POINTS` the older half is thinned, the newest kept."""
        pile = state.state.pile
        point = HistoryPoint(v, self.tracker.seq, inventory(state),
                             pile.default_bulk_density_t_m3, _figures(state), now_logged=live)
        self.points.append(point)
        self.last_point_valid_ns = v
        if len(self.points) > MAX_HISTORY_POINTS:   # thin the older half, keep the newest
            half = len(self.points) // 2
            self.points = self.points[:half:2] + self.points[half:]

    def _join_now(self, point: HistoryPoint, analytes) -> Figures:
        projection = self.tracker.projection
        return join_inventory(point.inventory, projection.lots, projection.assays,
                              self.tracker.known_ns, analytes, point.density_default)

    def revise(self, state, v: int) -> int:
        """Live: re-evaluate the kept history points as known now; re-log those that moved."""
        changed = 0
        for point in self.points:
            if point.valid_ns >= v:
                continue
            now = self._join_now(point, state.analytes)
            if same_figures(now, point.now):
                continue
            point.now = now
            changed += 1
            self.out.at(point.valid_ns, self.tracker.seq)
            self.log_figures("known_now", *now)
        if changed:
            self.out.text(f"{changed} past history point(s) revised as known now", "INFO",
                          valid_ns=v)
        return changed

    def flush(self, state, last_update_seq: int, last_update_valid_ns: int | None) -> None:
        """Log "as known now" (at the latest K) for every history point not yet logged so;
        the point of the last update (``state``) takes that update's figures."""
        for point in self.points:
            if point.now_logged:
                continue
            if point.seq == last_update_seq and point.valid_ns == last_update_valid_ns:
                now = _figures(state)
            else:
                now = self._join_now(point, state.analytes)
            point.now, point.now_logged = now, True
            self.out.at(point.valid_ns, self.tracker.seq)
            self.log_figures("known_now", *now)
