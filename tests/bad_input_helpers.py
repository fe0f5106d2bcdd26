"""Helpers the bad-input tests share: a ledger under test (:class:`Backend`, in memory or on
a DuckDB file; the ``backend`` fixture in conftest.py gives one of each), builders of valid
messages to spoil, and the checks of one ``[good, bad, good]`` batch: the outcome statuses
and code, one quarantine entry with its reason and raw bytes, and the good events kept with
dense global seqs.
"""

from __future__ import annotations

import math

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

from ledger import AppendOutcome, ManualClock, VerifyReport, open_ledger
from schemas import pb
from schemas.events import (
    Event,
    Malformed,
    make_event,
    set_timestamp_ns,
)
from schemas.times import NS_PER_H
from schemas.validate import REASON_CODES

#: valid time of the good events (2023-11-14T22:13:20Z)
V0 = 1_700_000_000_000_000_000
#: what the ledger's manual clock reads: recorded time of everything in these tests
NOW = V0 + NS_PER_H

GOOD_SOURCE = "bwr1.joints"
BAD_SOURCE = "lab.bad"


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
          status: int = pb.FINAL, repeatability=None) -> pb.Assay:
    m = pb.Assay(assay_id=assay_id, lot_id=lot_id, moisture_pct=6.0, bulk_density_t_m3=2.3,
                 lab_id="lab1")
    m.analytes.update({"Fe": 62.1, "SiO2": 4.4, "Al2O3": 2.2} if analytes is None else analytes)
    m.repeatability_pp.update(repeatability or {})
    m.status = status
    set_timestamp_ns(m.window_start, t_ns - NS_PER_H)
    set_timestamp_ns(m.window_end, t_ns)
    set_timestamp_ns(m.reported_time, t_ns + 4 * NS_PER_H)
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
