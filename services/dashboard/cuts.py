"""Reclaim cuts on the dashboard: what each cut took, then and now, and the planned bench.

:class:`CutLog` logs one point per cut at its end time (``/series/cuts/...``: tonnes by
geometry and belt scale, grade and assayed fraction at its end and as known now), a
reconciliation line in ``/log`` when a late assay moves a cut's grade by more than the
threshold, the ``/cuts/table`` document and the footprints ``/site/cuts`` coloured by
grade; :meth:`CutLog.log_plan` shows a reclaim plan's next bench (``/site/plan``,
``/plan/table``).
"""

from __future__ import annotations

import math

from services.dashboard.pose import cut_outline
from services.dashboard.recorder import iso, rr
from services.dashboard.style import colour_map

#: a cut's grade has moved when it differs from the one last logged by more than this, %
MOVED_PCT = 1e-9


class CutLog:
    """The cuts' series, reconciliation lines, table and footprints.

    Parameters
    ----------
    out : Recorder
    tracker : PileTracker
        The cuts' messages, the machines and the colour scales.
    config : Config
        ``analyte`` (table, footprints) and ``delta_threshold_pp`` (reconciliation).
    """

    def __init__(self, out, tracker, config) -> None:
        self.out, self.tracker, self.config = out, tracker, config
        self.at_end: dict = {}                        # cut -> the cut at its end
        self.logged: dict[str, dict[str, float]] = {}   # cut -> grade as last logged now
        self._sig = None

    def log_now(self, cut) -> None:
        """A cut's grade and assayed fraction as known now, at its end time."""
        self.out.at(cut.end_time_ns, self.tracker.seq)
        self.out.series("/series/cuts/assayed_fraction/known_now", cut.assayed_fraction)
        for a, g in cut.grade.items():
            self.out.series(f"/series/cuts/grade_pct/{a}/known_now", g)

    def log(self, state, v: int, *, live: bool) -> None:
        """An update's cuts (``v``: its V; ``live``: also as known now, each update)."""
        rows = []
        for cut in state.cuts:
            grade = dict(cut.grade)
            if cut.cut_id not in self.at_end:
                self._log_new(cut, grade, live=live)
            else:
                self._log_revised(cut, grade, v, live=live)
            rows.append(self._row(cut, grade))
        if rows:
            self._log_table(rows, v)
        self._log_footprints(state, v)

    def _log_new(self, cut, grade: dict[str, float], *, live: bool) -> None:
        self.at_end[cut.cut_id] = cut
        self.out.at(cut.end_time_ns, self.tracker.seq)
        self.out.series("/series/cuts/tonnes_t/geometry", cut.tonnes)
        self.out.band("/series/cuts/tonnes_t/geometry", cut.tonnes, cut.tonnes_sd)
        self.out.series("/series/cuts/tonnes_t/belt_scale", cut.tonnes_scale)
        self.out.series("/series/cuts/assayed_fraction/at_end", cut.assayed_fraction)
        for a, g in grade.items():
            self.out.series(f"/series/cuts/grade_pct/{a}/at_end", g)
            self.out.band(f"/series/cuts/grade_pct/{a}/at_end", g, cut.grade_sd.get(a))
        if live:
            self.log_now(cut)
        self.logged[cut.cut_id] = grade

    def _log_revised(self, cut, grade: dict[str, float], v: int, *, live: bool) -> None:
        """A known cut: re-logged as known now if its grade moved, and a reconciliation
        line if it moved by more than the threshold."""
        before = self.logged[cut.cut_id]
        moved = {a: g - before.get(a, math.nan) for a, g in grade.items()
                 if math.isfinite(g) and math.isfinite(before.get(a, math.nan))
                 and abs(g - before[a]) > MOVED_PCT}
        if not moved:
            return
        if live:
            self.log_now(cut)
        self.logged[cut.cut_id] = grade
        big = {a: d for a, d in moved.items() if abs(d) > self.config.delta_threshold_pp}
        if big:
            at_end = self.at_end[cut.cut_id].grade
            self.out.text(
                f"reconciliation: cut {cut.cut_id} "
                + ", ".join(f"{a} {before[a]:.2f} -> {grade[a]:.2f} % ({d:+.2f} pp; "
                            f"at its end {at_end.get(a, math.nan):.2f} %)"
                            for a, d in big.items())
                + f", assayed fraction {cut.assayed_fraction:.2f}", "WARN", valid_ns=v)

    def _row(self, cut, grade: dict[str, float]) -> str:
        at_end = self.at_end[cut.cut_id]
        a0 = self.config.analyte if self.config.analyte in grade else next(iter(grade), "")
        return (f"| {cut.cut_id} | {iso(cut.end_time_ns)} | {cut.tonnes:,.1f} | "
                f"{cut.tonnes_scale:,.1f} | {at_end.grade.get(a0, math.nan):.2f} | "
                f"{grade.get(a0, math.nan):.2f} | "
                f"{grade.get(a0, math.nan) - at_end.grade.get(a0, math.nan):+.2f} | "
                f"{at_end.assayed_fraction:.2f} / {cut.assayed_fraction:.2f} |")

    def _log_table(self, rows: list[str], v: int) -> None:
        rerun = rr()
        a0 = self.config.analyte
        self.out.at(v)
        self.out.log("/cuts/table", rerun.TextDocument(
            f"### Reclaim cuts of pile {self.tracker.pile_id} as known at ledger seq "
            f"{self.tracker.seq:,}\n\n"
            f"| cut | ended (UTC) | geometry t | belt scale t | {a0} at end % | {a0} now % "
            f"| d pp | assayed end / now |\n|---|---|---|---|---|---|---|---|\n"
            + "\n".join(rows), media_type=rerun.MediaType.MARKDOWN))

    def _log_footprints(self, state, v: int) -> None:
        """``/site/cuts``: each cut's footprint coloured by its grade, when one changed."""
        analyte = self.config.analyte
        sig = tuple((c.cut_id, round(c.grade.get(analyte, math.nan), 6)) for c in state.cuts)
        if sig == self._sig or not self.tracker.cut_msgs:
            return
        self._sig = sig
        strips, labels, colours = [], [], []
        lo, hi = self.tracker.colour_range(analyte)
        for cut in state.cuts:
            msg = self.tracker.cut_msgs.get(cut.cut_id)
            m = self.tracker.machines.get(msg.machine_id) if msg is not None else None
            if m is None:
                continue
            strips.append(cut_outline(m.reclaimer, msg.travel_m, msg.luff_rad,
                                      msg.slew_start_rad, msg.slew_end_rad))
            labels.append(cut.cut_id)
            colours.append(colour_map([cut.grade.get(analyte, math.nan)], lo, hi)[0])
        if strips:
            self.out.at(v)
            self.out.log("/site/cuts", rr().LineStrips3D(strips, labels=labels, colors=colours,
                                                         radii=0.15))

    def log_plan(self, plan: dict, v: int) -> int:
        """Show a reclaim plan (:func:`planner.cli.make_plan`) at ``v``: each planned cut's
        footprint at its floor coloured by its predicted grade, and a table; returns the
        number of cuts shown."""
        rerun = rr()
        m = self.tracker.machines.get(plan["machine_id"])
        if m is None or m.reclaimer is None or not plan["cuts"]:
            return 0
        analyte = self.config.analyte
        strips, labels, grades = [], [], []
        for c in plan["cuts"]:
            strips.append(cut_outline(m.reclaimer, c["travel_m"], c["luff_rad"],
                                      c["slew_start_rad"], c["slew_end_rad"]))
            g = c["grade"].get(analyte, math.nan)
            grades.append(g)
            labels.append(f"plan {c['cut']}: {c['tonnes']:,.4g} t, {analyte} {g:.2f} %")
        # the pile's colour scale, widened to the planned grades (none saturates)
        lo, hi = self.tracker.colour_range(analyte)
        finite = [g for g in grades if math.isfinite(g)]
        if finite:
            lo, hi = min(lo, *finite), max(hi, *finite)
        self.out.at(v)
        self.out.log("/site/plan", rerun.LineStrips3D(strips, labels=labels,
                                                      colors=colour_map(grades, lo, hi),
                                                      radii=0.2))
        self.out.log("/plan/table", rerun.TextDocument(
            f"### Next bench of pile {self.tracker.pile_id} by {plan['machine_id']} (planned)\n\n"
            f"Footprints coloured by predicted {analyte}: {lo:.3f} % blue to {hi:.3f} % red.\n\n"
            f"| cut | travel m | slew deg | tonnes | {analyte} % | assayed |\n"
            f"|---|---|---|---|---|---|\n{_plan_rows(plan, analyte)}",
            media_type=rerun.MediaType.MARKDOWN))
        return len(strips)


def _plan_rows(plan: dict, analyte: str) -> str:
    return "\n".join(
        f"| {c['cut']} | {c['travel_m']:.2f} | {math.degrees(c['slew_start_rad']):.1f} -> "
        f"{math.degrees(c['slew_end_rad']):.1f} | {c['tonnes']:,.4g} | "
        f"{c['grade'].get(analyte, math.nan):.2f} | {c['assayed_fraction']:.2f} |"
        for c in plan["cuts"])
