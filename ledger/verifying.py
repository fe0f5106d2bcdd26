"""Checks ``LedgerStore.verify`` makes beyond the chain: what the views read outside the
chained fields, recomputed from the stored rows."""

from __future__ import annotations

import bisect

from schemas.events import decode_payload

from ledger.records import FLAG_UNKNOWN_LOT, Gap, RecordedEvent


class OpenGapCheck:
    """The open gaps against the stored rows: per (source, epoch), the sequence numbers
    missing below its highest stored one are exactly the open gaps' (a gap row deleted,
    added or edited shows), and no stored row lies inside an open gap."""

    def __init__(self, open_gaps: list[Gap]) -> None:
        self.spans: dict[tuple[str, int], list[tuple[int, int]]] = {}
        for gap in open_gaps:
            self.spans.setdefault((gap.source, gap.epoch), []).append(
                (gap.first_seq, gap.last_seq))
        for spans in self.spans.values():
            spans.sort()
        self.starts = {key: [first for first, _last in spans] for key, spans in self.spans.items()}
        self.seen: dict[tuple[str, int], list[int]] = {}  # key -> [rows, highest seq]

    def row(self, row: RecordedEvent) -> str | None:
        key = (row.source, row.epoch)
        seen = self.seen.get(key)
        if seen is None:
            seen = self.seen[key] = [0, -1]
        seen[0] += 1
        if row.seq > seen[1]:
            seen[1] = row.seq
        spans = self.spans.get(key)
        if spans:
            i = bisect.bisect_right(self.starts[key], row.seq) - 1
            if i >= 0 and spans[i][1] >= row.seq:
                return (f"seq {row.seq} of {row.source} epoch {row.epoch} is stored but lies "
                        f"in the open gap {spans[i][0]}..{spans[i][1]}")
        return None

    def problem(self) -> str | None:
        for key in sorted(set(self.seen) | set(self.spans)):
            rows, highest = self.seen.get(key, (0, -1))
            missing = highest + 1 - rows
            in_gaps = sum(last - first + 1 for first, last in self.spans.get(key, ()))
            if missing != in_gaps:
                return (f"{key[0]} epoch {key[1]}: {missing} sequence numbers are missing below "
                        f"its highest stored one, the open gaps hold {in_gaps} (a gap row was "
                        "deleted, added or edited)")
        return None


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
