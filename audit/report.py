"""Audit and reconciliation reports over a ledger: pure computations, no printing.

Three reports, each answered from the ledger alone as known at a known time K (default:
everything the ledger holds):

:func:`audit_cuts`
    One row per reclaim cut of a pile: its tonnes and grade *as estimated when the cut
    ended* (the projection as of V = the cut's end, as known at the first moment the
    ledger knew the cut: K = max(end, the cut event's recorded time)) beside the same cut
    *as known at K*, the difference, the assayed fractions and the contributing lots.
    A late assay moves the second figure and never the first.
:func:`audit_history`
    The pile's tonnes and grade every ``every_ns`` of valid time, as known at K and as
    known at the time (K = that valid time).
:func:`audit_assays`
    Lateness per lab (recorded time minus the end of the sampling window, the
    ``lateness_h`` of the auditors' ``assays`` view), superseded and provisional assays,
    assays for lots that were not declared, and lots without assays.

How the projections are computed
--------------------------------
A report that needs the pile at many valid times folds the ledger's geometry events once,
in (valid time, global seq) order as known at K (:func:`ledger.store.LedgerStore.as_of`),
and takes a copy of the fold state at each requested valid time V (the state after every
event with valid time <= V), joining grades from the lots and assays known at the K that
row asks for (:func:`projector.query.summarise`).  That equals
``project(store, pile, V, K')`` exactly as long as no geometry event with valid time <= V
was recorded after K'; when one was (a late scan or cut), that row is projected on its own
with :func:`projector.query.project`, so no row is ever silently wrong.

Imports flow ``schemas <- ledger``: nothing here imports :mod:`services`.
"""

from __future__ import annotations

import bisect
import math
import statistics
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence

from common.options import DEFAULT_MAX_ROWS, check_range_rows
from audit.marks import history_count, history_marks
from schemas.events import decode_payload
from schemas.times import NS_PER_H

from projector import fold as F
from projector.grades import AssayRecord, grade_from_map, coerce_time_ns, effective_assays
from projector.query import FAR_FUTURE_NS, PileState, project, summarise

__all__ = ["CutAudit", "CutsReport", "HistoryPoint", "HistoryReport", "LabLateness",
           "AssayReport", "audit_cuts", "audit_history", "audit_assays", "resolve_known_ns",
           "LATENESS_BINS_H", "Progress"]

#: edges of the lateness histogram, hours: [0, 1), [1, 2), [2, 4), [4, 6), [6, 12), [12, inf)
LATENESS_BINS_H: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 6.0, 12.0)

#: ``progress(fraction 0..1, geometry events folded)``, called now and then during a fold
Progress = Callable[[float, int], None]


# -- results ------------------------------------------------------------------------------


@dataclass(frozen=True)
class CutAudit:
    """One reclaim cut, as estimated when it ended and as known at K.

    Attributes
    ----------
    cut_id, bench_id : str
    start_time_ns, end_time_ns : int
        The cut's slew (UTC ns).
    estimated_known_ns : int
        The K of the estimate at the time: the first moment the ledger knew the cut,
        ``max(end_time_ns, recorded time of the cut event)``.
    tonnes_at_end_t, tonnes_t : float
        Tonnes by the geometry (the removed bands times density), at the time and at K.
    tonnes_scale_t : float
        The belt scale's tonnes reported with the cut.
    grade_at_end_pct, grade_pct : dict
        Analyte -> mass %, at the time and at K (NaN where no grade is known).
    delta_pp : dict
        ``grade_pct - grade_at_end_pct`` per analyte, percentage points.
    assayed_fraction_at_end, assayed_fraction : float
        Share of the cut's tonnes whose grade came from an assay, at the time and at K.
    lots_t : dict
        Contributing lot -> tonnes (as known at K), largest first.
    residual_m3 : float
        Geometry residual attributed to the cut by later scans (as known at K).
    reprojected : bool
        True when a geometry event was recorded after the estimate's K, so the estimate
        was projected on its own rather than taken from the shared fold.
    tonnes_sd_t, grade_sd_pp : float, dict
        Standard deviations of ``tonnes_t`` (t) and ``grade_pct`` (pp per analyte).
    """

    cut_id: str
    bench_id: str
    start_time_ns: int
    end_time_ns: int
    estimated_known_ns: int
    tonnes_at_end_t: float
    tonnes_t: float
    tonnes_scale_t: float
    grade_at_end_pct: dict[str, float]
    grade_pct: dict[str, float]
    delta_pp: dict[str, float]
    assayed_fraction_at_end: float
    assayed_fraction: float
    lots_t: dict[str, float]
    residual_m3: float
    reprojected: bool = False
    tonnes_sd_t: float = math.nan
    grade_sd_pp: dict[str, float] = field(default_factory=dict)

    def changed(self, threshold_pp: float = 1e-9) -> bool:
        """Whether any analyte's grade moved by more than ``threshold_pp`` since the cut ended."""
        return any(math.isfinite(d) and abs(d) > threshold_pp for d in self.delta_pp.values())


@dataclass(frozen=True)
class CutsReport:
    """:func:`audit_cuts`'s answer."""

    pile_id: str
    known_time_ns: int
    analytes: tuple[str, ...]
    cuts: list[CutAudit]
    pile_tonnes_t: float
    events_folded: int


@dataclass(frozen=True)
class HistoryPoint:
    """The pile at one valid time, as known at K and as known at that time.

    Attributes
    ----------
    valid_time_ns : int
    volume_m3, tonnes_t, grade_pct, assayed_fraction
        As known at K.
    volume_then_m3, tonnes_then_t, grade_then_pct, assayed_fraction_then
        As known at the valid time itself (K = V).
    reprojected : bool
        The "then" figures were projected on their own (a geometry event arrived late).
    tonnes_sd_t, grade_sd_pp : float, dict
        Standard deviations of ``tonnes_t`` (t) and ``grade_pct`` (pp per analyte).
    """

    valid_time_ns: int
    volume_m3: float
    tonnes_t: float
    grade_pct: dict[str, float]
    assayed_fraction: float
    volume_then_m3: float
    tonnes_then_t: float
    grade_then_pct: dict[str, float]
    assayed_fraction_then: float
    reprojected: bool = False
    tonnes_sd_t: float = math.nan
    grade_sd_pp: dict[str, float] = field(default_factory=dict)

    @property
    def delta_pp(self) -> dict[str, float]:
        """Grade as known at K minus as known then, percentage points."""
        return {a: self.grade_pct.get(a, math.nan) - self.grade_then_pct.get(a, math.nan)
                for a in self.grade_pct}


@dataclass(frozen=True)
class HistoryReport:
    """:func:`audit_history`'s answer."""

    pile_id: str
    known_time_ns: int
    every_ns: int
    analytes: tuple[str, ...]
    points: list[HistoryPoint]
    events_folded: int


@dataclass(frozen=True)
class LabLateness:
    """How late one lab's assays were recorded (hours after the sampling window ended)."""

    lab_id: str
    assays: int
    min_h: float
    median_h: float
    mean_h: float
    p90_h: float
    max_h: float
    histogram: dict[str, int]


@dataclass(frozen=True)
class AssayReport:
    """:func:`audit_assays`'s answer (everything as known at ``known_time_ns``).

    ``superseded``: assays named by a later assay's ``supersedes``; ``provisional``: every
    PROVISIONAL assay with what replaced it (``replaced_by``: an assay id, or ``None`` while
    it still counts); ``unknown_lots``: assays whose lot was not declared when they were
    recorded (``declared_by_k`` says whether it is now); ``lots_without_assays``: declared
    lots with no assay; ``signatures``: per assay, who vouched for it (``signer`` key id,
    the name and role its declaration gave; None for an unsigned assay).
    """

    known_time_ns: int
    assays: int
    labs: list[LabLateness]
    superseded: list[dict[str, Any]]
    provisional: list[dict[str, Any]]
    unknown_lots: list[dict[str, Any]]
    lots_without_assays: list[dict[str, Any]]
    signatures: list[dict[str, Any]] = field(default_factory=list)


# -- helpers ------------------------------------------------------------------------------


def resolve_known_ns(store, known_time_ns: int | None) -> int:
    """K: the given time, or the recorded time of the ledger's head (everything)."""
    if known_time_ns is not None:
        return int(known_time_ns)
    head = store.head()
    if head.global_seq < 0 or head.recorded_time_ns is None:
        raise ValueError("the ledger is empty")
    return int(head.recorded_time_ns)


def _check_pile(store, pile_id: str, known_ns: int) -> int:
    """The valid time the pile was declared at (as known at K); ValueError if it was not."""
    for event in store.as_of(FAR_FUTURE_NS, known_ns, types=["pile_declared"]):
        if decode_payload(event.type, event.payload).pile_id == pile_id:
            return event.valid_time_ns
    raise ValueError(f"pile {pile_id!r} is not declared in the ledger"
                     + ("" if known_ns >= FAR_FUTURE_NS else " as known at that time"))


class _Grades:
    """Lots and assays as known at K, filterable to any (V, K' <= K) like ``as_of``."""

    def __init__(self, store, known_ns: int) -> None:
        self.lots: list[tuple[int, int, str, dict[str, float]]] = []
        self.assays: list[tuple[int, AssayRecord]] = []
        for event in store.as_of(FAR_FUTURE_NS, known_ns, types=["lot_declared", "assay"]):
            msg = decode_payload(event.type, event.payload)
            if event.type == "lot_declared":
                self.lots.append((event.valid_time_ns, event.recorded_time_ns, msg.lot_id,
                                  grade_from_map(msg.planned_grade)))
            else:
                self.assays.append((event.valid_time_ns,
                                    AssayRecord.from_message(msg, event.recorded_time_ns)))

    def at(self, valid_ns: int, known_ns: int):
        """``(lots, assays)`` with valid time <= V recorded at or before K."""
        lots = {lot: grade for v, r, lot, grade in self.lots if v <= valid_ns and r <= known_ns}
        assays = [a for v, a in self.assays if v <= valid_ns and a.recorded_ns <= known_ns]
        return lots, assays


def _fold_at(store, pile_id: str, known_ns: int, marks: Sequence[tuple[int, int]], *,
             progress: Progress | None = None, span: tuple[int, int] | None = None,
             counter: list[int] | None = None) -> Iterator[tuple[int, F.ProjectorState, bool]]:
    """Fold the geometry known at K once; yield ``(i, view, late)`` at each mark.

    ``marks[i] = (V, K_then)``.  ``view`` is the flushed fold state after every geometry
    event with valid time <= V (a copy: the caller may keep it); ``late`` is True when some
    of those events were recorded after ``K_then`` (the state as known at ``K_then``
    differs).  Marks are yielded in increasing V.
    """
    order = sorted(range(len(marks)), key=lambda i: (marks[i][0], i))
    valids = [marks[i][0] for i in order]
    thens = [marks[i][1] for i in order]
    # suffix minimum of K_then: whether any mark at or after j can be affected by an event
    suffix_min = list(thens)
    for j in range(len(suffix_min) - 2, -1, -1):
        suffix_min[j] = min(suffix_min[j], suffix_min[j + 1])
    late = [False] * len(order)
    state = F.initial_state(F.FoldConfig(pile_id=pile_id))
    j, n = 0, 0
    v0, v1 = span if span else (0, 0)
    for event in store.as_of(FAR_FUTURE_NS, known_ns, types=list(F.GEOMETRY_TYPES)):
        v = event.valid_time_ns
        while j < len(order) and valids[j] < v:
            view = state.copy()
            F.flush(view)
            yield order[j], view, late[j]
            j += 1
        if j == len(order):
            break   # every mark answered: the rest of the ledger is not needed
        if j < len(order) and event.recorded_time_ns > suffix_min[j]:
            for k in range(j, len(order)):
                if event.recorded_time_ns > thens[k]:
                    late[k] = True
        F.apply(state, event)
        n += 1
        if counter is not None:
            counter[0] = n
        if progress is not None and n % 5000 == 0:
            progress(min(1.0, max(0.0, (v - v0) / (v1 - v0))) if v1 > v0 else 0.0, n)
    while j < len(order):
        view = state.copy()
        F.flush(view)
        yield order[j], view, late[j]
        j += 1
    if progress is not None:
        progress(1.0, n)


def _span(store, known_ns: int) -> tuple[int, int]:
    """First and last valid time in the ledger; the last capped at K when K is before the
    head (events are recorded at about their valid time; the head holds everything)."""
    stats = store.stats()
    if stats.valid_time_range_ns is None:
        return (0, 0)
    first, last = stats.valid_time_range_ns
    head_ns = stats.head.recorded_time_ns
    if head_ns is not None and known_ns < head_ns:
        last = min(last, known_ns)
    return first, last


def _find_cut(state: PileState, cut_id: str, end_ns: int):
    for cut in state.cuts:
        if cut.cut_id == cut_id and cut.end_time_ns == end_ns:
            return cut
    for cut in state.cuts:
        if cut.cut_id == cut_id:
            return cut
    return None


def _nan_grade(analytes) -> dict[str, float]:
    return {a: math.nan for a in analytes}


# -- cuts ---------------------------------------------------------------------------------


def audit_cuts(store, pile_id: str, known_time_ns: int | None = None, *,
               progress: Progress | None = None) -> CutsReport:
    """Every reclaim cut of ``pile_id``: as estimated when it ended vs as known at K.

    Parameters
    ----------
    store : ledger.store.LedgerStore
    pile_id : str
    known_time_ns : int, optional
        K (UTC ns); default: everything the ledger holds (its head's recorded time).
    progress : callable, optional
        ``progress(fraction, events_folded)`` during the fold.

    Raises
    ------
    ValueError
        If the pile is not declared (as known at K) or the ledger is empty.
    """
    known = resolve_known_ns(store, known_time_ns)
    _check_pile(store, pile_id, known)
    cuts = []
    for event in store.as_of(FAR_FUTURE_NS, known, types=["reclaim_cut"]):
        msg = decode_payload(event.type, event.payload)
        if msg.pile_id != pile_id:
            continue
        end = event.valid_time_ns
        cuts.append((msg.cut_id, msg.bench_id, coerce_time_ns(msg.start_time), end,
                     max(end, event.recorded_time_ns), float(msg.tonnes)))
    grades = _Grades(store, known)
    marks = [(c[3], c[4]) for c in cuts] + [(FAR_FUTURE_NS, known)]
    at_end: dict[int, Any] = {}
    reprojected: set[int] = set()
    final: PileState | None = None
    counter = [0]
    for i, view, late in _fold_at(store, pile_id, known, marks, progress=progress,
                                  span=_span(store, known), counter=counter):
        if i == len(cuts):
            lots, assays = grades.at(FAR_FUTURE_NS, known)
            final = summarise(view, lots, assays, valid_time_ns=FAR_FUTURE_NS,
                              known_time_ns=known)
            continue
        _cid, _bench, _start, end, then, _belt = cuts[i]
        if late:
            state = project(store, pile_id, end, then)
            reprojected.add(i)
        else:
            lots, assays = grades.at(end, then)
            state = summarise(view, lots, assays, valid_time_ns=end, known_time_ns=then)
        at_end[i] = _find_cut(state, cuts[i][0], end)
    assert final is not None
    analytes = final.analytes
    rows = []
    for i, (cut_id, bench_id, start, end, then, belt) in enumerate(cuts):
        now = _find_cut(final, cut_id, end)
        was = at_end.get(i)
        grade = dict(now.grade) if now else _nan_grade(analytes)
        grade_then = dict(was.grade) if was else _nan_grade(analytes)
        lots_t: dict[str, float] = {}
        for d in (now.deposits if now else []):
            lots_t[d["lot_id"] or "-"] = lots_t.get(d["lot_id"] or "-", 0.0) + float(d["tonnes"])
        rows.append(CutAudit(
            cut_id=cut_id, bench_id=bench_id, start_time_ns=start, end_time_ns=end,
            estimated_known_ns=then,
            tonnes_at_end_t=float(was.tonnes) if was else math.nan,
            tonnes_t=float(now.tonnes) if now else math.nan, tonnes_scale_t=belt,
            grade_at_end_pct=grade_then, grade_pct=grade,
            delta_pp={a: grade.get(a, math.nan) - grade_then.get(a, math.nan) for a in analytes},
            assayed_fraction_at_end=float(was.assayed_fraction) if was else 0.0,
            assayed_fraction=float(now.assayed_fraction) if now else 0.0,
            lots_t=dict(sorted(lots_t.items(), key=lambda kv: -kv[1])),
            residual_m3=float(now.residual_m3) if now else math.nan,
            reprojected=i in reprojected, tonnes_sd_t=float(now.tonnes_sd) if now else math.nan,
            grade_sd_pp=dict(now.grade_sd) if now else {}))
    rows.sort(key=lambda r: (r.end_time_ns, r.cut_id))
    return CutsReport(pile_id, known, analytes, rows, float(final.tonnes), counter[0])


# -- history ------------------------------------------------------------------------------


def audit_history(store, pile_id: str, every_ns: int, known_time_ns: int | None = None, *,
                  start_ns: int | None = None, end_ns: int | None = None,
                  progress: Progress | None = None,
                  max_rows: int = DEFAULT_MAX_ROWS) -> HistoryReport:
    """The pile's tonnes and grade every ``every_ns`` of valid time, as known at K and then.

    Parameters
    ----------
    store : ledger.store.LedgerStore
    pile_id : str
    every_ns : int
        Interval between rows (ns, > 0).
    known_time_ns : int, optional
        K (default: everything the ledger holds).
    start_ns, end_ns : int, optional
        Valid-time range; default from the pile's declaration to the last valid time in the
        ledger (capped at K).
    progress : callable, optional
    max_rows : int
        The most rows; a longer range is refused before any is listed.

    Raises
    ------
    ValueError
        Unknown pile, empty ledger, a non-positive interval, an empty range or more rows
        than ``max_rows``.
    """
    if every_ns <= 0:
        raise ValueError("--every must be positive")
    known = resolve_known_ns(store, known_time_ns)
    declared = _check_pile(store, pile_id, known)
    span = _span(store, known)
    first = declared if start_ns is None else int(start_ns)
    last = span[1] if end_ns is None else int(end_ns)
    if last < first:
        raise ValueError("the valid-time range is empty (the end is before the start)")
    check_range_rows(history_count(first, last, every_ns), max_rows,
                     hint="choose a longer --every, a shorter --from/--to or raise --max-rows")
    times = history_marks(first, last, every_ns)
    grades = _Grades(store, known)
    marks = [(t, t) for t in times]
    points: dict[int, HistoryPoint] = {}
    counter = [0]
    analytes: tuple[str, ...] = ()
    for i, view, late in _fold_at(store, pile_id, known, marks, progress=progress,
                                  span=(first, last), counter=counter):
        t = times[i]
        lots, assays = grades.at(t, known)
        now = summarise(view, lots, assays, valid_time_ns=t, known_time_ns=known)
        if late:
            then = project(store, pile_id, t, t)
        else:
            lots_then, assays_then = grades.at(t, t)
            then = summarise(view, lots_then, assays_then, valid_time_ns=t, known_time_ns=t)
        analytes = now.analytes or analytes
        points[i] = HistoryPoint(
            valid_time_ns=t, volume_m3=now.volume_m3, tonnes_t=now.tonnes,
            grade_pct=dict(now.grade), assayed_fraction=now.assayed_fraction,
            volume_then_m3=then.volume_m3, tonnes_then_t=then.tonnes,
            grade_then_pct={a: then.grade.get(a, math.nan) for a in now.grade} or dict(then.grade),
            assayed_fraction_then=then.assayed_fraction, reprojected=late,
            tonnes_sd_t=now.tonnes_sd, grade_sd_pp=dict(now.grade_sd))
    return HistoryReport(pile_id, known, int(every_ns), analytes,
                         [points[i] for i in range(len(times))], counter[0])


# -- assays -------------------------------------------------------------------------------


def _percentile(sorted_values: list[float], q: float) -> float:
    """Linear-interpolated percentile (q in 0..1) of sorted values."""
    if not sorted_values:
        return math.nan
    pos = q * (len(sorted_values) - 1)
    lo, hi = math.floor(pos), math.ceil(pos)
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * (pos - lo)


def _bin_label(lo: float, hi: float | None) -> str:
    return f"{lo:g}-{hi:g} h" if hi is not None else f">={lo:g} h"


def lateness_histogram(lateness_h: Sequence[float]) -> dict[str, int]:
    """Counts per :data:`LATENESS_BINS_H` bin (negative lateness falls in the first)."""
    edges = list(LATENESS_BINS_H)
    out = {_bin_label(lo, hi): 0 for lo, hi in zip(edges, edges[1:] + [None])}
    labels = list(out)
    for h in lateness_h:
        k = max(0, bisect.bisect_right(edges, h) - 1)
        out[labels[k]] += 1
    return out


def audit_assays(store, known_time_ns: int | None = None) -> AssayReport:
    """Lateness per lab, superseded and provisional assays, unknown lots, lots without assays."""
    known = resolve_known_ns(store, known_time_ns)
    lots: dict[str, dict[str, Any]] = {}
    rows: list[dict[str, Any]] = []
    records: list[AssayRecord] = []
    keys: dict[str, Any] = {}
    for event in store.as_of(FAR_FUTURE_NS, known, types=["lot_declared", "assay",
                                                          "source_key_declared"]):
        msg = decode_payload(event.type, event.payload)
        if event.type == "source_key_declared":
            keys[msg.key_id] = msg
            continue
        if event.type == "lot_declared":
            lots.setdefault(msg.lot_id, {"lot_id": msg.lot_id,
                                         "declared_ns": event.recorded_time_ns,
                                         "planned_tonnes_t": float(msg.planned_tonnes)})
            continue
        record = AssayRecord.from_message(msg, event.recorded_time_ns)
        records.append(record)
        rows.append({
            "assay_id": record.assay_id, "lot_id": record.lot_id,
            "lab_id": str(getattr(msg, "lab_id", "") or event.source),
            "status": record.status, "supersedes": record.supersedes or None,
            "window_start_ns": record.window_start_ns, "window_end_ns": record.window_end_ns,
            "recorded_ns": event.recorded_time_ns, "global_seq": event.global_seq,
            "lateness_h": (event.recorded_time_ns - record.window_end_ns) / NS_PER_H,
            "unknown_lot_when_recorded": "unknown_lot" in (event.flags or ()),
            "analytes": dict(record.analytes), "signer": event.signer})
    # lateness per lab
    by_lab: dict[str, list[float]] = {}
    for row in rows:
        by_lab.setdefault(row["lab_id"], []).append(row["lateness_h"])
    labs = []
    for lab, values in sorted(by_lab.items()):
        s = sorted(values)
        labs.append(LabLateness(lab, len(s), s[0], statistics.median(s), statistics.fmean(s),
                                _percentile(s, 0.9), s[-1], lateness_histogram(s)))
    # superseded (named by a later assay's supersedes)
    by_id = {row["assay_id"]: row for row in rows}
    superseded = []
    for row in rows:
        target = row["supersedes"]
        if target and target != row["assay_id"]:
            old = by_id.get(target)
            superseded.append({
                "assay_id": target, "lot_id": old["lot_id"] if old else row["lot_id"],
                "status": old["status"] if old else None,
                "superseded_by": row["assay_id"], "by_status": row["status"],
                "recorded_ns": old["recorded_ns"] if old else None,
                "superseded_at_ns": row["recorded_ns"],
                "known": old is not None,
                "delta_pp": ({a: row["analytes"][a] - old["analytes"][a]
                              for a in row["analytes"] if a in old["analytes"]} if old else {})})
    # provisional: what replaced each (supersedes, or a FINAL of the lot over its window)
    alive = {a.assay_id for a in effective_assays(records, known)}
    replaced_by = {s["assay_id"]: s["superseded_by"] for s in superseded}
    finals = [r for r in records if r.is_final]
    provisional = []
    for record in records:
        if record.status != "PROVISIONAL":
            continue
        by = replaced_by.get(record.assay_id)
        if by is None and record.assay_id not in alive:
            overlapping = [f for f in finals if f.lot_id == record.lot_id
                           and max(f.window_start_ns, record.window_start_ns)
                           < min(f.window_end_ns, record.window_end_ns)]
            overlapping.sort(key=lambda f: f.recorded_ns)
            by = overlapping[0].assay_id if overlapping else None
        row = by_id[record.assay_id]
        provisional.append({"assay_id": record.assay_id, "lot_id": record.lot_id,
                            "lab_id": row["lab_id"], "recorded_ns": record.recorded_ns,
                            "window_end_ns": record.window_end_ns,
                            "replaced_by": by, "open": record.assay_id in alive})
    unknown = [{"assay_id": r["assay_id"], "lot_id": r["lot_id"], "lab_id": r["lab_id"],
                "recorded_ns": r["recorded_ns"], "declared_by_k": r["lot_id"] in lots}
               for r in rows if r["unknown_lot_when_recorded"] or r["lot_id"] not in lots]
    assayed_lots = {r["lot_id"] for r in rows}
    without = [dict(lot) for lot_id, lot in sorted(lots.items()) if lot_id not in assayed_lots]
    signatures = [dict(assay_id=r["assay_id"], lot_id=r["lot_id"], global_seq=r["global_seq"],
                       signer=r["signer"], signer_name=getattr(keys.get(r["signer"]), "name", None),
                       signer_role=getattr(keys.get(r["signer"]), "role", None)) for r in rows]
    return AssayReport(known, len(rows), labs, superseded, provisional, unknown, without,
                       signatures)
