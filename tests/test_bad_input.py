"""Bad input at the ledger boundary: every kind is quarantined with its reason and the rest
of its batch kept.  Each case appends ONE batch of ``[good, bad, good]`` to a fresh ledger
(in memory and DuckDB on a real file) and checks (a) the outcome status of each event, in
order, (b) the bad event's outcome ``code``, (c) exactly one quarantine entry with that
code, a detail naming the field, and the bad payload bytes (or the raw line for
:class:`~schemas.events.Malformed`) as ``raw``, (d) the two good events read back with dense
global seqs 0 and 1 and their payloads, and, for DuckDB, that all of it is still there after
closing and reopening the file (``run_reject_case`` in bad_input_helpers.py); then whole
batches of bad input, alone and mixed with good.  What must be accepted is in
test_bad_input_accepted.py, duplicates, conflicts and recorded times in
test_bad_input_duplicates.py.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random

import pytest
from google.protobuf.message import DecodeError

from bad_input_helpers import (
    BAD_SOURCE,
    GOOD_SOURCE,
    NOW,
    V0,
    assay,
    assert_quarantined_as,
    assert_rows,
    bad,
    clock_tick,
    frame_transform,
    joint_reading,
    location_fix,
    lot,
    machine,
    raw_of,
    reclaim_cut,
    run_reject_case,
    scan,
    scan_ranges,
    stack_ended,
    stack_started,
)
from ledger import AppendOutcome, VerifyReport
from ledger.records import FLAG_UNKNOWN_LOT
from schemas import pb
from schemas.events import (
    EVENT_TYPES,
    Event,
    encode_attachment,
    event_from_sample,
    make_event,
)
from schemas.jsonl import decode_line
from schemas.times import NS_PER_S

INT64_MAX = 2**63 - 1

#: seed of the random payload bytes (printed by the test that uses it)
RANDOM_SEED = 20_251_122


def with_nan(m, field: str, value: float):
    setattr(m, field, value)
    return m


def random_undecodable(type_name: str) -> bytes:
    """Seeded random bytes that do not parse as ``type_name`` (checked, not assumed)."""
    rng = random.Random(RANDOM_SEED)
    print(f"random payload seed: {RANDOM_SEED}")
    data = rng.randbytes(48)
    with pytest.raises(DecodeError):
        EVENT_TYPES[type_name].FromString(data)
    return data


# --- one test per bad-input case ----------------------------------------------------------


def _bytes_of_other_type() -> Event:
    # A StackEnded (time=1, pile_id=2, pass_id=3, tonnes=4) parses as a Clock (time=1)
    # with three unknown fields, and even carries the right valid time.
    payload = stack_ended(V0).SerializeToString()
    clock = pb.Clock.FromString(payload)  # precondition: it does parse
    assert clock.time.seconds == V0 // 1_000_000_000
    return Event("clock", BAD_SOURCE, 7, 0, V0, payload)


def _truncated() -> Event:
    payload = assay(V0).SerializeToString()[:-3]
    with pytest.raises(DecodeError):
        pb.Assay.FromString(payload)
    return Event("assay", BAD_SOURCE, 7, 0, V0, payload)


def _valid_time_mismatch() -> Event:
    return dataclasses.replace(bad(stack_ended(V0)), valid_time_ns=V0 + 1)


def _line(record: dict) -> str:
    return json.dumps(record, separators=(",", ":"))


UNKNOWN_TYPE_LINE = _line({"type": "bogus", "source": BAD_SOURCE, "epoch": 7, "seq": 0,
                           "valid_time_ns": V0, "body": {"time": "2023-11-14T22:13:20Z"}})

REJECTED = [
    # undecodable payloads
    pytest.param(lambda: Event("assay", BAD_SOURCE, 7, 0, V0, random_undecodable("assay")),
                 "undecodable", "stockpile.v1.Assay", id="undecodable-random-bytes"),
    pytest.param(_truncated, "undecodable", "stockpile.v1.Assay", id="undecodable-truncated"),
    pytest.param(_bytes_of_other_type, "undecodable", "unknown to stockpile.v1.Clock",
                 id="undecodable-other-message-type"),
    pytest.param(lambda: decode_line(_line({"type": "clock", "source": BAD_SOURCE, "epoch": 7,
                                            "seq": 0, "valid_time_ns": V0,
                                            "body": {"no_such_field": 1}})),
                 "undecodable", "no_such_field", id="undecodable-json-body"),
    # unknown types
    pytest.param(lambda: Event("bogus", BAD_SOURCE, 7, 0, V0, clock_tick(V0).SerializeToString()),
                 "unknown_type", "bogus", id="unknown-type-event"),
    pytest.param(lambda: decode_line(UNKNOWN_TYPE_LINE), "unknown_type", "bogus",
                 id="unknown-type-json-line"),
    # lines that are not event records
    pytest.param(lambda: decode_line('{"type": "clock", "source": '), "malformed", "not JSON",
                 id="malformed-not-json"),
    pytest.param(lambda: decode_line(b'\xff\xfe{"type":"clock"}'), "malformed", "not JSON",
                 id="malformed-not-utf8"),
    pytest.param(lambda: decode_line("[1, 2, 3]"), "malformed", "JSON object",
                 id="malformed-not-an-object"),
    pytest.param(lambda: decode_line(_line({"type": "clock", "source": BAD_SOURCE, "epoch": 7,
                                            "valid_time_ns": V0, "body": {}})),
                 "malformed", "seq", id="malformed-missing-seq"),
    pytest.param(lambda: decode_line(_line({"type": "clock", "source": BAD_SOURCE, "epoch": 7,
                                            "seq": "3", "valid_time_ns": V0, "body": {}})),
                 "malformed", "seq", id="malformed-string-seq"),
    # Zenoh samples with a bad key or attachment
    pytest.param(lambda: event_from_sample("stockpile/site1/@v1/clock", b"\x0a\x00", None),
                 "bad_key", "not a stockpile event key", id="bad-key"),
    pytest.param(lambda: event_from_sample("stockpile/site1/@v1/clock/" + BAD_SOURCE,
                                           clock_tick(V0).SerializeToString(), None),
                 "bad_attachment", "missing", id="bad-attachment-missing"),
    pytest.param(lambda: event_from_sample("stockpile/site1/@v1/clock/" + BAD_SOURCE,
                                           clock_tick(V0).SerializeToString(),
                                           encode_attachment(7, 0, V0)[:-1]),
                 "bad_attachment", "24 bytes", id="bad-attachment-short"),
    # valid time
    pytest.param(_valid_time_mismatch, "valid_time_mismatch", "valid_time_ns",
                 id="valid-time-mismatch"),
    pytest.param(lambda: dataclasses.replace(bad(assay(V0)), valid_time_ns=V0 - 3_600_000_000_000),
                 "valid_time_mismatch", "valid_time_ns", id="valid-time-is-window-start"),
    # NaN / infinity where a number is required
    pytest.param(lambda: bad(joint_reading(V0, travel=math.nan)), "non_finite", "travel_m",
                 id="nan-travel"),
    pytest.param(lambda: bad(joint_reading(V0, slew=math.inf)), "non_finite", "slew_rad",
                 id="inf-slew"),
    pytest.param(lambda: bad(joint_reading(V0, luff=-math.inf)), "non_finite", "luff_rad",
                 id="minus-inf-luff"),
    pytest.param(lambda: bad(stack_ended(V0, tonnes=math.nan)), "non_finite", "tonnes",
                 id="nan-tonnes"),
    pytest.param(lambda: bad(assay(V0, analytes={"Fe": math.nan})), "non_finite", "analytes",
                 id="nan-analyte"),
    pytest.param(lambda: bad(lot(V0, grade={"Fe": math.inf})), "non_finite", "planned_grade",
                 id="inf-planned-grade"),
    pytest.param(lambda: bad(frame_transform(V0, w=math.nan)), "non_finite", "rotation",
                 id="nan-in-nested-quaternion"),
    pytest.param(lambda: bad(scan(V0, [5.0, math.inf] + scan_ranges(179))), "non_finite",
                 "ranges", id="inf-scan-range"),
    pytest.param(lambda: bad(scan(V0, scan_ranges(), intensities=[math.inf] * 181)),
                 "non_finite", "intensities", id="inf-scan-intensity"),
    pytest.param(lambda: bad(with_nan(scan(V0, scan_ranges()), "start_angle", math.nan)),
                 "non_finite", "start_angle", id="nan-scan-angle"),
    # scan geometry: any step the count and the angles make, over at most one turn
    pytest.param(lambda: bad(scan(V0, scan_ranges(400), start=-math.pi,
                                  end=math.pi + math.radians(0.5))),
                 "ranges_angles_mismatch", "400 ranges over 360.500 deg", id="field-over-360-deg"),
    pytest.param(lambda: bad(scan(V0, scan_ranges(3), start=0.0, end=5e-324)),
                 "ranges_angles_mismatch", "give a step of 0.0", id="step-underflows-to-0"),
    pytest.param(lambda: bad(scan(V0, [5.0])), "ranges_angles_mismatch", "at least 2",
                 id="single-range"),
    pytest.param(lambda: bad(scan(V0, scan_ranges(), start=math.pi / 2, end=-math.pi / 2)),
                 "ranges_angles_mismatch", "end_angle", id="angles-reversed"),
    pytest.param(lambda: bad(scan(V0, scan_ranges(), intensities=[1.0] * 180)),
                 "ranges_angles_mismatch", "180 intensities", id="intensities-count"),
    pytest.param(lambda: bad(scan(V0, [5.0, -0.5] + scan_ranges(179))), "out_of_range",
                 "negative value in ranges", id="negative-scan-range"),
    # negative tonnes
    pytest.param(lambda: bad(stack_ended(V0, tonnes=-1.0)), "negative_tonnes", "tonnes",
                 id="negative-stack-ended-tonnes"),
    pytest.param(lambda: bad(reclaim_cut(V0, tonnes=-0.5)), "negative_tonnes", "tonnes",
                 id="negative-reclaim-cut-tonnes"),
    pytest.param(lambda: bad(lot(V0, tonnes=-10.0)), "negative_tonnes", "planned_tonnes",
                 id="negative-planned-tonnes"),
    # analytes
    pytest.param(lambda: bad(assay(V0, analytes={"Fe": 100.5})), "analyte_out_of_range",
                 "'Fe'", id="assay-analyte-over-100"),
    pytest.param(lambda: bad(assay(V0, analytes={"Fe": 62.0, "SiO2": -0.1})),
                 "analyte_out_of_range", "'SiO2'", id="assay-analyte-negative"),
    pytest.param(lambda: bad(assay(V0, analytes={"Fe": 65.0, "SiO2": 36.0})), "analyte_sum",
                 "101.000", id="assay-analytes-sum-101"),
    pytest.param(lambda: bad(assay(V0, analytes={"Fe": 64.15, "SiO2": 36.0})), "analyte_sum",
                 "analytes", id="assay-analytes-sum-just-over-tolerance"),
    pytest.param(lambda: bad(lot(V0, grade={"Fe": 101.0})), "analyte_out_of_range",
                 "planned_grade", id="lot-grade-over-100"),
    pytest.param(lambda: bad(lot(V0, grade={"Fe": -1.0})), "analyte_out_of_range",
                 "planned_grade", id="lot-grade-negative"),
    pytest.param(lambda: bad(lot(V0, grade={"Fe": 70.0, "SiO2": 31.0})), "analyte_sum",
                 "planned_grade", id="lot-grade-sum-101"),
    pytest.param(lambda: bad(assay(V0, analytes={"": 5.0})), "analyte_out_of_range",
                 "unnamed", id="assay-unnamed-analyte"),
    pytest.param(lambda: bad(assay(V0, repeatability={"Fe": 0.0})), "out_of_range",
                 "repeatability_pp['Fe'] = 0.0", id="assay-repeatability-zero"),
    pytest.param(lambda: bad(assay(V0, repeatability={"Fe": math.nan})), "non_finite",
                 "repeatability_pp['Fe']", id="assay-repeatability-nan"),
    pytest.param(lambda: bad(assay(V0, repeatability={"P": 0.01})), "out_of_range",
                 "does not report", id="assay-repeatability-of-an-unreported-analyte"),
    # enums: not in the schema, or unspecified where required
    pytest.param(lambda: bad(machine(V0, kind=99)), "unknown_enum", "kind = 99",
                 id="machine-kind-99"),
    pytest.param(lambda: bad(stack_started(V0, pattern=99)), "unknown_enum", "pattern = 99",
                 id="stack-pattern-99"),
    pytest.param(lambda: bad(assay(V0, status=99)), "unknown_enum", "status = 99",
                 id="assay-status-99"),
    pytest.param(lambda: bad(machine(V0, kind=pb.MACHINE_KIND_UNSPECIFIED)), "unknown_enum",
                 "kind is unspecified", id="machine-kind-unspecified"),
    pytest.param(lambda: bad(stack_started(V0, pattern=pb.STACK_PATTERN_UNSPECIFIED)),
                 "unknown_enum", "pattern is unspecified", id="stack-pattern-unspecified"),
    pytest.param(lambda: bad(assay(V0, status=pb.ASSAY_STATUS_UNSPECIFIED)), "unknown_enum",
                 "status is unspecified", id="assay-status-unspecified"),
    pytest.param(lambda: Event("machine_declared", BAD_SOURCE, 7, 0, V0,
                               machine(V0).SerializeToString() + b"\x18\xe7\x07"),
                 "unknown_enum", "kind = 999", id="machine-kind-999-crafted-bytes"),
    # bad identity
    pytest.param(lambda: bad(clock_tick(V0), source=""), "bad_identity", "source",
                 id="empty-source"),
    pytest.param(lambda: bad(clock_tick(V0), source="bad source"), "bad_identity", "source",
                 id="source-with-space"),
    pytest.param(lambda: bad(clock_tick(V0), source=".hidden"), "bad_identity", "source",
                 id="source-starts-with-dot"),
    pytest.param(lambda: bad(clock_tick(V0), seq=-1), "bad_identity", "seq", id="negative-seq"),
    pytest.param(lambda: bad(clock_tick(V0), epoch=-1), "bad_identity", "epoch",
                 id="negative-epoch"),
    pytest.param(lambda: dataclasses.replace(bad(clock_tick(V0)), valid_time_ns=float(V0)),
                 "bad_identity", "valid_time_ns", id="float-valid-time"),
    # other range checks and required identifiers
    pytest.param(lambda: bad(assay(V0, lot_id="")), "missing_field", "lot_id",
                 id="assay-without-lot"),
    pytest.param(lambda: bad(frame_transform(V0, w=0.9)), "out_of_range", "quaternion",
                 id="non-unit-quaternion"),
    pytest.param(lambda: bad(location_fix(V0, lat=91.0)), "out_of_range", "latitude",
                 id="latitude-91"),
]


@pytest.mark.parametrize(("make_bad", "code", "detail_has"), REJECTED)
def test_bad_input_is_quarantined_and_rest_of_batch_kept(backend, make_bad, code, detail_has):
    run_reject_case(backend, make_bad(), code, detail_has)


# --- numbers that do not fit the ledger's signed 64-bit columns ----------------------------
#
# Rejected by validation; the quarantine keeps them in the raw bytes and stores NULL for
# identity numbers that do not fit a BIGINT, so the batch's good events are kept.

OVERSIZED = [
    pytest.param(lambda: bad(clock_tick(V0), seq=2**63), "bad_identity", "seq", id="seq-2^63"),
    pytest.param(lambda: bad(clock_tick(V0), epoch=2**64), "bad_identity", "epoch",
                 id="epoch-2^64"),
    pytest.param(lambda: dataclasses.replace(bad(clock_tick(V0)), valid_time_ns=2**64),
                 "bad_identity", "valid_time_ns", id="valid-time-2^64"),
    pytest.param(lambda: decode_line(_line({"type": "clock", "source": BAD_SOURCE, "epoch": 7,
                                            "seq": 2**70, "valid_time_ns": V0, "body": {}})),
                 "bad_identity", "seq", id="json-line-seq-2^70"),
]


@pytest.mark.parametrize(("make_bad", "code", "detail_has"), OVERSIZED)
def test_oversized_identity_is_quarantined(backend, make_bad, code, detail_has):
    run_reject_case(backend, make_bad(), code, detail_has)


#: first whole second after the largest int64 nanosecond (2262-04-11T23:47:17Z)
_AFTER_INT64_NS = (INT64_MAX // NS_PER_S + 1) * NS_PER_S
#: last whole second before the smallest int64 nanosecond (1677-09-21T00:12:43Z)
_BEFORE_INT64_NS = (-(2**63) // NS_PER_S - 1) * NS_PER_S


@pytest.mark.parametrize(
    "make_bad",
    [
        pytest.param(lambda: bad(clock_tick(_AFTER_INT64_NS)), id="valid-time-after-2262"),
        pytest.param(lambda: bad(stack_ended(_BEFORE_INT64_NS)), id="valid-time-before-1677"),
        pytest.param(lambda: dataclasses.replace(bad(clock_tick(V0)), recorded_time_ns=2**63),
                     id="recorded-time-2^63"),
    ],
)
def test_time_outside_int64_ns_is_quarantined(backend, make_bad):
    """Times that have no int64 nanosecond value are refused, not fatal to the batch."""
    run_reject_case(backend, make_bad(), ("out_of_range", "bad_identity"), None)


# --- whole batches ------------------------------------------------------------------------


def test_batch_of_only_bad_input_stores_nothing(backend):
    store = backend.store
    items = [
        decode_line("{oops"),
        Event("bogus", BAD_SOURCE, 7, 0, V0, b"\x01\x02"),
        bad(joint_reading(V0, travel=math.nan), seq=1),
        bad(stack_ended(V0, tonnes=-3.0), seq=2),
        bad(assay(V0, analytes={"Fe": 80.0, "SiO2": 30.0}), seq=3),
        bad(machine(V0, kind=99), seq=4),
        bad(scan(V0, scan_ranges(400), start=-math.pi, end=3 * math.pi), seq=5),
    ]
    codes = ["malformed", "unknown_type", "non_finite", "negative_tonnes", "analyte_sum",
             "unknown_enum", "ranges_angles_mismatch"]
    result = store.append(items)
    assert [o.status for o in result.outcomes] == ["rejected"] * len(items)
    assert [o.code for o in result.outcomes] == codes
    assert result.head_seq == -1
    assert store.head().global_seq == -1
    assert list(store.read()) == []
    quarantine = store.quarantine()
    assert [q.quarantine_id for q in quarantine] == list(range(len(items)))
    for entry, item, code in zip(quarantine, items, codes):
        assert_quarantined_as(entry, item, code, None)
    assert store.verify() == VerifyReport(True, 0)
    assert store.stats().quarantine_by_code == {c: 1 for c in codes}
    if backend.persistent:
        reopened = backend.reopen(read_only=True)
        assert reopened.head().global_seq == -1
        assert list(reopened.read()) == []
        assert reopened.quarantine() == quarantine


def test_mixed_batches_survive_reopening(backend):
    """Several batches mixing good and bad input; everything is on disk after reopening."""
    store = backend.store
    lot_l1 = bad(lot(V0 - 1_000, "L1"), source="mes.lots", seq=0)
    goods1 = [
        make_event(joint_reading(V0), source=GOOD_SOURCE, epoch=1, seq=0),
        make_event(scan(V0, [math.nan] + scan_ranges(180)), source="bwr1.scanner", epoch=1, seq=0),
        make_event(frame_transform(V0), source="bwr1.tf", epoch=1, seq=0),
        lot_l1,
        make_event(assay(V0, "L1"), source="lab1", epoch=1, seq=0),
        make_event(assay(V0, "L9", assay_id="A9"), source="lab1", epoch=1, seq=1),
    ]
    bads1 = [
        (decode_line('{"type":'), "malformed", "not JSON"),
        (decode_line(UNKNOWN_TYPE_LINE), "unknown_type", "bogus"),
        (Event("assay", "lab1", 1, 9, V0, b"\x0a\xff\xff\xff\x0f"), "undecodable", "Assay"),
        (dataclasses.replace(make_event(joint_reading(V0), source=GOOD_SOURCE, epoch=1, seq=5),
                             valid_time_ns=V0 + 7), "valid_time_mismatch", "valid_time_ns"),
        (make_event(joint_reading(V0, travel=math.inf), source=GOOD_SOURCE, epoch=1, seq=6),
         "non_finite", "travel_m"),
        (make_event(scan(V0, [math.inf] + scan_ranges(180)), source="bwr1.scanner", epoch=1,
                    seq=1), "non_finite", "ranges"),
        (make_event(scan(V0, scan_ranges(400), start=-math.pi, end=3 * math.pi),
                    source="bwr1.scanner", epoch=1, seq=2), "ranges_angles_mismatch", "400"),
        (make_event(stack_ended(V0, tonnes=-1.0), source="belt", epoch=1, seq=0),
         "negative_tonnes", "tonnes"),
        (make_event(assay(V0, analytes={"Fe": 120.0}), source="lab1", epoch=1, seq=2),
         "analyte_out_of_range", "Fe"),
        (make_event(assay(V0, analytes={"Fe": 70.0, "SiO2": 31.0}), source="lab1", epoch=1,
                    seq=3), "analyte_sum", "analytes"),
        (make_event(machine(V0, kind=99), source="mes.machines", epoch=1, seq=0),
         "unknown_enum", "kind"),
        (make_event(assay(V0, "L1", analytes={"Fe": 1.0}), source="lab1", epoch=1, seq=0),
         "conflict", "global_seq 4"),
        (make_event(clock_tick(V0), source="", epoch=1, seq=0), "bad_identity", "source"),
    ]
    # interleave: good, bad, good, bad, ... then the remaining bad ones
    batch, expected_status = [], []
    for i in range(max(len(goods1), len(bads1))):
        if i < len(goods1):
            batch.append(goods1[i])
            expected_status.append("appended")
        if i < len(bads1):
            batch.append(bads1[i][0])
            expected_status.append("conflict" if bads1[i][1] == "conflict" else "rejected")
    result = store.append(batch)
    assert [o.status for o in result.outcomes] == expected_status
    bad_outcomes = [o for o in result.outcomes if o.status != "appended"]
    assert [o.code for o in bad_outcomes] == [b[1] for b in bads1]
    assert [o.global_seq for o in result.outcomes if o.status == "appended"] == list(range(6))
    assert [o.flags for o in result.outcomes if o.status == "appended"] == [
        (), (), (), (), (), (FLAG_UNKNOWN_LOT,)]

    # a second batch: a duplicate, a conflict with batch 1, a good one, a backwards time
    goods2 = make_event(joint_reading(V0 + 1_000), source=GOOD_SOURCE, epoch=1, seq=1)
    conflict2 = make_event(joint_reading(V0, travel=99.0), source=GOOD_SOURCE, epoch=1, seq=0)
    backwards = dataclasses.replace(make_event(clock_tick(V0), source="sim.clock", epoch=1, seq=0),
                                    recorded_time_ns=NOW - 1)
    result2 = store.append([goods1[0], conflict2, goods2, backwards])
    assert list(result2.outcomes[:1] + result2.outcomes[2:3]) == [
        AppendOutcome("duplicate", 0), AppendOutcome("appended", 6)]
    assert (result2.outcomes[1].status, result2.outcomes[1].global_seq) == ("conflict", 0)
    assert (result2.outcomes[3].status, result2.outcomes[3].code) == (
        "rejected", "recorded_time_backwards")

    quarantine = store.quarantine()
    all_bad = bads1 + [(conflict2, "conflict", "global_seq 0"),
                       (backwards, "recorded_time_backwards", "recorded_time_ns")]
    assert len(quarantine) == len(all_bad)
    assert [q.quarantine_id for q in quarantine] == list(range(len(all_bad)))
    for entry, (item, code, detail_has) in zip(quarantine, all_bad):
        existing = {"global_seq 4": 4, "global_seq 0": 0}.get(detail_has) if code == "conflict" \
            else None
        assert_quarantined_as(entry, item, code, detail_has, existing=existing)
    expected_rows = [(e, (FLAG_UNKNOWN_LOT,) if e.type == "assay" and i == 5 else ())
                     for i, e in enumerate(goods1)] + [(goods2, ())]
    assert_rows(store, expected_rows)

    reopened = backend.reopen(read_only=True)
    assert reopened.quarantine() == quarantine
    assert_rows(reopened, expected_rows)
    stats = reopened.stats()
    assert stats.events == 7
    assert stats.quarantined == len(all_bad)
    assert stats.flagged == {FLAG_UNKNOWN_LOT: 1}
    if backend.persistent:
        # the raw bytes survive byte for byte, including the non-UTF-8 payload
        assert [q.raw for q in reopened.quarantine()] == [raw_of(b[0]) for b in all_bad]
