"""The ledger's keys and recorded times under repeated input: an event with the key of a
stored one is a no-op duplicate when its bytes are the same and a quarantined conflict when
they differ (in the same batch, a later one, or after reopening), a rejected event claims
no key, and a preserved recorded time may not go back before the head (in memory and on a
DuckDB file).
"""

from __future__ import annotations

import dataclasses

import pytest

from bad_input_helpers import (
    NOW,
    V0,
    assay,
    assert_quarantined_as,
    assert_rows,
    bad,
    clock_tick,
    good_pair,
    reclaim_cut,
    run_reject_case,
    stack_ended,
)
from ledger import AppendOutcome
from ledger.records import FLAG_UNKNOWN_LOT
from schemas import pb
from schemas.jsonl import decode_line, encode_line


# --- duplicates and conflicts -------------------------------------------------------------


@pytest.mark.parametrize("reopen_between", [False, True], ids=["same-session", "reopened"])
def test_conflicting_duplicate_in_a_later_batch(backend, reopen_between):
    store = backend.store
    original = bad(stack_ended(V0, tonnes=1200.0))
    assert store.append([original]).outcomes == (AppendOutcome("appended", 0),)
    if reopen_between:
        store = backend.reopen()
    before, after = good_pair()
    conflicting = bad(stack_ended(V0, tonnes=1250.0))  # same (source, epoch, seq)
    assert conflicting.key == original.key and conflicting.payload != original.payload

    result = store.append([before, conflicting, after])

    assert [o.status for o in result.outcomes] == ["appended", "conflict", "appended"]
    assert result.outcomes[0] == AppendOutcome("appended", 1)
    assert result.outcomes[2] == AppendOutcome("appended", 2)
    outcome = result.outcomes[1]
    assert (outcome.code, outcome.global_seq) == ("conflict", 0)
    quarantine = store.quarantine()
    assert len(quarantine) == 1
    assert_quarantined_as(quarantine[0], conflicting, "conflict", "global_seq 0", existing=0)
    # the stored event is unchanged
    assert_rows(store, [(original, ()), (before, ()), (after, ())])
    assert pb.StackEnded.FromString(next(store.read(0, 1)).payload).tonnes == 1200.0

    if backend.persistent:
        reopened = backend.reopen(read_only=True)
        assert reopened.quarantine() == quarantine
        assert_rows(reopened, [(original, ()), (before, ()), (after, ())])


def test_conflicting_duplicate_in_the_same_batch(backend):
    store = backend.store
    first = bad(assay(V0, analytes={"Fe": 61.0}))
    conflicting = bad(assay(V0, analytes={"Fe": 61.5}))
    after = good_pair()[1]

    result = store.append([first, conflicting, after])

    assert [o.status for o in result.outcomes] == ["appended", "conflict", "appended"]
    assert result.outcomes[0] == AppendOutcome("appended", 0, flags=(FLAG_UNKNOWN_LOT,))
    assert result.outcomes[2] == AppendOutcome("appended", 1)
    assert (result.outcomes[1].code, result.outcomes[1].global_seq) == ("conflict", 0)
    quarantine = store.quarantine()
    assert len(quarantine) == 1
    assert_quarantined_as(quarantine[0], conflicting, "conflict", "global_seq 0", existing=0)
    assert_rows(store, [(first, (FLAG_UNKNOWN_LOT,)), (after, ())])
    assert pb.Assay.FromString(next(store.read(0, 1)).payload).analytes["Fe"] == 61.0


def test_identical_duplicate_is_a_no_op(backend):
    store = backend.store
    original = bad(reclaim_cut(V0))
    before, after = good_pair()
    assert store.append([original]).outcomes == (AppendOutcome("appended", 0),)

    # a later batch, and twice within one batch
    result = store.append([before, bad(reclaim_cut(V0)), original, after])

    assert list(result.outcomes) == [
        AppendOutcome("appended", 1),
        AppendOutcome("duplicate", 0),
        AppendOutcome("duplicate", 0),
        AppendOutcome("appended", 2),
    ]
    again = store.append([after, before])
    assert list(again.outcomes) == [AppendOutcome("duplicate", 2), AppendOutcome("duplicate", 1)]
    assert again.head_seq == 2
    assert store.quarantine() == []
    assert_rows(store, [(original, ()), (before, ()), (after, ())])


def test_reimported_json_line_is_a_duplicate_not_a_conflict(backend):
    store = backend.store
    original = bad(assay(V0, analytes={"Fe": 62.35, "SiO2": 4.05}))
    line = encode_line(original.type, original.source, original.epoch, original.seq,
                       original.valid_time_ns, original.payload)
    first = decode_line(line)
    assert store.append([first]).outcomes[0].status == "appended"
    assert store.append([decode_line(line)]).outcomes == (AppendOutcome("duplicate", 0),)
    assert store.quarantine() == []


def test_a_rejected_event_does_not_claim_its_key(backend):
    """A bad event is quarantined; a corrected one with the same key is then stored."""
    store = backend.store
    rejected = bad(stack_ended(V0, tonnes=-5.0))
    corrected = bad(stack_ended(V0, tonnes=5.0))
    result = store.append([rejected, corrected])
    assert [o.status for o in result.outcomes] == ["rejected", "appended"]
    assert result.outcomes[0].code == "negative_tonnes"
    assert result.outcomes[1] == AppendOutcome("appended", 0)
    assert [q.code for q in store.quarantine()] == ["negative_tonnes"]
    assert_rows(store, [(corrected, ())])


# --- preserved recorded time --------------------------------------------------------------


def test_preserved_recorded_time_before_the_head_is_rejected(backend):
    item = dataclasses.replace(bad(clock_tick(V0)), recorded_time_ns=NOW - 1)
    run_reject_case(backend, item, "recorded_time_backwards", "recorded_time_ns")


def test_preserved_recorded_time_at_or_after_the_head_is_kept(backend):
    store = backend.store
    before, after = good_pair()
    same = dataclasses.replace(bad(clock_tick(V0), seq=0), recorded_time_ns=NOW)
    later = dataclasses.replace(bad(clock_tick(V0 + 1), seq=1), recorded_time_ns=NOW + 5)
    result = store.append([before, same, later, after])
    assert [o.status for o in result.outcomes] == ["appended"] * 4
    rows = list(store.read())
    assert [r.recorded_time_ns for r in rows] == [NOW, NOW, NOW + 5, NOW + 5]
    assert store.verify().ok
