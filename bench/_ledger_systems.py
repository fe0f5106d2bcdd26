"""The ledger benchmark's inputs and the calls into the systems it measures (see
``bench/ledger.py``).

The pre-built workloads (:class:`Workload`: a ``scan`` stream from :func:`scan_workload`,
a ``yard mix`` stream from :class:`YardStream`) and, for each measurement, the call into
our ledger (:func:`ours_append` on a DuckDB file or a PostgreSQL URL, :func:`ours_read`)
and the matching call into ``eventsourcing``'s recorders (:func:`es_recorder` for SQLite,
:func:`es_stored`, :func:`es_append` for any of its application recorders,
:func:`es_read_notifications`, :func:`es_read_events`).  Each timed function returns
``(seconds, count)``; building the inputs is never timed.  The PostgreSQL server and
its databases are ``bench/_ledger_pg.py``'s.
"""

from __future__ import annotations

import gc
import itertools
import math
import time
import uuid
from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
from eventsourcing.persistence import IntegrityError, StoredEvent
from eventsourcing.sqlite import SQLiteApplicationRecorder, SQLiteDatastore
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan

from ledger import ManualClock, open_ledger
from schemas import Event, make_event, pb, set_timestamp_ns
from schemas.times import NS_PER_H, NS_PER_S

NS_PER_MS = 1_000_000

#: Start of the simulated yard stream (2026-03-01T00:00:00Z).
T0_NS = 1_772_323_200 * NS_PER_S

#: Ledger's recorded time = arrival time + this (transport latency).
LATENCY_NS = 20 * NS_PER_MS

SCAN_RANGES = 401
SCAN_START_RAD = math.radians(-50.0)
SCAN_END_RAD = math.radians(50.0)

ES_NAMESPACE = uuid.UUID("6f1c1e8e-2a53-4a4e-9a57-0b2f3c3d9e10")
ES_PAGE = 10_000


# --- building the events (never timed) ---------------------------------------------------


@dataclass
class Workload:
    """Pre-built events in arrival order, with when each reached the ledger (ns)."""

    name: str
    events: list[Event]
    arrival_ns: list[int]

    def __len__(self) -> int:
        return len(self.events)

    def head(self, n: int) -> Workload:
        return Workload(self.name, self.events[:n], self.arrival_ns[:n])

    @property
    def payload_mb(self) -> float:
        return sum(len(e.payload) for e in self.events) / 1e6


class YardStream:
    """A deterministic yard stream: one 100 ms tick at a time, in arrival order.

    Per tick: 1 scan (if ``scans``), 2 joint readings, 2 transforms of each of 2
    frames.  A lot is declared at the start; an assay of the lot arrives every
    ``assay_every_s`` of yard time, its window ending 4 h before it arrives.
    """

    TICK_NS = 100 * NS_PER_MS

    def __init__(self, rng: np.random.Generator, *, scans: bool, assay_every_s: int = 30) -> None:
        self.rng = rng
        self.scans = scans
        self.assay_every_ticks = assay_every_s * NS_PER_S // self.TICK_NS
        self.seq: dict[str, int] = {}
        self.profile = ScanProfile(rng)

    def _next_seq(self, source: str) -> int:
        s = self.seq.get(source, 0)
        self.seq[source] = s + 1
        return s

    def _event(self, message, source: str, arrival: int) -> tuple[Event, int]:
        return make_event(message, source=source, epoch=1, seq=self._next_seq(source)), arrival

    def __iter__(self) -> Iterator[tuple[Event, int]]:
        rng = self.rng
        lot = pb.LotDeclared(lot_id="L2026-0301-A", origin="pit3", planned_tonnes=250_000.0)
        set_timestamp_ns(lot.time, T0_NS)
        lot.planned_grade.update({"Fe": 62.0, "SiO2": 4.0, "Al2O3": 2.3, "P": 0.08, "LOI": 5.0})
        yield self._event(lot, "lims.lots", T0_NS)
        travel, slew, luff = 120.0, 0.3, 0.05
        for tick in itertools.count():
            base = T0_NS + tick * self.TICK_NS
            if self.scans:
                t = base + 3 * NS_PER_MS
                yield self._event(self.profile.scan(t), "bwr1.scanner", t)
            for k in range(2):
                t = base + k * 50 * NS_PER_MS + 7 * NS_PER_MS
                travel += 0.001 * rng.standard_normal()
                slew += 0.0005
                luff += 0.0001 * rng.standard_normal()
                jr = pb.JointReading(machine_id="bwr1", travel_m=travel, slew_rad=slew, luff_rad=luff)
                set_timestamp_ns(jr.time, t)
                yield self._event(jr, "bwr1.joints", t)
                for child, dz in (("bwr1/base", 0.0), ("bwr1/wheel", 12.5)):
                    ft = FrameTransform(parent_frame_id="site", child_frame_id=child)
                    set_timestamp_ns(ft.timestamp, t + 1_000)
                    ft.translation.x = travel
                    ft.translation.y = 35.0 * math.sin(slew) if dz else 0.0
                    ft.translation.z = 8.0 + dz * math.sin(luff)
                    ft.rotation.z = math.sin(slew / 2)
                    ft.rotation.w = math.cos(slew / 2)
                    yield self._event(ft, "bwr1.tf", t + 1_000)
            if tick % self.assay_every_ticks == self.assay_every_ticks - 1:
                arrival = base + 90 * NS_PER_MS
                n = tick // self.assay_every_ticks
                window_end = arrival - 4 * NS_PER_H
                assay = pb.Assay(assay_id=f"A{n:06d}", lot_id="L2026-0301-A", status=pb.FINAL,
                                 lab_id="lab1", moisture_pct=float(7.5 + rng.normal(0, 0.3)),
                                 bulk_density_t_m3=2.35)
                set_timestamp_ns(assay.window_start, window_end - NS_PER_H)
                set_timestamp_ns(assay.window_end, window_end)
                set_timestamp_ns(assay.reported_time, arrival - 60 * NS_PER_S)
                assay.analytes.update({
                    "Fe": round(float(62.0 + rng.normal(0, 0.6)), 2),
                    "SiO2": round(float(4.0 + rng.normal(0, 0.3)), 2),
                    "Al2O3": round(float(2.3 + rng.normal(0, 0.15)), 2),
                    "P": round(float(0.08 + rng.normal(0, 0.005)), 3),
                    "LOI": round(float(5.0 + rng.normal(0, 0.3)), 2),
                })
                yield self._event(assay, "lab1.assays", arrival)

    def take(self, n: int, name: str) -> Workload:
        events, arrivals = [], []
        for event, arrival in itertools.islice(self, n):
            events.append(event)
            arrivals.append(arrival)
        return Workload(name, events, arrivals)


class ScanProfile:
    """LMS200-like scans of a stockpile face: a smooth profile plus noise, a few NaN."""

    CHUNK = 1_000

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        angles = np.linspace(-1.0, 1.0, SCAN_RANGES)
        self.base = 18.0 + 14.0 * angles**2 + 4.0 * np.sin(3.0 * angles)
        self._noise: np.ndarray | None = None
        self._i = self.CHUNK

    def _ranges(self) -> list[float]:
        if self._i >= self.CHUNK:
            noise = self.rng.normal(0.0, 0.05, (self.CHUNK, SCAN_RANGES))
            drift = self.rng.normal(0.0, 1.5, (self.CHUNK, 1))
            r = np.clip(self.base + drift + noise, 2.0, 60.0).round(3)
            r[self.rng.random(r.shape) < 0.01] = np.nan  # no return
            self._noise, self._i = r, 0
        row = self._noise[self._i]
        self._i += 1
        return row.tolist()

    def scan(self, t_ns: int) -> LaserScan:
        msg = LaserScan(frame_id="bwr1/scanner", start_angle=SCAN_START_RAD,
                        end_angle=SCAN_END_RAD)
        set_timestamp_ns(msg.timestamp, t_ns)
        msg.ranges.extend(self._ranges())
        return msg


def scan_workload(rng: np.random.Generator, n: int) -> Workload:
    """``n`` scans at 10 Hz from one scanner."""
    profile = ScanProfile(rng)
    events, arrivals = [], []
    for i in range(n):
        t = T0_NS + i * 100 * NS_PER_MS
        events.append(make_event(profile.scan(t), source="bwr1.scanner", epoch=1, seq=i))
        arrivals.append(t)
    return Workload("scan", events, arrivals)


# --- the two systems under test ---------------------------------------------------------


def batches(n: int, size: int) -> list[tuple[int, int]]:
    return [(i, min(i + size, n)) for i in range(0, n, size)]


def ours_append(path: str, work: Workload, batch: int, store=None) -> tuple[float, dict[str, int]]:
    """Append ``work`` in batches to the ledger ``path`` names (a DuckDB file or a
    ``postgresql://`` URL, opened with :func:`ledger.open_ledger`); return (seconds,
    outcome counts).  Opening and closing the ledger are not timed."""
    own = store is None
    clock = ManualClock(T0_NS)
    if own:
        store = open_ledger(path, clock)
    else:
        clock = store.clock
    counts = {"appended": 0, "duplicate": 0, "conflict": 0, "rejected": 0}
    events, arrivals = work.events, work.arrival_ns
    spans = batches(len(events), batch)
    problems: list[str] = []
    gc.collect()
    start = time.perf_counter()
    for lo, hi in spans:
        clock.set_ns(arrivals[hi - 1] + LATENCY_NS)
        result = store.append(events[lo:hi])
        for k, v in result.counts.items():
            counts[k] += v
        if result.counts["rejected"] or result.counts["conflict"]:
            problems.extend(o.reason for o in result.outcomes if o.reason)
    seconds = time.perf_counter() - start
    if own:
        store.close()
    if problems:
        raise RuntimeError(f"ledger refused benchmark events, e.g. {problems[:3]}")
    return seconds, counts


def es_recorder(path: str):
    datastore = SQLiteDatastore(path)
    recorder = SQLiteApplicationRecorder(datastore)
    recorder.create_table()
    return datastore, recorder


def es_stored(work: Workload) -> list:
    """The same events as eventsourcing ``StoredEvent``s (same payload bytes)."""
    ids: dict[tuple[str, int], uuid.UUID] = {}
    out = []
    for e in work.events:
        oid = ids.get((e.source, e.epoch))
        if oid is None:
            oid = ids[(e.source, e.epoch)] = uuid.uuid5(ES_NAMESPACE, f"{e.source}/{e.epoch}")
        out.append(StoredEvent(originator_id=oid, originator_version=e.seq, topic=e.type,
                               state=e.payload))
    return out


def es_append(recorder, stored: list, batch: int, *, expect_duplicates: bool = False
              ) -> tuple[float, int]:
    """insert_events in batches into any eventsourcing application recorder (SQLite,
    PostgreSQL); return (seconds, batches refused with IntegrityError)."""
    refused = 0
    spans = batches(len(stored), batch)
    gc.collect()
    start = time.perf_counter()
    for lo, hi in spans:
        try:
            recorder.insert_events(stored[lo:hi])
        except IntegrityError:
            refused += 1
    seconds = time.perf_counter() - start
    if refused and not expect_duplicates:
        raise RuntimeError(f"eventsourcing refused {refused} batches of fresh events")
    return seconds, refused


def ours_read(path: str) -> tuple[float, int]:
    store = open_ledger(path, ManualClock(T0_NS), read_only=True)
    try:
        gc.collect()
        start = time.perf_counter()
        n = 0
        for _ in store.read():
            n += 1
        return time.perf_counter() - start, n
    finally:
        store.close()


def es_read_notifications(path: str) -> tuple[float, int]:
    datastore, recorder = es_recorder(path)
    try:
        gc.collect()
        start = time.perf_counter()
        n, next_id = 0, 1
        while True:
            page = recorder.select_notifications(start=next_id, limit=ES_PAGE)
            if not page:
                break
            n += len(page)
            next_id = page[-1].id + 1
        return time.perf_counter() - start, n
    finally:
        datastore.close()


def es_read_events(path: str, originators: Sequence[uuid.UUID]) -> tuple[float, int]:
    datastore, recorder = es_recorder(path)
    try:
        gc.collect()
        start = time.perf_counter()
        n = 0
        for oid in originators:
            n += len(recorder.select_events(oid))
        return time.perf_counter() - start, n
    finally:
        datastore.close()
