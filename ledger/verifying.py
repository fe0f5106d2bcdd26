"""Checks ``LedgerStore.verify`` makes beyond the rows' chain: the quarantine entries'
links of the chain, and what the views read outside the chained fields (flags, the gap
table), recomputed from the stored rows."""

from __future__ import annotations

import bisect
import dataclasses

from schemas.events import decode_payload

from ledger.chain import quarantine_hash
from ledger.signing import KEY_TYPES, KeyRegistry, SigningPolicy
from ledger.records import FLAG_UNKNOWN_LOT, Gap, QuarantineEntry, RecordedEvent


#: verify's finding when a row's chain value is not the one recomputed
CHAIN_MISMATCH = "chain hash mismatch (row fields, an earlier row or a quarantine entry changed)"


def quarantine_link(previous: bytes, entry: QuarantineEntry) -> bytes:
    """The chain link of a quarantine entry (:func:`ledger.chain.quarantine_hash`)."""
    return quarantine_hash(previous, entry.quarantine_id, entry.after_global_seq,
                           entry.recorded_time_ns, entry.epoch, entry.seq, entry.valid_time_ns,
                           entry.existing_global_seq, entry.type, entry.source, entry.code,
                           entry.detail, entry.raw)


class QuarantineLinks:
    """The quarantine entries (in id order) as links of the chain between the rows."""

    def __init__(self, entries: list[QuarantineEntry]) -> None:
        self.entries = entries
        self.next = 0

    def before(self, global_seq: int, previous: bytes) -> tuple[bytes, str | None]:
        """Check the entries stored before row ``global_seq`` from the link ``previous``;
        the last link and the problem found, if any."""
        while self.next < len(self.entries):
            entry = self.entries[self.next]
            if entry.after_global_seq >= global_seq:
                break
            where = f"quarantine entry {entry.quarantine_id}"
            if entry.quarantine_id != self.next:
                return previous, (f"{where} where {self.next} was expected "
                                  "(a quarantine entry was deleted or added)")
            lowest = self.entries[self.next - 1].after_global_seq if self.next else -1
            if entry.after_global_seq < lowest:
                return previous, f"{where} is placed before the entry ahead of it"
            link = quarantine_link(previous, entry)
            if link != entry.chain_sha256:
                return previous, (f"{where}: chain hash mismatch (the entry was edited, or one "
                                  "before it deleted)")
            previous = link
            self.next += 1
        return previous, None

    def problem_after(self, rows: int) -> str | None:
        """Entries placed after a row that is not stored (``rows``: rows checked)."""
        if self.next == len(self.entries):
            return None
        entry = self.entries[self.next]
        return (f"quarantine entry {entry.quarantine_id} is placed after global_seq "
                f"{entry.after_global_seq}, the ledger holds {rows} rows")


class GapHistory:
    """The gap table recomputed from the rows in global order, as the writer keeps it:
    a gap opens when a source skips sequence numbers and closes when one of them arrives,
    what is still missing opening again as new gaps (ids in order of opening)."""

    def __init__(self) -> None:
        self.streams: dict[tuple[str, int], tuple[list[int], list[Gap]]] = {}
        self.gaps: list[Gap] = []

    def _open(self, source: str, epoch: int, first: int, last: int, opened_ns: int) -> Gap:
        gap = Gap(len(self.gaps), source, epoch, first, last, opened_ns)
        self.gaps.append(gap)
        return gap

    def row(self, row: RecordedEvent) -> str | None:
        """Follow one row; the problem when it cannot be a new sequence number."""
        key = (row.source, row.epoch)
        highest, open_gaps = self.streams.setdefault(key, ([-1], []))
        seq = row.seq
        if seq > highest[0]:
            if seq > highest[0] + 1:
                open_gaps.append(self._open(row.source, row.epoch, highest[0] + 1, seq - 1,
                                            row.recorded_time_ns))
            highest[0] = seq
            return None
        starts = [g.first_seq for g in open_gaps]
        i = bisect.bisect_right(starts, seq) - 1
        if i < 0 or open_gaps[i].last_seq < seq:
            return f"seq {seq} of {row.source} epoch {row.epoch} is stored twice"
        gap = open_gaps.pop(i)
        self.gaps[gap.gap_id] = dataclasses.replace(gap, closed_recorded_ns=row.recorded_time_ns)
        remainders = [self._open(row.source, row.epoch, first, last, gap.opened_recorded_ns)
                      for first, last in ((gap.first_seq, seq - 1), (seq + 1, gap.last_seq))
                      if first <= last]
        open_gaps[i:i] = remainders
        return None

    def problem(self, stored: list[Gap]) -> str | None:
        """The stored gap table against the recomputed one (None when they agree)."""
        for expected, found in zip(self.gaps, stored):
            if expected != found:
                return (f"gap row {found.gap_id} is {_gap_text(found)} where the rows give "
                        f"{_gap_text(expected)} (a gap row was edited, deleted or added)")
        if len(stored) > len(self.gaps):
            return (f"{len(stored)} gap rows where the rows give {len(self.gaps)}: "
                    f"{_gap_text(stored[len(self.gaps)])} is not implied by the rows (a gap row "
                    "was added, or rows deleted)")
        if len(stored) < len(self.gaps):
            return (f"{len(stored)} gap rows where the rows give {len(self.gaps)}: "
                    f"{_gap_text(self.gaps[len(stored)])} has no gap row (a gap row was deleted)")
        return None


def _gap_text(gap: Gap) -> str:
    state = "open" if gap.closed_recorded_ns is None else f"closed at {gap.closed_recorded_ns}"
    return (f"gap {gap.gap_id} of {gap.source} epoch {gap.epoch} seq {gap.first_seq}.."
            f"{gap.last_seq} opened at {gap.opened_recorded_ns}, {state}")


def flags_problem(row: RecordedEvent, lots: set[str]) -> str | None:
    """Recompute a row's flags from the payloads before it (``lots``: the lots declared so
    far, updated here); the problem when the stored flags differ, else None."""
    expected: tuple[str, ...] = ()
    if row.type in ("assay", "lot_declared"):
        try:
            lot_id = decode_payload(row.type, row.payload).lot_id
        except Exception:  # noqa: BLE001 - a stored payload always decoded; say so if not
            return "payload does not decode"
        if row.type == "lot_declared":
            lots.add(lot_id)
        elif lot_id not in lots:
            expected = (FLAG_UNKNOWN_LOT,)
    if tuple(row.flags) != expected:
        return (f"flags {list(row.flags)} where the payloads before it give {list(expected)}")
    return None


class SignatureCheck:
    """Every stored signature re-checked in global order against the key registry the
    rows before it declare (as the writer checked it when it stored the row)."""

    def __init__(self, policy: SigningPolicy | None) -> None:
        # a policy's required types are not re-imposed: rows stored before a site
        # started signing are unsigned by right; the chain covers a removed signature
        self.policy = None if policy is None else SigningPolicy(frozenset(), policy.admin_key_id)
        self.keys = KeyRegistry()
        self.held = 0  # signed rows whose signature held

    def row(self, row: RecordedEvent) -> str | None:
        if row.signer is None and row.type not in KEY_TYPES:
            return None
        try:
            message = decode_payload(row.type, row.payload)
        except Exception:  # noqa: BLE001 - a stored payload always decoded; say so if not
            return "payload does not decode"
        refused = self.keys.problem(row.type, row.source, row.epoch, row.seq, row.valid_time_ns,
                                    row.payload_sha256, message, row.signer, row.signature,
                                    self.policy)
        if refused:
            return f"signature: {refused[0]}: {refused[1]}"
        if row.type in KEY_TYPES:
            self.keys.learn(row.type, message)
        self.held += row.signer is not None
        return None
