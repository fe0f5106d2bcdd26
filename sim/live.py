"""A simulated run's pace and its live mode: fast-forward to a live moment, then run paced.

A live run (``Simulation.run(live_at_ns=...)``, CLI ``--live-at``) evolves the world
exactly as a plain run of the same scenario and seed does (stacking, deposition, the lab,
reclaim planning and cuts), but before its live moment ``live_at_ns`` it samples no sensor
(encoders, GNSS, scanner, telegrams, clock start at ``live_at_ns``), emits nothing to any
sink and runs as fast as it can.  At the live moment every producer restarts as a device
does: epoch ``live_at_ns // 1e9``, seq 0 (the history, imported from an offline run, has
the scenario's start second as its epoch); the declarations at the start are not repeated.
From then on it runs paced (:class:`Pacer`) at the scenario's ``live_rates`` when set.

With a wall-clock moment ``live_wall_s`` (Unix s) the run waits after its fast-forward
until then, so that site time t happens at wall ``live_wall_s + (t - live_at_ns) / speed``
(throughout without an ``idle_speed``): two runs given the same live moment run in step.
Such a run keeps that mapping: behind it, it catches up rather than moving its schedule
on (:data:`REBASE_S`), so that the other bed's clock still dates its readings.  One that reaches the live moment late starts
at once and says on stderr how late.

:func:`milestones` is ``stockpile sim --milestones``: the timetable's moments without
running the world.  Times are site time (UTC ns) unless a name says otherwise.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import NamedTuple

from schemas.times import NS_PER_S, format_time_ns
from services.logfmt import log
from sim.grades import LabResult
from sim.motion import move_speed_m_s
from sim.records import lab_schedule
from sim.rng import named_rng
from sim.scenario import Scenario
from sim.timetable import Milestones, stacking_plan

__all__ = ["LATE_S", "REBASE_S", "LiveStart", "Pacer", "Rates", "live_start", "milestones",
           "prefixed_assays", "rates_of"]

#: a paced event handled this much (real seconds) behind schedule counts as late
LATE_S = 0.005
#: a paced run that falls further behind than this (real seconds) gives the lost time up:
#: its schedule moves on (site time runs slower for a moment) rather than catching up in a
#: burst, in which telegrams and clock ticks arrive together and a service that maps
#: arrival onto site time dates them seconds off
REBASE_S = 0.05


class Rates(NamedTuple):
    """The sensors' rates (Hz) while a machine works."""

    scan_hz: float
    gnss_hz: float
    encoder_hz: float


@dataclass(frozen=True)
class LiveStart:
    """Where a live run goes live: site time ``at_ns`` (UTC ns) and, optionally, the wall
    clock moment ``wall_s`` (Unix s, ``time.time()``) it must happen at."""

    at_ns: int
    wall_s: float | None = None

    @property
    def epoch(self) -> int:
        """The producers' epoch from the live moment on: its whole second."""
        return self.at_ns // NS_PER_S


def live_start(sc: Scenario, end_ns: int, at_ns: int | None, wall_s: float | None,
               speed: float) -> LiveStart | None:
    """The run's live moment (None: a plain run), checked against the scenario's start and
    the run's end ``end_ns``; ValueError, one line, when it cannot be."""
    if at_ns is None:
        if wall_s is not None:
            raise ValueError("a live wall time needs a live moment (--live-at)")
        return None
    at_ns = int(at_ns)
    if at_ns < sc.start_ns:
        raise ValueError(f"the live moment {format_time_ns(at_ns)} is before the scenario's "
                         f"start {format_time_ns(sc.start_ns)}")
    if at_ns > end_ns:
        raise ValueError(f"the live moment {format_time_ns(at_ns)} is after the run's end "
                         f"{format_time_ns(end_ns)}")
    if sc.start_ns < at_ns and at_ns // NS_PER_S == sc.start_ns // NS_PER_S:
        raise ValueError("the live moment must be the start or in a later second (the live "
                         "events' epoch is its second, the history's the start's)")
    if wall_s is not None and not speed > 0:
        raise ValueError("a live wall time paces the run: give a speed > 0 (--speed)")
    return LiveStart(at_ns, None if wall_s is None else float(wall_s))


def rates_of(sc: Scenario, live: LiveStart | None) -> Rates:
    """The sensors' rates of a run: the scenario's ``live_rates`` in a live run (its sensors
    run from the live moment only), else its ``scan_hz``, ``gnss_hz``, ``encoder_hz``."""
    if live is not None and sc.live_rates is not None:
        return Rates(*sc.live_rates)
    return Rates(sc.scan_hz, sc.gnss_hz, sc.encoder_hz)


def prefixed_assays(results: list[LabResult], prefix: str) -> list[LabResult]:
    """The lab's results with assay ids (and what they supersede) as ``<prefix>-<id>``, so
    that two runs on one site report distinct assays; unchanged without a prefix."""
    if not prefix:
        return results
    return [replace(r, assay_id=f"{prefix}-{r.assay_id}",
                    supersedes=f"{prefix}-{r.supersedes}" if r.supersedes else "")
            for r in results]


def milestones(sc: Scenario, seed: int, duration_h: float | None = None) -> dict:
    """The run's timetable without running the world (UTC ns): its start, the end of
    stacking (the last pass), of the survey, the start of reclaiming, the first cut's
    planned start (None: it is planned on the true pile when reclaiming starts), the
    default end (a minute after the last assay; later for a material whose delayed failures
    come after it) and the end with ``duration_h``."""
    plan = stacking_plan(sc)
    _belts, results = lab_schedule(sc, plan, named_rng(seed, "belt"))
    ms = Milestones.of(sc, plan, move_speed_m_s(sc.machine), results, None)
    end = Milestones.of(sc, plan, move_speed_m_s(sc.machine), results, duration_h).end_ns
    return {"scenario": sc.name, "seed": seed, "start_ns": sc.start_ns,
            "stacking_end_ns": plan[-1]["t1"], "survey_end_ns": ms.survey_end,
            "reclaim_start_ns": ms.reclaim_start, "first_cut_start_ns": None,
            "default_end_ns": ms.end_ns, "end_ns": end}


class Pacer:
    """Paces a run's site time against the wall clock: ``speed`` site seconds per wall
    second (``idle_speed`` while no machine works, if set); off until :meth:`start`, and
    always off at ``speed`` 0.  Counts late events and rebases in ``stats``
    (:class:`sim.runner.RunStats`)."""

    def __init__(self, speed: float, idle_speed: float, stats) -> None:
        self.speed, self.idle_speed, self.stats = speed, idle_speed, stats
        self.on = False
        self.rebase = True         # further behind than REBASE_S: move the schedule on
        self.wall_due_s = 0.0      # wall seconds from the schedule's start to the next event
        self.schedule0_s = 0.0     # the schedule's start, time.monotonic()

    def start(self, schedule0_s: float, *, rebase: bool = True) -> None:
        """Pace from now on, site time's current moment due at ``schedule0_s`` (monotonic);
        ``rebase`` False: keep to the schedule however far behind (catch up)."""
        self.on = self.speed > 0
        self.rebase = rebase
        self.wall_due_s, self.schedule0_s = 0.0, schedule0_s

    def wait(self, dt_ns: int, busy: bool) -> None:
        """Sleep until the event ``dt_ns`` of site time after the last one is due; a run
        further behind than REBASE_S moves its schedule on (if it rebases)."""
        if not self.on:
            return
        rate = self.idle_speed if (self.idle_speed and not busy) else self.speed
        self.wall_due_s += dt_ns / NS_PER_S / rate
        lag = self.wall_due_s - (time.monotonic() - self.schedule0_s)
        if lag > 0:
            time.sleep(lag)
        elif -lag > LATE_S:
            self.stats.late_events += 1
            self.stats.max_lag_s = max(self.stats.max_lag_s, -lag)
            if self.rebase and -lag > REBASE_S:
                self.schedule0_s -= lag          # lag < 0: the schedule moves on by it
                self.stats.rebases += 1
                self.stats.given_up_s -= lag


def live_schedule0(wall_s: float | None, stats) -> float:
    """When (``time.monotonic()``) the live moment happens: at the wall time ``wall_s``
    (Unix s), or now without one; now too when that has passed, and then one warning log
    line on stderr (``msg="reached the live moment late"``) says how late (kept in
    ``stats.live_late_s``)."""
    now = time.monotonic()
    if wall_s is None:
        return now
    late_s = time.time() - wall_s
    if late_s <= 0:
        return now - late_s
    stats.live_late_s = late_s
    log("sim", "reached the live moment late", level="warning", late_s=f"{late_s:.3f}",
        live_wall_s=f"{wall_s:.3f}", running="from now")
    return now
