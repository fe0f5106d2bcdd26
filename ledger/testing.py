"""The contract every ledger backend passes (the pattern of eventsourcing's persistence tests).

A backend's test module subclasses :class:`LedgerStoreContract` and implements
``create_store`` (and, for persistent backends, ``reopen``) plus ``tamper``::

    class TestMemoryStore(LedgerStoreContract):
        def create_store(self, clock, directory, signing=None):
            return MemoryStore(clock, signing=signing)
        ...

Requires pytest; the property test also needs hypothesis (the ``dev`` extra), imported when
it runs, so that the module imports without it.
"""

from __future__ import annotations

import abc
import dataclasses
import random
import tempfile
import threading
from pathlib import Path

from schemas import pb
from schemas.events import Event, Malformed, make_event, set_timestamp_ns

from ledger.chain import payload_hash
from ledger.clock import EventClock, ManualClock
from ledger.records import FLAG_UNKNOWN_LOT, Gap, QuarantineEntry, RecordedEvent, VerifyReport
from ledger.signing import SigningPolicy
from ledger.store import LedgerStore
from ledger.testing_resend import ResendContract
from ledger.testing_signing import SigningContract, rechained
from ledger.testing_stats import StatsContract
from ledger.verifying import CHAIN_MISMATCH


def joint_event(source: str, seq: int, valid_time_ns: int, travel_m: float = 0.0,
                epoch: int = 1) -> Event:
    """A small valid event (a joint reading) with the given identity and valid time."""
    message = pb.JointReading(machine_id="bwr1", travel_m=travel_m)
    set_timestamp_ns(message.time, valid_time_ns)
    return make_event(message, source=source, epoch=epoch, seq=seq)


def _histories(draw, st):
    """Batches of events with a non-decreasing site clock, late events included (a
    hypothesis ``composite`` body: ``draw`` and the ``strategies`` module are passed in)."""
    n_batches = draw(st.integers(1, 6))
    clock = 0
    next_seq: dict[str, int] = {}
    batches = []
    for _ in range(n_batches):
        clock += draw(st.integers(0, 50))
        size = draw(st.integers(0, 6))
        events = []
        for _ in range(size):
            source = draw(st.sampled_from(["a.src", "b.src", "c.src"]))
            # valid time anywhere up to the clock: most events are "late"
            valid = draw(st.integers(0, clock + 5))
            seq = next_seq.get(source, 0)
            next_seq[source] = seq + 1
            events.append((source, seq, valid))
        batches.append((clock, events))
    queries = draw(st.lists(st.tuples(st.integers(-1, clock + 10), st.integers(-1, clock + 10)),
                            min_size=1, max_size=8))
    return batches, queries


# -- tampering: what an attacker with write access to the storage might do ------------------

#: Stored fields a tamper case changes, one at a time (every field the chain hashes, the
#: payload and the stored hashes), ``payload_and_hash``: the payload edited together
#: with its stored sha256, so that only the chain can tell, and ``flags``: a flag added
#: (outside the chain: verify recomputes flags from the payloads before the row).
TAMPER_FIELDS: tuple[str, ...] = (
    "type", "source", "epoch", "seq", "valid_time_ns", "recorded_time_ns", "payload",
    "payload_sha256", "global_seq", "chain_sha256", "payload_and_hash", "flags")
#: Whole-row cases: ``delete`` a row (later rows renumbered down, so the sequence stays
#: dense), ``insert`` a forged row before a row (taking its number; its chain value made
#: right, later rows renumbered up), ``reorder`` a row and the next (numbers kept),
#: ``rechain_backwards``: a recorded time moved before the previous row's with every chain
#: value from there on recomputed (only the recorded-time order can tell).
TAMPER_ROWS: tuple[str, ...] = ("delete", "insert", "reorder", "rechain_backwards")


def _flip(b: bytes) -> bytes:
    return bytes([b[0] ^ 0x01]) + b[1:]


def tampered_rows(rows: list[RecordedEvent], global_seq: int, field: str) -> list[RecordedEvent]:
    """``rows`` (every stored row, in global order) after one tamper case at ``global_seq``.

    A field case changes that field of that row only (an integer by one, a text by an
    appended character, the payload by an appended byte, a stored hash by a flipped bit);
    the row cases are described at :data:`TAMPER_ROWS`.
    """
    rows = list(rows)
    i = global_seq
    r = rows[i]
    if field in ("epoch", "seq", "valid_time_ns", "recorded_time_ns", "global_seq"):
        rows[i] = r._replace(**{field: getattr(r, field) + 1})
    elif field in ("type", "source"):
        rows[i] = r._replace(**{field: getattr(r, field) + "x"})
    elif field == "payload":
        rows[i] = r._replace(payload=r.payload + b"\x00")
    elif field in ("payload_sha256", "chain_sha256"):
        rows[i] = r._replace(**{field: _flip(getattr(r, field))})
    elif field == "payload_and_hash":
        payload = r.payload + b"\x00"
        rows[i] = r._replace(payload=payload, payload_sha256=payload_hash(payload))
    elif field == "flags":
        rows[i] = r._replace(flags=r.flags + (FLAG_UNKNOWN_LOT,))
    elif field == "delete":
        del rows[i]
        rows[i:] = [x._replace(global_seq=x.global_seq - 1) for x in rows[i:]]
    elif field == "insert":
        forged = r._replace(seq=r.seq + 1_000)
        rows[i:] = [forged] + [x._replace(global_seq=x.global_seq + 1) for x in rows[i:]]
        rows[:i + 1] = rechained(rows[:i + 1], i)
    elif field == "reorder":
        a, b = rows[i], rows[i + 1]
        rows[i], rows[i + 1] = b._replace(global_seq=a.global_seq), a._replace(global_seq=b.global_seq)
    elif field == "rechain_backwards":
        rows[i] = r._replace(recorded_time_ns=rows[i - 1].recorded_time_ns - 1)
        rows = rechained(rows, i)
    else:
        raise ValueError(f"unknown tamper case {field!r}")
    return rows


def tamper_expectation(field: str, global_seq: int) -> VerifyReport:
    """The report verify must give for a tamper case at ``global_seq``."""
    if field == "insert":
        bad, problem = global_seq + 1, CHAIN_MISMATCH
    elif field in ("payload", "payload_sha256"):
        bad, problem = global_seq, "payload does not match its sha256"
    elif field == "global_seq":
        bad, problem = global_seq, f"global_seq {global_seq + 1} where {global_seq} was expected"
    elif field == "rechain_backwards":
        bad, problem = global_seq, "recorded time goes backwards"
    elif field == "flags":   # the tamper ledger's rows carry no flags of their own
        bad, problem = global_seq, f"flags ['{FLAG_UNKNOWN_LOT}'] where the payloads before it give []"
    else:
        bad, problem = global_seq, CHAIN_MISMATCH
    return VerifyReport(False, bad, bad, problem)


#: Cases on the quarantine and gap tables (an entry or gap row edited, deleted, added):
#: ``(table, case)``; plain verify must catch each (:func:`tampered_side`).
SIDE_TAMPER_CASES: tuple[tuple[str, str], ...] = (
    ("quarantine", "detail"), ("quarantine", "code"), ("quarantine", "raw"),
    ("quarantine", "recorded_time_ns"), ("quarantine", "last_detail"),
    ("quarantine", "delete_first"), ("quarantine", "delete_all"),
    ("gaps", "last_seq"), ("gaps", "reopen"), ("gaps", "close"), ("gaps", "delete_closed"),
    ("gaps", "delete_open"), ("gaps", "delete_all"), ("gaps", "add"))


def tampered_side(quarantine: list[QuarantineEntry], gaps: list[Gap],
                  case: tuple[str, str]) -> tuple[list[QuarantineEntry], list[Gap]]:
    """The quarantine and gap tables after one of :data:`SIDE_TAMPER_CASES`."""
    quarantine, gaps = list(quarantine), list(gaps)
    table, what = case
    closed = next(i for i, g in enumerate(gaps) if not g.is_open)
    still_open = next(i for i, g in enumerate(gaps) if g.is_open)
    if case == ("quarantine", "last_detail"):
        quarantine[-1] = dataclasses.replace(quarantine[-1], detail=quarantine[-1].detail + "x")
    elif table == "quarantine" and what in ("detail", "code"):
        quarantine[0] = dataclasses.replace(quarantine[0], **{what: getattr(quarantine[0], what) + "x"})
    elif what == "raw":
        quarantine[0] = dataclasses.replace(quarantine[0], raw=quarantine[0].raw + b"\x00")
    elif what == "recorded_time_ns":
        quarantine[0] = dataclasses.replace(quarantine[0], recorded_time_ns=quarantine[0].recorded_time_ns + 1)
    elif what == "delete_first":
        del quarantine[0]
    elif what == "delete_all":
        quarantine, gaps = ([], gaps) if table == "quarantine" else (quarantine, [])
    elif what == "last_seq":
        gaps[still_open] = dataclasses.replace(gaps[still_open], last_seq=gaps[still_open].last_seq + 1)
    elif what == "reopen":
        gaps[closed] = dataclasses.replace(gaps[closed], closed_recorded_ns=None)
    elif what == "close":
        gaps[still_open] = dataclasses.replace(gaps[still_open], closed_recorded_ns=10**12)
    elif what == "delete_closed":
        del gaps[closed]
    elif what == "delete_open":
        del gaps[still_open]
    elif what == "add":
        gaps.append(Gap(len(gaps), "a.src", 1, 1_000, 1_001, gaps[-1].opened_recorded_ns))
    else:
        raise ValueError(f"unknown side tamper case {case!r}")
    return quarantine, gaps


class LedgerStoreContract(ResendContract, SigningContract, StatsContract):
    """Behaviour every :class:`~ledger.store.LedgerStore` backend must show."""

    #: whether the backend keeps data across ``reopen``
    persistent: bool = False

    @abc.abstractmethod
    def create_store(self, clock: ManualClock, directory: Path,
                     signing: SigningPolicy | None = None) -> LedgerStore:
        """A new, empty store in ``directory`` using ``clock`` (and ``signing``)."""

    def reopen(self, store: LedgerStore, clock: ManualClock) -> LedgerStore:
        """Close ``store`` and open the same ledger again (persistent backends)."""
        return store

    @abc.abstractmethod
    @abc.abstractmethod
    def replace_side_tables(self, store: LedgerStore, quarantine: list[QuarantineEntry],
                            gaps: list[Gap]) -> LedgerStore:
        """Replace the stored quarantine and gap tables behind the store's back; return a
        store that reads the changed tables."""

    def tamper(self, store: LedgerStore, global_seq: int, field: str) -> LedgerStore:
        """Change the stored rows behind the store's back as :func:`tampered_rows` does
        (``field``: one of :data:`TAMPER_FIELDS` or :data:`TAMPER_ROWS`), in the backend's
        own storage; return the store to verify (possibly reopened)."""

    # -- helpers ------------------------------------------------------------------------

    def _new(self, tmp_path: Path, start_ns: int = 1_000) -> tuple[LedgerStore, ManualClock]:
        clock = ManualClock(start_ns)
        return self.create_store(clock, tmp_path), clock

    # -- the contract -------------------------------------------------------------------

    def test_empty_store(self, tmp_path):
        store, _ = self._new(tmp_path)
        assert store.head().global_seq == -1
        assert list(store.read()) == []
        assert list(store.as_of(10**18, 10**18)) == []
        assert store.gaps() == [] and store.quarantine() == []
        assert store.verify().ok and store.verify().rows_checked == 0
        store.close()

    def test_append_assigns_dense_global_seq_and_recorded_time(self, tmp_path):
        store, clock = self._new(tmp_path, 500)
        result = store.append([joint_event("a.src", i, 100 + i) for i in range(3)])
        assert [o.status for o in result.outcomes] == ["appended"] * 3
        assert [o.global_seq for o in result.outcomes] == [0, 1, 2]
        clock.set_ns(400)  # a clock that steps back never makes recorded time go backwards
        store.append([joint_event("b.src", 0, 50)])
        rows = list(store.read())
        assert [r.global_seq for r in rows] == [0, 1, 2, 3]
        assert [r.recorded_time_ns for r in rows] == [500, 500, 500, 500]
        assert store.head().global_seq == 3
        store.close()

    def test_idempotent_reappend(self, tmp_path):
        store, clock = self._new(tmp_path)
        batch = [joint_event("a.src", i, 100 + i, travel_m=i) for i in range(5)]
        store.append(batch)
        head = store.head()
        clock.advance_ns(1_000)
        again = store.append(batch)
        assert again.counts == {"appended": 0, "duplicate": 5, "conflict": 0, "rejected": 0}
        assert [o.global_seq for o in again.outcomes] == [0, 1, 2, 3, 4]
        assert store.head() == head
        store = self.reopen(store, clock)
        assert store.append(batch[2:4]).counts["duplicate"] == 2
        assert len(list(store.read())) == 5 and store.quarantine() == []
        store.close()

    def test_duplicate_within_one_batch(self, tmp_path):
        store, _ = self._new(tmp_path)
        e = joint_event("a.src", 0, 100)
        result = store.append([e, e])
        assert [o.status for o in result.outcomes] == ["appended", "duplicate"]
        assert result.outcomes[1].global_seq == 0
        store.close()

    def test_conflict_is_quarantined_never_overwrites(self, tmp_path):
        store, clock = self._new(tmp_path)
        original = joint_event("a.src", 0, 100, travel_m=1.0)
        store.append([original])
        store = self.reopen(store, clock)
        rival = joint_event("a.src", 0, 100, travel_m=2.0)
        result = store.append([rival, joint_event("a.src", 1, 101)])
        assert [o.status for o in result.outcomes] == ["conflict", "appended"]
        assert result.outcomes[0].code == "conflict" and result.outcomes[0].global_seq == 0
        [entry] = store.quarantine()
        assert entry.code == "conflict" and entry.raw == rival.payload
        assert entry.existing_global_seq == 0 and (entry.source, entry.epoch, entry.seq) == rival.key
        stored = list(store.read())
        assert stored[0].payload == original.payload and len(stored) == 2
        store.close()

    def test_epochs_are_separate_streams(self, tmp_path):
        store, _ = self._new(tmp_path)
        result = store.append([joint_event("a.src", 0, 1, epoch=1, travel_m=1),
                               joint_event("a.src", 0, 2, epoch=2, travel_m=2)])
        assert result.counts["appended"] == 2
        assert {(s.source, s.epoch) for s in store.streams()} == {("a.src", 1), ("a.src", 2)}
        store.close()

    def test_gaps_are_recorded_and_closed(self, tmp_path):
        store, clock = self._new(tmp_path, 1_000)
        store.append([joint_event("a.src", s, s) for s in (0, 1, 5)])
        [gap] = store.gaps()
        assert (gap.first_seq, gap.last_seq, gap.is_open, gap.opened_recorded_ns) == (2, 4, True, 1_000)
        [info] = store.streams()
        assert (info.highest_contiguous_seq, info.max_seq, info.missing) == (1, 5, 3)
        store = self.reopen(store, clock)
        clock.set_ns(2_000)
        store.append([joint_event("a.src", 3, 3)])
        gaps = store.gaps()
        closed = [g for g in gaps if not g.is_open]
        still_open = sorted((g.first_seq, g.last_seq) for g in gaps if g.is_open)
        assert [(g.first_seq, g.last_seq, g.closed_recorded_ns) for g in closed] == [(2, 4, 2_000)]
        assert still_open == [(2, 2), (4, 4)]
        assert all(g.opened_recorded_ns == 1_000 for g in gaps)
        store = self.reopen(store, clock)
        clock.set_ns(3_000)
        store.append([joint_event("a.src", 4, 4), joint_event("a.src", 2, 2)])
        assert store.gaps(open_only=True) == []
        [info] = store.streams()
        assert (info.highest_contiguous_seq, info.max_seq, info.open_gaps) == (5, 5, 0)
        # a late arrival of an already-filled seq is a duplicate, not a gap change
        assert store.append([joint_event("a.src", 3, 3)]).counts["duplicate"] == 1
        store.close()

    def test_first_event_not_at_zero_opens_a_gap(self, tmp_path):
        store, _ = self._new(tmp_path)
        store.append([joint_event("a.src", 3, 3)])
        assert [(g.first_seq, g.last_seq) for g in store.gaps(open_only=True)] == [(0, 2)]
        store.close()

    def test_gap_opened_and_filled_inside_one_batch_is_kept_closed(self, tmp_path):
        # the gap table does not depend on where the batches were cut
        one, _ = self._new(tmp_path / "one", 1_000)
        one.append([joint_event("a.src", s, s) for s in (0, 2, 1)])
        three, _ = self._new(tmp_path / "three", 1_000)
        for s in (0, 2, 1):
            three.append([joint_event("a.src", s, s)])
        assert one.gaps(open_only=True) == []
        assert one.gaps() == three.gaps() == [Gap(0, "a.src", 1, 1, 1, 1_000, 1_000)]
        assert one.verify().ok and three.verify().ok
        one.close()
        three.close()

    def test_concurrent_appenders_get_a_dense_global_sequence(self, tmp_path):
        store, _ = self._new(tmp_path)
        n_threads, n_batches, size = 4, 25, 8
        errors: list[BaseException] = []
        start = threading.Barrier(n_threads)

        def worker(t: int) -> None:
            try:
                start.wait()
                for b in range(n_batches):
                    store.append([joint_event(f"t{t}.src", b * size + i, b * size + i)
                                  for i in range(size)])
            except BaseException as exc:  # pragma: no cover - reported below
                errors.append(exc)

        threads = [threading.Thread(target=worker, args=(t,)) for t in range(n_threads)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert errors == []
        rows = list(store.read())
        total = n_threads * n_batches * size
        assert [r.global_seq for r in rows] == list(range(total))
        for t in range(n_threads):
            seqs = [r.seq for r in rows if r.source == f"t{t}.src"]
            assert seqs == list(range(n_batches * size))  # each thread's batches stay in order
        assert store.gaps() == [] and store.verify().ok
        store.close()

    def test_read_range_and_filters(self, tmp_path):
        store, _ = self._new(tmp_path)
        store.append([joint_event("a.src", i, i) for i in range(5)]
                     + [joint_event("b.src", i, i) for i in range(5)])
        assert [r.global_seq for r in store.read(3, 6)] == [3, 4, 5]
        assert [r.global_seq for r in store.read(8)] == [8, 9]
        assert [r.seq for r in store.read(sources=["b.src"])] == list(range(5))
        assert list(store.read(types=["assay"])) == []
        assert len(list(store.read(types=["joint_reading"]))) == 10
        store.close()

    def test_as_of_excludes_events_recorded_after_known_time(self, tmp_path):
        store, clock = self._new(tmp_path, 100)
        store.append([joint_event("a.src", 0, 90)])
        clock.set_ns(200)
        store.append([joint_event("a.src", 1, 50)])  # late: happened at 50, learned at 200
        assert [r.seq for r in store.as_of(100, 150)] == [0]
        assert [r.seq for r in store.as_of(100, 200)] == [1, 0]  # ordered by valid time
        assert [r.seq for r in store.as_of(60, 200)] == [1]
        store.close()

    # each backend subclass runs this same method: that is the point of a contract
    def test_as_of_matches_brute_force(self):
        # deferred: hypothesis is a dev dependency (this module ships in the package)
        from hypothesis import HealthCheck, given, settings
        from hypothesis import strategies as st

        histories = st.composite(lambda draw: _histories(draw, st))

        @settings(max_examples=40, deadline=None,
                  suppress_health_check=[HealthCheck.differing_executors])
        @given(histories())
        def check(history):
            self._check_as_of(history)

        check()

    def _check_as_of(self, history) -> None:
        batches, queries = history
        with tempfile.TemporaryDirectory() as directory:
            clock = ManualClock(0)
            store = self.create_store(clock, Path(directory))
            expected_rows = []  # (global_seq, valid, recorded) computed from the input alone
            for batch_clock, events in batches:
                clock.set_ns(batch_clock)
                store.append([joint_event(s, q, v) for s, q, v in events])
                for s, q, v in events:
                    expected_rows.append((len(expected_rows), v, batch_clock))
            for valid, known in queries:
                want = [g for g, v, r in sorted(expected_rows, key=lambda x: (x[1], x[0]))
                        if v <= valid and r <= known]
                got = [r.global_seq for r in store.as_of(valid, known)]
                assert got == want, (valid, known)
                # resuming after any position gives exactly the rest, in the same order
                rows = list(store.as_of(valid, known))
                for cut in {0, len(rows) // 2, len(rows) - 1} if rows else ():
                    mark = (rows[cut].valid_time_ns, rows[cut].global_seq)
                    rest = [r.global_seq for r in store.as_of(valid, known, after=mark)]
                    assert rest == want[cut + 1:], (valid, known, mark)
            store.close()

    def test_preserved_recorded_time_is_kept(self, tmp_path):
        store, _ = self._new(tmp_path, 10**9)
        e = joint_event("a.src", 0, 5)
        preserved = Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload, 77)
        store.append([preserved])
        assert [r.recorded_time_ns for r in store.read()] == [77]
        assert store.verify().ok
        store.close()

    def test_event_clock_follows_clock_events(self, tmp_path):
        def clock_event(seq: int, t: int) -> Event:
            m = pb.Clock()
            set_timestamp_ns(m.time, t)
            return make_event(m, source="sim.clock", epoch=1, seq=seq)

        with tempfile.TemporaryDirectory() as directory:
            store = self.create_store(EventClock(), Path(directory))
            store.append([clock_event(0, 1_000), joint_event("a.src", 0, 990),
                          clock_event(1, 2_000), joint_event("a.src", 1, 1_500)])
            assert [r.recorded_time_ns for r in store.read()] == [1_000, 1_000, 2_000, 2_000]
            store.close()

    # -- tamper evidence: the review's first two cases ------------------------------------

    def test_verify_detects_a_modified_payload(self, tmp_path):
        store, clock = self._new(tmp_path)
        store.append([joint_event("a.src", i, i, travel_m=i) for i in range(6)])
        assert store.verify().ok
        store = self.tamper(store, 3, "payload")
        report = store.verify()
        assert not report.ok and report.first_bad_seq == 3, report
        store.close()

    def test_verify_detects_a_modified_recorded_time(self, tmp_path):
        store, clock = self._new(tmp_path)
        store.append([joint_event("a.src", i, i) for i in range(6)])
        store = self.tamper(store, 4, "recorded_time_ns")
        report = store.verify()
        assert not report.ok and report.first_bad_seq == 4, report
        store.close()

    # -- tamper evidence: every hashed field, whole rows, the first and the last row -----

    def _tamper_ledger(self, directory: Path) -> tuple[LedgerStore, ManualClock]:
        """Six rows from two sources and epochs over three batches (recorded times 1000,
        1100, 1200), so every field differs between neighbours."""
        directory.mkdir(parents=True, exist_ok=True)
        store, clock = self._new(directory, 1_000)
        for b in range(3):
            store.append([joint_event("a.src", b, 10 * b + 1, travel_m=b, epoch=1),
                          joint_event("b.src", b, 10 * b + 2, travel_m=-b, epoch=2)])
            clock.advance_ns(100)
        return store, clock

    def _tamper_failures(self, tmp_path: Path, cases) -> list[str]:
        store, _ = self._tamper_ledger(tmp_path / "intact")
        assert store.verify() == VerifyReport(True, 6)
        store.close()
        failures = []
        for n, (field, at) in enumerate(cases):
            store, _ = self._tamper_ledger(tmp_path / f"case{n}")
            store = self.tamper(store, at, field)
            report = store.verify()
            if report != tamper_expectation(field, at):
                failures.append(f"{field} at {at}: {report}")
            store.close()
        return failures

    def test_verify_detects_every_tampered_field_of_the_first_a_middle_and_the_last_row(
            self, tmp_path):
        cases = [(field, at) for field in TAMPER_FIELDS for at in (0, 5)]
        cases += [("payload_and_hash", 3), ("source", 3)]
        assert self._tamper_failures(tmp_path, cases) == []

    def test_verify_detects_deleted_inserted_and_reordered_rows(self, tmp_path):
        cases = [("delete", 0), ("delete", 2), ("insert", 0), ("insert", 3), ("insert", 5),
                 ("reorder", 0), ("reorder", 2), ("reorder", 4),
                 ("rechain_backwards", 1), ("rechain_backwards", 5)]
        assert self._tamper_failures(tmp_path, cases) == []

    def _side_ledger(self, directory: Path) -> LedgerStore:
        """Rows with quarantine entries before, between and after them, a gap closed
        (with a remainder still open) and another open."""
        directory.mkdir(parents=True, exist_ok=True)
        store, clock = self._new(directory, 1_000)
        store.append([Malformed(b"{bad", "malformed: not JSON"), joint_event("a.src", 0, 1),
                      joint_event("a.src", 4, 2)])
        clock.advance_ns(100)
        store.append([joint_event("a.src", 2, 3), joint_event("a.src", 0, 1, travel_m=9.0),
                      joint_event("b.src", 3, 4)])
        clock.advance_ns(100)
        store.append([joint_event("b.src", 4, 5), Malformed(b"\xff", "malformed: not UTF-8")])
        return store

    def test_verify_detects_edited_deleted_and_added_quarantine_and_gap_rows(self, tmp_path):
        store = self._side_ledger(tmp_path / "intact")
        assert store.verify() == VerifyReport(True, 5)
        assert [q.after_global_seq for q in store.quarantine()] == [-1, 2, 4]
        assert len(store.gaps()) == 4 and sum(g.is_open for g in store.gaps()) == 3
        store.close()
        failures = []
        for n, case in enumerate(SIDE_TAMPER_CASES):
            store = self._side_ledger(tmp_path / f"case{n}")
            store = self.replace_side_tables(store, *tampered_side(store.quarantine(),
                                                                   store.gaps(), case))
            report = store.verify()
            named = ("quarantine entry" if case[0] == "quarantine" else "gap row") in (
                report.problem or "")
            # a deleted entry shows at the first row chained after it
            chained_after = case[0] == "quarantine" and report.problem == CHAIN_MISMATCH
            if report.ok or not (named or chained_after):
                failures.append(f"{case}: {report}")
            store.close()
        assert failures == []

    def test_randomised_batches_keep_every_invariant(self, tmp_path):
        seed = random.randrange(2**32)
        print(f"seed={seed}")
        rng = random.Random(seed)
        store, clock = self._new(tmp_path)
        sent: dict[tuple[str, int, int], bytes] = {}
        for _ in range(20):
            clock.advance_ns(rng.randrange(0, 1_000))
            batch = []
            for _ in range(rng.randrange(0, 20)):
                source = rng.choice(["a.src", "b.src"])
                seq = rng.randrange(0, 60)
                e = joint_event(source, seq, rng.randrange(0, 10_000), travel_m=rng.choice([0.0, 1.0]))
                batch.append(e)
            result = store.append(batch)
            for e, outcome in zip(batch, result.outcomes):
                first = sent.setdefault(e.key, e.payload)
                expected = ("appended", "duplicate") if first == e.payload else ("conflict",)
                assert outcome.status in expected, (seed, e.key, outcome)
        rows = list(store.read())
        assert [r.global_seq for r in rows] == list(range(len(sent)))
        assert {r.key: r.payload for r in rows} == sent
        for info in store.streams():
            stored = {r.seq for r in rows if (r.source, r.epoch) == (info.source, info.epoch)}
            missing = set(range(info.max_seq + 1)) - stored
            assert info.missing == len(missing), seed
            open_gap_seqs = {s for g in store.gaps(open_only=True)
                             if (g.source, g.epoch) == (info.source, info.epoch)
                             for s in range(g.first_seq, g.last_seq + 1)}
            assert open_gap_seqs == missing, seed
        assert store.verify().ok
        store.close()
