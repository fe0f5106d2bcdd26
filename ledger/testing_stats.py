"""The stats part of the backend contract (:class:`StatsContract`, a base of
:class:`ledger.testing.LedgerStoreContract`): ``stats()`` agrees with the rows ``read()``
returns, between batches and after a reopen."""

from __future__ import annotations

from collections import Counter

from schemas import pb
from schemas.events import Event, make_event, set_timestamp_ns

from ledger.records import FLAG_UNKNOWN_LOT


def _joint(source: str, seq: int, valid_time_ns: int) -> Event:
    message = pb.JointReading(machine_id="bwr1")
    set_timestamp_ns(message.time, valid_time_ns)
    return make_event(message, source=source, epoch=1, seq=seq)


def _unknown_lot_assay() -> Event:
    """An assay of an undeclared lot: appended and flagged ``unknown_lot``."""
    message = pb.Assay(assay_id="A1", lot_id="L9", analytes={"Fe": 61.0}, status=2)
    for name, t_ns in (("window_start", 5), ("window_end", 6), ("reported_time", 7)):
        set_timestamp_ns(getattr(message, name), t_ns)
    return make_event(message, source="lab.assays", epoch=1, seq=0)


def _span(values: list[int]) -> tuple[int, int] | None:
    return (min(values), max(values)) if values else None


class StatsContract:
    """``stats()`` as every backend must keep it (uses the contract's ``_new``, ``reopen``
    and ``persistent``)."""

    def _check_stats(self, store) -> None:
        rows, got = list(store.read()), store.stats()
        assert (got.events, got.per_type, got.per_source, got.flagged,
                got.valid_time_range_ns, got.recorded_time_range_ns) == (
            len(rows), dict(Counter(r.type for r in rows)),
            dict(Counter(r.source for r in rows)),
            dict(Counter(f for r in rows for f in r.flags)),
            _span([r.valid_time_ns for r in rows]), _span([r.recorded_time_ns for r in rows]))

    def test_stats_follow_every_batch(self, tmp_path):
        store, clock = self._new(tmp_path)
        self._check_stats(store)
        batches = [[_joint("a.src", 0, 300), _joint("b.src", 0, 20)],
                   [_unknown_lot_assay(), _joint("a.src", 0, 300)],   # a flag, a duplicate
                   [_joint("a.src", 3, 900), _joint("b.src", 1, 1)]]  # a gap, a new minimum
        for at_ns, batch in zip((100, 200, 300), batches):
            clock.set_ns(at_ns)
            store.append(batch)
            self._check_stats(store)
        assert store.stats().flagged == {FLAG_UNKNOWN_LOT: 1}
        if self.persistent:
            store = self.reopen(store, clock)
            self._check_stats(store)
        store.close()
