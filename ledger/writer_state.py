"""What the append planner decides from: the writer's in-memory state (per stream and
for the whole ledger) and the plan a batch leaves for a backend to persist
(:mod:`ledger.store`'s ``_BatchPlanner`` makes it, a backend's ``_commit`` writes it)."""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

from ledger.chain import GENESIS
from ledger.records import AppendOutcome, Gap, QuarantineEntry, RecordedEvent
from ledger.signing import KeyRegistry

Key = tuple[str, int, int]
#: what a store answers for a stored key: (global_seq, payload_sha256, type, valid_time_ns)
StoredKey = tuple[int, bytes, str, int]

#: Types whose decoded body is kept beside the payload (as JSON) for the SQL views.
BODY_TYPES: frozenset[str] = frozenset({
    "site_declared", "pile_declared", "machine_declared", "lot_declared", "stack_started",
    "stack_ended", "reclaim_cut", "assay"})


@dataclass
class StreamState:
    """Sequence bookkeeping of one (source, epoch): the writer's view."""

    max_seq: int = -1
    open_gaps: list[Gap] = field(default_factory=list)  # sorted by first_seq

    def copy(self) -> StreamState:
        return StreamState(self.max_seq, list(self.open_gaps))

    def gap_containing(self, seq: int) -> int | None:
        """Index in ``open_gaps`` of the gap holding ``seq``, or None."""
        starts = [g.first_seq for g in self.open_gaps]
        i = bisect.bisect_right(starts, seq) - 1
        if i >= 0 and self.open_gaps[i].last_seq >= seq:
            return i
        return None

    def is_stored(self, seq: int) -> bool:
        """Whether an event with ``seq`` has been stored for this stream."""
        return seq <= self.max_seq and self.gap_containing(seq) is None

    @property
    def highest_contiguous_seq(self) -> int:
        return self.open_gaps[0].first_seq - 1 if self.open_gaps else self.max_seq


@dataclass
class WriterState:
    """Everything the writer needs to decide a batch without reading rows back."""

    head_seq: int = -1
    head_chain: bytes = GENESIS  # the last row's chain value
    link_chain: bytes = GENESIS  # the last link: the last row's, or a quarantine entry's after it
    last_recorded_ns: int | None = None
    latest_clock_event_ns: int | None = None
    streams: dict[tuple[str, int], StreamState] = field(default_factory=dict)
    known_lots: set[str] = field(default_factory=set)
    keys: KeyRegistry = field(default_factory=KeyRegistry)
    next_gap_id: int = 0
    next_quarantine_id: int = 0


@dataclass
class BatchPlan:
    """What one batch writes; a backend persists it atomically in ``_commit``."""

    rows: list[RecordedEvent] = field(default_factory=list)
    bodies: list[str | None] = field(default_factory=list)  # JSON body per row (BODY_TYPES)
    quarantine: list[QuarantineEntry] = field(default_factory=list)
    opened_gaps: list[Gap] = field(default_factory=list)
    closed_gaps: list[Gap] = field(default_factory=list)  # with closed_recorded_ns set
    outcomes: list[AppendOutcome] = field(default_factory=list)
    state: WriterState | None = None  # the writer state after the batch
