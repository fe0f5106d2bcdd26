"""The reclaimer's part of a simulated run: each cut planned, made and its faces' behaviour.

:class:`ReclaimRun` holds the :class:`sim.runner.Simulation` handlers of the reclaim (the
runner calls ``_on_<kind>`` for each queued event): the next cut is planned online on the
true pile (``reclaim``), the wheel moves (``cut_start``), the cut removes material in
:data:`CUT_SUBSWEEPS` steps of its slew (``cut_part``), and once the wheel has passed the
walls do what the scenario's material does (:class:`sim.material.CutFaces`); a delayed
failure is queued for its due time (``face_failure``). Times are site time (UTC ns).
"""

from __future__ import annotations

import numpy as np

from schemas.times import NS_PER_S
from sim import messages
from sim.motion import Motion, bench_luff, landing_travel, slew_range
from sim.records import cut_record, cut_totals

__all__ = ["CUT_SUBSWEEPS", "ReclaimRun", "cut_id_of"]

CUT_SUBSWEEPS = 8        # a cut removes material in this many steps of its slew
#: a run that ends on its own goes on this long after the last delayed failure (ns)
AFTER_LAST_FAILURE_NS = 60 * NS_PER_S


def cut_id_of(c: dict) -> str:
    """The cut's id, ``B<bench>-C<cut>`` counted from 1 (``C`` two digits)."""
    return f"B{c['bench'] + 1}-C{c['cut'] + 1:02d}"


class ReclaimRun:
    """The reclaim handlers of :class:`sim.runner.Simulation` (mixed into it: they use its
    scenario, machine, grid, world, motion, producers, devices, belt stream, stats,
    ``faces`` and the run's end, ``end_ns`` with ``end_fixed``)."""

    def _on_reclaim(self, t: int, state, at) -> None:
        """Plan and start the next cut (state = bench, cut index, travel of the last cut)."""
        sc, m = self.scenario, self.machine
        bench, cut, travel = state
        if bench >= sc.benches:
            self.reclaiming = False
            return
        self.reclaiming = True
        luff = bench_luff(sc, m, self.world, bench)
        if travel is None:  # landing: approach from the low-y end until the wheel meets the pile
            travel = landing_travel(sc, m, self.grid, self.world, luff)
        else:
            travel += m.cut_depth_m
        slews = slew_range(m, self.grid, self.world, travel, luff)
        if slews is None or cut >= sc.cuts_per_bench[bench]:
            at(t + int(120 * NS_PER_S), "reclaim", (bench + 1, 0, None))
            return
        lo, hi = slews if cut % 2 == 0 else slews[::-1]
        current = self.motion.at(t)
        move_s = abs(travel - current[0]) / self.move_m_s + 20.0
        t_start = t + int(move_s * NS_PER_S)
        self.motion = Motion(t, t_start, current, (travel, lo, luff))
        at(t_start, "cut_start", {"bench": bench, "cut": cut, "travel": travel, "luff": luff,
                                  "slew_start": lo, "slew_end": hi, "t0": t_start,
                                  "t1": t_start + int(sc.cut_duration_s * NS_PER_S), "parts": []})

    def _on_cut_start(self, t: int, c: dict, at) -> None:
        if self.cut_surfaces:
            if not self.truth_cut_surfaces:
                # the layers as stacked, before any cut or its slump moved them
                parcels = self.world.parcels()
                self.truth_first_cut_parcels = {
                    "first_cut_thickness": parcels["thickness"].astype(np.float32),
                    "first_cut_time_ns": parcels["time_ns"]}
            self.truth_cut_surfaces.append(self.world.surface_z().astype(np.float32))
        self.motion = Motion(c["t0"], c["t1"], (c["travel"], c["slew_start"], c["luff"]),
                             (c["travel"], c["slew_end"], c["luff"]))
        if self.real:
            self.devices.cut_started(t, c, cut_id_of(c))
        for k in range(CUT_SUBSWEEPS):
            at(c["t0"] + (c["t1"] - c["t0"]) * (k + 1) // CUT_SUBSWEEPS, "cut_part", (c, k))

    def _on_cut_part(self, t: int, payload, at) -> None:
        c, k = payload
        a = c["slew_start"] + (c["slew_end"] - c["slew_start"]) * k / CUT_SUBSWEEPS
        b = c["slew_start"] + (c["slew_end"] - c["slew_start"]) * (k + 1) / CUT_SUBSWEEPS
        truth = self.world.reclaim_cut(self.machine, c["travel"], c["luff"], a, b, int(t),
                                       relax=False)
        c["parts"].append(truth)
        if k == CUT_SUBSWEEPS - 1:
            # the walls of the whole cut do what the material does once the wheel has passed
            self._settle_faces(t, c, at)
            self._finish_cut(t, c, at)

    def _settle_faces(self, t: int, c: dict, at) -> None:
        """The finished cut's faces per the material; a delayed failure is queued, and a
        run that ends on its own goes on until a minute after it."""
        due_ns = self.faces.after_cut(cut_id_of(c), t, c["parts"])
        if due_ns is not None:
            at(due_ns, "face_failure", len(self.faces.failures) - 1)
            if not self.end_fixed:
                self.end_ns = max(self.end_ns, due_ns + AFTER_LAST_FAILURE_NS)

    def _on_face_failure(self, t: int, index: int, at) -> None:
        """A delayed failure's slide (``index`` into ``faces.failures``)."""
        self.faces.fail(t, index)

    def _finish_cut(self, t: int, c: dict, at) -> None:
        sc = self.scenario
        totals = cut_totals(c["parts"], self.world.analytes)
        tonnes = totals["true_tonnes"]
        belt = tonnes * (1.0 + self.rng_belt.normal(0.0, sc.belt_scale_error_frac)) if tonnes > 0 else 0.0
        cut_id = cut_id_of(c)
        self.producers["reclaimer"].emit(messages.reclaim_cut(sc, c, cut_id, belt))
        if self.real:
            self.devices.cut_ended(t, belt)
        self.cuts.append(cut_record(c, cut_id, totals, belt))
        self.stats.cuts += 1
        at(t + int(30 * NS_PER_S), "reclaim", (c["bench"], c["cut"] + 1, c["travel"]))
