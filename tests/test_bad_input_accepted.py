"""Input at the edge of the rules that the ledger must accept: NaN scan ranges (no return),
analyte sums within the tolerance, zero tonnes and every valid enum, and assays of a lot
not declared (yet) that are appended with a flag, not quarantined; each good event is
appended between two others and read back (in memory and on a DuckDB file).
"""

from __future__ import annotations

import math

import pytest
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan

from bad_input_helpers import (
    V0,
    Backend,
    assay,
    assert_rows,
    bad,
    frame_transform,
    good_pair,
    location_fix,
    lot,
    machine,
    reclaim_cut,
    scan,
    scan_ranges,
    stack_ended,
    stack_started,
)
from ledger import AppendOutcome
from ledger.records import FLAG_UNKNOWN_LOT
from schemas import pb
from schemas.events import Event
from schemas.validate import ANALYTE_SUM_TOLERANCE_PCT


# --- what must be accepted ----------------------------------------------------------------


def run_accept_case(backend: Backend, item: Event, flags: tuple[str, ...] = ()) -> None:
    store = backend.store
    before, after = good_pair()
    result = store.append([before, item, after])
    assert list(result.outcomes) == [
        AppendOutcome("appended", 0),
        AppendOutcome("appended", 1, flags=flags),
        AppendOutcome("appended", 2),
    ]
    assert store.quarantine() == []
    assert_rows(store, [(before, ()), (item, flags), (after, ())])


def _any_scanner(step_deg: float, count: int, start_deg: float):
    """A scan of ``count`` ranges from ``start_deg`` at ``step_deg`` steps (any scanner)."""
    end = math.radians(start_deg + (count - 1) * step_deg)
    return bad(scan(V0, scan_ranges(count), start=math.radians(start_deg), end=end))


@pytest.mark.parametrize(
    "make_item",
    [
        pytest.param(lambda: _any_scanner(0.1667, 1141, -95.0), id="lms5xx-0.1667-deg"),
        pytest.param(lambda: _any_scanner(0.3333, 811, -135.0), id="tim-0.3333-deg-270"),
        pytest.param(lambda: _any_scanner(0.25, 1441, -180.0), id="full-turn-0.25-deg"),
        pytest.param(lambda: _any_scanner(100.0 / 399, 400, 0.0), id="400-ranges-over-100-deg"),
        pytest.param(lambda: _any_scanner(180.0 / 179, 180, -90.0), id="180-ranges-over-180-deg"),
    ],
)
def test_any_consistent_step_and_field_is_accepted(backend, make_item):
    """The ledger takes any scanner's scan whose count and angles make a step > 0 over a
    field of at most 360 deg, not only the LMS200's 0.25 / 0.5 / 1 deg."""
    item = make_item()
    run_accept_case(backend, item)
    stored = LaserScan.FromString(next(backend.store.read(1, 2)).payload)
    sent = LaserScan.FromString(item.payload)
    assert (stored.start_angle, stored.end_angle, len(stored.ranges)) == (
        sent.start_angle, sent.end_angle, len(sent.ranges))


@pytest.mark.parametrize(
    "make_item",
    [
        pytest.param(lambda: bad(scan(V0, [5.0, math.nan, 6.0] + scan_ranges(178))),
                     id="one-nan-range"),
        pytest.param(lambda: bad(scan(V0, [math.nan] * 181)), id="all-nan-ranges"),
        pytest.param(lambda: bad(scan(V0, [5.0, math.nan] + scan_ranges(179),
                                      intensities=[math.nan] * 181)), id="nan-intensities"),
        pytest.param(lambda: bad(scan(V0, scan_ranges(401), start=0.0,
                                      end=math.radians(100.0))), id="401-ranges-over-100-deg"),
    ],
)
def test_nan_scan_range_means_no_return_and_is_accepted(backend, make_item):
    item = make_item()
    run_accept_case(backend, item)
    stored = LaserScan.FromString(next(backend.store.read(1, 2)).payload)
    assert list(stored.ranges) == pytest.approx(list(LaserScan.FromString(item.payload).ranges),
                                                nan_ok=True)


@pytest.mark.parametrize(
    "make_item",
    [
        pytest.param(lambda: bad(assay(V0, lot_id="L1", analytes={"Fe": 64.05, "SiO2": 36.0})),
                     id="assay-100.05"),
        pytest.param(lambda: bad(lot(V0, grade={"Fe": 64.05, "SiO2": 36.0})), id="lot-100.05"),
        pytest.param(lambda: bad(assay(V0, lot_id="L1", analytes={"Fe": 100.0})),
                     id="assay-exactly-100"),
        pytest.param(lambda: bad(lot(V0, grade={"Fe": 0.0, "SiO2": 0.0})), id="lot-zeros"),
    ],
)
def test_analyte_sum_within_tolerance_is_accepted(backend, make_item):
    assert 100.05 - 100.0 < ANALYTE_SUM_TOLERANCE_PCT
    item = make_item()
    # the assay's lot is unknown here, which flags (not rejects) it
    run_accept_case(backend, item, (FLAG_UNKNOWN_LOT,) if item.type == "assay" else ())


def test_zero_tonnes_and_valid_enums_are_accepted(backend):
    store = backend.store
    items = [
        bad(stack_ended(V0, tonnes=0.0), seq=0),
        bad(reclaim_cut(V0, tonnes=0.0), seq=1),
        bad(lot(V0, tonnes=0.0), seq=2),
        bad(machine(V0, kind=pb.STACKER), seq=3),
        bad(stack_started(V0, pattern=pb.STRATA), seq=4),
        bad(assay(V0, status=pb.PROVISIONAL), seq=5),
        bad(frame_transform(V0, w=math.sqrt(0.5), z=math.sqrt(0.5)), seq=6),
        bad(location_fix(V0, lat=-90.0, lon=180.0), seq=7),
    ]
    result = store.append(items)
    assert [o.status for o in result.outcomes] == ["appended"] * len(items), result.outcomes
    assert store.quarantine() == []
    assert_rows(store, [(e, ()) for e in items])


# --- unknown lots: accepted and flagged ---------------------------------------------------


def test_assay_for_unknown_lot_is_appended_and_flagged(backend):
    item = bad(assay(V0, lot_id="L-404"))
    run_accept_case(backend, item, (FLAG_UNKNOWN_LOT,))
    if backend.persistent:
        reopened = backend.reopen(read_only=True)
        assert [r.flags for r in reopened.read()] == [(), (FLAG_UNKNOWN_LOT,), ()]
        assert reopened.stats().flagged == {FLAG_UNKNOWN_LOT: 1}
        assert reopened.quarantine() == []


@pytest.mark.parametrize("reopen_between", [False, True], ids=["same-session", "reopened"])
def test_assay_for_lot_declared_in_an_earlier_batch_is_not_flagged(backend, reopen_between):
    store = backend.store
    declared = bad(lot(V0 - 86_400_000_000_000, "L7"), source="mes.lots", seq=0)
    assert store.append([declared]).outcomes == (AppendOutcome("appended", 0),)
    if reopen_between:
        store = backend.reopen()
    known = bad(assay(V0, "L7", assay_id="A7"), seq=0)
    unknown = bad(assay(V0, "L8", assay_id="A8"), seq=1)
    result = store.append([known, unknown])
    assert list(result.outcomes) == [
        AppendOutcome("appended", 1),
        AppendOutcome("appended", 2, flags=(FLAG_UNKNOWN_LOT,)),
    ]
    assert_rows(store, [(declared, ()), (known, ()), (unknown, (FLAG_UNKNOWN_LOT,))])


def test_lot_known_from_earlier_in_the_same_batch_only(backend):
    store = backend.store
    early_assay = bad(assay(V0, "L3", assay_id="A0"), seq=0)       # before its lot: flagged
    declared = bad(lot(V0, "L3"), source="mes.lots", seq=0)
    late_assay = bad(assay(V0, "L3", assay_id="A1"), seq=1)        # after its lot: not flagged
    rejected_lot = bad(lot(V0, "L5", tonnes=-1.0), source="mes.lots", seq=1)
    orphan = bad(assay(V0, "L5", assay_id="A2"), seq=2)            # its lot was rejected
    result = store.append([early_assay, declared, late_assay, rejected_lot, orphan])
    assert [o.status for o in result.outcomes] == [
        "appended", "appended", "appended", "rejected", "appended"]
    assert [o.flags for o in result.outcomes] == [
        (FLAG_UNKNOWN_LOT,), (), (), (), (FLAG_UNKNOWN_LOT,)]
    assert result.outcomes[3].code == "negative_tonnes"
    assert_rows(store, [(early_assay, (FLAG_UNKNOWN_LOT,)), (declared, ()), (late_assay, ()),
                        (orphan, (FLAG_UNKNOWN_LOT,))])
    assert [q.code for q in store.quarantine()] == ["negative_tonnes"]
