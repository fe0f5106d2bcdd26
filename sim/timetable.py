"""The simulated yard's timetable in site time: stacking passes, survey, reclaim, the queue.

:func:`stacking_plan` lays out a scenario's passes (lot by lot, alternating direction
along the pile); :class:`Milestones` says when the scanner's run-on and survey end, when
reclaiming starts and when the run ends; :class:`Queue` is the event queue the runner
works through (site time, then the order things were scheduled in). Times are UTC ns.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

from schemas.times import NS_PER_S
from sim.grades import LabResult
from sim.scenario import Scenario

CHUNK_S = 30.0           # stacking is released in chunks of this much site time
PATROL_LAG_S = 2 * CHUNK_S  # the scanner trails the stacker by this much while it stacks


def stacking_plan(sc: Scenario) -> list[dict]:
    """The scenario's passes in order: pass id, lot (and its index), start and end time
    (``t0``, ``t1``), deposit number and the run along the pile (``y0`` -> ``y1``, m)."""
    t = sc.start_ns + 300 * NS_PER_S
    plan = []
    n = 0
    for lot_index, lot in enumerate(sc.lots):
        for p in range(sc.passes_per_lot):
            t0, t1 = t, t + int(sc.pass_duration_s * NS_PER_S)
            forward = n % 2 == 0
            plan.append({"pass_id": f"{lot.lot_id}-P{p + 1}", "lot": lot, "lot_index": lot_index,
                         "t0": t0, "t1": t1, "deposit": n,
                         "y0": sc.pile_origin_y_m + (0.1 if forward else 0.9) * sc.pile_length_m,
                         "y1": sc.pile_origin_y_m + (0.9 if forward else 0.1) * sc.pile_length_m})
            t = t1 + int(sc.pass_gap_s * NS_PER_S)
            n += 1
    return plan


@dataclass(frozen=True)
class Milestones:
    """When the stacking's aftermath ends and reclaiming starts (UTC ns).

    After the last pass the scanner runs on over its far end (``run_on_end``), then
    surveys the finished pile end to end, a scan line per surface cell at most at the
    travel speed (``survey_end``), before the first cut (``reclaim_start``); the run ends
    a minute after the last assay is reported (``end_ns``), or after ``duration_h``.
    """

    run_on_end: int
    survey_end: int
    reclaim_start: int
    end_ns: int

    @classmethod
    def of(cls, sc: Scenario, plan: list[dict], move_m_s: float, lab_results: list[LabResult],
           duration_h: float | None) -> "Milestones":
        run_on_end = plan[-1]["t1"] + int((PATROL_LAG_S + sc.pile_length_m / move_m_s)
                                          * NS_PER_S)
        survey_m_s = min(move_m_s, sc.surface_cell_m * sc.scan_hz)
        survey_end = run_on_end + int(sc.pile_length_m / survey_m_s * NS_PER_S)
        reclaim_start = max(plan[-1]["t1"] + int(600 * NS_PER_S), survey_end + int(30 * NS_PER_S))
        end_ns = (max(r.reported_ns for r in lab_results) if lab_results else reclaim_start)
        end_ns += 60 * NS_PER_S
        if duration_h is not None:
            end_ns = sc.start_ns + int(duration_h * 3600 * NS_PER_S)
        return cls(run_on_end, survey_end, reclaim_start, end_ns)


class Queue:
    """Things to do in site time: ``(t_ns, order, kind, payload)``, earliest first, and
    at one time in the order they were scheduled."""

    def __init__(self) -> None:
        self.items: list[tuple[int, int, str, object]] = []
        self._order = 0

    def at(self, t_ns: int, kind: str, payload: object = None) -> None:
        """Schedule ``kind`` (a runner handler ``_on_<kind>``) with ``payload`` at ``t_ns``."""
        self._order += 1
        heapq.heappush(self.items, (int(t_ns), self._order, kind, payload))

    def pop(self) -> tuple[int, int, str, object]:
        return heapq.heappop(self.items)

    def __bool__(self) -> bool:
        return bool(self.items)
