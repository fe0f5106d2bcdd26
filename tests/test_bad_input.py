"""Bad input at the ledger boundary: quarantined with its reason, the rest of the batch kept.

Every case appends ONE batch of ``[good, bad, good]`` to a fresh ledger (in-memory
and DuckDB on a real file) and checks:

(a) the outcome status of each event, in order;
(b) the bad event's outcome ``code``;
(c) exactly one quarantine entry with that code, a detail naming the field, and the
    bad payload bytes (or the raw line for :class:`~schemas.events.Malformed`) as ``raw``;
(d) the two good events read back with dense global seqs 0 and 1 and their payloads;

and, for DuckDB, that all of it is still there after closing and reopening the file.
"""

from __future__ import annotations

import dataclasses
import math
import random

import pytest
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from google.protobuf.message import DecodeError

from ledger import AppendOutcome, ManualClock, VerifyReport, open_ledger
from ledger.records import FLAG_UNKNOWN_LOT
from schemas import pb
from schemas.events import (
    EVENT_TYPES,
    Event,
    Malformed,
    encode_attachment,
    event_from_sample,
    make_event,
    set_timestamp_ns,
)
from schemas.jsonl import decode_line, encode_line
from schemas.validate import ANALYTE_SUM_TOLERANCE_PCT, REASON_CODES

#: valid time of the good events (2023-11-14T22:13:20Z)
V0 = 1_700_000_000_000_000_000
#: what the ledger's manual clock reads: recorded time of everything in these tests
NOW = V0 + 3_600_000_000_000

GOOD_SOURCE = "bwr1.joints"
BAD_SOURCE = "lab.bad"
INT64_MAX = 2**63 - 1

#: seed of the random payload bytes (printed by the test that uses it)
RANDOM_SEED = 20_251_122


# --- backends -----------------------------------------------------------------------------


class Backend:
    """One ledger under test; ``reopen`` closes and reopens a DuckDB file."""

    def __init__(self, kind: str, tmp_path) -> None:
        self.kind = kind
        self.clock = ManualClock(NOW)
        self.path = tmp_path / "ledger.duckdb" if kind == "duckdb" else None
        self.store = open_ledger(":memory:" if self.path is None else self.path, self.clock)

    @property
    def persistent(self) -> bool:
        return self.path is not None

    def reopen(self, *, read_only: bool = False):
        """Close and reopen the file (DuckDB); the in-memory store stays as it is."""
        if self.path is None:
            return self.store
        self.store.close()
        self.store = open_ledger(self.path, self.clock, read_only=read_only)
        return self.store

    def close(self) -> None:
        self.store.close()


@pytest.fixture(params=["memory", "duckdb"])
def backend(request, tmp_path):
    b = Backend(request.param, tmp_path)
    try:
        yield b
    finally:
        b.close()


# --- messages -----------------------------------------------------------------------------


def joint_reading(t_ns: int, *, machine: str = "bwr1", travel: float = 10.0,
                  slew: float = 0.1, luff: float = 0.05) -> pb.JointReading:
    m = pb.JointReading(machine_id=machine, travel_m=travel, slew_rad=slew, luff_rad=luff)
    set_timestamp_ns(m.time, t_ns)
    return m


def clock_tick(t_ns: int) -> pb.Clock:
    m = pb.Clock()
    set_timestamp_ns(m.time, t_ns)
    return m


def scan(t_ns: int, ranges, *, start: float = -math.pi / 2, end: float = math.pi / 2,
         intensities=()) -> LaserScan:
    m = LaserScan(frame_id="bwr1/scanner", start_angle=start, end_angle=end)
    m.pose.orientation.w = 1.0
    m.ranges.extend(ranges)
    m.intensities.extend(intensities)
    set_timestamp_ns(m.timestamp, t_ns)
    return m


def scan_ranges(n: int = 181) -> list[float]:
    return [5.0 + 0.01 * i for i in range(n)]


def frame_transform(t_ns: int, *, w: float = 1.0, z: float = 0.0) -> FrameTransform:
    m = FrameTransform(parent_frame_id="bwr1/wheel", child_frame_id="bwr1/scanner")
    m.rotation.w, m.rotation.z = w, z
    m.translation.x = 1.5
    set_timestamp_ns(m.timestamp, t_ns)
    return m


def location_fix(t_ns: int, *, lat: float = -20.3, lon: float = 118.6) -> LocationFix:
    m = LocationFix(frame_id="bwr1/gnss", latitude=lat, longitude=lon, altitude=10.0)
    set_timestamp_ns(m.timestamp, t_ns)
    return m


def lot(t_ns: int, lot_id: str = "L1", *, tonnes: float = 50_000.0, grade=None) -> pb.LotDeclared:
    m = pb.LotDeclared(lot_id=lot_id, origin="pit A", planned_tonnes=tonnes)
    m.planned_grade.update({"Fe": 62.0, "SiO2": 4.5} if grade is None else grade)
    set_timestamp_ns(m.time, t_ns)
    return m


def assay(t_ns: int, lot_id: str = "L1", *, assay_id: str = "A1", analytes=None,
          status: int = pb.FINAL) -> pb.Assay:
    m = pb.Assay(assay_id=assay_id, lot_id=lot_id, moisture_pct=6.0, bulk_density_t_m3=2.3,
                 lab_id="lab1")
    m.analytes.update({"Fe": 62.1, "SiO2": 4.4, "Al2O3": 2.2} if analytes is None else analytes)
    m.status = status
    set_timestamp_ns(m.window_start, t_ns - 3_600_000_000_000)
    set_timestamp_ns(m.window_end, t_ns)
    set_timestamp_ns(m.reported_time, t_ns + 4 * 3_600_000_000_000)
    return m


def stack_started(t_ns: int, *, pattern: int = pb.CHEVRON) -> pb.StackStarted:
    m = pb.StackStarted(pile_id="P1", pass_id="S1", lot_id="L1", machine_id="st1",
                        start_y_m=0.0, end_y_m=300.0)
    m.pattern = pattern
    set_timestamp_ns(m.time, t_ns)
    return m


def stack_ended(t_ns: int, *, tonnes: float = 1200.0) -> pb.StackEnded:
    m = pb.StackEnded(pile_id="P1", pass_id="S1", tonnes=tonnes)
    set_timestamp_ns(m.time, t_ns)
    return m


def reclaim_cut(t_ns: int, *, tonnes: float = 350.0) -> pb.ReclaimCut:
    m = pb.ReclaimCut(pile_id="P1", cut_id="C1", bench_id="B1", machine_id="bwr1",
                      travel_m=120.0, luff_rad=0.1, slew_start_rad=-0.6, slew_end_rad=0.6,
                      tonnes=tonnes)
    set_timestamp_ns(m.start_time, t_ns - 120_000_000_000)
    set_timestamp_ns(m.end_time, t_ns)
    return m


def machine(t_ns: int, *, kind: int = pb.BUCKET_WHEEL_RECLAIMER) -> pb.MachineDeclared:
    m = pb.MachineDeclared(machine_id="bwr1", rail_x_m=-5.0, rail_z_m=1.0, l2_m=3.0, l3_m=2.0,
                           l4_m=1.0, l5_m=40.0, wheel_radius_m=4.0, cutting_radius_m=4.5,
                           bucket_width_m=1.2)
    m.kind = kind
    set_timestamp_ns(m.time, t_ns)
    return m


def bad(message, *, source: str = BAD_SOURCE, epoch: int = 7, seq: int = 0) -> Event:
    """The event under test, on its own stream."""
    return make_event(message, source=source, epoch=epoch, seq=seq)


def good_pair() -> tuple[Event, Event]:
    """The good event before and the good event after the bad one."""
    before = make_event(joint_reading(V0), source=GOOD_SOURCE, epoch=1, seq=0)
    after = make_event(joint_reading(V0 + 100_000_000, travel=10.25), source=GOOD_SOURCE,
                       epoch=1, seq=1)
    return before, after


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


# --- checks -------------------------------------------------------------------------------


def raw_of(item: Event | Malformed) -> bytes:
    return item.raw if isinstance(item, Malformed) else bytes(item.payload)


def _int_or_none(value):
    """Identity numbers as the quarantine keeps them: NULL when not a signed 64-bit int."""
    if isinstance(value, int) and not isinstance(value, bool) and -(2**63) <= value < 2**63:
        return value
    return None


def assert_quarantined_as(entry, item: Event | Malformed, code: str | tuple[str, ...],
                          detail_has: str | None,
                          existing: int | None = None) -> None:
    codes = (code,) if isinstance(code, str) else tuple(code)
    assert entry.code in codes
    assert entry.code in REASON_CODES
    if detail_has is not None:
        assert detail_has in entry.detail, entry.detail
    assert entry.detail
    assert entry.raw == raw_of(item)
    assert isinstance(entry.raw, bytes)
    assert entry.type == str(item.type or "")
    assert entry.source == str(item.source or "")
    assert entry.epoch == _int_or_none(item.epoch)
    assert entry.seq == _int_or_none(item.seq)
    assert entry.valid_time_ns == _int_or_none(item.valid_time_ns)
    assert entry.recorded_time_ns == NOW
    assert entry.existing_global_seq == existing


def assert_rows(store, expected: list[tuple[Event, tuple[str, ...]]]) -> None:
    """The ledger holds exactly ``expected`` (event, flags), with dense global seqs from 0."""
    rows = list(store.read())
    assert [r.global_seq for r in rows] == list(range(len(expected)))
    for row, (event, flags) in zip(rows, expected):
        assert (row.type, row.source, row.epoch, row.seq, row.valid_time_ns) == (
            event.type, event.source, event.epoch, event.seq, event.valid_time_ns)
        assert row.payload == bytes(event.payload)
        assert row.flags == flags
        assert row.recorded_time_ns == NOW
    assert store.head().global_seq == len(expected) - 1
    assert store.verify() == VerifyReport(True, len(expected))


def run_reject_case(backend: Backend, bad_item: Event | Malformed, code: str | tuple[str, ...],
                    detail_has: str | None, status: str = "rejected") -> None:
    """Append ``[good, bad_item, good]`` to a fresh ledger and check (a)-(d), then reopen.

    ``code`` is the expected reason code, or a tuple of acceptable ones.
    """
    codes = (code,) if isinstance(code, str) else tuple(code)
    store = backend.store
    assert store.head().global_seq == -1 and store.quarantine() == []
    before, after = good_pair()

    result = store.append([before, bad_item, after])

    # (a) statuses in order, (b) the code
    assert [o.status for o in result.outcomes] == ["appended", status, "appended"]
    assert result.outcomes[0] == AppendOutcome("appended", 0)
    assert result.outcomes[2] == AppendOutcome("appended", 1)
    outcome = result.outcomes[1]
    assert outcome.code in codes
    assert outcome.global_seq is None
    assert outcome.flags == ()
    assert result.head_seq == 1
    # (c) exactly one quarantine entry, with reason and raw bytes
    quarantine = store.quarantine()
    assert len(quarantine) == 1
    assert_quarantined_as(quarantine[0], bad_item, outcome.code, detail_has)
    assert quarantine[0].detail == outcome.detail
    assert quarantine[0].quarantine_id == 0
    # (d) the good events were kept
    assert_rows(store, [(before, ()), (after, ())])

    if backend.persistent:
        reopened = backend.reopen(read_only=True)
        assert reopened.quarantine() == quarantine
        assert_rows(reopened, [(before, ()), (after, ())])


# --- one test per bad-input case --------------------------------------------------------


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
    import json

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
    # scan geometry
    pytest.param(lambda: bad(scan(V0, scan_ranges(400), start=0.0, end=math.radians(100.0))),
                 "ranges_angles_mismatch", "400 ranges", id="400-ranges-over-100-deg"),
    pytest.param(lambda: bad(scan(V0, scan_ranges(180))), "ranges_angles_mismatch",
                 "180 ranges", id="180-ranges-over-180-deg"),
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
_AFTER_INT64_NS = (INT64_MAX // 1_000_000_000 + 1) * 1_000_000_000
#: last whole second before the smallest int64 nanosecond (1677-09-21T00:12:43Z)
_BEFORE_INT64_NS = (-(2**63) // 1_000_000_000 - 1) * 1_000_000_000


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


# --- what must be accepted -----------------------------------------------------------------


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


# --- duplicates and conflicts --------------------------------------------------------------


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


# --- unknown lots: accepted and flagged ------------------------------------------------------


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


# --- preserved recorded time -----------------------------------------------------------------


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


# --- whole batches -----------------------------------------------------------------------------


def test_batch_of_only_bad_input_stores_nothing(backend):
    store = backend.store
    items = [
        decode_line("{oops"),
        Event("bogus", BAD_SOURCE, 7, 0, V0, b"\x01\x02"),
        bad(joint_reading(V0, travel=math.nan), seq=1),
        bad(stack_ended(V0, tonnes=-3.0), seq=2),
        bad(assay(V0, analytes={"Fe": 80.0, "SiO2": 30.0}), seq=3),
        bad(machine(V0, kind=99), seq=4),
        bad(scan(V0, scan_ranges(400), start=0.0, end=math.radians(100.0)), seq=5),
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
        (make_event(scan(V0, scan_ranges(400), start=0.0, end=math.radians(100.0)),
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
