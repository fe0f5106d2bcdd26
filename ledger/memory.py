"""In-memory ledger store: the second backend, for tests and short-lived tools.

It passes the same contract tests as the DuckDB store
(:class:`ledger.testing.LedgerStoreContract`) but keeps nothing after the process
ends.  Not a replacement for the DuckDB ledger.
"""

from __future__ import annotations

import bisect
from typing import Iterator, Sequence

from schemas.analytes import AnalyteOptions, AnalytePolicy

from ledger.clock import SiteClock
from ledger.records import Gap, QuarantineEntry, RecordedEvent
from ledger.signing import SigningPolicy
from ledger.store import LedgerStore
from ledger.writer_state import BatchPlan, Key, StoredKey


class MemoryStore(LedgerStore):
    """A ledger held in Python lists; commits are atomic by construction."""

    backend = "memory"

    def __init__(self, clock: SiteClock | None = None, *,
                 signing: SigningPolicy | None = None,
                 analytes: AnalytePolicy | AnalyteOptions | None = None) -> None:
        super().__init__(clock, signing=signing, analytes=analytes)
        self._rows: list[RecordedEvent] = []
        self._index: dict[Key, int] = {}
        self._gaps: dict[int, Gap] = {}
        self._quarantine: list[QuarantineEntry] = []
        self._recorded: list[int] = []  # recorded time per row, non-decreasing

    def _lookup(self, keys: Sequence[Key], valid_span_ns: tuple[int, int] | None = None
                ) -> dict[Key, StoredKey]:
        out = {}
        for key in keys:
            i = self._index.get(key)
            if i is not None:
                row = self._rows[i]
                out[key] = (row.global_seq, row.payload_sha256, row.type, row.valid_time_ns)
        return out

    def _commit(self, plan: BatchPlan) -> None:
        # nothing below can fail half-way (no I/O, no validation): the batch is atomic
        self._rows.extend(plan.rows)
        self._recorded.extend(r.recorded_time_ns for r in plan.rows)
        for row in plan.rows:
            self._index[row.key] = row.global_seq
        for gap in plan.closed_gaps + plan.opened_gaps:
            self._gaps[gap.gap_id] = gap
        self._quarantine.extend(plan.quarantine)

    def read(self, start_seq: int = 0, stop_seq: int | None = None, *,
             types: Sequence[str] | None = None,
             sources: Sequence[str] | None = None) -> Iterator[RecordedEvent]:
        with self._lock:
            self._check_open()
            rows = self._rows[max(start_seq, 0):stop_seq if stop_seq is None else max(stop_seq, 0)]
        type_set = set(types) if types is not None else None
        source_set = set(sources) if sources is not None else None
        for row in rows:
            if type_set is not None and row.type not in type_set:
                continue
            if source_set is not None and row.source not in source_set:
                continue
            yield row

    def as_of(self, valid_time_ns: int, known_time_ns: int, *,
              types: Sequence[str] | None = None,
              after: tuple[int, int] | None = None) -> Iterator[RecordedEvent]:
        with self._lock:
            self._check_open()
            # recorded time is non-decreasing along the global sequence
            known = self._rows[:bisect.bisect_right(self._recorded, known_time_ns)]
        type_set = set(types) if types is not None else None
        chosen = [r for r in known if r.valid_time_ns <= valid_time_ns
                  and (type_set is None or r.type in type_set)
                  and (after is None or (r.valid_time_ns, r.global_seq) > tuple(after))]
        chosen.sort(key=lambda r: (r.valid_time_ns, r.global_seq))
        return iter(chosen)

    def gaps(self, *, open_only: bool = False) -> list[Gap]:
        with self._lock:
            self._check_open()
            return [g for _, g in sorted(self._gaps.items()) if g.is_open or not open_only]

    def quarantine(self) -> list[QuarantineEntry]:
        with self._lock:
            self._check_open()
            return list(self._quarantine)
