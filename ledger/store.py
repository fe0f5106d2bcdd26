"""The ledger store interface and the append logic every backend shares.

A store is an append-only log of :class:`~ledger.records.RecordedEvent` rows with a
dense global sequence, plus a quarantine and a table of sequence gaps.  One
:class:`LedgerStore` object is the single writer of its ledger; threads may share
it (appends are serialised by a lock).

Appending a batch (:meth:`LedgerStore.append`) is atomic: every event of it is
either stored, found to be a duplicate, or quarantined with a reason, and the
batch's rows, quarantine entries and gap changes commit together or not at all.
The decisions are made here, by :class:`_BatchPlanner`, from the writer's
in-memory :class:`WriterState`; a backend only persists a :class:`BatchPlan`
(``_commit``) and answers reads.  Both backends therefore behave identically, which
:class:`ledger.testing.LedgerStoreContract` checks.
"""

from __future__ import annotations

import abc
import dataclasses
from hashlib import sha256
import threading
from typing import Iterable, Iterator, Sequence

from schemas.events import MAX_COUNTER, Event, Malformed
from schemas.jsonl import body_json, storable_text
from schemas.analytes import AnalyteOptions, AnalytePolicy
from schemas.validate import (ANALYTE_TYPES, REASON_CODES, InvalidEvent, check_analyte_names,
                              check_event, is_time_ns)

from ledger.chain import GENESIS, chain_hash, payload_hash
from ledger.clock import SiteClock, WallClock
from ledger.errors import InterfaceError, LedgerError
from ledger.mirror import plan_mirror
from ledger.signing import KEY_TYPES, SigningPolicy, signature_block
from ledger.verifying import (CHAIN_MISMATCH, GapHistory, QuarantineLinks, SignatureCheck,
                              flags_problem, quarantine_link)
from ledger.records import (FLAG_UNKNOWN_LOT, AppendOutcome, AppendResult, Gap, Head,
                            LedgerStats, QuarantineEntry, RecordedEvent, StreamInfo, VerifyReport)
from ledger.writer_state import (BODY_TYPES, BatchPlan, Key, StoredKey, StreamState,
                                 WriterState)


def _int64_or_none(value: object) -> int | None:
    return value if is_time_ns(value) else None


def _split_reason(reason: str) -> tuple[str, str]:
    code, sep, detail = reason.partition(": ")
    if sep and code in REASON_CODES:
        return code, detail
    return "malformed", reason


class _BatchPlanner:
    """Decides one batch against a copy-on-write view of the writer state."""

    def __init__(self, state: WriterState, clock: SiteClock,
                 signing: SigningPolicy | None = None,
                 analytes: AnalytePolicy | None = None) -> None:
        self.base = state
        self.clock = clock
        self.signing = signing
        self.analytes = analytes or AnalytePolicy()
        self.state = WriterState(
            head_seq=state.head_seq,
            head_chain=state.head_chain,
            link_chain=state.link_chain,
            last_recorded_ns=state.last_recorded_ns,
            latest_clock_event_ns=state.latest_clock_event_ns,
            streams=dict(state.streams),  # values copied on first touch
            known_lots=state.known_lots,  # copied on first change
            keys=state.keys,  # copied on first change
            next_gap_id=state.next_gap_id,
            next_quarantine_id=state.next_quarantine_id,
        )
        self._touched: set[tuple[str, int]] = set()
        self._origin: str | None = None  # where the current event came from (FILE:LINE)
        self._lots_copied = False
        self._keys_copied = False
        self.plan = BatchPlan()
        self._opened_at: dict[int, int] = {}  # gap id -> its index in plan.opened_gaps

    # -- state helpers --------------------------------------------------------------

    def _stream(self, source: str, epoch: int) -> StreamState:
        sid = (source, epoch)
        if sid not in self._touched:
            self._touched.add(sid)
            existing = self.state.streams.get(sid)
            self.state.streams[sid] = existing.copy() if existing else StreamState()
        return self.state.streams[sid]

    def _recorded_ns(self, preserved: int | None, clock_event_ns: int | None) -> int:
        last = self.state.last_recorded_ns
        if preserved is not None:
            if last is not None and preserved < last:
                raise InvalidEvent(
                    "recorded_time_backwards",
                    f"recorded_time_ns {preserved} is before the ledger head's {last}",
                )
            return preserved
        now = self.clock.now_ns(clock_event_ns)
        return now if last is None or now > last else last

    def _quarantine(self, item: Event | Malformed, code: str, detail: str,
                    existing: int | None = None) -> None:
        s = self.state
        recorded = self.clock.now_ns(s.latest_clock_event_ns)
        if s.last_recorded_ns is not None and recorded < s.last_recorded_ns:
            recorded = s.last_recorded_ns
        if isinstance(item, Malformed):
            raw, epoch, seq, valid = item.raw, item.epoch, item.seq, item.valid_time_ns
        else:
            raw = bytes(item.payload) if isinstance(item.payload, (bytes, bytearray, memoryview)) else b""
            epoch, seq, valid = item.epoch, item.seq, item.valid_time_ns
            if self._origin:
                detail = f"{self._origin}: {detail}"
        entry = QuarantineEntry(
            quarantine_id=s.next_quarantine_id,
            recorded_time_ns=recorded,
            # text a store cannot hold (lone surrogates) is kept as backslash escapes
            type=storable_text(str(item.type or "")),
            source=storable_text(str(item.source or "")),
            epoch=epoch,
            seq=seq,
            valid_time_ns=valid,
            code=code,
            detail=storable_text(detail),
            raw=raw,
            existing_global_seq=existing,
        )
        # identity numbers that do not fit the store are kept only in the raw bytes
        entry = dataclasses.replace(entry, epoch=_int64_or_none(epoch), seq=_int64_or_none(seq),
                                    valid_time_ns=_int64_or_none(valid),
                                    after_global_seq=s.head_seq)
        entry = dataclasses.replace(entry, chain_sha256=quarantine_link(s.link_chain, entry))
        s.link_chain = entry.chain_sha256
        s.next_quarantine_id += 1
        self.plan.quarantine.append(entry)
        status = "conflict" if code == "conflict" else "rejected"
        self.plan.outcomes.append(AppendOutcome(status, existing, code, detail))

    def _open_in_plan(self, gap: Gap) -> None:
        """Add ``gap`` to the plan's opened gaps, indexed by id (a fill in the same batch
        stores it closed instead)."""
        self._opened_at[gap.gap_id] = len(self.plan.opened_gaps)
        self.plan.opened_gaps.append(gap)

    def _track_sequence(self, source: str, epoch: int, seq: int, recorded_ns: int) -> None:
        stream = self._stream(source, epoch)
        if seq == stream.max_seq + 1:  # the common case: the next one in order
            stream.max_seq = seq
            return
        s = self.state
        if seq > stream.max_seq:
            if seq > stream.max_seq + 1:
                gap = Gap(s.next_gap_id, source, epoch, stream.max_seq + 1, seq - 1, recorded_ns)
                s.next_gap_id += 1
                stream.open_gaps.append(gap)
                self._open_in_plan(gap)
            stream.max_seq = seq
            return
        index = stream.gap_containing(seq)
        assert index is not None, "planner called _track_sequence for a stored seq"
        gap = stream.open_gaps.pop(index)
        closed = Gap(gap.gap_id, source, epoch, gap.first_seq, gap.last_seq,
                     gap.opened_recorded_ns, recorded_ns)
        # a gap opened earlier in this same batch is stored closed (every gap is kept, so
        # the gap table is the same whatever the batches were)
        opened_here = self._opened_at.get(gap.gap_id)
        if opened_here is not None:
            self.plan.opened_gaps[opened_here] = closed
        else:
            self.plan.closed_gaps.append(closed)
        remainders = []
        for first, last in ((gap.first_seq, seq - 1), (seq + 1, gap.last_seq)):
            if first <= last:
                new = Gap(s.next_gap_id, source, epoch, first, last, gap.opened_recorded_ns)
                s.next_gap_id += 1
                remainders.append(new)
                self._open_in_plan(new)
        stream.open_gaps[index:index] = remainders

    # -- the batch --------------------------------------------------------------------

    def run(self, batch: Sequence[Event | Malformed],
            stored: dict[Key, StoredKey],
            origins: Sequence[str] | None = None) -> BatchPlan:
        if origins is None:
            for item in batch:
                self._one(item, stored)
        else:
            for item, origin in zip(batch, origins, strict=True):
                self._origin = origin
                self._one(item, stored)
        self.plan.state = self.state
        return self.plan

    def _one(self, item: Event | Malformed, stored: dict[Key, StoredKey]) -> None:
        # the hot path of the ledger: keep it flat (every event of every batch runs it)
        if type(item) is not Event:
            if isinstance(item, Malformed):
                self._quarantine(item, *_split_reason(item.reason))
                return
            if not isinstance(item, Event):
                raise InterfaceError(f"append takes Event or Malformed, not {type(item).__name__}")
        if stored and self._sent_again(item, stored):
            return
        try:
            message = check_event(item)
        except InvalidEvent as exc:
            self._quarantine(item, exc.code, exc.detail)
            return
        type_name, source, epoch, seq = item.type, item.source, item.epoch, item.seq
        payload = item.payload if type(item.payload) is bytes else bytes(item.payload)
        digest = sha256(payload).digest()
        s = self.state
        stream = s.streams.get((source, epoch))
        if stream is not None and stream.is_stored(seq):
            key = (source, epoch, seq)
            prior = stored.get(key) or self._appended_in_batch(key)
            if prior is None:  # pragma: no cover - would mean state and rows disagree
                raise LedgerError(f"stored event {key} not found; the writer state is stale")
            if prior[1] == digest:
                self.plan.outcomes.append(AppendOutcome("duplicate", prior[0]))
            else:
                self._quarantine(item, "conflict",
                                 f"{key} is stored as global_seq {prior[0]} with another payload",
                                 existing=prior[0])
            return
        if type_name in ANALYTE_TYPES:
            try:
                check_analyte_names(type_name, message, self.analytes)
            except InvalidEvent as exc:
                self._quarantine(item, exc.code, exc.detail)
                return
        if item.signer is not None or type_name in KEY_TYPES or (
                self.signing is not None and type_name in self.signing.signed_types):
            refused = s.keys.problem(type_name, source, epoch, seq, item.valid_time_ns, digest,
                                     message, item.signer, item.signature, self.signing)
            if refused:
                self._quarantine(item, *refused)
                return
        clock_event_ns = s.latest_clock_event_ns
        if type_name == "clock" and (clock_event_ns is None or item.valid_time_ns > clock_event_ns):
            clock_event_ns = item.valid_time_ns  # a tick is learned at its own time
        try:
            recorded = self._recorded_ns(item.recorded_time_ns, clock_event_ns)
        except InvalidEvent as exc:
            self._quarantine(item, exc.code, exc.detail)
            return
        s.latest_clock_event_ns = clock_event_ns
        flags: tuple[str, ...] = ()
        body = None
        if type_name in BODY_TYPES:
            body = body_json(message)
            if type_name == "assay" and message.lot_id not in s.known_lots:
                flags = (FLAG_UNKNOWN_LOT,)
            elif type_name == "lot_declared" and message.lot_id not in s.known_lots:
                if not self._lots_copied:
                    s.known_lots = set(s.known_lots)
                    self._lots_copied = True
                s.known_lots.add(message.lot_id)
        if type_name in KEY_TYPES:
            if not self._keys_copied:
                s.keys = s.keys.copy()
                self._keys_copied = True
            s.keys.learn(type_name, message)
        global_seq = s.head_seq + 1
        valid = item.valid_time_ns
        signer, signature = item.signer, item.signature
        chain = chain_hash(s.link_chain, global_seq, type_name, source, epoch, seq, valid,
                           recorded, digest, signature_block(signer, signature))
        s.head_seq, s.head_chain, s.link_chain, s.last_recorded_ns = (global_seq, chain, chain,
                                                                      recorded)
        self._track_sequence(source, epoch, seq, recorded)
        plan = self.plan
        plan.rows.append(RecordedEvent(global_seq, type_name, source, epoch, seq, valid,
                                       recorded, payload, digest, chain, flags, signer,
                                       signature))
        plan.bodies.append(body)
        plan.outcomes.append(AppendOutcome("appended", global_seq, None, None, flags))

    def _appended_in_batch(self, key: Key) -> StoredKey | None:
        """What a store would answer for ``key`` if this batch appended it (rare path)."""
        for row in reversed(self.plan.rows):
            if (row.source, row.epoch, row.seq) == key:
                return row.global_seq, row.payload_sha256, row.type, row.valid_time_ns
        return None

    def _sent_again(self, item: Event, stored: dict[Key, StoredKey]) -> bool:
        """Record ``item`` as a duplicate if it is a stored event sent again: its key is
        stored with the same type, valid time and payload bytes.  Such an event is not
        decoded again (it passed the same checks when it was stored); anything else goes
        through the full path, which also tells a conflict from a duplicate."""
        payload = item.payload
        if type(payload) is not bytes or not _storable_key(item):
            return False
        prior = stored.get((item.source, item.epoch, item.seq))
        if (prior is None or prior[2] != item.type or prior[3] != item.valid_time_ns
                or prior[1] != sha256(payload).digest()):
            return False
        recorded = item.recorded_time_ns
        if recorded is not None and not is_time_ns(recorded):
            return False
        self.plan.outcomes.append(AppendOutcome("duplicate", prior[0]))
        return True


def _storable_key(item: Event) -> bool:
    """Whether ``item``'s (source, epoch, seq) has the types and ranges of a stored key."""
    epoch, seq = item.epoch, item.seq
    return (type(epoch) is int and type(seq) is int and type(item.source) is str
            and 0 <= epoch <= MAX_COUNTER and 0 <= seq <= MAX_COUNTER)


def keys_to_look_up(state: WriterState, batch: Iterable[Event | Malformed]
                    ) -> tuple[list[Key], tuple[int, int] | None]:
    """Keys of a batch that may already be stored (so their payload hash is needed), and
    the span of those events' valid times (ns; None when none is a 64-bit integer).

    Only keys a store can hold are looked up: an epoch or seq outside [0, 2^63) is never
    stored (the planner quarantines it as ``bad_identity``).  The span is a hint: a
    duplicate was stored at its own valid time, so a store can look there first.
    """
    keys = []
    low = high = None
    for item in batch:
        if not isinstance(item, Event) or not _storable_key(item):
            continue
        stream = state.streams.get((item.source, item.epoch))
        if stream is not None and stream.is_stored(item.seq):
            keys.append((item.source, item.epoch, item.seq))
            valid = item.valid_time_ns
            if is_time_ns(valid):
                low = valid if low is None or valid < low else low
                high = valid if high is None or valid > high else high
    return keys, (None if low is None else (low, high))


class LedgerStore(abc.ABC):
    """An append-only event ledger.  Subclasses: the DuckDB and in-memory stores.

    Parameters
    ----------
    clock : SiteClock, optional
        Source of recorded time (default: the wall clock).
    signing : SigningPolicy, optional
        The types that must be signed and the admin key trusted (default: signatures
        are checked when present, none is required).
    analytes : AnalytePolicy or AnalyteOptions, optional
        The site's declared analytes and unknown-analyte policy (default: the built-in
        list, unknown ones flagged; a DuckDB ledger resolves it against its recorded one).
    """

    #: short backend name for messages ("duckdb", "memory")
    backend: str = "abstract"

    def __init__(self, clock: SiteClock | None = None, *, read_only: bool = False,
                 signing: SigningPolicy | None = None,
                 analytes: AnalytePolicy | AnalyteOptions | None = None) -> None:
        self.clock: SiteClock = clock or WallClock()
        self.read_only = read_only
        self.signing = signing
        self.analytes: AnalytePolicy = analytes.resolve(None) if analytes else AnalytePolicy()
        self._lock = threading.RLock()
        self._closed = False
        self._state = WriterState()

    # -- writing ------------------------------------------------------------------------

    def append(self, batch: Sequence[Event | Malformed], *,
               origins: Sequence[str] | None = None) -> AppendResult:
        """Append one batch atomically; return an outcome per event, in input order.

        Events are validated (:func:`schemas.validate.check_event`); an event whose
        ``(source, epoch, seq)`` is already stored with the same payload is a
        ``duplicate`` (a no-op); with another payload a ``conflict`` (quarantined,
        never overwriting).  Rejected and conflicting events are quarantined with
        their reason and raw bytes; the rest of the batch is kept.  ``origins`` (one per
        event, e.g. ``FILE:LINE``) prefixes the reason of each refused event.

        Raises
        ------
        InterfaceError
            The store is closed or read-only.
        DatabaseError
            The backend failed; nothing of the batch was stored.
        """
        batch = list(batch)
        with self._lock:
            self._check_writable()
            keys, valid_span_ns = keys_to_look_up(self._state, batch)
            stored = self._lookup(keys, valid_span_ns) if keys else {}
            if origins is not None and len(origins) != len(batch):
                raise InterfaceError(f"{len(origins)} origins for {len(batch)} events")
            plan = _BatchPlanner(self._state, self.clock, self.signing,
                                 self.analytes).run(batch, stored, origins)
            if plan.rows or plan.quarantine or plan.opened_gaps or plan.closed_gaps:
                self._commit(plan)
            assert plan.state is not None
            self._state = plan.state
            return AppendResult(tuple(plan.outcomes), self._state.head_seq)

    def mirror(self, rows: Sequence[RecordedEvent], quarantine: Sequence[QuarantineEntry] = (),
               gaps: Sequence[Gap] = ()) -> Head:
        """Append another ledger's rows and quarantine entries verbatim after this head,
        atomically, its gap table ``gaps`` compared; the new head.  Raises MirrorRefused
        naming what was tampered with or does not continue this ledger (:mod:`ledger.mirror`)."""
        with self._lock:
            self._check_writable()
            plan = plan_mirror(_BatchPlanner(self._state, self.clock), rows, quarantine, gaps,
                               self.gaps() if gaps else (), BODY_TYPES)
            if plan.rows or plan.quarantine:
                self._commit(plan)
            self._state = plan.state
            return self.head()

    # -- reading ------------------------------------------------------------------------

    def head(self) -> Head:
        """The committed end of the ledger (global seq -1 when empty)."""
        with self._lock:
            self._check_open()
            s = self._state
            return Head(s.head_seq, s.last_recorded_ns, s.head_chain)

    @abc.abstractmethod
    def read(
        self,
        start_seq: int = 0,
        stop_seq: int | None = None,
        *,
        types: Sequence[str] | None = None,
        sources: Sequence[str] | None = None,
    ) -> Iterator[RecordedEvent]:
        """Events with ``start_seq <= global_seq < stop_seq`` in global order (catch-up).

        ``types`` / ``sources`` keep only those event types / sources.
        """

    @abc.abstractmethod
    def as_of(
        self,
        valid_time_ns: int,
        known_time_ns: int,
        *,
        types: Sequence[str] | None = None,
        after: tuple[int, int] | None = None,
    ) -> Iterator[RecordedEvent]:
        """The ledger as it was known at ``known_time_ns`` about ``valid_time_ns``.

        Events with valid time <= V recorded at or before K, ordered by
        (valid time, global seq).  ``after=(valid_ns, global_seq)`` keeps only the
        events that come after that position in this order (a fold resuming from a
        snapshot).
        """

    @abc.abstractmethod
    def gaps(self, *, open_only: bool = False) -> list[Gap]:
        """Sequence gaps, ordered by gap id (open and closed unless ``open_only``)."""

    @abc.abstractmethod
    def quarantine(self) -> list[QuarantineEntry]:
        """Every quarantined input, in arrival order."""

    def streams(self) -> list[StreamInfo]:
        """Sequence bookkeeping per (source, epoch), sorted."""
        with self._lock:
            self._check_open()
            return [
                StreamInfo(source, epoch, st.highest_contiguous_seq, st.max_seq,
                           len(st.open_gaps), sum(g.size for g in st.open_gaps))
                for (source, epoch), st in sorted(self._state.streams.items())
            ]

    def verify(self) -> VerifyReport:
        """Recompute payload hashes and the chain over every row and quarantine entry, each
        row's flags from the payloads before it, and the gap table from the rows; name the
        first bad row (or entry, or gap)."""
        with self._lock:
            self._check_open()
            previous = GENESIS
            last_recorded: int | None = None
            count = 0
            lots: set[str] = set()
            gaps = GapHistory()
            links = QuarantineLinks(self.quarantine())
            signatures = SignatureCheck(self.signing)
            for row in self._rows_for_verify():
                if row.global_seq != count:
                    return VerifyReport(False, count, count,
                                        f"global_seq {row.global_seq} where {count} was expected")
                previous, problem = links.before(count, previous)
                if problem:
                    return VerifyReport(False, count, None, problem)
                if payload_hash(row.payload) != row.payload_sha256:
                    return VerifyReport(False, count, row.global_seq,
                                        "payload does not match its sha256")
                if last_recorded is not None and row.recorded_time_ns < last_recorded:
                    return VerifyReport(False, count, row.global_seq, "recorded time goes backwards")
                expected = chain_hash(previous, row.global_seq, row.type, row.source, row.epoch,
                                      row.seq, row.valid_time_ns, row.recorded_time_ns,
                                      row.payload_sha256, signature_block(row.signer, row.signature))
                if expected != row.chain_sha256:
                    return VerifyReport(False, count, row.global_seq, CHAIN_MISMATCH)
                problem = flags_problem(row, lots) or gaps.row(row) or signatures.row(row)
                if problem:
                    return VerifyReport(False, count, row.global_seq, problem)
                previous, last_recorded = row.chain_sha256, row.recorded_time_ns
                count += 1
            _, problem = links.before(count, previous)
            problem = problem or links.problem_after(count) or gaps.problem(self.gaps())
            if problem:
                return VerifyReport(False, count, None, problem)
            return VerifyReport(True, count, signatures=signatures.held)

    def stats(self) -> LedgerStats:
        """Counts per type and source, gaps, quarantine and time ranges."""
        with self._lock:
            self._check_open()
            return LedgerStats.of(self._rows_for_stats(), self.head(), self.gaps(),
                                  self.quarantine())

    # -- lifecycle ------------------------------------------------------------------------

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._close()

    def __enter__(self) -> LedgerStore:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise InterfaceError(f"the {self.backend} ledger is closed")

    def _check_writable(self) -> None:
        self._check_open()
        if self.read_only:
            raise InterfaceError(f"the {self.backend} ledger was opened read-only")

    # -- what a backend provides ------------------------------------------------------------

    @abc.abstractmethod
    def _lookup(self, keys: Sequence[Key], valid_span_ns: tuple[int, int] | None = None
                ) -> dict[Key, StoredKey]:
        """``key -> (global_seq, payload_sha256, type, valid_time_ns)`` for the stored events
        among ``keys``.  ``valid_span_ns`` (first, last) is where most of them are likely to
        lie in valid time; every stored key is answered whatever its valid time."""

    @abc.abstractmethod
    def _commit(self, plan: BatchPlan) -> None:
        """Persist a plan atomically (all of it or nothing), or raise DatabaseError."""

    def _rows_for_verify(self) -> Iterator[RecordedEvent]:
        return self.read()

    def _rows_for_stats(self) -> Iterator[RecordedEvent]:
        return self.read()

    def _close(self) -> None:
        return None
