"""A generated sample yard session, as canonical JSON lines in arrival order.

``stockpile demo --sample`` ledgers it.  It is small (about 12,000 events over 6
simulated hours) but exercises everything the ledger does: declarations, stacking
passes, sensor streams, reclaim cuts, a site clock, assays that arrive hours late
(one before its lot is declared, one superseded), and bad input (malformed lines, an
infinite scan range, a conflicting retransmission, an exact retransmission, a dropped
sequence number).

Lines are in *arrival* order; recorded time comes from the ``clock`` events
(import with ``--clock events``).  Deterministic for a given seed.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from google.protobuf.message import Message

from schemas import pb
from schemas.events import make_event, set_timestamp_ns
from schemas.jsonl import encode_line, event_line
from schemas.times import NS_PER_H, NS_PER_S

#: 2026-11-01T00:00:00Z
SESSION_START_NS = 1_793_491_200_000_000_000

ANALYTES = ("Fe", "SiO2", "Al2O3", "P", "LOI")
#: planned grades of the sample's lots, mass % (magnitudes of thesis Table 5.4)
LOT_GRADES = {
    "LOT-A": {"Fe": 62.4, "SiO2": 3.9, "Al2O3": 2.2, "P": 0.08, "LOI": 5.1},
    "LOT-B": {"Fe": 60.8, "SiO2": 5.6, "Al2O3": 2.6, "P": 0.10, "LOI": 5.6},
    "LOT-C": {"Fe": 63.1, "SiO2": 3.2, "Al2O3": 1.9, "P": 0.07, "LOI": 4.8},
}


@dataclass
class _Stream:
    source: str
    epoch: int
    seq: int = 0


@dataclass
class SampleSession:
    """The generated lines plus what was planted in them, for the demo's report."""

    lines: list[str] = field(default_factory=list)
    planted: dict[str, int] = field(default_factory=dict)
    start_ns: int = SESSION_START_NS
    end_ns: int = SESSION_START_NS


def _stamp(message: Message, name: str, t_ns: int) -> Message:
    set_timestamp_ns(getattr(message, name), t_ns)
    return message


class _Arrivals:
    """Messages with their arrival time and stream, in the order they were emitted."""

    def __init__(self) -> None:
        self.items: list[tuple[int, int, Message, _Stream]] = []  # (arrival ns, order, msg, stream)

    def emit(self, arrival_ns: int, message: Message, stream: _Stream) -> None:
        self.items.append((arrival_ns, len(self.items), message, stream))


def _declare_yard(arrivals: _Arrivals, t0: int, config: _Stream) -> None:
    """The site, the pile and the reclaimer, declared at the session's start."""
    emit = arrivals.emit
    emit(t0, _stamp(pb.SiteDeclared(site_id="demo", datum_lat_deg=-20.3, datum_lon_deg=118.6,
                                     datum_alt_m=6.0, crs_epsg=7850), "time", t0), config)
    emit(t0, _stamp(pb.PileDeclared(pile_id="P1", origin_x_m=0.0, origin_y_m=0.0, length_m=220.0,
                                    width_m=60.0, ground_z_m=0.0, cell_m=0.25, voxel_m=1.0,
                                    default_bulk_density_t_m3=2.4), "time", t0), config)
    machine = pb.MachineDeclared(
        machine_id="bwr1", kind=pb.BUCKET_WHEEL_RECLAIMER, rail_x_m=-10.0, rail_z_m=0.0,
        l2_m=6.0, l3_m=5.0, l4_m=5.0, l5_m=50.0, wheel_radius_m=7.0, cutting_radius_m=10.0,
        wheel_tilt_rad=math.radians(5), bucket_width_m=1.2, fall_angle_rad=math.radians(15))
    machine.scanner.parent_frame_id = "bwr1/wheel"
    machine.scanner.child_frame_id = "bwr1/scanner"
    machine.scanner.translation.z = 3.0
    machine.scanner.rotation.w = 1.0
    emit(t0, _stamp(machine, "time", t0), config)


def _pass_assay(rng: random.Random, lot: str, grade: dict[str, float], pass_id: str,
                start: int, stop: int) -> pb.Assay:
    """A provisional assay of one stacking pass's window (its times not yet stamped)."""
    assay = pb.Assay(assay_id=f"{pass_id}-A", lot_id=lot, status=pb.PROVISIONAL,
                     lab_id="lab1", moisture_pct=rng.uniform(4, 7),
                     bulk_density_t_m3=rng.uniform(2.3, 2.5))
    for a in ANALYTES:
        assay.analytes[a] = round(grade[a] * rng.uniform(0.97, 1.03), 3)
    _stamp(assay, "window_start", start)
    _stamp(assay, "window_end", stop)
    return assay


def _final_assay(assay: pb.Assay, arrival: int) -> pb.Assay:
    """A FINAL assay superseding ``assay``, 0.4 points lower in Fe, reported an hour later."""
    final = pb.Assay()
    final.CopyFrom(assay)
    final.assay_id = f"{assay.assay_id}-final"
    final.status = pb.FINAL
    final.supersedes = assay.assay_id
    final.analytes["Fe"] = round(final.analytes["Fe"] - 0.4, 3)
    _stamp(final, "reported_time", arrival + NS_PER_H)
    return final


def _stack_lots(arrivals: _Arrivals, rng: random.Random, t0: int, config: _Stream,
                belt: _Stream, lab: _Stream) -> None:
    """Three lots, two passes each, over the first 3 hours, and an assay per pass."""
    pass_length_s = 1800
    for i, (lot, grade) in enumerate(LOT_GRADES.items()):
        declared = t0 + (i * 2 * pass_length_s + 60) * NS_PER_S
        lot_msg = pb.LotDeclared(lot_id=lot, origin=f"pit-{i + 1}", planned_tonnes=24_000.0)
        lot_msg.planned_grade.update(grade)
        # LOT-C's first assay arrives before LOT-C is declared: it will be flagged
        arrivals.emit(declared, _stamp(lot_msg, "time", declared), config)
        for p in range(2):
            start = declared + (p * pass_length_s + 30) * NS_PER_S
            stop = start + (pass_length_s - 60) * NS_PER_S
            pass_id = f"{lot}-pass{p + 1}"
            arrivals.emit(start, _stamp(pb.StackStarted(
                pile_id="P1", pass_id=pass_id, lot_id=lot, machine_id="stacker1",
                pattern=pb.CHEVRON, start_y_m=10.0, end_y_m=210.0), "time", start), belt)
            tonnes = 12_000.0 * rng.uniform(0.99, 1.01)
            arrivals.emit(stop, _stamp(pb.StackEnded(pile_id="P1", pass_id=pass_id, tonnes=tonnes),
                                       "time", stop), belt)
            # one assay per pass, reported 2-4 hours after its window closed
            late = int(rng.uniform(2.0, 4.0) * 3600 * NS_PER_S)
            assay = _pass_assay(rng, lot, grade, pass_id, start, stop)
            arrival = stop + late
            if lot == "LOT-C" and p == 0:
                arrival = declared - 120 * NS_PER_S  # before its lot: accepted and flagged
                _stamp(assay, "window_start", declared - 600 * NS_PER_S)
                _stamp(assay, "window_end", declared - 300 * NS_PER_S)
            _stamp(assay, "reported_time", arrival)
            arrivals.emit(arrival, assay, lab)
            if lot == "LOT-A" and p == 0:
                arrivals.emit(arrival + NS_PER_H, _final_assay(assay, arrival), lab)


def _reclaim_bench(arrivals: _Arrivals, rng: random.Random, t0: int, reclaimer: _Stream) -> None:
    """A bench of eight cuts in the last two hours."""
    for c in range(8):
        start = t0 + int((4 * 3600 + c * 600) * NS_PER_S)
        stop = start + 480 * NS_PER_S
        cut = pb.ReclaimCut(pile_id="P1", cut_id=f"B1-C{c + 1}", bench_id="B1", machine_id="bwr1",
                            travel_m=20.0 + 1.08 * c, luff_rad=math.radians(-8),
                            slew_start_rad=math.radians(30), slew_end_rad=math.radians(80),
                            tonnes=rng.uniform(1400, 1700))
        _stamp(cut, "start_time", start)
        _stamp(cut, "end_time", stop)
        arrivals.emit(stop, cut, reclaimer)


def _sensor_streams(arrivals: _Arrivals, rng: random.Random, t0: int, end: int,
                    streams: dict[str, _Stream]) -> None:
    """The site clock (10 s), joints and wheel poses (5 s) and scans (30 s) over the session."""
    emit = arrivals.emit
    for t in range(t0, end + 1, 10 * NS_PER_S):
        emit(t, _stamp(pb.Clock(), "time", t), streams["clock"])
    for k, t in enumerate(range(t0, end, 5 * NS_PER_S)):
        travel = 20.0 + 10.0 * math.sin(k / 400.0)
        slew = math.radians(55.0 + 25.0 * math.sin(k / 37.0))
        luff = math.radians(-8.0)
        emit(t, _stamp(pb.JointReading(machine_id="bwr1", travel_m=travel + rng.gauss(0, 0.002),
                                       slew_rad=slew, luff_rad=luff), "time", t), streams["joints"])
        pose = FrameTransform(parent_frame_id="site", child_frame_id="bwr1/wheel")
        rho = 5.0 + 50.0 * math.cos(luff)
        pose.translation.x = -10.0 + rho * math.sin(slew)
        pose.translation.y = travel + rho * math.cos(slew)
        pose.translation.z = 11.0 + 50.0 * math.sin(luff)
        pose.rotation.z, pose.rotation.w = math.sin(slew / 2), math.cos(slew / 2)
        emit(t, _stamp(pose, "timestamp", t), streams["poses"])
    for t in range(t0, end, 30 * NS_PER_S):
        scan = LaserScan(frame_id="bwr1/scanner", start_angle=math.radians(-50),
                         end_angle=math.radians(50))
        for i in range(401):
            r = 25.0 + 8.0 * math.cos(math.radians(-50 + i * 0.25)) + rng.gauss(0, 0.015)
            scan.ranges.append(r if rng.random() > 0.01 else math.nan)
        emit(t, _stamp(scan, "timestamp", t), streams["scanner"])


def _plant_bad_scan(session: SampleSession, message: Message, stream: _Stream) -> None:
    """A scanner glitch after the scan: an infinite range (quarantined)."""
    bad = LaserScan()
    bad.CopyFrom(message)
    bad.ranges[200] = math.inf
    bad_event = make_event(bad, source=stream.source, epoch=stream.epoch, seq=stream.seq)
    stream.seq += 1
    session.lines.append(event_line(bad_event))
    session.planted["bad_scans"] += 1


def _plant_retransmissions(session: SampleSession, line: str, event, message: Message) -> None:
    """An exact retransmission of the line (a no-op) and a conflicting one (same identity)."""
    session.lines.append(line)  # an exact retransmission: a duplicate, no-op
    session.planted["retransmissions"] += 1
    # a conflicting retransmission: same identity, different payload
    rival = FrameTransform()
    rival.CopyFrom(message)
    rival.translation.x += 0.5
    session.lines.append(encode_line(event.type, event.source, event.epoch, event.seq,
                                     event.valid_time_ns, rival.SerializeToString()))
    session.planted["conflicts"] += 1


def _encode_session(arrivals: _Arrivals, streams: dict[str, _Stream], session: SampleSession
                    ) -> None:
    """The messages as lines in arrival order, numbered per stream, with the bad input planted."""
    clock, joints = streams["clock"], streams["joints"]
    # at equal arrival times the clock ticks first, so nothing is recorded before the clock
    ordered = sorted(arrivals.items, key=lambda a: (a[0], a[3] is not clock, a[1]))
    session.planted = {"malformed_lines": 0, "bad_scans": 0, "conflicts": 0,
                       "retransmissions": 0, "dropped": 0}
    for arrival, _, message, stream in ordered:
        event = make_event(message, source=stream.source, epoch=stream.epoch, seq=stream.seq)
        stream.seq += 1
        if stream is joints and event.seq == 1000:
            session.planted["dropped"] += 1  # lost on the network: leaves a gap in the ledger
            continue
        line = event_line(event)
        session.lines.append(line)
        if stream is streams["scanner"] and event.seq == 100:
            _plant_bad_scan(session, message, stream)
        if stream is streams["poses"] and event.seq == 2000:
            _plant_retransmissions(session, line, event, message)
        if stream is joints and event.seq == 3000:
            session.lines.append('{"type": "joint_reading", "source": "bwr1.encoders", ')
            session.lines.append("garbage from a half-written file")
            session.planted["malformed_lines"] += 2


def generate_sample(seed: int = 7, hours: float = 6.0) -> SampleSession:
    """Generate the sample session; see the module docstring."""
    rng = random.Random(seed)
    t0 = SESSION_START_NS
    end = t0 + int(hours * 3600 * NS_PER_S)
    streams = {"config": _Stream("yard.config", 1), "clock": _Stream("sim.clock", 1),
               "joints": _Stream("bwr1.encoders", 1), "poses": _Stream("bwr1.localizer", 1),
               "scanner": _Stream("bwr1.scanner", 1), "belt": _Stream("stacker1.belt", 1),
               "reclaimer": _Stream("bwr1.control", 1), "lab": _Stream("lab1", 1)}
    arrivals = _Arrivals()
    _declare_yard(arrivals, t0, streams["config"])
    _stack_lots(arrivals, rng, t0, streams["config"], streams["belt"], streams["lab"])
    _reclaim_bench(arrivals, rng, t0, streams["reclaimer"])
    _sensor_streams(arrivals, rng, t0, end, streams)
    session = SampleSession(start_ns=t0, end_ns=end)
    _encode_session(arrivals, streams, session)
    return session
