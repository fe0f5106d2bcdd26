"""The resend part of the backend contract (:class:`ResendContract`, a base of
:class:`ledger.testing.LedgerStoreContract`): a stored event sent again is a
``duplicate`` only when it is the same event (type, valid time and payload); anything
else sent under a stored key is judged as a new event would be, wherever the stored
row lies in valid time."""

from __future__ import annotations

import dataclasses

from schemas import pb
from schemas.events import Event, make_event, set_timestamp_ns


def _joint(seq: int, valid_time_ns: int, travel_m: float = 0.0) -> Event:
    message = pb.JointReading(machine_id="bwr1", travel_m=travel_m)
    set_timestamp_ns(message.time, valid_time_ns)
    return make_event(message, source="r.src", epoch=1, seq=seq)


class ResendContract:
    """A batch sent again as every backend must judge it (uses the contract's ``_new``
    and ``reopen``)."""

    def _stored_batch(self, tmp_path):
        store, clock = self._new(tmp_path)
        batch = [_joint(i, 1_000 + i, travel_m=i) for i in range(4)]
        store.append(batch)
        clock.advance_ns(1_000)
        return self.reopen(store, clock), batch

    def test_a_resent_event_is_a_duplicate_of_its_row(self, tmp_path):
        store, batch = self._stored_batch(tmp_path)
        again = [dataclasses.replace(batch[2], payload=bytearray(batch[2].payload)), batch[1],
                 dataclasses.replace(batch[3], recorded_time_ns=5)]
        result = store.append(again)
        assert [(o.status, o.global_seq) for o in result.outcomes] == [
            ("duplicate", 2), ("duplicate", 1), ("duplicate", 3)]
        assert store.quarantine() == [] and store.head().global_seq == 3
        store.close()

    def test_the_same_payload_under_another_type_or_time_is_judged_afresh(self, tmp_path):
        store, batch = self._stored_batch(tmp_path)
        result = store.append([
            dataclasses.replace(batch[0], type="location_fix"),
            dataclasses.replace(batch[1], valid_time_ns=batch[1].valid_time_ns + 1),
            dataclasses.replace(batch[2], recorded_time_ns=2**64),
        ])
        assert [(o.status, o.code) for o in result.outcomes] == [
            ("rejected", "undecodable"), ("rejected", "valid_time_mismatch"),
            ("rejected", "bad_identity")]
        assert store.head().global_seq == 3
        store.close()

    def test_a_conflict_far_from_the_stored_valid_time_is_found(self, tmp_path):
        store, batch = self._stored_batch(tmp_path)
        far = _joint(1, 10**15, travel_m=9.0)     # another reading under seq 1, much later
        result = store.append([batch[0], far])
        assert [(o.status, o.global_seq) for o in result.outcomes] == [
            ("duplicate", 0), ("conflict", 1)]
        [entry] = store.quarantine()
        assert entry.code == "conflict" and entry.existing_global_seq == 1
        store.close()
