"""Immutable record types the ledger returns.  All times are UTC nanoseconds."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Iterable, Literal, NamedTuple

from schemas.events import Event

Status = Literal["appended", "duplicate", "conflict", "rejected"]
STATUSES: tuple[Status, ...] = ("appended", "duplicate", "conflict", "rejected")

#: Flag on an assay whose lot had not been declared when it was recorded.
FLAG_UNKNOWN_LOT = "unknown_lot"


class RecordedEvent(NamedTuple):
    """An event as stored: its identity and payload plus what the ledger added.

    An immutable record (a NamedTuple: the ledger builds and reads millions of these,
    and a tuple is four times cheaper to make than a frozen dataclass).
    """

    global_seq: int
    type: str
    source: str
    epoch: int
    seq: int
    valid_time_ns: int
    recorded_time_ns: int
    payload: bytes
    payload_sha256: bytes
    chain_sha256: bytes
    flags: tuple[str, ...] = ()
    signer: str | None = None  # key id of the producer's signing key, when signed
    signature: bytes | None = None

    @property
    def key(self) -> tuple[str, int, int]:
        """The idempotency key ``(source, epoch, seq)``."""
        return (self.source, self.epoch, self.seq)

    def to_event(self, *, keep_recorded_time: bool = True) -> Event:
        """Back to an :class:`~schemas.events.Event` (for copying between ledgers), with
        its signature."""
        return Event(self.type, self.source, self.epoch, self.seq, self.valid_time_ns,
                     self.payload, self.recorded_time_ns if keep_recorded_time else None,
                     self.signer, self.signature)


class AppendOutcome(NamedTuple):
    """What happened to one event of a batch (an immutable record).

    ``global_seq`` is the event's position for ``appended``, the stored event's for
    ``duplicate`` and ``conflict``, and ``None`` for ``rejected``.  ``code`` and
    ``detail`` say why for ``conflict`` and ``rejected``
    (codes: :data:`schemas.validate.REASON_CODES`).
    """

    status: Status
    global_seq: int | None = None
    code: str | None = None
    detail: str | None = None
    flags: tuple[str, ...] = ()

    @property
    def reason(self) -> str | None:
        return None if self.code is None else f"{self.code}: {self.detail}"


@dataclass(frozen=True, slots=True)
class AppendResult:
    """Per-event outcomes of one atomic batch, in input order."""

    outcomes: tuple[AppendOutcome, ...]
    head_seq: int  # last global sequence after the batch, -1 for an empty ledger

    @property
    def counts(self) -> dict[str, int]:
        """Number of events per status, every status present."""
        counter = Counter(o.status for o in self.outcomes)
        return {status: counter.get(status, 0) for status in STATUSES}

    @property
    def appended(self) -> int:
        return sum(1 for o in self.outcomes if o.status == "appended")


@dataclass(frozen=True, slots=True)
class Gap:
    """A missing range of source sequence numbers, ``first_seq..last_seq`` inclusive.

    Open while ``closed_recorded_ns`` is ``None``.  When some of the missing events
    arrive the gap is closed and what is still missing is opened again as new gaps
    (which keep the original ``opened_recorded_ns``).
    """

    gap_id: int
    source: str
    epoch: int
    first_seq: int
    last_seq: int
    opened_recorded_ns: int
    closed_recorded_ns: int | None = None

    @property
    def is_open(self) -> bool:
        return self.closed_recorded_ns is None

    @property
    def size(self) -> int:
        return self.last_seq - self.first_seq + 1


@dataclass(frozen=True, slots=True)
class StreamInfo:
    """Sequence bookkeeping of one (source, epoch)."""

    source: str
    epoch: int
    highest_contiguous_seq: int  # -1 when seq 0 is still missing
    max_seq: int
    open_gaps: int
    missing: int  # events in open gaps


@dataclass(frozen=True, slots=True)
class QuarantineEntry:
    """Something that arrived and was not stored as an event, with why and its raw bytes."""

    quarantine_id: int
    recorded_time_ns: int
    type: str
    source: str
    epoch: int | None
    seq: int | None
    valid_time_ns: int | None
    code: str
    detail: str
    raw: bytes
    existing_global_seq: int | None = None  # for conflicts: the stored event's
    after_global_seq: int = -1  # the last row stored before it (-1: none)
    chain_sha256: bytes = b""  # its link of the hash chain (ledger.chain.quarantine_hash)

    @property
    def reason(self) -> str:
        return f"{self.code}: {self.detail}"


@dataclass(frozen=True, slots=True)
class Head:
    """The committed end of the ledger."""

    global_seq: int  # -1 for an empty ledger
    recorded_time_ns: int | None
    chain_sha256: bytes


@dataclass(frozen=True, slots=True)
class VerifyReport:
    """Result of recomputing hashes and the chain over every row."""

    ok: bool
    rows_checked: int
    first_bad_seq: int | None = None
    problem: str | None = None
    signatures: int = 0  # signed rows whose signature held (counted on a clean report)


@dataclass(frozen=True, slots=True)
class LedgerStats:
    """Counts and time ranges for people and dashboards."""

    events: int
    head: Head
    per_type: dict[str, int] = field(default_factory=dict)
    per_source: dict[str, int] = field(default_factory=dict)
    valid_time_range_ns: tuple[int, int] | None = None
    recorded_time_range_ns: tuple[int, int] | None = None
    open_gaps: int = 0
    missing_events: int = 0
    closed_gaps: int = 0
    quarantined: int = 0
    quarantine_by_code: dict[str, int] = field(default_factory=dict)
    flagged: dict[str, int] = field(default_factory=dict)

    @classmethod
    def of(cls, rows: Iterable[RecordedEvent], head: Head, gaps: list[Gap],
           quarantine: list[QuarantineEntry]) -> LedgerStats:
        """The stats of a ledger's rows (one pass), its head, gaps and quarantine."""
        tally = EventTally()
        tally.add(rows)
        return tally.stats(head, gaps, quarantine)


class EventTally:
    """Running counts of an event log: per type, per source and per flag, and the valid
    and recorded time ranges (ns).  :meth:`add` takes rows as they are committed, so a
    store answers :meth:`~ledger.store.LedgerStore.stats` without reading its log again."""

    __slots__ = ("per_type", "per_source", "flagged", "valid", "recorded")

    def __init__(self) -> None:
        self.per_type: Counter[str] = Counter()
        self.per_source: Counter[str] = Counter()
        self.flagged: Counter[str] = Counter()
        self.valid: tuple[int, int] | None = None
        self.recorded: tuple[int, int] | None = None

    def add(self, rows: Iterable[RecordedEvent]) -> None:
        """Count ``rows`` in."""
        for row in rows:
            self.per_type[row.type] += 1
            self.per_source[row.source] += 1
            for flag in row.flags:
                self.flagged[flag] += 1
            self.valid = _widen(self.valid, row.valid_time_ns)
            self.recorded = _widen(self.recorded, row.recorded_time_ns)

    def stats(self, head: Head, gaps: list[Gap],
              quarantine: list[QuarantineEntry]) -> LedgerStats:
        """The :class:`LedgerStats` of the rows counted, with ``head``, ``gaps`` and
        ``quarantine``."""
        return LedgerStats(
            events=sum(self.per_type.values()),
            head=head,
            per_type=dict(sorted(self.per_type.items())),
            per_source=dict(sorted(self.per_source.items())),
            valid_time_range_ns=self.valid,
            recorded_time_range_ns=self.recorded,
            open_gaps=sum(1 for g in gaps if g.is_open),
            missing_events=sum(g.size for g in gaps if g.is_open),
            closed_gaps=sum(1 for g in gaps if not g.is_open),
            quarantined=len(quarantine),
            quarantine_by_code=dict(sorted(Counter(q.code for q in quarantine).items())),
            flagged=dict(sorted(self.flagged.items())),
        )


def _widen(span: tuple[int, int] | None, value: int) -> tuple[int, int]:
    return (value, value) if span is None else (min(span[0], value), max(span[1], value))
