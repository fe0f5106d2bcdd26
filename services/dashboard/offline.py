"""``stockpile dashboard``: a finished ledger rendered offline to the Rerun dashboard.

:func:`render_ledger` opens the ledger read-only and feeds every record, in global
order, to a :class:`~services.dashboard.core.Dashboard` exactly as the live service
would have seen them (updates at recorded-time boundaries), logs the ledger's gaps and
quarantined input as they became known, then "as known now" at the head and, with
``--plan-machine``, the next bench's plan.  :func:`register` adds the command,
:func:`cmd_dashboard` runs it.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from common.options import (add_duration, add_ledger, add_progress, describe_ledger,
                            is_ledger_url)
from common.progress import Progress, enabled_from_args, progress as progress_bar
from ledger import open_ledger
from planner.cli import make_plan, plan_args
from projector.query import CANONICAL_ANALYTES
from schemas.analytes import canonical_grades
from schemas.events import decode_payload
from services.dashboard.config import DEFAULT_EVERY_S, READ_CHUNK, Config, add_common_arguments
from services.dashboard.core import Dashboard, feed, rebuild_from
from services.dashboard.viewer import WebViewer, close_recording, make_recording
from services.service import Stopper, log

#: records between two progress reports
PROGRESS_EVERY = 5000


@dataclass(frozen=True)
class RenderResult:
    """What an offline render did."""

    pile_id: str
    records: int
    updates: int
    history_points: int
    rebuilds: int
    head_seq: int
    known_time_ns: int
    tonnes_t: float
    rrd: str | None
    url: str | None = None
    planned_cuts: int = 0


class StoreSource:
    """The offline source: a read-only ledger store, the client's interface."""

    def __init__(self, store, head_seq: int) -> None:
        self.store, self.head_seq = store, head_seq

    def read(self, start: int = 0, stop: int | None = None):
        return self.store.read(start, stop)

    def head(self) -> dict[str, Any]:
        return {"global_seq": self.head_seq}


def single_pile(store) -> str:
    """The only pile the ledger declares (ValueError if none or several)."""
    piles = []
    for event in store.read(types=["pile_declared"]):
        pid = decode_payload(event.type, event.payload).pile_id
        if pid not in piles:
            piles.append(pid)
    if not piles:
        raise ValueError("the ledger declares no pile")
    if len(piles) > 1:
        raise ValueError(f"the ledger declares several piles ({', '.join(piles)}): pass --pile")
    return piles[0]


def _pile_boxes(store) -> dict[str, tuple[float, float, float, float, float]]:
    """Each declared pile's ``(origin_x_m, origin_y_m, width_m, length_m, ground_z_m)``."""
    piles = {}
    for e in store.read(types=["pile_declared"]):
        msg = decode_payload(e.type, e.payload)
        piles.setdefault(msg.pile_id, (msg.origin_x_m, msg.origin_y_m, msg.width_m,
                                       msg.length_m, msg.ground_z_m))
    return piles


def _analytes(store) -> tuple[str, ...]:
    """The analytes the ledger's lots declare, canonical ones first."""
    names: set[str] = set()
    for e in store.read(types=["lot_declared"]):
        names.update(canonical_grades(decode_payload(e.type, e.payload).planned_grade))
    return tuple([a for a in CANONICAL_ANALYTES if a in names]
                 + sorted(names - set(CANONICAL_ANALYTES))) or CANONICAL_ANALYTES


def render_ledger(path: str, pile_id: str | None, config: Config, *,
                  progress: Callable[[int, int], None] | None = None,
                  recording_id: str | None = None, keep_serving: Stopper | None = None
                  ) -> RenderResult:
    """Render a finished ledger to Rerun (``config.rrd`` and/or ``config.serve``).

    Raises ValueError for a missing ledger or an unknown pile.
    """
    if not is_ledger_url(path) and not Path(path).exists():
        raise ValueError(f"no ledger at {path}")
    with open_ledger(path, read_only=True) as store:
        head = store.head()
        if head.global_seq < 0:
            raise ValueError(f"the ledger {describe_ledger(path)} is empty")
        pile_id = pile_id or single_pile(store)
        piles = _pile_boxes(store)
        if pile_id not in piles:
            raise ValueError(f"pile {pile_id!r} is not declared in {describe_ledger(path)}")
        analytes = _analytes(store)
        rec, uri = make_recording(config, analytes, recording_id=recording_id,
                                  pile=piles[pile_id])
        viewer = None
        try:
            viewer = WebViewer(config, uri) if config.serve and uri else None
            url = viewer.url if viewer else None
            if url:
                log("dashboard", "web viewer", url=url, grpc=uri)
            result = _render(store, head, pile_id, rec, config, progress, url, str(path))
            if keep_serving is not None and config.serve:
                log("dashboard", "serving until interrupted", url=url)
                keep_serving.wait()
        finally:
            if viewer is not None:
                viewer.close()
            close_recording(rec)
    return result


def _render(store, head, pile_id: str, rec, config: Config, progress, url,
            ledger_path: str = "") -> RenderResult:
    """Feed every record of ``store`` to a :class:`Dashboard` (the body of render_ledger)."""
    dash = Dashboard(rec, pile_id, config, offline=True)
    source = StoreSource(store, head.global_seq)
    gaps, quarantine = store.gaps(), store.quarantine()
    seen: set = set()
    total = head.global_seq + 1

    def on_record(n: int) -> None:
        if progress is not None and n % PROGRESS_EVERY == 0:
            progress(n, total)

    def rebuild() -> None:
        rebuild_from(source, dash)

    records = 0
    for chunk_start in range(0, total, READ_CHUNK * 4):
        chunk = list(store.read(chunk_start, min(total, chunk_start + READ_CHUNK * 4)))
        records += feed(dash, chunk, rebuild=rebuild,
                        on_record=lambda n, base=records: on_record(base + n))
        if gaps or quarantine:
            _log_gaps_and_quarantine(dash, gaps, quarantine, seen, dash.known_ns)
    if dash.projection.stale:
        rebuild()
    dash.projection.advance(everything=True)
    dash.reasons.add("end")
    dash.update()   # everything read (a no-op when the last update already had it all)
    _log_gaps_and_quarantine(dash, gaps, quarantine, seen, dash.known_ns)
    dash.flush_known_now()
    planned = 0
    if config.plan_machine:
        plan = make_plan(plan_args(ledger_path, pile_id, config.plan_machine,
                                   cuts=config.plan_cuts), store)
        planned = dash.log_plan(plan)
    if progress is not None:
        progress(total, total)
    state = dash.last_state
    return RenderResult(pile_id, records, dash.updates, len(dash.points), dash.rebuilds,
                        head.global_seq, dash.known_ns,
                        float(state.tonnes) if state is not None else math.nan,
                        config.rrd, url, planned)


def _log_gaps_and_quarantine(dash: Dashboard, gaps, quarantine, seen: set, known_ns: int) -> None:
    """Log gaps and quarantined input the ledger knew by ``known_ns`` (each once)."""
    for g in gaps:
        key = ("gap", g.gap_id, g.closed_recorded_ns is not None and g.closed_recorded_ns <= known_ns)
        if g.opened_recorded_ns > known_ns or key in seen:
            continue
        seen.add(key)
        if key[2]:
            dash.log_text(f"gap {g.gap_id} closed: {g.source} epoch {g.epoch} seq "
                          f"{g.first_seq}..{g.last_seq}", "INFO")
        else:
            dash.log_text(f"gap {g.gap_id} open: {g.source} epoch {g.epoch} seq {g.first_seq}.."
                          f"{g.last_seq} ({g.size:,} events missing)", "WARN")
    for q in quarantine:
        key = ("q", q.quarantine_id)
        if q.recorded_time_ns > known_ns or key in seen:
            continue
        seen.add(key)
        dash.log_text(f"quarantined {q.type or '?'} from {q.source or '?'}: {q.code}: "
                      f"{q.detail}", "ERROR")


# -- the command ------------------------------------------------------------------------------


def _progress_printer(bar: Progress) -> Callable[[int, int], None]:
    """``progress(done, total)`` for :func:`render_ledger`, drawn by ``bar``; the bar closes
    when the render is done (before a ``--serve`` keeps serving)."""

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update_to(done)
        if done >= total:
            bar.close()

    return progress


def cmd_dashboard(args: argparse.Namespace) -> int:
    """``stockpile dashboard``: render, print a one-line summary."""
    if not args.out and not args.serve:
        raise ValueError("give --out OUT.rrd and/or --serve")
    config = Config(pile_id=args.pile, serve=args.serve, rrd=args.out, grpc_port=args.grpc_port,
                    web_port=args.web_port, every_s=args.every,
                    analyte=args.analyte, layers=args.layers, layer_step_m=args.layer_step_m,
                    delta_threshold_pp=args.delta_threshold_pp, reorder_s=args.reorder_s,
                    plan_machine=args.plan_machine, plan_cuts=args.plan_cuts)
    t0 = time.monotonic()
    stopper = Stopper() if args.serve else None
    with progress_bar(unit="records", desc="dashboard", enabled=enabled_from_args(args)) as bar:
        result = render_ledger(args.ledger, args.pile, config, progress=_progress_printer(bar),
                               keep_serving=stopper)
    print(f"dashboard: pile {result.pile_id}: {result.records:,} records, {result.updates} "
          f"updates, {result.history_points} history points, {result.rebuilds} rebuilds, "
          f"{result.tonnes_t:,.1f} t at the end"
          + (f", {result.planned_cuts} planned cuts" if args.plan_machine else "")
          + (f" -> {result.rrd}" if result.rrd else "")
          + f" ({time.monotonic() - t0:.1f} s)")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """``stockpile dashboard --ledger PATH --out OUT.rrd``: render a finished ledger."""
    p = subparsers.add_parser(
        "dashboard", help="render a ledger to a Rerun dashboard (.rrd and/or the web viewer)",
        description="Render a finished ledger offline to the operators' Rerun dashboard: the "
        "same entities, timelines and blueprint as `stockpile service dashboard`.")
    add_ledger(p, help="opened read-only")
    p.add_argument("--pile", help="pile id (default: the only pile the ledger declares)")
    add_common_arguments(p)
    add_duration(p, "--every", default=DEFAULT_EVERY_S,
                 help="valid (site) time between history points, with a unit (default 5min)")
    add_progress(p)
    p.add_argument("--plan-machine", metavar="ID",
                   help="also plan the next bench of this reclaimer and show its cuts as "
                   "footprints coloured by predicted grade")
    p.add_argument("--plan-cuts", type=int, default=10, metavar="N",
                   help="cuts in the planned bench (default %(default)s)")
    p.set_defaults(func=cmd_dashboard)
