"""The demo's drone survey: the simulator flies one between stacking and reclaiming, and
the demo reconciles the model against it, as a yard does with its month-end survey.

- :func:`survey_time_ns`: when (halfway between the scanner's survey pass and the start
  of reclaiming, whole seconds), or None when the run ends before it;
- :func:`reconcile_survey`: ``stockpile survey import`` of the simulator's LAZ file into
  the finished ledger, then ``stockpile audit survey``'s figures for it;
- :func:`say_survey`: the summary's lines.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from audit.surveys import audit_surveys
from ledger import open_ledger
from schemas.times import NS_PER_S, format_time_ns
from sim.live import milestones
from sim.survey import survey_stem
from surveys.importer import import_survey

__all__ = ["survey_time_ns", "reconcile_survey", "say_survey"]


def survey_time_ns(scenario, seed: int, duration_h: float | None) -> int | None:
    """The survey's time (UTC ns, whole seconds) for ``scenario`` run with ``seed``, or
    None when the run (``duration_h`` site hours) ends before it."""
    m = milestones(scenario, seed, duration_h)
    t = (m["survey_end_ns"] + m["reclaim_start_ns"]) // 2
    t -= t % NS_PER_S
    return t if m["start_ns"] < t < m["end_ns"] else None


def reconcile_survey(ledger_path: Path, sim_dir: Path, pile_id: str,
                     time_ns: int) -> dict[str, Any]:
    """Import the simulator's survey at ``time_ns`` into the ledger and reconcile the pile
    against it: the import's outcome and the report's figures (m3, t, %)."""
    laz = sim_dir / f"{survey_stem(time_ns)}.laz"
    with open_ledger(ledger_path) as store:
        done = import_survey(laz, store, pile_id, time_ns, provider="sim drone",
                             accuracy_m=0.03)
        rows = [r for r in audit_surveys(store, pile_id) if r.survey_id == done.survey_id]
    result: dict[str, Any] = {"file": str(laz), "outcome": done.outcome,
                              "reason": done.reason, "points": done.points}
    if rows:
        r = rows[0]
        result.update({"time": format_time_ns(r.time_ns), "area_m2": r.area_m2,
                       "survey_m3": r.survey_m3, "model_m3": r.model_now_m3,
                       "diff_m3": r.diff_now_m3, "diff_t": r.diff_now_t,
                       "diff_pct": r.diff_now_pct,
                       "largest_blocks": [{"x_m": x, "y_m": y, "diff_m3": d}
                                          for x, y, d in r.largest_blocks(3)]})
    return result


def say_survey(result: dict[str, Any], ledger_path: Path, pile_id: str) -> None:
    """Print :func:`reconcile_survey`'s result."""
    print(f"   {result['file']}: {result['points']:,} points, {result['outcome']}"
          f"{' (' + result['reason'] + ')' if result['reason'] else ''}", flush=True)
    if "diff_pct" not in result:
        return
    where = "; ".join(f"x {b['x_m']:.0f} y {b['y_m']:.0f} m: {b['diff_m3']:+,.1f} m3"
                      for b in result["largest_blocks"])
    print(f"   at {result['time']} over {result['area_m2']:,.0f} m2: survey "
          f"{result['survey_m3']:,.1f} m3, model {result['model_m3']:,.1f} m3, difference "
          f"{result['diff_m3']:+,.1f} m3 ({result['diff_t']:+,.0f} t, "
          f"{result['diff_pct']:+.2f} %); largest by 10 m block: {where}", flush=True)
    print(f"   stockpile audit survey --ledger {ledger_path} --pile {pile_id}", flush=True)
