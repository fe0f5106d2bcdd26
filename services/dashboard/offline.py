"""``stockpile dashboard``: a finished ledger rendered offline to the Rerun dashboard.

:func:`render_ledger` opens the ledger read-only and feeds every record, in global
order, to a :class:`~services.dashboard.core.Dashboard` exactly as the live service
would have seen them (updates at recorded-time boundaries), logs the ledger's gaps and
quarantined input as they became known, then "as known now" at the head and, with
``--plan-machine``, the next bench's plan.  :func:`render_piles` renders several piles
(``--pile`` repeated) into one recording the same way, the ledger read once and each
pile's entities under ``/piles/<id>`` (:class:`~services.dashboard.piles.PileSet`; a plan
takes a single pile).  :func:`register` adds the command, :func:`cmd_dashboard` runs it.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from common.options import (add_duration, add_ledger, add_progress, describe_ledger,
                            is_ledger_url)
from common.progress import Progress, enabled_from_args, progress as progress_bar
from ledger import open_ledger
from planner.cli import make_plan, plan_args
from projector.query import CANONICAL_ANALYTES
from schemas.analytes import canonical_grades
from schemas.events import decode_payload
from services.dashboard.config import DEFAULT_EVERY_S, READ_CHUNK, Config, add_common_arguments
from services.dashboard.core import Dashboard, rebuild_from
from services.dashboard.piles import PileSet
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
    """Render one pile of a finished ledger to Rerun (``config.rrd`` and/or
    ``config.serve``; ``pile_id`` None: the only pile the ledger declares).

    Raises ValueError for a missing ledger or an unknown pile.
    """
    return render_piles(path, (pile_id,) if pile_id else (), config, progress=progress,
                        recording_id=recording_id, keep_serving=keep_serving)[0]


def render_piles(path: str, pile_ids: Sequence[str], config: Config, *,
                 progress: Callable[[int, int], None] | None = None,
                 recording_id: str | None = None, keep_serving: Stopper | None = None
                 ) -> list[RenderResult]:
    """Render piles of a finished ledger to one Rerun recording, reading it once; returns
    a result per pile, in order (``pile_ids`` empty: the only pile the ledger declares;
    ``config.piles`` is replaced by them).

    Raises ValueError for a missing ledger, an unknown or repeated pile, or
    ``config.plan_machine`` with several piles.
    """
    if not is_ledger_url(path) and not Path(path).exists():
        raise ValueError(f"no ledger at {path}")
    pile_ids = tuple(pile_ids)
    if pile_ids:
        config = replace(config, pile_id=pile_ids[0], piles=pile_ids)   # checks repeats
        if config.plan_machine and len(pile_ids) > 1:
            raise ValueError("--plan-machine plans one pile: give a single --pile")
    with open_ledger(path, read_only=True) as store:
        head = store.head()
        if head.global_seq < 0:
            raise ValueError(f"the ledger {describe_ledger(path)} is empty")
        pile_ids = pile_ids or (single_pile(store),)
        config = replace(config, pile_id=pile_ids[0], piles=pile_ids)
        boxes = _pile_boxes(store)
        for pile_id in pile_ids:
            if pile_id not in boxes:
                raise ValueError(f"pile {pile_id!r} is not declared in {describe_ledger(path)}")
        analytes = _analytes(store)
        rec, uri = make_recording(config, analytes, recording_id=recording_id,
                                  pile=boxes[pile_ids[0]], boxes=boxes)
        viewer = None
        try:
            viewer = WebViewer(config, uri) if config.serve and uri else None
            url = viewer.url if viewer else None
            if url:
                log("dashboard", "web viewer", url=url, grpc=uri)
            results = _render(store, head, rec, config, progress, url, str(path))
            if keep_serving is not None and config.serve:
                log("dashboard", "serving until interrupted", url=url)
                keep_serving.wait()
        finally:
            if viewer is not None:
                viewer.close()
            close_recording(rec)
    return results


def _render(store, head, rec, config: Config, progress, url,
            ledger_path: str = "") -> list[RenderResult]:
    """Feed every record of ``store`` to the dashboards of ``config.piles`` (the body of
    render_piles)."""
    piles = PileSet(rec, config, offline=True)
    source = StoreSource(store, head.global_seq)
    for dash in piles:
        dash.surveys.source = lambda: store
    gaps, quarantine = store.gaps(), store.quarantine()
    seen: set = set()
    total = head.global_seq + 1

    def on_record(n: int) -> None:
        if progress is not None and n % PROGRESS_EVERY == 0:
            progress(n, total)

    def rebuild(dash: Dashboard) -> None:
        rebuild_from(source, dash)

    records = 0
    for chunk_start in range(0, total, READ_CHUNK * 4):
        chunk = list(store.read(chunk_start, min(total, chunk_start + READ_CHUNK * 4)))
        records += piles.feed(chunk, rebuild=rebuild,
                              on_record=lambda n, base=records: on_record(base + n))
        if gaps or quarantine:
            _log_gaps_and_quarantine(piles, gaps, quarantine, seen, piles.known_ns)
    for dash in piles:
        if dash.projection.stale:
            rebuild(dash)
        dash.projection.advance(everything=True)
        dash.reasons.add("end")
        dash.update()   # everything read (a no-op when the last update already had it all)
    _log_gaps_and_quarantine(piles, gaps, quarantine, seen, piles.known_ns)
    piles.flush_known_now()
    planned = 0
    if config.plan_machine:
        plan = make_plan(plan_args(ledger_path, config.pile_id, config.plan_machine,
                                   cuts=config.plan_cuts), store)
        planned = piles.first.log_plan(plan)
    if progress is not None:
        progress(total, total)
    return [RenderResult(dash.pile_id, records, dash.updates, len(dash.points), dash.rebuilds,
                         head.global_seq, dash.known_ns,
                         float(dash.last_state.tonnes) if dash.last_state is not None
                         else math.nan, config.rrd, url, planned)
            for dash in piles]


def _log_gaps_and_quarantine(dash, gaps, quarantine, seen: set, known_ns: int) -> None:
    """Log gaps and quarantined input the ledger knew by ``known_ns`` (each once) with
    ``dash.log_text`` (a :class:`Dashboard`, or a :class:`PileSet`: every pile's log)."""
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
    """``stockpile dashboard``: render, print a one-line summary per pile."""
    if not args.out and not args.serve:
        raise ValueError("give --out OUT.rrd and/or --serve")
    config = Config(piles=tuple(args.pile or ()), serve=args.serve, rrd=args.out,
                    grpc_port=args.grpc_port, web_port=args.web_port, every_s=args.every,
                    analyte=args.analyte, layers=args.layers, layer_step_m=args.layer_step_m,
                    delta_threshold_pp=args.delta_threshold_pp, reorder_s=args.reorder_s,
                    plan_machine=args.plan_machine, plan_cuts=args.plan_cuts)
    t0 = time.monotonic()
    stopper = Stopper() if args.serve else None
    with progress_bar(unit="records", desc="dashboard", enabled=enabled_from_args(args)) as bar:
        results = render_piles(args.ledger, config.piles, config,
                               progress=_progress_printer(bar), keep_serving=stopper)
    for result in results:   # a line per pile
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
    p.add_argument("--pile", action="append", metavar="ID",
                   help="pile id (default: the only pile the ledger declares); repeat it to "
                   "show several piles in one recording, each under /piles/<id>")
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
