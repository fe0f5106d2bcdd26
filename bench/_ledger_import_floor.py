"""Two sections of ``bench/ledger.py``: the import of JSON lines beside eventsourcing
storing the same lines, and what this machine's disk and DuckDB allow an append at all.

5. **Import of JSON lines** (:func:`section_import`): the yard mix written as canonical
   JSON lines (``schemas.jsonl.event_line``, the format ``stockpile ledger export``
   writes and ``stockpile ledger import`` reads), then ours: ``ledger.importing.import_lines``
   from the file into a fresh DuckDB ledger (every check on, batches of 1,000, what the
   command runs), against ``eventsourcing``'s SQLite recorder storing the same lines: each
   line read, its identity taken from the line's head with one regular expression (the
   peer need not parse the body) and the line stored as the event's state, in batches
   of 1,000.
6. **The floor** (:func:`section_floor`): the median ``fsync`` of this disk (one is the
   least a durable commit costs), and DuckDB alone appending the yard mix's rows as
   pre-built Arrow tables at batch 1,000 into our table, each batch a transaction, no
   checks at all: the most any DuckDB ledger that commits each batch can append here.
"""

from __future__ import annotations

import os
import re
import statistics
import time
import uuid

import duckdb
import pyarrow as pa
from eventsourcing.persistence import StoredEvent

from bench._ledger_systems import ES_NAMESPACE, Workload, batches, es_recorder
from ledger import ManualClock, open_ledger
from ledger.chain import GENESIS
from ledger.duckdb_sql import (_BEGIN, _COMMIT, _DDL, _EVENT_SCHEMA, _INSERT_NEW_EVENTS,
                               _NEW_EVENTS)
from ledger.duckdb_store import _SET_CHECKPOINT_THRESHOLD
from ledger.importing import import_lines
from schemas.jsonl import event_line

BATCH = 1_000
#: the head of a canonical line: type, source, epoch and seq, in that order
_ENVELOPE = re.compile(rb'\{"type":"([^"]+)","source":"([^"]+)","epoch":(\d+),"seq":(\d+),')
FSYNC_SAMPLES = 100


def _lines_file(work: Workload, path: str) -> int:
    with open(path, "w") as out:
        for event in work.events:
            out.write(event_line(event) + "\n")
    return os.path.getsize(path)


def ours_import(lines_path: str, ledger_path: str) -> tuple[float, int]:
    """``import_lines`` of a whole file into a fresh ledger; (seconds, lines appended)."""
    with open_ledger(ledger_path, ManualClock(0)) as store, open(lines_path, "rb") as lines:
        start = time.perf_counter()
        counts = import_lines(store, lines, name=lines_path, batch_size=BATCH)
        seconds = time.perf_counter() - start
    return seconds, counts["appended"]


def es_import(lines_path: str, sqlite_path: str) -> tuple[float, int]:
    """The same lines stored by eventsourcing's SQLite recorder; (seconds, lines)."""
    datastore, recorder = es_recorder(sqlite_path)
    ids: dict[tuple[str, int], uuid.UUID] = {}
    start = time.perf_counter()
    stored, count = [], 0
    with open(lines_path, "rb") as lines:
        for line in lines:
            count += 1
            type_name, source, epoch, seq = _ENVELOPE.match(line).groups()
            key = (source, epoch)
            oid = ids.get(key)
            if oid is None:
                oid = ids[key] = uuid.uuid5(ES_NAMESPACE, f"{source.decode()}/{int(epoch)}")
            stored.append(StoredEvent(originator_id=oid, originator_version=int(seq),
                                      topic=type_name.decode(), state=line))
            if len(stored) == BATCH:
                recorder.insert_events(stored)
                stored = []
    if stored:
        recorder.insert_events(stored)
    seconds = time.perf_counter() - start
    datastore.close()
    return seconds, count


def section_import(work: Workload, tmp: str, out) -> tuple[float, float]:
    """Section 5; returns (ours, eventsourcing) lines/s."""
    lines_path = os.path.join(tmp, "yard.jsonl")
    size = _lines_file(work, lines_path)
    ours_s, ours_n = ours_import(lines_path, os.path.join(tmp, "import.duckdb"))
    es_s, es_n = es_import(lines_path, os.path.join(tmp, "import.sqlite"))
    if ours_n != len(work.events) or es_n != len(work.events):
        raise RuntimeError(f"import stored {ours_n} and {es_n} of {len(work.events)} lines")
    ours_r, es_r = ours_n / ours_s, es_n / es_s
    out(f"5. Import of JSON lines: the yard mix, {len(work.events):,} lines, "
        f"{size / 1e6:,.1f} MB, batches of {BATCH:,}")
    out(f"   ours (import_lines into DuckDB, every check on): {ours_r:>10,.0f} lines/s")
    out(f"   eventsourcing SQLite (identity from the head, line stored):{es_r:>10,.0f} lines/s")
    out(f"   ratio ours/eventsourcing: {ours_r / es_r:.2f}x")
    out()
    return ours_r, es_r


def fsync_ms(directory: str) -> float:
    """Median seconds of one small write plus fsync in ``directory``, in ms."""
    path = os.path.join(directory, "fsync.probe")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o600)
    samples = []
    try:
        for _ in range(FSYNC_SAMPLES):
            os.write(fd, b"x" * 4096)
            start = time.perf_counter()
            os.fsync(fd)
            samples.append(time.perf_counter() - start)
    finally:
        os.close(fd)
        os.remove(path)
    return statistics.median(samples) * 1e3


def duckdb_floor(work: Workload, path: str) -> float:
    """Rows/s of DuckDB alone: the workload's rows as Arrow tables, a transaction each."""
    tables = []
    for lo, hi in batches(len(work.events), BATCH):
        events = work.events[lo:hi]
        n = hi - lo
        tables.append(pa.Table.from_arrays([
            pa.array(range(lo, hi), pa.int64()),
            pa.array([e.type for e in events], pa.string()),
            pa.array([e.source for e in events], pa.string()),
            pa.array([e.epoch for e in events], pa.int64()),
            pa.array([e.seq for e in events], pa.int64()),
            pa.array([e.valid_time_ns for e in events], pa.int64()),
            pa.array(work.arrival_ns[lo:hi], pa.int64()),
            pa.array([e.payload for e in events], pa.binary()),
            pa.array([GENESIS] * n, pa.binary()), pa.array([GENESIS] * n, pa.binary()),
            pa.nulls(n, pa.string()), pa.nulls(n, pa.string()), pa.nulls(n, pa.string()),
            pa.nulls(n, pa.binary()),
        ], schema=_EVENT_SCHEMA))
    con = duckdb.connect(path)
    try:
        con.execute(_SET_CHECKPOINT_THRESHOLD)
        for statement in _DDL:
            con.execute(statement)
        start = time.perf_counter()
        for table in tables:
            con.execute(_BEGIN)           # the store's own statements
            con.register(_NEW_EVENTS, table)
            con.execute(_INSERT_NEW_EVENTS)
            con.unregister(_NEW_EVENTS)
            con.execute(_COMMIT)
        seconds = time.perf_counter() - start
    finally:
        con.close()
    return len(work.events) / seconds


def section_floor(work: Workload, tmp: str, out, ours_r: float, es_r: float) -> None:
    """Section 6: the fsync and DuckDB's own append beside ours and eventsourcing's."""
    sync_ms = fsync_ms(tmp)
    floor_r = duckdb_floor(work, os.path.join(tmp, "floor.duckdb"))
    out(f"6. The floor: yard mix, {len(work.events):,} events at batch {BATCH:,}")
    out(f"   fsync of this disk (median of {FSYNC_SAMPLES}): {sync_ms:.2f} ms, so at most "
        f"{BATCH / sync_ms * 1e3:,.0f} events/s for a commit that waits for one")
    out(f"   DuckDB alone (pre-built Arrow rows, no checks): {floor_r:>10,.0f} events/s"
        f" = {floor_r / es_r:.2f}x eventsourcing SQLite")
    out(f"   ours, every check on:                           {ours_r:>10,.0f} events/s"
        f" = {ours_r / floor_r:.2f}x DuckDB alone")
    out()
